"""The pusher's friction on an object, read from the recorded contact force.

While the pusher touches the object, the force on the object (minus the force on the pusher,
`RecordedPush.force`) makes an angle with the outline's inward normal at the contact. Where
the pusher slides along the outline (a push at a large angle to the normal, beyond the
friction cone) that angle is the cone's edge and |tan| of it is the pusher's friction
coefficient, measured without any model of the floor: a check on the friction `comexp-real
replay` fits from the motion alone. Where the angle is near zero the force passes through
the contact normal; on a disc, through its centre, so the pusher exerts no torque about it.

A sample counts when the pusher's disc is within `CONTACT_GAP_M` of the outline (the
recorded geometry is uncertain by ~1.5 mm), the force is at least `MIN_FORCE_N` and presses
on the object (a contact cannot pull: a sample that pulls reads something else, a sensor's
offset or drift); a push with fewer than `MIN_SAMPLES` such samples has no reading (in the
shared data, most of rect1's pushes, whose sensor reads nearly nothing).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from comexp.real.logs import RecordedObject, RecordedPush, nearest_on_outline, push_contact

CONTACT_GAP_M = 0.0015
MIN_FORCE_N = 0.5
MIN_SAMPLES = 20
SLIDING_DEG = 35.0  # pushes at least this far from the normal slide on the pusher (mu < 0.7)

RECORD_FIELDS = (
    "push",
    "object",
    "speed_mm_s",
    "angle_to_normal_deg",
    "samples",
    "force_from_normal_deg",
    "force_n",
    "sliding",
)


@dataclass(frozen=True)
class ContactForce:
    """One push's contact force: the medians over its samples in contact (module docstring)
    of the force's signed angle from the inward normal (CCW positive, as the push's angle to
    the normal) and of its magnitude."""

    push: str
    object: str
    speed_mm_s: float | None
    angle_to_normal_deg: float
    samples: int
    force_from_normal_deg: float
    force_n: float
    sliding: bool  # pushed at least SLIDING_DEG from the normal

    def record(self) -> dict[str, object]:
        return {k: getattr(self, k) for k in RECORD_FIELDS}


def contact_force(
    push: RecordedPush, obj: RecordedObject, sliding_deg: float = SLIDING_DEG
) -> ContactForce | None:
    """The push's `ContactForce`, or None when it records no force, never moved the object or
    has fewer than `MIN_SAMPLES` samples in contact."""
    pc = push_contact(push, obj)
    if push.force is None or not pc.moved or pc.angle_to_normal_rad is None:
        return None
    t, f = push.force[:, 0], push.force[:, 1:3]
    inside = (t >= max(push.t_s[0], push.pusher_t_s[0])) & (
        t <= min(push.t_s[-1], push.pusher_t_s[-1])
    )
    t, on_object = t[inside], -f[inside]
    x, y = np.interp(t, push.t_s, push.x_m), np.interp(t, push.t_s, push.y_m)
    yaw = np.interp(t, push.t_s, push.yaw_rad)
    px = np.interp(t, push.pusher_t_s, push.pusher_x_m) - x
    py = np.interp(t, push.pusher_t_s, push.pusher_y_m) - y
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.column_stack([c * px + s * py, -s * px + c * py])  # the pusher, object frame
    radius = obj.pusher_radius_m or 0.0
    angles, sizes = [], []
    for k in range(len(t)):
        size = float(np.hypot(*on_object[k]))
        if size < MIN_FORCE_N:
            continue
        q, inward = nearest_on_outline(obj.outline_m, local[k])
        if np.hypot(*(local[k] - q)) - radius > CONTACT_GAP_M:
            continue
        n = np.array([c[k] * inward[0] - s[k] * inward[1], s[k] * inward[0] + c[k] * inward[1]])
        along = float(n @ on_object[k])
        if along <= 0.0:
            continue
        across = float(n[0] * on_object[k, 1] - n[1] * on_object[k, 0])
        angles.append(math.degrees(math.atan2(across, along)))
        sizes.append(size)
    if len(angles) < MIN_SAMPLES:
        return None
    push_deg = math.degrees(pc.angle_to_normal_rad)
    return ContactForce(
        push=push.name,
        object=obj.name,
        speed_mm_s=None if push.speed_m_s is None else push.speed_m_s * 1000.0,
        angle_to_normal_deg=push_deg,
        samples=len(angles),
        force_from_normal_deg=float(np.median(angles)),
        force_n=float(np.median(sizes)),
        sliding=abs(push_deg) >= sliding_deg,
    )


def pusher_friction(forces: Sequence[ContactForce]) -> float | None:
    """The median |tan(force from normal)| over the sliding pushes: the pusher's friction
    coefficient (None without a sliding push)."""
    slid = [abs(math.tan(math.radians(f.force_from_normal_deg))) for f in forces if f.sliding]
    return float(np.median(slid)) if slid else None


@dataclass(frozen=True)
class FrictionReading:
    """`pusher_friction` over a group of pushes: every push (`speed_mm_s` None) or one
    nominal speed."""

    speed_mm_s: int | None
    pushes: int
    sliding: int
    mu_pusher: float | None


def friction_by_speed(forces: Sequence[ContactForce]) -> list[FrictionReading]:
    """The reading over every push, then one per nominal speed (pushes without one: in the
    first only)."""
    groups: dict[int | None, list[ContactForce]] = {None: list(forces)}
    for f in forces:
        if f.speed_mm_s is not None:
            groups.setdefault(round(f.speed_mm_s), []).append(f)
    return [
        FrictionReading(v, len(g), sum(f.sliding for f in g), pusher_friction(g))
        for v, g in sorted(groups.items(), key=lambda kv: -1 if kv[0] is None else kv[0])
    ]
