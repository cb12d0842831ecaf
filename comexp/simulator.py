"""The one simulator interface that perception, the estimator and the workers use.

A backend builds a scene from engine-independent dataclasses (`comexp.scene`), renders the
top-down depth image, executes straight pushes and lets the object come to rest. The true
object state is for evaluation, tests and failure detection only; the estimator never reads it
unless `rotation_source=oracle` is asked for.
"""

from __future__ import annotations

import enum
import importlib
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from comexp.scene import (
    CameraModel,
    DepthImage,
    ObjectState,
    Pose2D,
    PushCommand,
    SceneSpec,
    SimSettings,
)

BACKENDS: dict[str, str] = {
    "pybullet": "comexp.backends.pybullet_sim:PybulletSimulator",
    "mujoco": "comexp.backends.mujoco_sim:MujocoSimulator",
}


class PushStatus(enum.StrEnum):
    OK = "ok"
    TIPPED = "tipped"
    LEFT_VIEW = "left_view"
    SIM_UNSTABLE = "sim_unstable"
    NOT_SETTLED = "not_settled"
    PATH_BLOCKED = "path_blocked"  # the pusher's start position overlaps the object


@dataclass(frozen=True)
class PushOutcome:
    status: PushStatus
    pose_before: Pose2D
    pose_after: Pose2D
    sim_time_s: float
    steps: int
    contact_made: bool
    max_pusher_lag_m: float  # worst |actual - commanded| pusher position during the push
    max_tilt_deg: float

    @property
    def ok(self) -> bool:
        return self.status is PushStatus.OK

    @property
    def rotation_deg(self) -> float:
        """True CCW rotation of the object during the push, wrapped to (-180, 180]."""
        return math.degrees(wrap_angle(self.pose_after.yaw_rad - self.pose_before.yaw_rad))


def wrap_angle(a: float) -> float:
    return math.atan2(math.sin(a), math.cos(a))


def classify_state(
    state: ObjectState,
    outline_m: np.ndarray,
    camera: CameraModel,
    settings: SimSettings,
) -> PushStatus | None:
    """Failure check shared by both backends; None when the state is healthy.

    Order matters: a non-finite state makes the other checks meaningless, and a tipped object
    is reported as tipped even if it then also leaves the view.
    """
    if not state.is_finite:
        return PushStatus.SIM_UNSTABLE
    if state.tilt_deg > settings.tip_limit_deg:
        return PushStatus.TIPPED
    corners = state.pose.to_world(outline_m)
    uv = camera.world_to_pixel(corners[:, 0], corners[:, 1], 0.0)
    inside = (
        (uv[:, 0] >= 0)
        & (uv[:, 0] <= camera.width_px - 1)
        & (uv[:, 1] >= 0)
        & (uv[:, 1] <= camera.height_px - 1)
    )
    if not bool(np.all(inside)):
        return PushStatus.LEFT_VIEW
    return None


class Simulator(ABC):
    """One engine instance; `build` may be called many times (scene reuse is the backend's job)."""

    name: str = ""

    def __init__(self, settings: SimSettings | None = None) -> None:
        self.settings = settings or SimSettings()

    @abstractmethod
    def build(self, scene: SceneSpec) -> None:
        """(Re)create floor, object at `scene.initial_pose` resting on the floor, the pusher
        parked out of the camera's view, and the camera."""

    @abstractmethod
    def render_depth(self) -> DepthImage:
        """Top-down metric depth image of the current scene (pusher parked, out of view)."""

    @abstractmethod
    def push(self, cmd: PushCommand) -> PushOutcome:
        """Execute the push, let the object come to rest, park the pusher, report."""

    @abstractmethod
    def object_state(self) -> ObjectState:
        """True state of the object frame: evaluation and tests only."""

    def true_pose(self) -> Pose2D:
        return self.object_state().pose

    # --- test hooks: used by physics validation, never by the estimator ---------------------
    @abstractmethod
    def set_object_velocity(
        self, linear_m_s: tuple[float, float, float], angular_rad_s: tuple[float, float, float]
    ) -> None:
        """Overwrite the object's velocity (world frame)."""

    @abstractmethod
    def step(self, duration_s: float) -> None:
        """Advance the simulation by `duration_s` (rounded to whole steps), pusher held still."""

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release engine resources."""

    def __enter__(self) -> Simulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def backend_names() -> list[str]:
    return sorted(BACKENDS)


def make_simulator(name: str, settings: SimSettings | None = None) -> Simulator:
    """Create a backend by name (`pybullet` or `mujoco`); engines are imported lazily."""
    try:
        target = BACKENDS[name]
    except KeyError:
        raise ValueError(f"unknown backend {name!r}; choose one of {backend_names()}") from None
    module_name, cls_name = target.split(":")
    cls = getattr(importlib.import_module(module_name), cls_name)
    return cls(settings)


def contact_push(
    contact_xy_m: tuple[float, float] | np.ndarray,
    inward_normal_xy: tuple[float, float] | np.ndarray,
    push_length_m: float,
    speed_m_s: float,
    pusher_radius_m: float,
    approach_gap_m: float = 0.01,
) -> PushCommand:
    """The push that drives the pusher's surface `push_length_m` past a contact point along
    the inward normal, starting `approach_gap_m` clear of it (world frame)."""
    n = np.asarray(inward_normal_xy, dtype=float)
    n = n / np.linalg.norm(n)
    c = np.asarray(contact_xy_m, dtype=float)
    start = c - n * (pusher_radius_m + approach_gap_m)
    return PushCommand(
        start_xy_m=(float(start[0]), float(start[1])),
        direction_xy=(float(n[0]), float(n[1])),
        travel_m=approach_gap_m + push_length_m,
        speed_m_s=speed_m_s,
    )
