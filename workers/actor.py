"""The Ray worker: one process, one simulator, many episodes.

Building an engine costs far more than one episode's scene, so the simulator is created once
per actor (`SimulatorSpec.make`: the backend's class, imported in the worker) and reused; each
episode runs through the episode loop (`comexp.episode.loop.run_episode`, the default
`runner`; the pool's tests hand cheap fakes in its place).

Time limit: an episode that runs longer than `episode_timeout_s` becomes a failed result with
`failure="timeout"` and the worker carries on with a fresh simulator. Both engines step from
Python, so a SIGALRM (delivered to the main thread, where Ray runs a plain actor's methods)
interrupts a hanging episode between two engine calls. An engine stuck *inside* one C call
never returns to Python; for that a watchdog thread ends the whole worker process after a
grace period, which the pool treats like any dying worker (retry, then `worker_died`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import signal
import socket
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import ray

from comexp.backends.physics_settings import physics_identity
from comexp.episode.loop import run_episode
from comexp.episode.task import EpisodeResult, EpisodeSpec
from comexp.sim.simulator import SimulatorSpec

# an episode runner: the episode loop, or a test's fake
Runner = Callable[[EpisodeSpec, Any], EpisodeResult]


def failed_result(spec: EpisodeSpec, failure: str, detail: str, wall_s: float) -> EpisodeResult:
    return EpisodeResult(
        spec=spec,
        status="failed",
        failure=failure,
        est_com_cm=None,
        error_cm=None,
        n_pushes=0,
        pushes=(),
        wall_s=wall_s,
        detail=detail[-2000:],
    )


def has_sigalrm() -> bool:
    """Whether the per-episode time limit can use SIGALRM (POSIX: Linux and macOS) besides its
    watchdog. Without it (Windows) the worker keeps only its watchdog thread, which ends a
    worker whose episode overruns the limit plus its grace period (the pool then retries the
    batch, and finally stores `worker_died`)."""
    return hasattr(signal, "SIGALRM") and hasattr(signal, "setitimer")


class EpisodeTimeout(BaseException):  # noqa: N818 - a signal, not an error class
    """Raised by SIGALRM in the worker's main thread when an episode overruns its time limit.

    A BaseException on purpose: `run_episode` turns every `Exception` into a failed result
    with `failure="error"` (a sweep must survive any episode), which would hide the timeout.
    """


class _Watchdog:
    """Ends the process when an episode is still running `grace_s` after its time limit.

    The last resort for a hang inside one C call (SIGALRM handlers only run between Python
    bytecodes). A daemon thread: it never keeps the worker alive on its own.
    """

    def __init__(self, grace_s: float) -> None:
        self.grace_s = grace_s
        self._cond = threading.Condition()
        self._deadline: float | None = None
        self._what = ""
        self._thread = threading.Thread(target=self._run, name="episode-watchdog", daemon=True)
        self._thread.start()

    def arm(self, timeout_s: float, what: str) -> None:
        with self._cond:
            self._deadline = time.monotonic() + timeout_s + self.grace_s
            self._what = what
            self._cond.notify()

    def disarm(self) -> None:
        with self._cond:
            self._deadline = None
            self._cond.notify()

    def _run(self) -> None:
        with self._cond:
            while True:
                if self._deadline is None:
                    self._cond.wait()
                    continue
                left = self._deadline - time.monotonic()
                if left > 0:
                    self._cond.wait(left)
                    continue
                print(
                    f"comexp worker {os.getpid()}: {self._what} still running "
                    f"{self.grace_s:g} s after its time limit; ending the worker process",
                    file=sys.stderr,
                    flush=True,
                )
                os._exit(70)


def use_one_cpu() -> None:
    """Keep this process's native thread pools to the one CPU a worker is given.

    The pool gives each worker one CPU and runs as many workers as CPUs. Ray sets
    OMP_NUM_THREADS=1 in its workers, which OpenBLAS follows; OpenCV's pool does not: it
    ran perception's connected components on two threads, and its idle threads then spin
    waiting for work, on the CPU of the other worker. In process on this machine kind a
    planar episode took 31.1 ms of the process's CPU against 26.7 ms with one thread (iso
    40 cm/s), MuJoCo 184.7 against 174.2 ms (aniso 4 cm/s); the results are the same bits
    (docs/performance.md)."""
    import cv2

    cv2.setNumThreads(1)


class EpisodeWorker:
    """Plain class (testable without Ray); `RemoteEpisodeWorker` is its actor form.

    `simulator`: the backend this worker's simulator is made of. `runner(spec, sim)` runs one
    episode (the episode loop; a test's fake). `episode_timeout_s` (None or <= 0: no limit)
    bounds each episode; `kill_grace_s` is how long after that the watchdog waits before
    ending the process (default: the limit itself, at least 10 s, so a slow but live step
    always gets the SIGALRM path first).
    """

    def __init__(
        self,
        simulator: SimulatorSpec,
        runner: Runner = run_episode,
        episode_timeout_s: float | None = None,
        kill_grace_s: float | None = None,
    ) -> None:
        use_one_cpu()
        self.simulator = simulator
        self.backend = simulator.name
        self._runner = runner
        ok = episode_timeout_s is not None and math.isfinite(episode_timeout_s)
        self.episode_timeout_s = episode_timeout_s if ok and episode_timeout_s > 0 else None
        self._watchdog: _Watchdog | None = None
        if self.episode_timeout_s is not None:
            grace = kill_grace_s if kill_grace_s is not None else max(10.0, self.episode_timeout_s)
            self._watchdog = _Watchdog(grace)
            if not has_sigalrm():
                print(
                    f"comexp worker {os.getpid()}: no SIGALRM on {sys.platform}: an episode over "
                    f"its time limit ends this worker after {grace:g} s more (watchdog)",
                    file=sys.stderr,
                    flush=True,
                )
        self._sim: Any = simulator.make()
        self.episodes_run = 0
        self._physics: str | None = None
        info = self.ready()
        self._where = f"{info['node_ip']}:{info['pid']}"

    def ready(self) -> dict[str, Any]:
        """Returns once the simulator exists: lets the pool surface init errors up front, and
        tells it where this worker runs (pid and node address, for logs and fault drills)."""
        try:
            node_ip = ray.util.get_node_ip_address() if ray.is_initialized() else "local"
        except Exception:  # noqa: BLE001 - provenance only
            node_ip = "?"
        return {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "node_ip": node_ip,
            "backend": self.backend,
        }

    def run_batch(self, specs: Sequence[EpisodeSpec]) -> list[EpisodeResult]:
        return [self.run_one(s) for s in specs]

    def run_one(self, spec: EpisodeSpec) -> EpisodeResult:
        """Never raises: an exception becomes a failed result (`failure="error"`), an overrun
        one with `failure="timeout"`; either way the simulator is rebuilt (lazily, by the next
        episode) so that a half-finished episode cannot leak into the next one. (Building the
        simulator is not timed: it happens once per worker, and the pool bounds start-up.)"""
        t0 = time.perf_counter()
        result: EpisodeResult | None = None
        try:
            if self._sim is None:
                self._sim = self.simulator.make()
            mismatch = self._physics_mismatch(spec)
            if mismatch:
                self.episodes_run += 1
                res = failed_result(spec, "physics_mismatch", mismatch, time.perf_counter() - t0)
                return dataclasses.replace(res, worker=self._where)
            with self._time_limit(spec):
                result = self._runner(spec, self._sim)
        except EpisodeTimeout:
            if result is None:  # else the alarm raced the return: keep the finished result
                wall = time.perf_counter() - t0
                detail = f"episode exceeded its time limit of {self.episode_timeout_s:g} s"
                result = failed_result(spec, "timeout", detail, wall)
                self._drop_simulator()
        except Exception as e:
            detail = f"{type(e).__name__}: {e}\n{traceback.format_exc(limit=8)}"
            result = failed_result(spec, "error", detail, time.perf_counter() - t0)
            self._drop_simulator()
        self.episodes_run += 1
        return dataclasses.replace(result, worker=self._where)

    def _physics_mismatch(self, spec: EpisodeSpec) -> str:
        """A node whose engine or backend revision differs from the driver's would compute
        other physics under the same episode identity: refuse, saying what differs."""
        if not spec.physics or spec.backend != self.backend:
            return ""
        if self._physics is None:
            sim = self.simulator
            try:
                self._physics = physics_identity(sim.name, sim.target, options=dict(sim.options))
            except ValueError:  # a fake backend in tests has no identity
                self._physics = ""
        if self._physics and self._physics != spec.physics:
            return f"this worker runs {self._physics}, the episode asks for {spec.physics}"
        return ""

    @contextlib.contextmanager
    def _time_limit(self, spec: EpisodeSpec) -> Iterator[None]:
        """SIGALRM after `episode_timeout_s` (main thread only: Python delivers signals
        there) plus the watchdog; both are cancelled on the way out."""
        limit = self.episode_timeout_s
        if limit is None:
            yield
            return
        assert self._watchdog is not None
        what = f"episode {spec.object} com {spec.com_index}"
        # SIGALRM is POSIX (not on Windows): without it the watchdog alone bounds an episode
        use_alarm = threading.current_thread() is threading.main_thread() and has_sigalrm()
        previous: Any = None
        if use_alarm:

            def on_alarm(signum: int, frame: Any) -> None:
                raise EpisodeTimeout(what)

            previous = signal.signal(signal.SIGALRM, on_alarm)
        self._watchdog.arm(limit, what)
        try:
            if use_alarm:
                signal.setitimer(signal.ITIMER_REAL, limit)
            yield
        finally:
            # Nested so that an alarm firing right here (it fires once) still lets the
            # handler be restored and the watchdog disarmed.
            try:
                if use_alarm:
                    signal.setitimer(signal.ITIMER_REAL, 0)
            finally:
                if use_alarm:
                    signal.signal(signal.SIGALRM, previous or signal.SIG_DFL)
                self._watchdog.disarm()

    def _drop_simulator(self) -> None:
        sim, self._sim = self._sim, None
        if sim is not None:
            # a broken engine may fail to close; the next one is what matters
            with contextlib.suppress(Exception):
                sim.close()

    def close(self) -> None:
        self._drop_simulator()


RemoteEpisodeWorker = ray.remote(EpisodeWorker)
