"""The command lines: `comexp` (`run`: run experiment jobs) and `comexp-db` (`query`: read the
results database)."""
