"""The workers' settings, importable without Ray: how episodes are run (`PoolSettings`, the
`execution` config node), where the workers run (`RaySettings`, the `ray` node) and how many
(`workers`, checked by `check_workers`). The config composes them; the pool and the Ray session
read them: each default is written here once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

AUTO = "auto"
DEFAULT_LOCAL_WORKERS = 2


@dataclass
class RaySettings:
    """Where the workers run (the `ray` config node)."""

    address: str | None = None  # None: start a local Ray; "auto" or host:port: join a cluster
    log_to_driver: bool = False  # worker stdout/stderr on the terminal (engines are chatty)


def check_workers(workers: Any) -> int | str | None:
    """`workers` as configured, checked: a count >= 1, `AUTO` or None; ValueError (one line)
    otherwise. A count given as text ("4", from a command line) becomes an int."""
    if workers is None:
        return None
    if isinstance(workers, str):
        text = workers.strip().lower()
        if text == AUTO:
            return AUTO
        if not text.isdigit():
            raise ValueError(f"workers must be a count >= 1 or auto, got {workers!r}")
        workers = int(text)
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a count >= 1 or auto, got {workers!r}")
    return workers


@dataclass
class PoolSettings:
    """How episodes are run (the `execution` config node)."""

    batch_size: int = 8  # episodes per Ray task: ~0.5 ms overhead vs ~100 ms per episode
    max_retries: int = 2  # a batch whose worker dies is retried this often, then split
    restart_timeout_s: float = 60.0  # a replacement worker not up by then is dropped
    # An episode still running after this is failed with `failure="timeout"` and its worker
    # carries on (episodes take ~0.1-0.3 s; quasi-static ones a few s): catches hangs only.
    episode_timeout_s: float = 120.0
