"""The recorded contact force: the pusher's friction and its torque on the object.

While the pusher touches the object, the force on the object (minus the force on the pusher,
`RecordedPush.force`) makes an angle with the outline's inward normal at the contact. Where
the pusher slides along the outline, the force lies on the friction cone's edge and |tan| of
that angle is the pusher's friction coefficient, measured without any model of the floor: a
check on the friction `comexp-real replay` fits from the motion alone. Whether a sample
slides is read from the motion, not from the push's angle (a pusher that starts at 40 deg
from a disc's normal slides round it until the push passes through the centre, then
sticks): the pusher's velocity relative to the object's material point at the contact,
along the outline, is at least `SLIDING_M_S` and `SLIDING_SHARE` of the pusher's speed
(velocities by finite differences of the recorded streams; below that, a sticking contact's
jitter). The force's torque about the true CoM (the outline's centroid when it is
not known) says how hard the pusher turned the object.

A sample counts when the pusher's disc is within `CONTACT_GAP_M` of the outline, inside or
out (`comexp.real.logs.signed_gap`; the recorded geometry is uncertain by ~1.5 mm), the force
is at least `MIN_FORCE_N` and presses on the object (a contact cannot pull: a sample that
pulls reads something else, a sensor's offset or drift); a push with fewer than
`MIN_SAMPLES` such samples has no reading (in the shared data, most of rect1's pushes, whose
sensor reads nearly nothing), and its friction needs `MIN_SAMPLES` sliding ones making at
least `MIN_SLIDING_SHARE` of them (a few "sliding" samples of a push that sticks are the
streams' jitter).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from comexp.method.frames import Pose2D
from comexp.real.logs import (
    RecordedObject,
    RecordedPush,
    in_object_frame,
    nearest_on_outline,
    push_contact,
    signed_gap,
)

CONTACT_GAP_M = 0.0015
MIN_FORCE_N = 0.5
MIN_SAMPLES = 20
SLIDING_M_S = 0.003  # the relative speed along the outline above the streams' noise
SLIDING_SHARE = 0.25  # ... and at least this share of the pusher's own speed
MIN_SLIDING_SHARE = 0.25  # a push's friction needs this share of its samples sliding

RECORD_FIELDS = (
    "push",
    "object",
    "speed_mm_s",
    "angle_to_normal_deg",
    "samples",
    "force_from_normal_deg",
    "force_n",
    "torque_mean_nmm",
    "sliding_samples",
    "friction",
)


@dataclass(frozen=True)
class ContactForce:
    """One push's contact force over its samples in contact (module docstring): the median
    of the force's signed angle from the inward normal (CCW positive, as the push's angle to
    the normal) and of its size, the mean torque about the CoM (N mm, CCW positive), and over
    the sliding samples the median |tan| of the angle (None with too few: module docstring)."""

    push: str
    object: str
    speed_mm_s: float | None
    angle_to_normal_deg: float
    samples: int
    force_from_normal_deg: float
    force_n: float
    torque_mean_nmm: float
    sliding_samples: int
    friction: float | None

    def record(self) -> dict[str, object]:
        return {k: getattr(self, k) for k in RECORD_FIELDS}


def _rate(t: np.ndarray, v: np.ndarray, at: np.ndarray) -> np.ndarray:
    """d v / d t at the times `at` (central differences of the stream, interpolated)."""
    return np.interp(at, t, np.gradient(v, t))


def contact_force(
    push: RecordedPush, obj: RecordedObject, sliding_m_s: float = SLIDING_M_S
) -> ContactForce | None:
    """The push's `ContactForce`, or None when it records no force, never moved the object or
    has fewer than `MIN_SAMPLES` samples in contact."""
    if push.force is None or len(push.t_s) < 2 or len(push.pusher_t_s) < 2:
        return None
    pc = push_contact(push, obj)
    if not pc.moved or pc.angle_to_normal_rad is None:
        return None
    t = push.force[:, 0]
    inside = (t >= max(push.t_s[0], push.pusher_t_s[0])) & (
        t <= min(push.t_s[-1], push.pusher_t_s[-1])
    )
    t, on_object = t[inside], -push.force[inside, 1:3]
    pusher_w = np.column_stack(
        [np.interp(t, push.pusher_t_s, push.pusher_x_m),
         np.interp(t, push.pusher_t_s, push.pusher_y_m)]
    )  # fmt: skip
    local = in_object_frame(push, t, pusher_w[:, 0], pusher_w[:, 1])
    radius = obj.pusher_radius_m or 0.0
    near = np.abs(signed_gap(obj.outline_m, local, radius)) <= CONTACT_GAP_M
    near &= np.hypot(*on_object.T) >= MIN_FORCE_N
    idx = np.nonzero(near)[0]
    if len(idx) < MIN_SAMPLES:
        return None
    ox, oy = np.interp(t, push.t_s, push.x_m), np.interp(t, push.t_s, push.y_m)
    yaw = np.interp(t, push.t_s, push.yaw_rad)
    vo = np.column_stack([_rate(push.t_s, push.x_m, t), _rate(push.t_s, push.y_m, t)])
    w = _rate(push.t_s, push.yaw_rad, t)
    vp = np.column_stack(
        [_rate(push.pusher_t_s, push.pusher_x_m, t), _rate(push.pusher_t_s, push.pusher_y_m, t)]
    )
    com = np.zeros(2) if obj.true_com_m is None else np.asarray(obj.true_com_m, dtype=float)
    angles, sizes, torques, slid = [], [], [], []
    for k in idx:
        pose = Pose2D(float(ox[k]), float(oy[k]), float(yaw[k]))
        q, inward = nearest_on_outline(obj.outline_m, local[k])
        point, centre = pose.to_world(np.array([q, com]))  # where the force acts, the CoM
        n = pose.to_world(inward) - pose.to_world(np.zeros(2))  # the normal, turned
        f = on_object[k]
        along = float(n @ f)
        if along <= 0.0:
            continue
        across = float(n[0] * f[1] - n[1] * f[0])
        angles.append(math.degrees(math.atan2(across, along)))
        sizes.append(float(np.hypot(*f)))
        arm = point - centre
        torques.append(float(arm[0] * f[1] - arm[1] * f[0]) * 1000.0)
        r = point - np.array([ox[k], oy[k]])
        material = vo[k] + w[k] * np.array([-r[1], r[0]])  # the object's point under the contact
        tangent = np.array([-n[1], n[0]])
        speed = float(np.hypot(*vp[k]))
        if abs(float((vp[k] - material) @ tangent)) >= max(sliding_m_s, SLIDING_SHARE * speed):
            slid.append(abs(across / along))
    if len(angles) < MIN_SAMPLES:
        return None
    min_sliding = max(MIN_SAMPLES, math.ceil(MIN_SLIDING_SHARE * len(angles)))
    return ContactForce(
        push=push.name,
        object=obj.name,
        speed_mm_s=None if push.speed_m_s is None else push.speed_m_s * 1000.0,
        angle_to_normal_deg=math.degrees(pc.angle_to_normal_rad),
        samples=len(angles),
        force_from_normal_deg=float(np.median(angles)),
        force_n=float(np.median(sizes)),
        torque_mean_nmm=float(np.mean(torques)),
        sliding_samples=len(slid),
        friction=float(np.median(slid)) if len(slid) >= min_sliding else None,
    )


def pusher_friction(forces: Sequence[ContactForce]) -> float | None:
    """The median over the pushes of their sliding samples' friction: the pusher's friction
    coefficient (None without a push that slid)."""
    values = [f.friction for f in forces if f.friction is not None]
    return float(np.median(values)) if values else None


@dataclass(frozen=True)
class FrictionReading:
    """`pusher_friction` over a group of pushes: every push (`speed_mm_s` None) or one
    nominal speed."""

    speed_mm_s: int | None
    pushes: int
    slid: int  # pushes with a friction reading (enough of their samples slid)
    mu_pusher: float | None


def friction_by_speed(forces: Sequence[ContactForce]) -> list[FrictionReading]:
    """The reading over every push, then one per nominal speed (pushes without one: in the
    first only)."""
    groups: dict[int | None, list[ContactForce]] = {None: list(forces)}
    for f in forces:
        if f.speed_mm_s is not None:
            groups.setdefault(round(f.speed_mm_s), []).append(f)
    return [
        FrictionReading(v, len(g), sum(f.friction is not None for f in g), pusher_friction(g))
        for v, g in sorted(groups.items(), key=lambda kv: -1 if kv[0] is None else kv[0])
    ]
