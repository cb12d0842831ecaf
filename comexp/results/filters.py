"""Episode selections (`EpisodeFilter`): the filters of `comexp-db` and of the reports, as
SQL clauses over the episodes table."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from comexp.results.schema import EPISODES

_FLOAT_TOL = 1e-9  # condition filters compare stored floats with this tolerance


@dataclass(frozen=True)
class EpisodeFilter:
    """Selection of episodes; None means "any". Floats match within 1e-9.

    `mu_floor` selects isotropic floors with mu_x = mu_y = mu_floor; anisotropic floors are
    selected by orientation with `mu_floor_x` / `mu_floor_y`.
    """

    backend: str | None = None
    floor: str | None = None
    speed_cm_s: float | None = None
    mu_floor: float | None = None
    mu_floor_x: float | None = None
    mu_floor_y: float | None = None
    mu_pusher: float | None = None
    izz_scale: float | None = None
    object: str | None = None
    com_index: int | None = None
    status: str | None = None
    failure: str | None = None
    sweep_id: int | None = None
    rotation_source: str | None = None

    def __post_init__(self) -> None:
        if self.status not in (None, "ok", "failed"):
            raise ValueError(f"status must be ok or failed, not {self.status!r}")
        for name in ("speed_cm_s", "mu_floor", "mu_floor_x", "mu_floor_y", "mu_pusher"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, not {v!r}")
        if self.mu_floor is not None and (
            self.mu_floor_x is not None or self.mu_floor_y is not None
        ):
            raise ValueError("give either mu_floor (isotropic) or mu_floor_x/mu_floor_y, not both")

    def describe(self) -> str:
        parts = [f"{f.name}={getattr(self, f.name)}" for f in dataclasses.fields(self)]
        return " ".join(p for p in parts if not p.endswith("=None")) or "(no filter)"

    def clauses(self) -> list[Any]:
        c = EPISODES.c
        out: list[Any] = []

        def near(col: Any, v: float) -> Any:
            return col.between(v - _FLOAT_TOL, v + _FLOAT_TOL)

        for name in ("backend", "floor", "object", "status", "failure", "rotation_source"):
            v = getattr(self, name)
            if v is not None:
                out.append(c[name] == v)
        for name in ("com_index", "sweep_id"):
            v = getattr(self, name)
            if v is not None:
                out.append(c[name] == int(v))
        for name in ("speed_cm_s", "mu_floor_x", "mu_floor_y", "mu_pusher", "izz_scale"):
            v = getattr(self, name)
            if v is not None:
                out.append(near(c[name], float(v)))
        if self.mu_floor is not None:
            out += [near(c.mu_floor_x, self.mu_floor), near(c.mu_floor_y, self.mu_floor)]
        return out
