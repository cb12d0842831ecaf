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
    stamp = "from comexp.backends.numba_kernels import stamp_with_sources" if stamped else ""
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


def test_a_direct_call_is_the_dispatcher_s_call_without_its_type_resolution():
    """`DirectCall` answers as the dispatcher does, through the overload's entry point from
    the second call on, on the friction kernel pybullet calls every step."""
    import numpy as np

    from comexp.backends.floor_friction import FootprintFriction, impulse_kernel
    from comexp.backends.numba_kernels import DirectCall
    from comexp.experiment.objects import com_point, load_objects
    from comexp.sim.scene import PusherSpec

    od = load_objects(["l_shape"])["l_shape"]
    spec = od.model(com_point(od, 0), izz_scale=1.0, mu_pusher=0.5)
    a, b = (FootprintFriction(spec, 0.3, 1.0, PusherSpec()) for _ in range(2))
    call = DirectCall(impulse_kernel)
    rng = np.random.default_rng(0)
    for k in range(20):
        xi = rng.normal(0.0, [0.05, 0.05, 1.0])
        yaw, pushed = float(rng.uniform(-3, 3)), bool(k % 2)
        ref = impulse_kernel(a.geo, a.fs, a.normal, a.dxw, a.dyw, xi, yaw, 1e-3, pushed)
        got = call(b.geo, b.fs, b.normal, b.dxw, b.dyw, xi.copy(), yaw, 1e-3, pushed)
        np.testing.assert_array_equal(got, ref)
        np.testing.assert_array_equal(b.fs, a.fs)
        assert call._entry is not None and call._entry is not impulse_kernel
    assert np.abs(ref).max() > 0.0
