"""Recorded pushes driven on a simulator: the physics checked against reality.

Each push is replayed in its own scene, in the object frame at the log's first pose (the
object at the origin, yaw 0): the object's outline, mass, height and true CoM from the logs,
the pusher's radius, and one surface's friction (`Surface`). The pusher follows the recorded
path resampled at the timestep (`recorded_path`: the robot's ramps and any angle to the
normal included) or the idealised push, a straight line at the nominal speed from the
recorded start to the recorded end (`ideal_push`); either goes through the same push protocol
as every episode (`comexp.sim.protocol.push`). What is compared (`ReplayedPush`): the net turn
(unwrapped, recorded first pose to last; simulated to rest) and the final position of the
object frame's origin (the outline's area centroid).

A recorded start may overlap the outline by the recorded geometry's noise (a few tenths of a
millimetre, docs/real_robot.md): the protocol refuses to start a push inside the object, so
the whole path is moved out along the outline's normal until the pusher starts `START_GAP_M`
clear (`start_shift_mm` says by how much), at most `MAX_START_SHIFT_M`.

The friction of a surface is given (`Surface`), or fitted once for the surface on all its
pushes (`fit_surface`: planar, the reference model, over a grid of floor and pusher
friction), never per push. `summarise` puts the replay beside a do-nothing prediction (the
object stays where it was), so a reader sees what the model adds. `friction_floor` bounds
what any friction can do on this model: every push replayed on every pair of a grid, the
best pair for each figure, and each push with the pair that replays it best (figures no
friction for the whole surface can beat).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from comexp.method.frames import Pose2D
from comexp.real.logs import (
    PushContact,
    RecordedObject,
    RecordedPush,
    name_fields,
    nearest_on_outline,
    push_contact,
)
from comexp.sim.bodies import prism_object
from comexp.sim.contact import pusher_clearance_m
from comexp.sim.protocol import Frame, PushOutcome, push
from comexp.sim.scene import FloorSpec, PushCommand, PusherSpec, SceneSpec
from comexp.sim.simulator import Simulator

START_GAP_M = 1e-4  # where a recorded start that overlaps the outline is moved back to
MAX_START_SHIFT_M = 0.003  # the reader's bound on a recorded start's overlap (logs.py)
SIGN_MIN_TURN_DEG = 2.0  # turn signs and relative turn errors count pushes turning more
PATHS = ("recorded", "ideal")
# `fit_surface`'s grid: the floor's and the pusher's friction coefficient
FIT_MU_FLOOR = (0.1, 0.125, 0.15, 0.175, 0.2, 0.25, 0.3)
FIT_MU_PUSHER = (0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5)
# `friction_floor`'s grid: `fit_surface`'s, widened either way
FLOOR_MU_FLOOR = (*FIT_MU_FLOOR, 0.4, 0.5, 0.7)
FLOOR_MU_PUSHER = (0.05, *FIT_MU_PUSHER, 0.7, 1.0)


class ReplayError(ValueError):
    """A push or object that cannot be replayed: one line naming what is missing."""


@dataclass(frozen=True)
class Surface:
    """One surface's friction: the floor's (isotropic) and the pusher's on the objects.
    `fitted`: found by `fit_surface` on the surface's pushes, else given."""

    name: str
    mu_floor: float
    mu_pusher: float
    fitted: bool = False


