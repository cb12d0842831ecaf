"""The simulator's vocabulary: the scene a backend builds, the push it executes, the protocol's
settings and the object's true state (SI units; frames: `comexp.method.frames`).

Plain dataclasses every backend reads; the episode makes them from its task
(`comexp.episode.task.build_scene`), the protocol (`comexp.sim.protocol`) reads the state.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from comexp.method.frames import CameraSpec, Point2, Polygon2, Pose2D

GRAVITY_M_S2 = 9.81


class PushStatus(enum.StrEnum):
    """How a push ended (`comexp.sim.protocol.push`): ok, or the failure an episode reports."""

    OK = "ok"
    TIPPED = "tipped"
    LEFT_VIEW = "left_view"
    SIM_UNSTABLE = "sim_unstable"
    NOT_SETTLED = "not_settled"
    PATH_BLOCKED = "path_blocked"  # the pusher's start position overlaps the object


@dataclass(frozen=True)
class FloorSpec:
    """Square floor; Coulomb friction against the object is mu_x along world x, mu_y along y."""

    mu_x: float
    mu_y: float
    size_m: float = 0.6
    thickness_m: float = 0.02

    def __post_init__(self) -> None:
        if self.mu_x < 0 or self.mu_y < 0:
            raise ValueError(f"floor friction must be >= 0, got ({self.mu_x}, {self.mu_y})")
        if self.size_m <= 0:
            raise ValueError(f"floor size must be > 0, got {self.size_m}")

    @property
    def isotropic(self) -> bool:
        return self.mu_x == self.mu_y


@dataclass(frozen=True)
class ObjectSpec:
    """An extruded polygon ("prism") standing on the floor.

    `outline_m` is the footprint (counter-clockwise, object frame, origin at its area
    centroid). `convex_parts_m` are counter-clockwise convex polygons whose union is the
    outline: engines collide with convex shapes only. Inertia is about the CoM, in axes parallel
    to the object frame (off-diagonal terms are neglected: only planar motion matters).
    """

    name: str
    outline_m: Polygon2
    convex_parts_m: tuple[Polygon2, ...]
    height_m: float
    com_m: Point2
    mass_kg: float
    ixx_kg_m2: float
    iyy_kg_m2: float
    izz_kg_m2: float
    mu_pusher: float

    def __post_init__(self) -> None:
        if self.mass_kg <= 0 or self.height_m <= 0:
            raise ValueError(f"{self.name}: mass and height must be > 0")
        if min(self.ixx_kg_m2, self.iyy_kg_m2, self.izz_kg_m2) <= 0:
            raise ValueError(f"{self.name}: inertia must be > 0")
        a, b, c = self.ixx_kg_m2, self.iyy_kg_m2, self.izz_kg_m2
        tol = 1e-12
        if a + b < c - tol or a + c < b - tol or b + c < a - tol:
            raise ValueError(f"{self.name}: inertia violates the triangle inequality")
        if self.mu_pusher < 0:
            raise ValueError(f"{self.name}: pusher friction must be >= 0")
        if not self.convex_parts_m:
            raise ValueError(f"{self.name}: needs at least one convex part")


@dataclass(frozen=True)
class PusherSpec:
    """A vertical cylinder, position-controlled in the horizontal plane.

    Its bottom is `clearance_m` above the floor (it never touches the floor), so the only
    contact it makes is with the object's side.
    """

    radius_m: float = 0.005
    length_m: float = 0.06
    clearance_m: float = 0.002


def tilt_deg(roll_rad: float, pitch_rad: float) -> float:
    """Angle between a body's z axis and world z, from its roll and pitch (ZYX Euler)."""
    c = math.cos(roll_rad) * math.cos(pitch_rad)
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


class _ComputedOnce:
    """`functools.cached_property` without its lock: Python 3.11 takes one at the first read
    of every instance, and the protocol makes a new state, and reads its derived values, a
    thousand times an episode. The first read stores the value in the instance's __dict__,
    which then shadows this non-data descriptor. Only for immutable instances."""

    def __init__(self, fn: Callable) -> None:
        self.fn = fn
        self.name = fn.__name__
        self.__doc__ = fn.__doc__

    def __get__(self, obj: object, owner: type | None = None):
        if obj is None:
            return self
        value = obj.__dict__[self.name] = self.fn(obj)
        return value


