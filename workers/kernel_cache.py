"""Compile the backend's Numba kernels once, in a short-lived process, before the workers start.

The kernels are compiled on first use and cached on disk (`cache=True`). With a cold cache (the
first job after an install or a kernel edit) every worker would compile them itself, and the
compiler's memory stays with the worker for the whole job: a pybullet worker holds ~380 MB
(PSS) instead of ~240, and a 2-worker job goes over 1 GB (`bench/memory.py`). Running one
episode of the job in a child process fills the cache; the child exits, its memory goes back to
the system, and the workers load the compiled kernels from disk. With a warm cache the child
only loads them (1.0 - 1.3 s per backend, once per driver process).

It runs beside Ray's start (`meanwhile`: the head's processes, ~2 s; the workers start after
it), which hides the ~1 s it takes with a warm cache; the compiler's peak on a cold one never
meets the workers' memory. Only for workers on this machine (callers skip it for a cluster,
whose nodes have caches of their own), and only for the built-in backends, whose kernels it
knows (a plug-in backend's workers compile what they use). A child that fails or overruns is a
warning, never an error: the workers then compile for themselves, as they always could.
"""

from __future__ import annotations

import logging
import os
import pickle
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable

from comexp.backends.physics_settings import BUILTIN_PHYSICS
from comexp.episode.loop import run_episode
from comexp.episode.task import EpisodeSpec
from comexp.sim.simulator import SimulatorSpec

log = logging.getLogger("comexp.pool")

WARM_UP_TIMEOUT_S = 600.0  # a cold compile of every kernel: 18 - 27 s on 2 cores
# (backend, options) whose kernels this process has already had compiled
_warmed: set[str] = set()


def warm_kernel_cache(
    simulator: SimulatorSpec,
    spec: EpisodeSpec,
    *,
    timeout_s: float = WARM_UP_TIMEOUT_S,
    meanwhile: Callable[[], None] | None = None,
) -> bool:
    """Run `spec` on `simulator` in a child process (this process's environment, which local
    workers inherit) so that every kernel a job of it needs is in Numba's cache before the
    workers start; once per backend and options per process. `meanwhile` runs while the
    child works (always, also when there is no child; its error ends the child). Returns
    whether the child ran the episode (False when skipped or failed: the workers compile
    what they miss)."""
    backend = simulator.name
    key = repr((simulator.target, sorted(simulator.options.items())))
    built_in = simulator.target.rpartition(".")[0] in BUILTIN_PHYSICS
    if key in _warmed or not built_in or _numba_disabled():
        if meanwhile is not None:
            meanwhile()
        return False
    _warmed.add(key)  # a failure is not retried: the workers compile for themselves
    payload = pickle.dumps((simulator, spec))
    log.info("%s: loading the compiled kernels (compiling them if the cache is cold)", backend)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="comexp-warm-up-") as tmp:
        job = os.path.join(tmp, "episode.pickle")  # not stdin: the pipes carry its output only
        with open(job, "wb") as f:
            f.write(payload)
        try:
            child = subprocess.Popen(
                [sys.executable, "-m", __name__, job],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
            )
        except OSError as e:
            log.warning("%s: cannot start the kernel warm-up (%s)", backend, e)
            if meanwhile is not None:
                meanwhile()
            return False
        try:
            if meanwhile is not None:
                meanwhile()
            left_s = max(timeout_s - (time.perf_counter() - t0), 0.0)
            _, err = child.communicate(timeout=left_s)
        except subprocess.TimeoutExpired:
            child.kill()
            child.communicate()
            log.warning(
                "%s: compiling the kernels took over %.0f s; the workers compile what is missing",
                backend,
                timeout_s,
            )
            return False
        except BaseException:
            child.kill()
            child.communicate()
            raise
    if child.returncode != 0:
        tail = err.decode(errors="replace").strip().splitlines()[-1:] or ["?"]
        log.warning(
            "%s: the kernel warm-up failed (exit %d: %s); the workers compile for themselves",
            backend,
            child.returncode,
            tail[0][:300],
        )
        return False
    log.info(
        "%s: kernels ready in %.1f s%s",
        backend,
        time.perf_counter() - t0,
        " (Ray started meanwhile)" if meanwhile is not None else "",
    )
    return True


def _numba_disabled() -> bool:
    """`NUMBA_DISABLE_JIT=1`: nothing to compile, and the child's episode would run in Python."""
    return os.environ.get("NUMBA_DISABLE_JIT", "0").strip() not in ("", "0")


def _run_one_episode(simulator: SimulatorSpec, spec: EpisodeSpec) -> str:
    """The workers' own episode: the same simulator and runner, so the same kernels compile."""
    sim = simulator.make()
    try:
        return run_episode(spec, sim).status
    finally:
        sim.close()


def main() -> int:
    with open(sys.argv[1], "rb") as f:
        simulator, spec = pickle.load(f)  # noqa: S301 - our parent's
    _run_one_episode(simulator, spec)
    return 0


if __name__ == "__main__":
    sys.exit(main())
