"""One CoM estimation episode: scene + estimator settings + backend -> estimate and push records.

Everything an episode needs travels in `EpisodeSpec` (plain data, picklable for Ray): the
object's polygon is included so that workers never read config files.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from comexp.experiment.config import CameraConfig, EpisodeConfig
from comexp.experiment.objects import object_model
from comexp.experiment.simulator import Frame, Simulator, contact_push
from comexp.method.estimator import EstimatorSettings, floor_force_direction, make_estimator
from comexp.method.motion_estimator import PushPath
from comexp.method.perception import (
    PerceptionError,
    PoseTracker,
    mask_pusher,
    observe,
    observe_boundary,
    perceive_first,
)
from comexp.method.scene import FloorSpec, Pose2D, PusherSpec, SceneSpec, wrap_angle

__all__ = [
    "EpisodeResult",
    "EpisodeSpec",
    "EstimatorSettings",
    "PushRecord",
    "initial_yaw_rad",
    "run_episode",
]


# the protocol's defaults are the structured config's (one place: comexp.experiment.config)
_EPISODE_DEFAULTS = EpisodeConfig()
_CAMERA_DEFAULTS = CameraConfig()


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
    mass_kg: float = _EPISODE_DEFAULTS.mass_kg
    push_length_cm: float = _EPISODE_DEFAULTS.push_length_cm
    estimator: EstimatorSettings = field(default_factory=EstimatorSettings)
    seed: int = 0
    # Protocol: after a push that leaves the object's origin farther than this from the floor
    # centre, the object is put back at the centre (same yaw, at rest) before the next image, as
    # an experimenter would; 0 disables. A 40 cm/s push slides an object ~11 cm on the mu 0.1
    # floor, so without this about 15% of 5-push episodes there leave the 0.6 m floor.
    recenter_beyond_cm: float = _EPISODE_DEFAULTS.recenter_beyond_cm
    # What determines the physics (`comexp.experiment.simulator.physics_identity`: backend
    # model revision, engine version, backend and protocol settings); part of the episode's
    # identity, so a database is never resumed across physics versions. "" = not pinned.
    physics: str = ""
    # Tracking frames per second taken while the object moves during a push (`camera.fps`);
    # 0 = the images before and after each push only. Vision only (the oracle needs none).
    camera_fps: float = _CAMERA_DEFAULTS.fps  # `camera.fps`'s default (docs/method.md)

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


def needs_recentering(pose: Pose2D, recenter_beyond_cm: float) -> bool:
    """True when the object has drifted far enough that the next push could carry it out of the
    camera's view (see `EpisodeSpec.recenter_beyond_cm`)."""
    return recenter_beyond_cm > 0 and math.hypot(pose.x_m, pose.y_m) * 100.0 > recenter_beyond_cm


def _compose(a: Pose2D, b: Pose2D) -> Pose2D:
    """a o b: the pose b (given in a's frame) expressed in the world."""
    p = a.to_world(np.array([b.x_m, b.y_m]))
    return Pose2D(float(p[0]), float(p[1]), a.yaw_rad + b.yaw_rad)


def _relative(a: Pose2D, b: Pose2D) -> Pose2D:
    """a^-1 o b: the pose b expressed in a's frame."""
    p = a.to_object(np.array([b.x_m, b.y_m]))
    return Pose2D(float(p[0]), float(p[1]), b.yaw_rad - a.yaw_rad)


