"""A cached kernel runs the code of today's sources, also of the modules it calls."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

CALLEE = """
from numba import njit

@njit(cache=True)
def gain(x):
    return {factor} * x
"""

CALLER = """
from numba import njit
import callee
from callee import gain
{stamp}

@njit(cache=True)
def run(x):
    return gain(x) + 1.0

{call}
print(run(2.0))
"""


def _value(folder: Path) -> float:
    env = {**os.environ, "PYTHONPATH": str(folder), "NUMBA_CACHE_DIR": str(folder / "cache")}
    out = subprocess.run(
        [sys.executable, "-c", "import caller"], cwd=folder, env=env, check=True,
        capture_output=True, text=True,
    )  # fmt: skip
    return float(out.stdout.split()[-1])


def _write(folder: Path, factor: float, stamped: bool) -> None:
    (folder / "callee.py").write_text(CALLEE.format(factor=factor))
    if (folder / "caller.py").exists():
        return  # the caller's file, and so Numba's own stamp of its cache, stays as it was
    stamp = "from comexp.backends.kernel_cache import stamp_with_sources" if stamped else ""
    call = "stamp_with_sources(globals(), callee)" if stamped else ""
    (folder / "caller.py").write_text(CALLER.format(stamp=stamp, call=call))


@pytest.mark.parametrize("stamped", [True, False])
def test_a_cached_kernel_follows_a_change_of_the_module_it_calls(tmp_path, stamped):
    """Numba alone keeps the caller's cached machine code (the callee compiled into it) after
    the callee's file changes: the unstamped case shows the hazard is real on this Numba."""
    _write(tmp_path, 10.0, stamped)
    assert _value(tmp_path) == 21.0
    assert _value(tmp_path) == 21.0  # from the cache
    _write(tmp_path, 100.0, stamped)
    expected = 201.0 if stamped else 21.0
    assert _value(tmp_path) == expected