@dataclass(frozen=True)
class ReplayedPush:
    """One push recorded and simulated, in the object frame at the log's first pose."""

    push: str
    object: str
    surface: str
    backend: str
    path: str  # "recorded" or "ideal"
    status: str  # the protocol's (`PushStatus`), "ok" when it ran through
    turn_recorded_deg: float
    turn_simulated_deg: float | None
    final_recorded_m: tuple[float, float]
    final_simulated_m: tuple[float, float] | None
    start_shift_mm: float
    speed_mm_s: float
    angle_to_normal_deg: float | None

    @property
    def position_error_mm(self) -> float | None:
        if self.final_simulated_m is None:
            return None
        d = np.subtract(self.final_simulated_m, self.final_recorded_m)
        return float(np.hypot(*d)) * 1000.0

    @property
    def stay_error_mm(self) -> float:
        """The do-nothing prediction's error: how far the object really went."""
        return float(np.hypot(*self.final_recorded_m)) * 1000.0

    @property
    def turn_error_deg(self) -> float | None:
        if self.turn_simulated_deg is None:
            return None
        return self.turn_simulated_deg - self.turn_recorded_deg

    def record(self) -> dict[str, object]:
        """The record `comexp-real replay` prints (mm, deg; 6 decimals)."""
        rec: dict[str, object] = {
            "push": self.push,
            "object": self.object,
            "surface": self.surface,
            "backend": self.backend,
            "path": self.path,
            "status": self.status,
            "speed_mm_s": self.speed_mm_s,
            "angle_to_normal_deg": self.angle_to_normal_deg,
            "turn_recorded_deg": self.turn_recorded_deg,
            "turn_simulated_deg": self.turn_simulated_deg,
            "turn_error_deg": self.turn_error_deg,
            "position_error_mm": self.position_error_mm,
            "stay_error_mm": self.stay_error_mm,
            "start_shift_mm": self.start_shift_mm,
        }
        return {k: round(v, 6) if isinstance(v, float) else v for k, v in rec.items()}


def surface_of(push: RecordedPush) -> str:
    """The surface a push was recorded on: its file name's `surface` field (the dataset's),
    else one surface for the folder."""
    return name_fields(push.path).get("surface") or "surface"


