"""Every object's CoM from its recorded pushes, with any estimator: the paper's
(`estimate_com_world`), `magnitude` (the same with `EstimatorSettings(method="magnitude")`),
`motion` (`estimate_com_motion`, which also reads the tracked path), `fit` (the CoM whose
replays on planar reproduce the pushes: `comexp.real.fit`, the referee as its model) or a plug-in
`module:Class` (the `Estimator` protocol of `comexp.method.estimator`, fed the observed pushes).

Each push gives (`comexp.real.logs.push_contact`): the contact where the object first moves
(the pusher's axis then, projected onto the outline), the push direction (the pusher's
direction of travel then), the unwrapped net turn and the tracked path. A push that never
moved the object says nothing of its CoM (the pusher slid along it) and is left out; so are
pushes farther from the contact normal than `max_angle_deg`, when it is given.

Why a region for every estimator: the paper's Algorithm 2 region, computed from the same
pushes, says whether the pushes' turn signs alone are consistent with the true CoM (a wrong
sign cuts it away), whatever estimator gave the estimate.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from comexp.method.estimator import (
    METHODS,
    EstimatorSettings,
    WorldPush,
    estimate_com_world,
    is_plugin,
    outline_contacts,
    region_from_outline,
)
from comexp.method.estimators import make_estimator
from comexp.method.frames import Pose2D
from comexp.method.motion_estimator import MotionPush, estimate_com_motion
from comexp.real.fit import fit_com
from comexp.real.logs import PushContact, RecordedObject, RecordedPush, RecordedPushes, push_contact
from comexp.sim.simulator import Simulator

# The grid spacing of the CoM region (the paper's pixel): 1 mm, finer than the recorded
# geometry's ~1.5 mm uncertainty. It also sets the paper's band (C_bw_px = 10 pixels = 1 cm).
DEFAULT_PIXEL_M = 0.001
# estimators that read recorded pushes their own way: `fit` replays them on planar with the
# recorded pusher path (`comexp.real.fit`), the referee itself as its forward model where an
# episode's `estimator.method=fit` uses its quasi-static reduction (docs/method.md)
RECORDED_ONLY = ("fit",)

RECORD_FIELDS = (
    "object",
    "estimator",
    "pushes",
    "pushes_skipped",
    "com_x_cm",
    "com_y_cm",
    "true_com_x_cm",
    "true_com_y_cm",
    "error_cm",
    "paper_region_cm2",
    "paper_region_keeps_true_com",
    "paper_region_miss_mm",
    "pixel_mm",
)


@dataclass(frozen=True, eq=False)
class ObjectEstimate:
    """One object's estimate: in its object frame (origin at the outline's area centroid),
    with the error against the true CoM when it is known, and the paper's region from the same
    pushes (its area, and whether the true CoM lies within half a pixel of one of its points)."""

    object: str
    estimator: str
    pushes: int
    pushes_skipped: int
    com_m: np.ndarray
    true_com_m: np.ndarray | None
    paper_region_m: np.ndarray
    pixel_m: float

    @property
    def error_cm(self) -> float | None:
        if self.true_com_m is None:
            return None
        return float(np.hypot(*(self.com_m - self.true_com_m))) * 100.0

    @property
    def paper_region_keeps_true_com(self) -> bool | None:
        """The true CoM lies in the cell (one pixel square) of a point of the region."""
        if self.true_com_m is None:
            return None
        off = np.abs(self.paper_region_m - self.true_com_m).max(axis=1)
        return bool(off.min() <= 0.5 * self.pixel_m + 1e-12)

    @property
    def paper_region_miss_mm(self) -> float | None:
        """How far the true CoM lies from the region's nearest point (0 when kept): a cut
        through the CoM loses it by chance within the geometry's noise, a wrong sign by far."""
        if self.true_com_m is None:
            return None
        if self.paper_region_keeps_true_com:
            return 0.0
        return float(np.hypot(*(self.paper_region_m - self.true_com_m).T).min()) * 1000.0

    def record(self) -> dict[str, Any]:
        """The record the command prints (`RECORD_FIELDS`; cm, cm^2, mm; floats to 6
        decimals, far below the recorded geometry's ~1.5 mm)."""
        true = self.true_com_m
        rec = {
            "object": self.object,
            "estimator": self.estimator,
            "pushes": self.pushes,
            "pushes_skipped": self.pushes_skipped,
            "com_x_cm": float(self.com_m[0]) * 100.0,
            "com_y_cm": float(self.com_m[1]) * 100.0,
            "true_com_x_cm": None if true is None else float(true[0]) * 100.0,
            "true_com_y_cm": None if true is None else float(true[1]) * 100.0,
            "error_cm": self.error_cm,
            "paper_region_cm2": len(self.paper_region_m) * (self.pixel_m * 100.0) ** 2,
            "paper_region_keeps_true_com": self.paper_region_keeps_true_com,
            "paper_region_miss_mm": self.paper_region_miss_mm,
            "pixel_mm": self.pixel_m * 1000.0,
        }
        return {k: round(v, 6) if isinstance(v, float) else v for k, v in rec.items()}


def check_estimator(name: str) -> str:
    """`name` if it names a built-in method or an importable plug-in class, else ValueError
    (one line)."""
    if name in RECORDED_ONLY:
        return name
    if name not in METHODS and not is_plugin(name):
        known = ", ".join(dict.fromkeys((*METHODS, *RECORDED_ONLY)))
        raise ValueError(f"unknown estimator {name!r}: one of {known} or module:Class")
    EstimatorSettings(method=name)  # imports and checks a plug-in: ValueError in one line
    return name


def _pose_before(push: RecordedPush) -> Pose2D:
    return Pose2D(float(push.x_m[0]), float(push.y_m[0]), float(push.yaw_rad[0]))


