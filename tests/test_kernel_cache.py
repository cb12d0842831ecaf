"""The kernel warm-up: one child process fills Numba's cache before a local job's workers start,
so that they load the kernels instead of each compiling them (workers/kernel_cache.py)."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest
from test_episode import spec_for

from comexp.episode.task import EpisodeSpec
from comexp.sim.simulator import SimulatorSpec
from comexp.workers import kernel_cache

PLANAR = SimulatorSpec("planar", "comexp.backends.planar_sim.PlanarSimulator")


def _pybullet(floor_friction: str) -> SimulatorSpec:
    target = "comexp.backends.pybullet_sim.PybulletSimulator"
    return SimulatorSpec("pybullet", target, {"floor_friction": floor_friction})


def planar_spec(n_push: int = 1) -> EpisodeSpec:
    """A real planar episode (the camera watching its pushes, as a job's)."""
    return spec_for(backend="planar", fps=30.0, n_push=n_push)


@pytest.fixture
def fresh(monkeypatch):
    """A process that has warmed nothing yet, with Numba on."""
    monkeypatch.setattr(kernel_cache, "_warmed", set())
    for k in ("NUMBA_DISABLE_JIT",):
        monkeypatch.delenv(k, raising=False)
    return monkeypatch


def test_the_warm_up_runs_once_per_backend_and_options_and_not_for_plugins(fresh):
    children: list[tuple[list[str], bytes]] = []

    class Child:  # a child that ran the episode it was sent
        returncode = 0

        def __init__(self, cmd, **kw):
            with open(cmd[-1], "rb") as f:
                children.append((cmd[:-1], f.read()))

        def communicate(self, timeout=None):
            return b"", b""

    fresh.setattr(kernel_cache.subprocess, "Popen", Child)
    spec = planar_spec()
    assert kernel_cache.warm_kernel_cache(PLANAR, spec)
    assert not kernel_cache.warm_kernel_cache(PLANAR, spec)  # this process has them
    assert kernel_cache.warm_kernel_cache(_pybullet("model"), spec)
    assert kernel_cache.warm_kernel_cache(_pybullet("native"), spec)
    assert [c[0][-2:] for c in children] == [["-m", "comexp.workers.kernel_cache"]] * 3
    assert children[0][0][0] == sys.executable
    fresh.setattr(kernel_cache, "_warmed", set())
    plugin = SimulatorSpec("toy", "my_backends.ToyPlanar")  # its kernels are not known here
    assert not kernel_cache.warm_kernel_cache(plugin, spec)
    fresh.setenv("NUMBA_DISABLE_JIT", "1")  # nothing to compile; the episode would crawl
    assert not kernel_cache.warm_kernel_cache(PLANAR, spec)
    assert len(children) == 3


def test_ray_starts_while_the_child_loads_the_kernels(fresh):
    """`meanwhile` (Ray's start in `comexp`) runs while the child is at work, and also when
    there is no child; an error in it ends the child and reaches the caller."""
    started: list[float] = []
    spec = planar_spec()

    def meanwhile() -> None:
        child = [p for p in _children() if "comexp.workers.kernel_cache" in p]
        started.append(len(child))

    assert kernel_cache.warm_kernel_cache(PLANAR, spec, meanwhile=meanwhile)
    assert started == [1]  # the child was running
    assert not kernel_cache.warm_kernel_cache(PLANAR, spec, meanwhile=meanwhile)
    assert started == [1, 0]  # warmed already: no child, Ray still started

    def fails() -> None:
        raise RuntimeError("no Ray")

    fresh.setattr(kernel_cache, "_warmed", set())
    with pytest.raises(RuntimeError, match="no Ray"):
        kernel_cache.warm_kernel_cache(PLANAR, spec, meanwhile=fails)
    assert not [p for p in _children() if "comexp.workers.kernel_cache" in p]


def _children() -> list[str]:
    """The command lines of this process's children."""
    out = []
    for pid in os.listdir("/proc"):
        try:
            with open(f"/proc/{pid}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            if ppid == os.getpid():
                with open(f"/proc/{pid}/cmdline", "rb") as f:
                    out.append(f.read().replace(b"\0", b" ").decode())
        except (OSError, ValueError, IndexError):
            continue
    return out


def test_a_failing_warm_up_is_a_warning_naming_the_child_s_error(fresh, caplog):
    spec = planar_spec()
    with caplog.at_level(logging.WARNING, logger="comexp.pool"):
        bad = SimulatorSpec("planar", PLANAR.target, {"no_such_option": 1})
        assert not kernel_cache.warm_kernel_cache(bad, spec)
    (record,) = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert "kernel warm-up failed (exit 1" in record.getMessage()
    assert "no_such_option" in record.getMessage()


def test_an_overrunning_warm_up_is_ended_with_a_warning(fresh, caplog):
    with caplog.at_level(logging.WARNING, logger="comexp.pool"):
        assert not kernel_cache.warm_kernel_cache(PLANAR, planar_spec(), timeout_s=0.05)
    assert any("took over" in r.getMessage() for r in caplog.records)


@pytest.mark.slow
def test_after_the_warm_up_a_fresh_process_compiles_nothing(fresh, tmp_path: Path):
    """On a cold cache (a Numba cache directory of its own) the warm-up compiles every kernel
    an episode of the job needs: a worker-like process then only loads them. ~30 s: a cold
    compile of every kernel."""
    fresh.setenv("NUMBA_CACHE_DIR", str(tmp_path / "numba"))
    spec = planar_spec(n_push=2)
    assert kernel_cache.warm_kernel_cache(PLANAR, spec)
    assert list((tmp_path / "numba").rglob("*.nbi"))
    probe = f"""
import pickle, sys
from numba.core.dispatcher import Dispatcher
from comexp.sim.simulator import SimulatorSpec
from comexp.workers.kernel_cache import _run_one_episode
spec = pickle.loads({pickle_bytes(spec)!r})
_run_one_episode(SimulatorSpec("planar", {PLANAR.target!r}), spec)
hits = misses = 0
for name, mod in list(sys.modules.items()):
    if name.startswith("comexp"):
        for obj in vars(mod).values():
            if isinstance(obj, Dispatcher) and obj.signatures:
                hits += sum(obj.stats.cache_hits.values())
                misses += sum(obj.stats.cache_misses.values())
print(hits, misses)
"""
    out = subprocess.run(
        [sys.executable, "-c", probe], env=dict(os.environ), capture_output=True, text=True,
        check=True,
    )  # fmt: skip
    hits, misses = map(int, out.stdout.split()[-2:])
    assert hits > 0 and misses == 0, out.stdout


def pickle_bytes(spec: EpisodeSpec) -> bytes:
    import pickle

    return pickle.dumps(spec)
