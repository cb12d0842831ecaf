"""`comexp-real estimate --estimator fit`: the CoM that makes the physics reproduce what was
recorded.

The forward model is the replay (`comexp.real.replay`): each recorded push driven on planar, the
reference model, with the recorded pusher path. For a candidate CoM and a friction pair (the
pusher's friction on the object, the floor's), every push of the object is replayed and its
simulated net turn and final position are compared with the recorded ones; the loss is the
sum over the pushes of (position error / 1 mm)^2 + (turn error / 1 deg)^2, the size of the
recorded geometry's own effect on a replay (docs/real_robot.md, "What the replay shows"). A
push the protocol cannot finish with that CoM counts as `FAILED_LOSS`.

The search: every point of a `COARSE_M` grid over the outline's convex hull with the middle
friction pair; from the `STARTS` best of them, for every friction pair, a pattern search over
the CoM (8 neighbours, steps `STEPS_M`) down to the finest step. The friction pair is a
nuisance, fitted with the CoM and reported; the inertia is the uniform plate's about the
candidate CoM, and the mass cancels (friction and inertia both scale with it): an unknown mass
or height is taken as `DEFAULT_MASS_KG` / `DEFAULT_HEIGHT_M`. What it assumes: the floor
presses uniformly (the centre of pressure under the CoM, as planar's model does) and the same
way on every push, and one friction pair holds for all the object's pushes; where the real
floor does not (docs/real_robot.md, "What the replay shows"), the fitted CoM is the one that
best absorbs it. A fit whose every candidate fails every push is refused (ValueError).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from comexp.method.estimator import region_from_outline
from comexp.real.logs import RecordedObject, RecordedPush
from comexp.real.replay import ReplayError, Surface, replay_push
from comexp.sim.simulator import Simulator

COARSE_M = 0.01  # the first grid's spacing over the hull
STARTS = 3  # coarse points refined
STEPS_M = (0.005, 0.0025, 0.00125)  # the pattern search's steps
MU_PUSHER = (0.15, 0.25, 0.4)  # the pusher's friction: the nuisance grid
MU_FLOOR = 0.3  # the floor's: the replays barely depend on it (docs/real_robot.md)
POSITION_SCALE_MM = 1.0
TURN_SCALE_DEG = 1.0
FAILED_LOSS = 2500.0  # a push the protocol could not finish: (50 mm)^2
DEFAULT_MASS_KG = 1.0
DEFAULT_HEIGHT_M = 0.01
NEIGHBOURS = np.array([(1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1)])


@dataclass(frozen=True)
class FitResult:
    """The fitted CoM (object frame, m), the friction pair with it, its loss and how many
    candidate (CoM, friction) pairs were replayed."""

    com_m: np.ndarray
    mu_pusher: float
    mu_floor: float
    loss: float
    evaluations: int


def push_loss(sim: Simulator, obj: RecordedObject, push: RecordedPush, surface: Surface) -> float:
    """One push's share of the loss (module docstring)."""
    try:
        r = replay_push(sim, obj, push, surface)
    except ValueError:  # a CoM the model cannot stand (ReplayError, or beyond the support)
        return FAILED_LOSS
    if r.position_error_mm is None or r.turn_error_deg is None:
        return FAILED_LOSS
    return (r.position_error_mm / POSITION_SCALE_MM) ** 2 + (r.turn_error_deg / TURN_SCALE_DEG) ** 2


def _as_model(obj: RecordedObject) -> RecordedObject:
    """`obj` with what the replay needs and the fit does not depend on filled in."""
    if obj.pusher_radius_m is None:
        raise ReplayError(f"{obj.name}: the fit needs the pusher's radius (pusher_radius_m)")
    return dataclasses.replace(
        obj,
        mass_kg=obj.mass_kg or DEFAULT_MASS_KG,
        height_m=obj.height_m or DEFAULT_HEIGHT_M,
    )


def fit_com(
    sim: Simulator,
    obj: RecordedObject,
    pushes: Sequence[RecordedPush],
) -> FitResult:
    """The CoM and friction pair that replay `pushes` best (module docstring); `sim` is a
    planar simulator."""
    model = _as_model(obj)
    cache: dict[tuple[int, int, float], float] = {}

    def loss(com: np.ndarray, mu_pusher: float) -> float:
        key = (round(com[0] * 1e5), round(com[1] * 1e5), mu_pusher)
        if key not in cache:
            candidate = dataclasses.replace(model, true_com_m=np.asarray(com, dtype=float))
            surface = Surface("fit", MU_FLOOR, mu_pusher)
            cache[key] = sum(push_loss(sim, candidate, p, surface) for p in pushes)
        return cache[key]

    grid = region_from_outline(model.outline_m, COARSE_M)
    middle = MU_PUSHER[len(MU_PUSHER) // 2]
    coarse = sorted((loss(g, middle), i) for i, g in enumerate(grid))
    best: tuple[float, np.ndarray, float] | None = None
    for _, i in coarse[:STARTS]:
        for mu_pusher in MU_PUSHER:
            com, value = _pattern_search(grid[i], mu_pusher, loss)
            if best is None or value < best[0]:
                best = (value, com, mu_pusher)
    assert best is not None
    if best[0] >= FAILED_LOSS * len(pushes):
        raise ValueError(
            f"{obj.name}: the fit found no CoM with which planar could replay its pushes"
        )
    return FitResult(best[1], best[2], MU_FLOOR, best[0], len(cache))


def _pattern_search(
    start: np.ndarray, mu_pusher: float, loss: Callable[[np.ndarray, float], float]
) -> tuple[np.ndarray, float]:
    """Move to the best of the 8 neighbours while one is better, at each step of `STEPS_M`."""
    com, value = np.asarray(start, dtype=float), loss(start, mu_pusher)
    for step in STEPS_M:
        while True:
            trial = [(loss(com + step * d, mu_pusher), tuple(com + step * d)) for d in NEIGHBOURS]
            v, c = min(trial)
            if not v < value:
                break
            value, com = v, np.array(c)
    return com, value