@dataclass(frozen=True)
class ObjectState:
    """Full rigid-body state of the object frame, for evaluation, tests and failure checks."""

    position_m: tuple[float, float, float]
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    linear_velocity_m_s: tuple[float, float, float]
    angular_velocity_rad_s: tuple[float, float, float]

    @_ComputedOnce
    def pose(self) -> Pose2D:
        """The planar pose (asked several times per protocol check: built once)."""
        return Pose2D(self.position_m[0], self.position_m[1], self.yaw_rad)

    @_ComputedOnce
    def tilt_deg(self) -> float:
        """Angle between the object's z axis and world z."""
        return tilt_deg(self.roll_rad, self.pitch_rad)

    @_ComputedOnce
    def is_finite(self) -> bool:
        """Every coordinate finite (asked several times per protocol check: computed once)."""
        vals = (
            *self.position_m,
            self.roll_rad,
            self.pitch_rad,
            self.yaw_rad,
            *self.linear_velocity_m_s,
            *self.angular_velocity_rad_s,
        )
        return all(map(math.isfinite, vals))


@dataclass(frozen=True)
class SceneSpec:
    floor: FloorSpec
    obj: ObjectSpec
    pusher: PusherSpec = field(default_factory=PusherSpec)
    camera: CameraSpec = field(default_factory=CameraSpec)
    initial_pose: Pose2D = field(default_factory=lambda: Pose2D(0.0, 0.0, 0.0))


@dataclass(frozen=True)
class PushCommand:
    """A push: the pusher's axis starts at `start_xy_m` (world; must be clear of the object),
    moves along the unit vector `direction_xy` for `travel_m` at `speed_m_s`, stops, and the
    object is left to come to rest. A recorded push gives its path instead (`along`):
    `path_xy_m`, where the pusher is at the end of every step; `direction_xy` is then the
    chord's (the push line the pusher backs off along) and `speed_m_s` its mean speed."""

    start_xy_m: Point2
    direction_xy: Point2
    travel_m: float
    speed_m_s: float
    path_xy_m: tuple[Point2, ...] | None = None

    def __post_init__(self) -> None:
        if not self.speed_m_s > 0:
            raise ValueError(f"push speed must be > 0, got {self.speed_m_s}")
        if not self.travel_m > 0:
            raise ValueError(f"push travel must be > 0, got {self.travel_m}")
        n = math.hypot(*self.direction_xy)
        if abs(n - 1.0) > 1e-6:
            raise ValueError(f"push direction must be a unit vector, |d| = {n}")

    @classmethod
    def along(cls, start_xy_m: Point2, path_xy_m: Sequence[Point2], step_s: float) -> PushCommand:
        """The push that drives the pusher from `start_xy_m` through `path_xy_m`, one point at
        the end of each step of `step_s` (a recorded path, resampled at the timestep)."""
        path = tuple((float(x), float(y)) for x, y in path_xy_m)
        if not path:
            raise ValueError("a push path needs at least one point")
        dx, dy = path[-1][0] - start_xy_m[0], path[-1][1] - start_xy_m[1]
        travel = math.hypot(dx, dy)
        if not travel > 0:
            raise ValueError("a push path must end away from its start")
        start = (float(start_xy_m[0]), float(start_xy_m[1]))
        return cls(start, (dx / travel, dy / travel), travel, travel / (len(path) * step_s), path)


@dataclass(frozen=True)
class SimSettings:
    """The push protocol's settings, the same for every engine (`Simulator.push`).

    At rest: the object frame's floor point moves slower than `settle_speed_m_s` and it turns
    slower than `settle_spin_rad_s` at every check for `settle_hold_s`. Then the pusher backs
    off along the push line by `retract_m` at `retract_speed_m_s` and is parked once it is
    `clear_m` clear of the object.
    """

    timestep_s: float = 0.001
    settle_speed_m_s: float = 2e-3
    settle_spin_rad_s: float = 0.02
    settle_hold_s: float = 0.05
    max_settle_s: float = 5.0
    tip_limit_deg: float = 15.0
    retract_m: float = 0.006
    retract_speed_m_s: float = 0.1
    clear_m: float = 5e-4
