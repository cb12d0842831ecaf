"""Where an episode's time goes: a phase timer the episode loop reports to (`run_episode`'s
`timer`), the supported hook for benchmarks (bench/episode_profile.py), so that nothing needs
patching to be measured. The default, `NO_TIMER`, costs a shared no-op context per phase.

Phases (nested where one holds another): "build" (the scene built, the first image taken and
perceived), "choose" (Algorithm 1: the next contact), "push" (the push protocol, tracking
frames included), "track" (a tracking frame: pusher masked, boundary observed, pose fitted),
"measure" (after a push: re-centring, the image at rest, the pose fit), "estimate" (the
estimator takes the push: Algorithm 2, the path).
"""

from __future__ import annotations

import contextlib
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import AbstractContextManager as ContextManager
from typing import Protocol

PHASES = ("build", "choose", "push", "track", "measure", "estimate")


class Timer(Protocol):
    def phase(self, name: str) -> ContextManager[None]:
        """A context around one occurrence of phase `name`."""
        ...


class _NoTimer:
    """Times nothing: every phase is the same no-op context."""

    _null = contextlib.nullcontext()

    def phase(self, name: str) -> ContextManager[None]:
        return self._null


NO_TIMER: Timer = _NoTimer()


class PhaseTimer:
    """Wall time (`time.perf_counter`) and CPU time (`time.process_time`, robust to other load
    on a shared machine) per phase, summed over every occurrence, and the occurrences."""

    def __init__(self) -> None:
        self.wall_s: Counter[str] = Counter()
        self.cpu_s: Counter[str] = Counter()
        self.calls: Counter[str] = Counter()

    @contextlib.contextmanager
    def phase(self, name: str) -> Iterator[None]:
        w0, c0 = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            self.wall_s[name] += time.perf_counter() - w0
            self.cpu_s[name] += time.process_time() - c0
            self.calls[name] += 1
