"""The Ray worker: one process, one simulator, many episodes.

Building an engine costs far more than one episode's scene, so the simulator is created once
per actor and reused. The episode runner and the simulator factory are dotted paths (resolved
inside the worker) so that tests can swap in cheap fakes without pickling functions.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import socket
import time
import traceback
from collections.abc import Callable, Sequence
from typing import Any

import ray

from comexp.episode import EpisodeResult, EpisodeSpec

DEFAULT_RUNNER = "comexp.episode:run_episode"
DEFAULT_SIMULATOR_FACTORY = "comexp.simulator:make_simulator"


def import_dotted(path: str) -> Callable[..., Any]:
    """`package.module:attr` (or `package.module.attr`) -> the object."""
    if ":" in path:
        mod, _, attr = path.partition(":")
    else:
        mod, _, attr = path.rpartition(".")
    if not mod or not attr:
        raise ValueError(f"not a dotted path: {path!r}")
    obj: Any = importlib.import_module(mod)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


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


class EpisodeWorker:
    """Plain class (testable without Ray); `RemoteEpisodeWorker` is its actor form."""

    def __init__(
        self,
        backend: str,
        runner: str = DEFAULT_RUNNER,
        simulator_factory: str = DEFAULT_SIMULATOR_FACTORY,
        runner_kwargs: dict[str, Any] | None = None,
    ) -> None:
        self.backend = backend
        self._runner = import_dotted(runner)
        self._factory = import_dotted(simulator_factory)
        self._runner_kwargs = dict(runner_kwargs or {})
        self._sim: Any = self._factory(backend)
        self.episodes_run = 0

    def ready(self) -> dict[str, Any]:
        """Returns once the simulator exists: lets the pool surface init errors up front."""
        return {"pid": os.getpid(), "host": socket.gethostname(), "backend": self.backend}

    def run_batch(self, specs: Sequence[EpisodeSpec]) -> list[EpisodeResult]:
        return [self.run_one(s) for s in specs]

    def run_one(self, spec: EpisodeSpec) -> EpisodeResult:
        """Never raises: an exception becomes a failed result (`failure="error"`), and the
        simulator is rebuilt (lazily, by the next episode) so that a half-finished episode
        cannot leak into the next one."""
        t0 = time.perf_counter()
        try:
            if self._sim is None:
                self._sim = self._factory(self.backend)
            result = self._runner(spec, self._sim, **self._runner_kwargs)
        except Exception as e:
            detail = f"{type(e).__name__}: {e}\n{traceback.format_exc(limit=8)}"
            result = failed_result(spec, "error", detail, time.perf_counter() - t0)
            self._drop_simulator()
        self.episodes_run += 1
        return result

    def _drop_simulator(self) -> None:
        sim, self._sim = self._sim, None
        if sim is not None:
            # a broken engine may fail to close; the next one is what matters
            with contextlib.suppress(Exception):
                sim.close()

    def close(self) -> None:
        self._drop_simulator()


RemoteEpisodeWorker = ray.remote(EpisodeWorker)