def _rotate(v: np.ndarray, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


def run_episode(spec: EpisodeSpec, sim: Simulator) -> EpisodeResult:
    """One CoM estimation: build, perceive, then n_push times choose a contact (Alg. 1), push,
    measure the rotation, update the region (Alg. 2). Never raises: failures are results.

    The estimator works in its own frame (the first image's world frame, origin at the hull
    centroid). The true initial pose is used only at the end, to express the estimate and the
    push records in the object's own frame for evaluation; the true pose during the episode
    only with `rotation_source=oracle`.
    """
    t0 = time.perf_counter()
    pushes: list[PushRecord] = []
    sim_time = 0.0

    def failed(reason: str, detail: str = "") -> EpisodeResult:
        return EpisodeResult(
            spec=spec,
            status="failed",
            failure=reason,
            est_com_cm=None,
            error_cm=None,
            n_pushes=len(pushes),
            pushes=tuple(pushes),
            wall_s=time.perf_counter() - t0,
            sim_time_s=sim_time,
            detail=detail,
        )

    try:
        settings = spec.estimator
        scene = build_scene(spec)
        sim.build(scene)
        true0 = sim.true_pose()
        perc, obs0 = perceive_first(sim.render_depth(), settings.contact_spacing_px)
        frame0 = perc.frame_pose  # estimator frame in the world at the first image
        # estimator frame -> true object frame (evaluation only)
        frame_in_obj = _relative(true0, frame0)
        est = make_estimator(
            perc.region_m,
            perc.contacts_m,
            perc.contact_normals,
            perc.pixel_m,
            settings,
            outline_m=perc.outline_m,
            pusher_radius_m=scene.pusher.radius_m,
        )
        tracker = PoseTracker(perc, obs0) if settings.rotation_source == "vision" else None
        frame = frame0  # current estimate of the estimator frame's pose in the world
        true_prev = true0
        speed_m_s = spec.speed_cm_s / 100.0
        details: list[str] = []
        path: list[tuple[float, Pose2D]] = []  # (t_s, pose) per tracked frame of a push (motion)
        for k in range(settings.n_push):
            choice = est.next_push()
            if choice is None:
                if k == 0:
                    return failed("no_valid_contact", "no reachable push line cuts the region")
                details.append(f"stopped after {k} pushes: no valid contact")
                break
            P, N = choice
            cmd = contact_push(
                frame.to_world(P),
                _rotate(N, frame.yaw_rad),
                spec.push_length_cm / 100.0,
                speed_m_s,
                scene.pusher.radius_m,
            )
            used = 0
            path.clear()
            if tracker is not None and spec.camera_fps > 0:
                tracker.begin_push()

                def on_frame(f: Frame) -> None:
                    nonlocal used
                    img = mask_pusher(f.image, f.pusher_xy_m, f.pusher_radius_m)
                    last = tracker.last
                    try:
                        view = observe_boundary(img, (last.x_m, last.y_m))
                    except PerceptionError:
                        return  # a frame that shows no object is not used
                    tracker.track(view, f.t_s)
                    path.append((f.t_s, tracker.last))
                    used += 1

                out = sim.push(
                    cmd,
                    on_frame=on_frame,
                    frame_interval_s=1.0 / spec.camera_fps,
                    on_still=tracker.hold,
                    frame_wanted=lambda t_s, driving: tracker.wants_frame(
                        t_s, driving, settings.track_step_deg, settings.track_gap_s
                    ),
                )
            else:
                out = sim.push(cmd)
            sim_time += out.sim_time_s
            if not out.ok:
                return failed(out.status.value, f"push {k}: {out.status.value}")
            if not out.contact_made:
                details.append(f"push {k}: pusher missed the object")
            true_now = sim.true_pose()
            rot_true = out.true_rotation_deg
            if rot_true is None:  # a simulator that does not track it: wrapped
                rot_true = math.degrees(wrap_angle(true_now.yaw_rad - true_prev.yaw_rad))
            if needs_recentering(true_now, spec.recenter_beyond_cm):
                sim.build(replace(scene, initial_pose=Pose2D(0.0, 0.0, true_now.yaw_rad)))
                # Placement keeps the yaw, so it adds no rotation; the next image (vision) or the
                # placed true pose (oracle) carries the estimator frame along.
                true_now = sim.true_pose()
                details.append(f"re-centred after push {k}")
            if tracker is not None:
                new_frame = tracker.fit(observe(sim.render_depth())).pose
                # the tracker's yaw is unwrapped: through frames it may turn beyond half a turn
                turn = new_frame.yaw_rad - frame.yaw_rad
                rot = math.degrees(turn if used else wrap_angle(turn))
            else:  # oracle: carry the frame with the true rigid motion
                new_frame = _compose(true_now, _relative(true_prev, frame))
                rot = rot_true
            line = None
            if settings.method == "magnitude" and settings.mag_floor_model:
                # the robot knows its floor and pusher; the yaw is the estimator's own (vision)
                line = floor_force_direction(
                    N, frame.yaw_rad, spec.mu_floor_x, spec.mu_floor_y, spec.mu_pusher
                )
            # --- estimators that use the path of the push (`observe_path`, e.g. motion) ---
            observe_path = getattr(est, "observe_path", None)
            if observe_path is not None:
                observe_path(
                    PushPath(
                        pose_before=frame,
                        t_s=tuple(t for t, _ in path),
                        poses=tuple(p for _, p in path),
                        pose_after=new_frame,
                        t_contact_s=float(np.hypot(*(frame.to_world(P) - cmd.start_xy_m)))
                        / speed_m_s
                        - scene.pusher.radius_m / speed_m_s,
                        speed_m_s=speed_m_s,
                        rotation_deg=rot,
                    )
                )
            # ---
            decision = est.observe(P, N, rot, line)
            frame, true_prev = new_frame, true_now
            c_obj = frame_in_obj.to_world(P)
            d_obj = _rotate(N, frame_in_obj.yaw_rad)
            pushes.append(
                PushRecord(
                    k=k,
                    contact_x_cm=float(c_obj[0] * 100.0),
                    contact_y_cm=float(c_obj[1] * 100.0),
                    dir_x=float(d_obj[0]),
                    dir_y=float(d_obj[1]),
                    rotation_deg=rot,
                    rotation_true_deg=rot_true,
                    decision=decision,
                    region_px=est.region_px,
                    n_frames=used,
                )
            )
        est_obj = frame_in_obj.to_world(est.estimate_m) * 100.0
        err = math.hypot(est_obj[0] - spec.com_cm[0], est_obj[1] - spec.com_cm[1])
        return EpisodeResult(
            spec=spec,
            status="ok",
            failure=None,
            est_com_cm=(float(est_obj[0]), float(est_obj[1])),
            error_cm=float(err),
            n_pushes=len(pushes),
            pushes=tuple(pushes),
            wall_s=time.perf_counter() - t0,
            sim_time_s=sim_time,
            detail="; ".join(details),
        )
    except PerceptionError as exc:
        return failed(exc.failure, str(exc))
    except Exception as exc:  # noqa: BLE001 - a sweep must survive any single episode
        return failed("error", f"{type(exc).__name__}: {exc}")
