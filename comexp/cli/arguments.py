"""Number arguments of the command-line tools, checked by argparse in one line each."""

from __future__ import annotations

import argparse
import math


def nonnegative_float(text: str) -> float:
    """A finite number >= 0 (argparse `type=`)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(v) or v < 0:
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0: {text!r}")
    return v


def positive_float(text: str) -> float:
    """A finite number > 0 (argparse `type=`)."""
    v = nonnegative_float(text)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0: {text!r}")
    return v
