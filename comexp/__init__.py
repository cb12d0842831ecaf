"""comexp: centre-of-mass estimation by dynamic pushing.

`comexp.load_results(db, table="episodes")` (a pandas DataFrame) and
`comexp.replay(db, episode_id)` are imported on first use, so `import comexp` stays light.
"""

from typing import Any

__version__ = "0.1.0"
__all__ = ["load_results", "replay"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from comexp import results

        return getattr(results, name)
    raise AttributeError(f"module 'comexp' has no attribute {name!r}")
