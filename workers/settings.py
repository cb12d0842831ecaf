"""The workers' settings, importable without Ray: how episodes are run (`PoolSettings`, the
`execution` config node), where the workers run (`RaySettings`, the `ray` node) and how many
(`workers`, checked by `check_workers`). The config composes them; the pool and the Ray session
read them: each default is written here once.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

AUTO = "auto"
LOCAL = "local"  # `ray.address=local`: a local Ray of the job's own, never the kept one
DEFAULT_LOCAL_WORKERS = 2


@dataclass
class RaySettings:
    """Where the workers run (the `ray` config node)."""

    address: str | None = field(
        default=None,
        metadata={
            "help": "null: the kept Ray (comexp-ray start) if one runs, else a local Ray of "
            "the job's own; local: always one of its own; auto or HOST:PORT: join that cluster"
        },
    )
    log_to_driver: bool = field(
        default=False, metadata={"help": "workers' stdout/stderr on the terminal (chatty)"}
    )


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

    batch_size: int = field(
        default=8, metadata={"help": "episodes per Ray task (a dying worker costs one batch)"}
    )
    max_retries: int = field(
        default=2, metadata={"help": "a batch whose worker dies is retried this often, then split"}
    )
    restart_timeout_s: float = field(
        default=60.0, metadata={"help": "a replacement worker not up by then is dropped (s)"}
    )
    # episodes take ~0.1-0.3 s, quasi-static ones a few s: the limit catches hangs only
    episode_timeout_s: float = field(
        default=120.0,
        metadata={"help": "an episode still running after this (s) fails with timeout"},
    )