def world_push(push: RecordedPush, pc: PushContact) -> WorldPush:
    """The push as `estimate_com_world` takes it: the pose at the log's start, the contact and
    direction mapped into the world with it, the unwrapped net turn."""
    pose = _pose_before(push)
    direction = pose.to_world(pc.direction) - pose.to_world(np.zeros(2))
    return WorldPush(pose, pose.to_world(pc.contact_m), direction, rotation_deg=pc.turn_deg)


def motion_push(push: RecordedPush, pc: PushContact) -> MotionPush:
    """The push as `estimate_com_motion` takes it: `world_push`'s, plus the tracked poses
    (times since the pusher started moving), the contact's time (the onset), the pusher's stop
    (so the slide after it can weigh the floor) and its speed (nominal, else measured)."""
    w = world_push(push, pc)
    poses = [
        Pose2D(float(x), float(y), float(a))
        for x, y, a in zip(push.x_m[1:], push.y_m[1:], push.yaw_rad[1:], strict=True)
    ]
    return MotionPush(
        contact_m=w.contact_m,
        direction=w.direction,
        pose_before=w.pose_before,
        t_s=tuple(push.t_s[1:] - pc.t_start_s),
        poses=tuple(poses),
        pose_after=poses[-1],
        t_contact_s=pc.t_onset_s - pc.t_start_s,
        rotation_deg=pc.turn_deg,
        speed_m_s=push.speed_m_s if push.speed_m_s is not None else pc.speed_m_s,
        t_end_s=pc.t_end_s - pc.t_start_s,
    )


def usable_pushes(
    pushes: Sequence[RecordedPush], obj: RecordedObject, max_angle_deg: float | None = None
) -> list[tuple[RecordedPush, PushContact]]:
    """The pushes that moved the object (and, with `max_angle_deg`, pushed within that angle
    of the contact normal), with their geometry."""
    out = []
    for push in pushes:
        pc = push_contact(push, obj)
        if not pc.moved:
            continue
        if max_angle_deg is not None and abs(math.degrees(pc.angle_to_normal_rad)) > max_angle_deg:
            continue
        out.append((push, pc))
    return out


def _plugin_com(
    name: str, obj: RecordedObject, used: list[tuple[RecordedPush, PushContact]], pixel_m: float
) -> np.ndarray:
    """A plug-in estimator fed the observed pushes in order (object frame), as an episode
    feeds it, without asking it for pushes; one with `observe_path` (as `motion`) also gets
    each push's tracked path first, as episodes give it."""
    outline = obj.outline_m
    contacts, normals = outline_contacts(outline)
    est = make_estimator(
        region_from_outline(outline, pixel_m),
        contacts,
        normals,
        pixel_m,
        EstimatorSettings(method=name),
        outline_m=outline,
        pusher_radius_m=obj.pusher_radius_m,
    )
    observe_path = getattr(est, "observe_path", None)
    for push, pc in used:
        if observe_path is not None:
            observe_path(motion_push(push, pc).path())
        est.observe(np.array(pc.contact_m), np.array(pc.direction), pc.turn_deg)
    return np.asarray(est.estimate_m, dtype=float)


def estimate_object(
    obj: RecordedObject,
    pushes: Sequence[RecordedPush],
    estimator: str = "paper",
    pixel_m: float = DEFAULT_PIXEL_M,
    max_angle_deg: float | None = None,
    simulator: Simulator | None = None,
) -> ObjectEstimate:
    """One object's CoM from its recorded pushes (module docstring). ValueError when none of
    its pushes is usable. `simulator`: a planar simulator, for `fit`."""
    used = usable_pushes(pushes, obj, max_angle_deg)
    if not used:
        raise ValueError(f"{obj.name}: none of its {len(pushes)} pushes moved the object")
    world = [world_push(p, pc) for p, pc in used]
    paper = estimate_com_world(obj.outline_m, world, pixel_m, EstimatorSettings(method="paper"))
    if estimator == "paper":
        com = paper.com_object_m
    elif estimator == "magnitude":
        settings = EstimatorSettings(method="magnitude")
        com = estimate_com_world(obj.outline_m, world, pixel_m, settings).com_object_m
    elif estimator == "motion":
        motion = [motion_push(p, pc) for p, pc in used]
        com = estimate_com_motion(obj.outline_m, motion, pixel_m).com_object_m
    elif estimator == "fit":
        if simulator is None:
            raise ValueError("the fit estimator needs a planar simulator (simulator=...)")
        com = fit_com(simulator, obj, [p for p, _ in used]).com_m
    else:
        com = _plugin_com(check_estimator(estimator), obj, used, pixel_m)
    return ObjectEstimate(
        object=obj.name,
        estimator=estimator,
        pushes=len(used),
        pushes_skipped=len(pushes) - len(used),
        com_m=np.asarray(com, dtype=float),
        true_com_m=obj.true_com_m,
        paper_region_m=paper.region_m,
        pixel_m=pixel_m,
    )


def estimate_all(
    rec: RecordedPushes,
    estimator: str = "paper",
    pixel_m: float = DEFAULT_PIXEL_M,
    max_angle_deg: float | None = None,
    simulator: Simulator | None = None,
    on_object: Callable[[ObjectEstimate], None] | None = None,
) -> list[ObjectEstimate]:
    """`estimate_object` for every object of `read_pushes`' result, by name (`on_object` is
    told of each as it is done)."""
    check_estimator(estimator)
    out = []
    for name in sorted(rec.objects):
        e = estimate_object(
            rec.objects[name], rec.of(name), estimator, pixel_m, max_angle_deg, simulator
        )
        out.append(e)
        if on_object is not None:
            on_object(e)
    return out