def _local(push: RecordedPush, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """World points in the object frame at the log's first pose."""
    c, s = math.cos(push.yaw_rad[0]), math.sin(push.yaw_rad[0])
    dx, dy = np.asarray(x) - push.x_m[0], np.asarray(y) - push.y_m[0]
    return np.column_stack([c * dx + s * dy, -s * dx + c * dy])


def recorded_path(push: RecordedPush, step_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The recorded pusher path in the object frame at the log's first pose: where it starts
    and where it is at the end of every step of `step_s` (linear between samples, held at its
    last sample) until the log ends."""
    t0 = float(push.pusher_t_s[0])
    t_end = max(float(push.pusher_t_s[-1]), float(push.t_s[-1]))
    n = max(1, int(math.floor((t_end - t0) / step_s + 1e-9)))
    t = t0 + step_s * np.arange(1, n + 1)
    x = np.interp(t, push.pusher_t_s, push.pusher_x_m)
    y = np.interp(t, push.pusher_t_s, push.pusher_y_m)
    start = _local(push, push.pusher_x_m[:1], push.pusher_y_m[:1])[0]
    return start, _local(push, x, y)


def ideal_push(push: RecordedPush, speed_m_s: float) -> PushCommand:
    """The idealised push: straight from the recorded start to the recorded end at the nominal
    speed (object frame at the log's first pose)."""
    ends = _local(push, push.pusher_x_m[[0, -1]], push.pusher_y_m[[0, -1]])
    d = ends[1] - ends[0]
    travel = float(np.hypot(*d))
    return PushCommand(tuple(ends[0]), tuple(d / travel), travel, speed_m_s)


def object_scene(obj: RecordedObject, surface: Surface) -> SceneSpec:
    """The scene of `obj` on `surface`, the object at the origin; ReplayError (one line) when
    something the physics needs is unknown."""
    missing = [
        key
        for key, value in (
            ("mass_kg", obj.mass_kg),
            ("height_m", obj.height_m),
            ("pusher_radius_m", obj.pusher_radius_m),
            ("true_com_m", obj.true_com_m),
        )
        if value is None
    ]
    if missing:
        raise ReplayError(
            f"{obj.name}: replay needs its {', '.join(missing)} ({obj.source}: give "
            f"{'them' if len(missing) > 1 else 'it'} in the object's parameters)"
        )
    body = prism_object(
        obj.name,
        obj.outline_m,
        obj.height_m,
        obj.true_com_m,
        mass_kg=obj.mass_kg,
        mu_pusher=surface.mu_pusher,
    )
    return SceneSpec(
        floor=FloorSpec(surface.mu_floor, surface.mu_floor),
        obj=body,
        pusher=PusherSpec(radius_m=obj.pusher_radius_m),
        initial_pose=Pose2D(0.0, 0.0, 0.0),
    )


def _clear_start(
    sim: Simulator, start: np.ndarray, path: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """The path moved out along the outline's normal nearest to its start when that start
    overlaps the outline (module docstring); the shift (m)."""
    state, outline, radius = sim.object_state(), sim.outline_m(), sim.pusher_radius_m()
    gap = pusher_clearance_m(start, state, outline, radius)
    if gap >= START_GAP_M:
        return start, path, 0.0
    _, inward = nearest_on_outline(outline, start)  # the object is at the origin, yaw 0
    shift = 0.0
    for _ in range(20):
        shift += START_GAP_M - gap
        gap = pusher_clearance_m(start - shift * inward, state, outline, radius)
        if gap >= START_GAP_M:
            break
    return start - shift * inward, path - shift * inward, shift


def replay_push(
    sim: Simulator,
    obj: RecordedObject,
    rec: RecordedPush,
    surface: Surface,
    path: str = "recorded",
    backend: str | None = None,
    offset_m: Sequence[float] = (0.0, 0.0),
) -> ReplayedPush:
    """Drive one recorded push on `sim` (module docstring) and compare. `offset_m` moves the
    pusher's whole path (object frame at the log's first pose): `geometry_spread`'s probe."""
    if path not in PATHS:
        raise ValueError(f"path must be one of {PATHS}, got {path!r}")
    pc = push_contact(rec, obj)
    speed = rec.speed_m_s if rec.speed_m_s is not None else pc.speed_m_s
    sim.build(object_scene(obj, surface))
    dt = sim.settings.timestep_s
    start, steps = recorded_path(rec, dt)
    start, steps = start + np.asarray(offset_m), steps + np.asarray(offset_m)
    start, steps, shift = _clear_start(sim, start, steps)
    if shift > MAX_START_SHIFT_M:
        raise ReplayError(f"{rec.path}: the pusher starts {shift * 1000:.1f} mm inside {obj.name}")
    if path == "recorded":
        cmd = PushCommand.along(tuple(start), steps, dt)
    else:
        ideal = ideal_push(rec, speed)
        cmd = PushCommand(tuple(start), ideal.direction_xy, ideal.travel_m, speed)
    outcome = push(sim, cmd)
    return _compare(rec, obj, surface, outcome, path, backend or sim.name, shift, speed, pc)


def _compare(
    rec: RecordedPush,
    obj: RecordedObject,
    surface: Surface,
    outcome: PushOutcome,
    path: str,
    backend: str,
    shift: float,
    speed: float,
    pc: PushContact,
) -> ReplayedPush:
    end = _local(rec, rec.x_m[-1:], rec.y_m[-1:])[0]
    ok = outcome.ok
    after = outcome.pose_after
    angle = pc.angle_to_normal_rad
    return ReplayedPush(
        push=rec.name,
        object=obj.name,
        surface=surface.name,
        backend=backend,
        path=path,
        status=outcome.status.value if not ok else "ok",
        turn_recorded_deg=math.degrees(float(rec.yaw_rad[-1] - rec.yaw_rad[0])),
        turn_simulated_deg=outcome.true_rotation_deg if ok else None,
        final_recorded_m=(float(end[0]), float(end[1])),
        final_simulated_m=(after.x_m, after.y_m) if ok else None,
        start_shift_mm=shift * 1000.0,
        speed_mm_s=speed * 1000.0,
        angle_to_normal_deg=None if angle is None else math.degrees(angle),
    )


def replay_all(
    sim: Simulator,
    objects: dict[str, RecordedObject],
    pushes: Sequence[RecordedPush],
    surfaces: dict[str, Surface],
    path: str = "recorded",
    backend: str | None = None,
    on_push: Callable[[ReplayedPush], None] | None = None,
) -> list[ReplayedPush]:
    """`replay_push` for every push, on its surface's friction."""
    out = []
    for rec in pushes:
        r = replay_push(
            sim, objects[rec.object_name], rec, surfaces[surface_of(rec)], path, backend
        )
        out.append(r)
        if on_push is not None:
            on_push(r)
    return out


@dataclass(frozen=True)
class GeometrySpread:
    """How far one push's replay moves when its recorded geometry is off by `amplitude_m`:
    the RMS over the pusher's path moved by +-amplitude along the contact normal and along
    the edge, against the replay as recorded (simulation against simulation)."""

    push: str
    amplitude_m: float
    position_mm: float
    turn_deg: float
    turn_recorded_deg: float


def geometry_spread(
    sim: Simulator,
    objects: dict[str, RecordedObject],
    pushes: Sequence[RecordedPush],
    surfaces: dict[str, Surface],
    amplitude_m: float,
) -> list[GeometrySpread]:
    """`GeometrySpread` of every push that moved the object: how much of a replay's error the
    recorded contact geometry's uncertainty (~1.5 mm, the dataset's README) can explain."""
    out = []
    for rec in pushes:
        obj, surface = objects[rec.object_name], surfaces[surface_of(rec)]
        pc = push_contact(rec, obj)
        if not pc.moved:
            continue
        n = np.asarray(pc.normal)
        base = replay_push(sim, obj, rec, surface)
        moved = [
            replay_push(sim, obj, rec, surface, offset_m=amplitude_m * d)
            for d in (n, -n, np.array([-n[1], n[0]]), np.array([n[1], -n[0]]))
        ]
        if base.final_simulated_m is None or any(m.final_simulated_m is None for m in moved):
            continue
        dp = [np.hypot(*np.subtract(m.final_simulated_m, base.final_simulated_m)) for m in moved]
        dt = [m.turn_simulated_deg - base.turn_simulated_deg for m in moved]
        out.append(
            GeometrySpread(
                rec.name,
                amplitude_m,
                float(np.sqrt(np.mean(np.square(dp)))) * 1000.0,
                float(np.sqrt(np.mean(np.square(dt)))),
                base.turn_recorded_deg,
            )
        )
    return out


def fit_loss(replayed: Sequence[ReplayedPush]) -> float:
    """What `fit_surface` minimises: the replay's figures each over its goal (docs/real_robot.md,
    "Replay"): median turn error / 10%, median position error / 2 mm, its 90th percentile /
    4 mm, plus one per wrong turn sign; a push the protocol failed counts as a wrong sign
    with the do-nothing prediction's errors."""
    s = summarise(replayed)
    stay = [r.stay_error_mm for r in replayed if r.position_error_mm is None]
    pos = [r.position_error_mm for r in replayed if r.position_error_mm is not None] + stay
    wrong = s.turning - s.sign_right + s.failed
    return float(
        s.turn_error_median_pct / 10.0 + np.median(pos) / 2.0 + np.percentile(pos, 90) / 4.0 + wrong
    )


def fit_surface(
    sim: Simulator,
    objects: dict[str, RecordedObject],
    pushes: Sequence[RecordedPush],
    name: str,
    path: str = "recorded",
    mu_floor: Sequence[float] = FIT_MU_FLOOR,
    mu_pusher: Sequence[float] = FIT_MU_PUSHER,
) -> tuple[Surface, float]:
    """The friction pair of the grid that replays the surface's pushes best (`fit_loss`), and
    its loss: one pair for all of them."""
    best: tuple[float, Surface] | None = None
    for mf in mu_floor:
        for mp in mu_pusher:
            surface = Surface(name, mf, mp, fitted=True)
            loss = fit_loss(replay_all(sim, objects, pushes, {name: surface}, path))
            if best is None or loss < best[0]:
                best = (loss, surface)
    assert best is not None
    return best[1], best[0]


@dataclass(frozen=True)
class FrictionFloor:
    """Every push replayed on every friction pair of a grid. `pairs`: each pair's `summarise`,
    one pair for all the pushes as a surface's friction is; the best of them for a figure is
    the floor of that figure for any surface's friction on this model (a uniform floor, the
    recorded geometry and CoM) over the grid's range. `position` and `turn`: each push with
    the pair that replays it best, by its final position and by its turn: no friction for the
    whole surface leaves a push closer than its best here, so `summarise` of either is a
    floor even for a friction chosen push by push."""

    pairs: dict[tuple[float, float], ReplaySummary]
    position: tuple[ReplayedPush, ...]
    turn: tuple[ReplayedPush, ...]

    def best_pair(self, figure: Callable[[ReplaySummary], float]) -> tuple[float, float]:
        """The grid's (floor, pusher) friction pair with the lowest `figure`."""
        return min(self.pairs, key=lambda pair: figure(self.pairs[pair]))


def friction_floor(
    sim: Simulator,
    objects: dict[str, RecordedObject],
    pushes: Sequence[RecordedPush],
    path: str = "recorded",
    mu_floor: Sequence[float] = FLOOR_MU_FLOOR,
    mu_pusher: Sequence[float] = FLOOR_MU_PUSHER,
    backend: str | None = None,
) -> FrictionFloor:
    """`FrictionFloor` of `pushes` over the grid `mu_floor` x `mu_pusher` (every push on every
    pair: the grid's size times a replay; a push no pair replays keeps its failed replay)."""
    names = {surface_of(p) for p in pushes}
    grid = {}
    for mf in mu_floor:
        for mp in mu_pusher:
            surfaces = {n: Surface(n, mf, mp) for n in names}
            grid[mf, mp] = replay_all(sim, objects, pushes, surfaces, path, backend)
    replays = list(grid.values())

    def best(i: int, error: Callable[[ReplayedPush], float | None]) -> ReplayedPush:
        ran = [g[i] for g in replays if error(g[i]) is not None]
        return min(ran, key=lambda r: abs(error(r) or 0.0)) if ran else replays[0][i]

    return FrictionFloor(
        {pair: summarise(g) for pair, g in grid.items()},
        tuple(best(i, lambda r: r.position_error_mm) for i in range(len(pushes))),
        tuple(best(i, lambda r: r.turn_error_deg) for i in range(len(pushes))),
    )


@dataclass(frozen=True)
class ReplaySummary:
    """The replay's figures against the do-nothing prediction's (the object stays)."""

    pushes: int
    failed: int
    turning: int  # pushes whose recorded turn exceeds SIGN_MIN_TURN_DEG
    sign_right: int
    turn_error_median_pct: float
    turn_error_median_deg: float
    position_error_median_mm: float
    position_error_p90_mm: float
    stay_turn_error_median_deg: float
    stay_position_error_median_mm: float
    stay_position_error_p90_mm: float

    def line(self) -> str:
        return (
            f"{self.pushes} pushes ({self.failed} failed): turn sign right on "
            f"{self.sign_right} of {self.turning} turning > {SIGN_MIN_TURN_DEG:g} deg, median "
            f"turn error {self.turn_error_median_pct:.1f}% of the recorded turn "
            f"({self.turn_error_median_deg:.2f} deg), final position error median "
            f"{self.position_error_median_mm:.2f} mm, p90 {self.position_error_p90_mm:.2f} mm; "
            f"the object stays: turn error {self.stay_turn_error_median_deg:.2f} deg, position "
            f"error median {self.stay_position_error_median_mm:.2f} mm, "
            f"p90 {self.stay_position_error_p90_mm:.2f} mm"
        )


def summarise(replayed: Sequence[ReplayedPush]) -> ReplaySummary:
    """Turn sign and relative turn error over the pushes turning more than
    `SIGN_MIN_TURN_DEG`; absolute turn and position errors over all pushes that ran (a failed
    push counts in `failed` only)."""
    ok = [r for r in replayed if r.turn_simulated_deg is not None]
    turning = [r for r in ok if abs(r.turn_recorded_deg) > SIGN_MIN_TURN_DEG]
    sign = sum(np.sign(r.turn_simulated_deg) == np.sign(r.turn_recorded_deg) for r in turning)
    rel = [abs(r.turn_error_deg) / abs(r.turn_recorded_deg) * 100.0 for r in turning]
    pos = [r.position_error_mm for r in ok]
    stay = [r.stay_error_mm for r in replayed]

    def med(v: Sequence[float]) -> float:
        return float(np.median(v)) if len(v) else math.nan

    def p90(v: Sequence[float]) -> float:
        return float(np.percentile(v, 90)) if len(v) else math.nan

    return ReplaySummary(
        pushes=len(replayed),
        failed=len(replayed) - len(ok),
        turning=len(turning),
        sign_right=int(sign),
        turn_error_median_pct=med(rel),
        turn_error_median_deg=med([abs(r.turn_error_deg) for r in ok]),
        position_error_median_mm=med(pos),
        position_error_p90_mm=p90(pos),
        stay_turn_error_median_deg=med([abs(r.turn_recorded_deg) for r in replayed]),
        stay_position_error_median_mm=med(stay),
        stay_position_error_p90_mm=p90(stay),
    )


# --- logs the project writes itself --------------------------------------------------------


def record_push(sim: Simulator, cmd: PushCommand) -> tuple[dict[str, list[float]], PushOutcome]:
    """Run `cmd` on `sim`'s built scene through the protocol and log it as a robot would:
    the plain layout's columns (`comexp.real.logs.PLAIN_COLUMNS`), a row at the push's start,
    at every protocol check while the object moves or the pusher drives, and one at rest
    after; the pusher's column is the commanded path. With `write_plain_push`, a log that
    `comexp-real` reads back (the round trip of tests/test_real_replay.py). A straight push
    only (`cmd.path_xy_m` None): its pusher column is computed from the command."""
    if cmd.path_xy_m is not None:
        raise ValueError("record_push logs a straight push (a PushCommand without a path)")
    dt = sim.settings.timestep_s
    start = np.asarray(cmd.start_xy_m, dtype=float)
    direction = np.asarray(cmd.direction_xy, dtype=float)
    drive_end_s = math.ceil(cmd.travel_m / (cmd.speed_m_s * dt) - 1e-9) * dt
    rows: list[tuple[float, Pose2D]] = [(0.0, sim.object_state().pose)]
    done = [False]

    def pusher_at(t: float) -> np.ndarray:
        return start + min(cmd.speed_m_s * t, cmd.travel_m) * direction

    def on_frame(frame: Frame) -> None:
        if not done[0]:
            rows.append((frame.t_s, sim.object_state().pose))

    def on_still(t_s: float) -> None:
        if done[0]:
            return
        rows.append((t_s, sim.object_state().pose))  # at rest: the pose is that of t_s
        done[0] = t_s > drive_end_s + 1e-9

    chunk = max(1, int(sim.check_every_steps))
    outcome = push(sim, cmd, on_frame=on_frame, frame_interval_s=chunk * dt, on_still=on_still)
    t_last = rows[-1][0] + chunk * dt
    rows.append((t_last, outcome.pose_after))
    cols: dict[str, list[float]] = {k: [] for k in ("t_s", "x_m", "y_m", "yaw_rad")}
    cols |= {"pusher_x_m": [], "pusher_y_m": []}
    for t, pose in rows:
        p = pusher_at(t)
        for k, v in zip(cols, (t, pose.x_m, pose.y_m, pose.yaw_rad, p[0], p[1]), strict=True):
            cols[k].append(float(v))
    return cols, outcome
