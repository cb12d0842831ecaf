"""The task of an episode: what is pushed (scene, push commands) and what is scored (results).

An episode is a task run by a loop (`comexp.episode.loop.run_episode`), kept apart as
dm_control keeps its Task apart from its Physics. Everything an episode needs travels in
`EpisodeSpec` (plain data, picklable for Ray): the object's polygon is included so that workers
never read config files. What is pushed: the scene an `EpisodeSpec` describes (`build_scene`)
and the push through a chosen contact (`push_command`). What is scored: the estimate and the
pushes in the object's own frame (`Scoring`), or the failure (`failed_result`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from comexp.method.estimator import EstimatorSettings
from comexp.method.frames import Pose2D
from comexp.sim.bodies import prism_object
from comexp.sim.contact import contact_push
from comexp.sim.scene import FloorSpec, ObjectSpec, PushCommand, PusherSpec, SceneSpec


@dataclass
class EpisodeSettings:
    """The push protocol of every episode (the `episode` config node; docs/method.md,
    "Episode runner"): the one place its defaults are written."""

    push_length_cm: float = field(
        default=3.0, metadata={"help": "how far the pusher goes past the contact (paper: 3 cm)"}
    )
    recenter_beyond_cm: float = field(
        default=10.0,
        metadata={"help": "put the object back at the floor's centre beyond this; 0: never"},
    )
    mass_kg: float = field(default=0.2, metadata={"help": "the object's mass (paper: 0.2 kg)"})


@dataclass
class CameraSettings:
    """The depth camera (the `camera` config node). `fps`: tracking frames per second while
    the object moves during a push, so that the rotation is followed frame to frame
    (unwrapped); 0 = the images before and after each push only. The default is the lowest
    measured rate that unwraps every rotation of the study (docs/method.md, "Tracking during
    the push")."""

    fps: float = field(
        default=30.0,
        metadata={"help": "tracking frames per second during a push; 0: before and after only"},
    )
    renderer: str = field(
        default="raycast",
        metadata={
            "help": "engines' depth images: raycast (the exact ray cast of the prism, planar's "
            "camera) | engine (the engine's own renderer)"
        },
    )


@dataclass(frozen=True)
class EpisodeSpec:
    backend: str
    floor: str  # iso | aniso (the config group name, for the database)
    mu_floor_x: float
    mu_floor_y: float
    mu_pusher: float
    speed_cm_s: float
    izz_scale: float
    object: str
    outline_cm: tuple[tuple[float, float], ...]  # footprint, object frame (origin at its centroid)
    height_cm: float
    com_index: int
    com_cm: tuple[float, float]  # true CoM, object frame
    mass_kg: float = EpisodeSettings.mass_kg
    push_length_cm: float = EpisodeSettings.push_length_cm
    estimator: EstimatorSettings = field(default_factory=EstimatorSettings)
    seed: int = 0
    # Protocol: after a push that leaves the object's origin farther than this from the floor
    # centre, the object is put back at the centre (same yaw, at rest) before the next image, as
    # an experimenter would; 0 disables. A 40 cm/s push slides an object ~11 cm on the mu 0.1
    # floor, so without this about 15% of 5-push episodes there leave the 0.6 m floor.
    recenter_beyond_cm: float = EpisodeSettings.recenter_beyond_cm
    # What determines the physics (`comexp.experiment.registry.physics_identity`: backend
    # model revision, engine version, backend and protocol settings); part of the episode's
    # identity, so a database is never resumed across physics versions. "" = not pinned.
    physics: str = ""
    # Tracking frames per second taken while the object moves during a push (`camera.fps`);
    # 0 = the images before and after each push only. Vision only (the oracle needs none).
    camera_fps: float = CameraSettings.fps  # `camera.fps`'s default (docs/method.md)

    @classmethod
    def for_object(
        cls, obj: Any, com_index: int, com_cm: Sequence[float], **conditions: Any
    ) -> EpisodeSpec:
        """The episode of CoM `com_index` (at `com_cm`) of an object definition (anything with
        `name`, `outline_cm`, `height_cm`, e.g. `comexp.experiment.objects.ObjectDef`);
        `conditions` are the remaining fields (backend, floor, frictions, speed, Izz, ...)."""
        return cls(
            object=obj.name,
            outline_cm=tuple((float(x), float(y)) for x, y in obj.outline_cm),
            height_cm=float(obj.height_cm),
            com_index=com_index,
            com_cm=(float(com_cm[0]), float(com_cm[1])),
            **conditions,
        )


@dataclass(frozen=True)
class PushRecord:
    k: int
    contact_x_cm: float  # object frame, at the time of the push
    contact_y_cm: float
    dir_x: float  # unit push direction, object frame
    dir_y: float
    rotation_deg: float  # measured (vision or oracle)
    rotation_true_deg: float
    # ccw | cw | band; ccw-empty | cw-empty | band-empty when that update would have left no
    # point, so the region was kept (`comexp.method.estimator.update_region`)
    decision: str
    region_px: int  # region size after the update
    n_frames: int = 0  # tracking frames the rotation was measured through (0: before/after)
    # the convex hull of the region the estimator kept after the update (object frame, cm;
    # `comexp-db show` draws it); None from an estimator that does not show its region
    region_cm: tuple[tuple[float, float], ...] | None = None


@dataclass(frozen=True)
class EpisodeResult:
    spec: EpisodeSpec
    status: str  # ok | failed
    # failed: tipped, left_view, sim_unstable, not_settled, path_blocked (pusher start inside
    # the object), no_valid_contact, perception, timeout, worker_died, physics_mismatch, error
    failure: str | None
    est_com_cm: tuple[float, float] | None
    error_cm: float | None
    n_pushes: int
    pushes: tuple[PushRecord, ...]
    wall_s: float
    sim_time_s: float = 0.0
    detail: str = ""
    worker: str = ""  # which worker ran it ("node_ip:pid"), set by the Ray actor


def initial_yaw_rad(seed: int) -> float:
    """The object's initial yaw for an episode: uniform in [-pi, pi), a function of the seed."""
    return float(np.random.default_rng([seed, 0x5EED]).uniform(-math.pi, math.pi))


def object_model(
    name: str,
    outline_cm: Sequence[Sequence[float]],
    height_cm: float,
    com_cm: Sequence[float],
    *,
    izz_scale: float,
    mu_pusher: float,
    mass_kg: float,
) -> ObjectSpec:
    """The simulator's rigid-body model (SI units) of an object definition (cm) with its CoM at
    `com_cm`: the one conversion, used by every episode (`build_scene`)."""
    return prism_object(
        name,
        [(x / 100.0, y / 100.0) for x, y in outline_cm],
        height_cm / 100.0,
        (com_cm[0] / 100.0, com_cm[1] / 100.0),
        mass_kg=mass_kg,
        izz_scale=izz_scale,
        mu_pusher=mu_pusher,
    )


def build_scene(spec: EpisodeSpec, pusher: PusherSpec | None = None) -> SceneSpec:
    """The simulator scene of an episode (centimetres -> metres), object at the floor centre."""
    obj = object_model(
        spec.object,
        spec.outline_cm,
        spec.height_cm,
        spec.com_cm,
        izz_scale=spec.izz_scale,
        mu_pusher=spec.mu_pusher,
        mass_kg=spec.mass_kg,
    )
    return SceneSpec(
        floor=FloorSpec(spec.mu_floor_x, spec.mu_floor_y),
        obj=obj,
        pusher=pusher or PusherSpec(),
        initial_pose=Pose2D(0.0, 0.0, initial_yaw_rad(spec.seed)),
    )


def _rotate(v: np.ndarray, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


def push_command(
    spec: EpisodeSpec, frame: Pose2D, contact_m: np.ndarray, normal: np.ndarray, radius_m: float
) -> PushCommand:
    """The push through contact `contact_m` along the inward `normal` (both in the estimator's
    frame, whose pose in the world is `frame`), the spec's length and speed."""
    return contact_push(
        frame.to_world(contact_m),
        _rotate(normal, frame.yaw_rad),
        spec.push_length_cm / 100.0,
        spec.speed_cm_s / 100.0,
        radius_m,
    )


@dataclass(frozen=True)
class Scoring:
    """What is scored, in the object's own frame: the estimator works in its own frame (the
    first image's world frame, origin at the hull centroid); `frame_in_obj` is that frame in
    the true object frame at the first image (`at_first_image`: evaluation only)."""

    spec: EpisodeSpec
    frame_in_obj: Pose2D

    @classmethod
    def at_first_image(cls, spec: EpisodeSpec, true0: Pose2D, frame0: Pose2D) -> Scoring:
        """`true0`: the object's true pose, `frame0`: the estimator frame's, at the first image."""
        return cls(spec, true0.relative(frame0))

    def record(
        self,
        k: int,
        contact_m: np.ndarray,
        normal: np.ndarray,
        rotation_deg: float,
        rotation_true_deg: float,
        decision: str,
        region_px: int,
        n_frames: int,
        region_m: np.ndarray | None = None,
    ) -> PushRecord:
        """Push `k` (contact and normal in the estimator frame) as the database stores it;
        `region_m`: the points the estimator kept (its frame), stored as their hull."""
        c_obj = self.frame_in_obj.to_world(contact_m)
        d_obj = _rotate(normal, self.frame_in_obj.yaw_rad)
        return PushRecord(
            k=k,
            contact_x_cm=float(c_obj[0] * 100.0),
            contact_y_cm=float(c_obj[1] * 100.0),
            dir_x=float(d_obj[0]),
            dir_y=float(d_obj[1]),
            rotation_deg=rotation_deg,
            rotation_true_deg=rotation_true_deg,
            decision=decision,
            region_px=region_px,
            n_frames=n_frames,
            region_cm=None if region_m is None else self._hull_cm(region_m),
        )

    def _hull_cm(self, region_m: np.ndarray) -> tuple[tuple[float, float], ...]:
        """The convex hull of region points (estimator frame, m) in the object frame, cm,
        rounded to 1 um (a few vertices for hundreds of points)."""
        pts = np.asarray(region_m, dtype=np.float64).reshape(-1, 2)
        if len(pts) > 2:
            hull = cv2.convexHull(pts.astype(np.float32), returnPoints=False).ravel()
            pts = pts[np.sort(hull)]
        obj = self.frame_in_obj.to_world(pts) * 100.0
        return tuple((round(float(x), 4), round(float(y), 4)) for x, y in obj)

    def result(
        self,
        estimate_m: np.ndarray,
        pushes: Sequence[PushRecord],
        wall_s: float,
        sim_time_s: float,
        detail: str,
    ) -> EpisodeResult:
        """The episode's result: the estimate (estimator frame) and its error in cm."""
        spec = self.spec
        est_obj = self.frame_in_obj.to_world(estimate_m) * 100.0
        err = math.hypot(est_obj[0] - spec.com_cm[0], est_obj[1] - spec.com_cm[1])
        return EpisodeResult(
            spec=spec,
            status="ok",
            failure=None,
            est_com_cm=(float(est_obj[0]), float(est_obj[1])),
            error_cm=float(err),
            n_pushes=len(pushes),
            pushes=tuple(pushes),
            wall_s=wall_s,
            sim_time_s=sim_time_s,
            detail=detail,
        )


def failed_result(
    spec: EpisodeSpec,
    reason: str,
    detail: str,
    pushes: Sequence[PushRecord],
    wall_s: float,
    sim_time_s: float,
) -> EpisodeResult:
    """A failed episode (`EpisodeResult.failure` lists the reasons), with the pushes so far."""
    return EpisodeResult(
        spec=spec,
        status="failed",
        failure=reason,
        est_com_cm=None,
        error_cm=None,
        n_pushes=len(pushes),
        pushes=tuple(pushes),
        wall_s=wall_s,
        sim_time_s=sim_time_s,
        detail=detail,
    )
