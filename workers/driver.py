"""The driver's loop: results from the pool handed to the store in chunks as they arrive, so an
interrupted job keeps what it finished, and the progress display (tqdm on a terminal, log lines
otherwise; `COMEXP_PROGRESS=bar` or `log` chooses)."""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from comexp.episode.task import EpisodeResult, EpisodeSpec

from .pool import EpisodePool

log = logging.getLogger("comexp.pool")


@dataclass
class RunStats:
    total: int
    done: int = 0
    failed: int = 0
    stored: int = 0
    wall_s: float = 0.0
    failures: collections.Counter[str] = field(default_factory=collections.Counter)
    first_failure: EpisodeResult | None = None  # the first failed result that came back


PROGRESS_ENV = "COMEXP_PROGRESS"


def _bar_wanted() -> bool:
    """`COMEXP_PROGRESS=bar` (`comexp.run` sets it: its caller's stderr is a notebook's, not
    the pipe the child sees) or `log`; otherwise a bar when stderr is a terminal."""
    choice = os.environ.get(PROGRESS_ENV, "").strip().lower()
    if choice in ("bar", "log"):
        return choice == "bar"
    return sys.stderr.isatty()


class Progress:
    """tqdm on a terminal; plain periodic log lines otherwise (log files, CI).
    `COMEXP_PROGRESS=bar` or `log` overrides the terminal test."""

    def __init__(self, total: int, desc: str = "", *, tty: bool | None = None, every_s=10.0):
        self.total = total
        self.desc = desc
        self.every_s = every_s
        self.t0 = time.monotonic()
        self._last = self.t0
        self._bar = None
        if tty if tty is not None else _bar_wanted():
            self._bar = tqdm(total=total, desc=desc, unit="ep", dynamic_ncols=True, smoothing=0.1)

    def update(self, n: int, stats: RunStats) -> None:
        if self._bar is not None:
            self._bar.update(n)
            self._bar.set_postfix(failed=stats.failed, refresh=False)
            return
        now = time.monotonic()
        if now - self._last >= self.every_s or stats.done == self.total:
            self._last = now
            log.info("%s", self.line(stats))

    def line(self, stats: RunStats) -> str:
        el = time.monotonic() - self.t0
        rate = stats.done / el if el > 0 else 0.0
        eta = (self.total - stats.done) / rate if rate > 0 else math.inf
        eta_s = "?" if math.isinf(eta) else time.strftime("%H:%M:%S", time.gmtime(eta))
        return (
            f"{self.desc} {stats.done}/{self.total} done, {stats.failed} failed, "
            f"{rate:.1f} ep/s, ETA {eta_s}"
        ).strip()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()

    def log_lines(self) -> contextlib.AbstractContextManager[None]:
        """While the bar is drawn, log lines are printed above it (tqdm's redirect of the
        console handlers), not over its line."""
        if self._bar is None:
            return contextlib.nullcontext()
        return logging_redirect_tqdm()


def run_and_store(
    pool: EpisodePool,
    specs: Sequence[EpisodeSpec],
    store: Callable[[list[EpisodeResult]], int],
    *,
    flush_every: int = 32,
    flush_interval_s: float = 2.0,
    progress: Progress | None = None,
) -> RunStats:
    """Run `specs` on the pool and hand results to `store` in chunks as they arrive.

    Whatever arrived is stored even when the run is interrupted (Ctrl-C, a pool error), so
    rerunning the same command resumes where this one stopped.
    """
    stats = RunStats(total=len(specs))
    pending: list[EpisodeResult] = []
    t0 = time.monotonic()
    last_flush = t0

    def flush() -> None:
        nonlocal pending, last_flush
        if pending:
            stats.stored += store(pending)
        pending = []
        last_flush = time.monotonic()

    def take(results: list[EpisodeResult]) -> None:
        pending.extend(results)
        stats.done += len(results)
        for r in results:
            if r.status != "ok":
                stats.failed += 1
                stats.failures[r.failure or "unknown"] += 1
                if stats.first_failure is None:
                    stats.first_failure = r
        if progress is not None:
            progress.update(len(results), stats)
        if len(pending) >= flush_every or time.monotonic() - last_flush >= flush_interval_s:
            flush()

    lines = progress.log_lines() if progress is not None else contextlib.nullcontext()
    try:
        with lines:
            for results in pool.run(specs):
                take(results)
    finally:
        try:
            flush()
        finally:
            stats.wall_s = time.monotonic() - t0
            if progress is not None:
                progress.close()
    return stats
