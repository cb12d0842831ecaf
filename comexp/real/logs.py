"""The reader of recorded pushes: object poses and the pusher's path over time, per push, plus
each object's outline, in the frames of docs/real_robot.md (world z up, yaw CCW about +z; the
object frame's origin at the outline's area centroid; metres, radians, seconds).

Two layouts, one entry point, `read_pushes(DIR)` (docs/real_robot.md, "Recorded pushes"):

- the dataset layout (the MIT pushing dataset): one HDF5 file per push anywhere under DIR
  (`object_pose`: t, x, y, yaw; `tip_pose`: t, x, y of the pusher's axis), the push's fields in
  its file name (`shape=hex_..._v=100_..._t=0.349`), the outlines in `obj/<shape>_ext.npy`
  turned +90 deg from the pose frame, the physical parameters in `comexp/real/mit_push.yaml`
  (or DIR/objects.yaml, same keys);
- the plain layout for a robot's own logs: DIR/<object>/outline.csv (x_m, y_m in the frame
  whose pose the logs record), an optional DIR/<object>/object.yaml (true_com_m, mass_kg,
  pusher_radius_m) and one CSV per push in DIR/<object>/pushes/ (t_s, x_m, y_m, yaw_rad,
  pusher_x_m, pusher_y_m, and optionally force_x_n, force_y_n). DIR may also be one object's
  folder.

Where a log records the force on the pusher (the dataset's `ft_wrench`, the plain layout's
force columns; world frame, newtons) the push carries it (`RecordedPush.force`):
`comexp.real.force` reads the pusher's friction from it.

Why the checks: a log in the wrong frame (the outline turned, shifted or mirrored against the
poses) still gives an estimate, silently wrong. So every push is checked against its outline
when it is read (`check_push`), and a bad log raises `RecordedPushError`, one line that names
the file. The poses are re-expressed for the outline's area centroid, whatever point the
recorder tracked, and yaws are unwrapped, so a net turn is never read modulo a full turn.
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import shapely
import yaml

from comexp.method.geometry import ccw, centroid

# --- what a log may look like (margins from the shared MIT subset, 50 pushes) -----------------
# Samples whose time is not later than the latest kept one are dropped (repeats, steps back).
# Measured: steps back of at most 1.7 ms, at most 3 of ~300 samples in a push. A log with a
# step back longer than this, or with more than this share dropped, is refused as out of order.
MAX_STEP_BACK_S = 0.1
MAX_DROPPED_SHARE = 0.1
# The object has started moving once some point of its outline is farther than this from where
# it was at the log's first sample and stays farther for the rest of the log. Pose jitter at
# rest is ~5 um and ~0.005 deg; two ellip1 pushes at 80 deg to the normal never reach it (the
# pusher slides along the disc, which moves < 0.5 mm): they count as "not moved".
ONSET_M = 0.0005
# The pusher has started (stopped) moving once it is this far from its first (last) position.
PUSHER_MOVES_M = 0.0005
# The push direction at the onset is the pusher's chord over this much travel around it.
DIRECTION_WINDOW_M = 0.005
# The pusher's disc may overlap the outline at the log's start by at most this much: measured at
# most 0.25 mm (the README: recorded geometry uncertain by ~1.5 mm); the outlines un-turned put
# it 4-26 mm inside hex and ellip3.
MAX_START_OVERLAP_M = 0.003
# When the object starts moving the disc must be within this of the outline (gap or overlap):
# measured -1.6 .. +1.4 mm; the same bound as `estimate_com_world`'s `max_contact_offset_m`.
MAX_CONTACT_GAP_M = 0.010

PLAIN_COLUMNS = ("t_s", "x_m", "y_m", "yaw_rad", "pusher_x_m", "pusher_y_m")
FORCE_COLUMNS = ("force_x_n", "force_y_n")  # optional: the force on the pusher, world frame
OBJECT_KEYS = ("true_com_m", "mass_kg", "pusher_radius_m", "height_m")
DATASET_KEYS = ("outline_turn_deg", "pusher_radius_m", "height_m", "true_com", "objects")
DATASET_DEFAULTS = Path(__file__).with_name("mit_push.yaml")


class RecordedPushError(ValueError):
    """A log that cannot be read as it is: the message is one line, starting with the file."""

    def __init__(self, path: Path | str, message: str) -> None:
        super().__init__(f"{path}: {message}")
        self.path = Path(path)


@dataclass(frozen=True, eq=False)
class RecordedObject:
    """An object of the logs: its outline in the object frame (CCW, centred on its area
    centroid) and what is known of it. `centroid_offset_m`: where that centroid lies in the
    frame whose poses were recorded (the shift the reader applied to the poses)."""

    name: str
    outline_m: np.ndarray
    source: Path
    true_com_m: np.ndarray | None = None
    mass_kg: float | None = None
    pusher_radius_m: float | None = None
    centroid_offset_m: np.ndarray | None = None
    height_m: float | None = None


@dataclass(frozen=True, eq=False)
class RecordedPush:
    """One recorded push: the object frame's poses (its origin at the outline's centroid, yaw
    unwrapped) at `t_s`, and the pusher axis' path at `pusher_t_s` (both seconds since the log's
    first sample, strictly increasing), plus the nominal speed and push angle (rad, from the
    contact normal) when the log says them. `force`: the force on the pusher where the log
    records it, rows of (t_s on the same clock, fx_n, fy_n) in the world frame, else None.
    `samples_dropped`: repeated or back-stepping timestamps dropped on reading."""

    name: str
    object_name: str
    path: Path
    t_s: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray
    pusher_t_s: np.ndarray
    pusher_x_m: np.ndarray
    pusher_y_m: np.ndarray
    speed_m_s: float | None = None
    push_angle_rad: float | None = None
    samples_dropped: int = 0
    force: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class RecordedPushes:
    """What `read_pushes` returns: the objects by name and their pushes (sorted by object, then
    file), and which layout the folder has (`dataset` or `plain`)."""

    layout: str
    objects: dict[str, RecordedObject]
    pushes: tuple[RecordedPush, ...]

    def of(self, name: str) -> tuple[RecordedPush, ...]:
        return tuple(p for p in self.pushes if p.object_name == name)


@dataclass(frozen=True, eq=False)
class PushContact:
    """What a recorded push says for estimation, in the object frame at the onset (when the
    object first moves): the contact (the pusher's axis projected onto the outline, i.e. the
    axis minus the radius along the normal), the inward normal there, the pusher's direction
    of travel, its signed angle from the normal (rad, CCW), the unwrapped net turn (first pose
    to last, deg), when the pusher starts and stops moving, and its mean speed in between.
    Gaps are between the pusher's disc and the outline (m; negative: overlap). Without an
    onset (`moved` False) the contact fields are None."""

    moved: bool
    turn_deg: float
    t_start_s: float
    t_end_s: float
    speed_m_s: float
    start_overlap_m: float
    closest_gap_m: float
    onset_index: int | None = None
    t_onset_s: float | None = None
    contact_m: np.ndarray | None = None
    normal: np.ndarray | None = None
    direction: np.ndarray | None = None
    angle_to_normal_rad: float | None = None
    contact_gap_m: float | None = None

    def line_offset_m(self, com_m: np.ndarray) -> float:
        """How far `com_m` (object frame) lies left of the line the pusher travels along through
        the contact (m; negative: right). Positive: the push's torque about `com_m` turns the
        object counter-clockwise. Needs the contact (`moved`)."""
        if self.contact_m is None or self.direction is None:
            raise ValueError("a push that never moved its object has no contact line")
        d = np.asarray(self.direction, dtype=float) / np.linalg.norm(self.direction)
        r = np.asarray(com_m, dtype=float) - self.contact_m
        return float(d[0] * r[1] - d[1] * r[0])


# --- timestamps, poses, outlines ----------------------------------------------------------------


def increasing(t: np.ndarray, path: Path, what: str) -> np.ndarray:
    """Indices of the samples kept so that time strictly increases: a sample whose time is not
    later than the latest kept one (a repeat, or a step back) is dropped; the first one of a
    repeated time is kept. Too many dropped, or a long step back: RecordedPushError."""
    t = np.asarray(t, dtype=float)
    if len(t) < 2:
        raise RecordedPushError(path, f"{what}: {len(t)} samples, at least 2 needed")
    if not np.all(np.isfinite(t)):
        raise RecordedPushError(path, f"{what}: a time is not a finite number")
    latest = np.maximum.accumulate(t)
    keep = np.ones(len(t), dtype=bool)
    keep[1:] = t[1:] > latest[:-1]
    back = float(np.max(latest - t))
    dropped = int(len(t) - keep.sum())
    if back > MAX_STEP_BACK_S or dropped > MAX_DROPPED_SHARE * len(t):
        raise RecordedPushError(
            path,
            f"{what}: time is not increasing ({dropped} of {len(t)} samples repeat or step back, "
            f"by up to {back:.3f} s)",
        )
    return np.flatnonzero(keep)


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


def _turned(points: np.ndarray, angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.asarray(points, dtype=float) @ np.array([[c, s], [-s, c]])


def make_object(
    name: str,
    outline_m: np.ndarray,
    source: Path,
    true_com_m: Sequence[float] | None = None,
    mass_kg: float | None = None,
    pusher_radius_m: float | None = None,
    height_m: float | None = None,
) -> RecordedObject:
    """An object from its outline in the recorded pose frame: made CCW and centred on its area
    centroid (the true CoM, if given in the same frame, moves with it)."""
    pts = np.asarray(outline_m, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 3 or not np.all(np.isfinite(pts)):
        raise RecordedPushError(source, "an outline needs at least 3 finite (x_m, y_m) points")
    if len(pts) > 3 and np.allclose(pts[0], pts[-1]):
        pts = pts[:-1]  # a closed ring: the repeated first point is not a vertex
    poly = shapely.Polygon(pts)
    if not poly.is_valid or poly.area <= 0:
        raise RecordedPushError(source, "the outline is not a simple polygon (it crosses itself)")
    c = centroid(pts)
    com = None if true_com_m is None else _frozen(np.asarray(true_com_m, dtype=float) - c)
    return RecordedObject(
        name=name,
        outline_m=_frozen(ccw(pts - c)),
        source=Path(source),
        true_com_m=com,
        mass_kg=None if mass_kg is None else float(mass_kg),
        pusher_radius_m=None if pusher_radius_m is None else float(pusher_radius_m),
        centroid_offset_m=_frozen(c),
        height_m=None if height_m is None else float(height_m),
    )


def make_push(
    name: str,
    obj: RecordedObject,
    path: Path,
    pose: np.ndarray,
    pusher: np.ndarray,
    speed_m_s: float | None = None,
    push_angle_rad: float | None = None,
    force: np.ndarray | None = None,
) -> RecordedPush:
    """A push from its raw rows: `pose` (n, 4) t, x, y, yaw of the recorded frame, `pusher`
    (m, 3) t, x, y of the pusher's axis, optionally `force` (k, 3) t, fx, fy on the pusher, on
    one clock. Drops out-of-order samples (`increasing`), unwraps the yaw, moves the poses to
    the outline's centroid and counts time from the log's first pose or pusher sample."""
    pose, pusher = np.asarray(pose, dtype=float), np.asarray(pusher, dtype=float)
    if pose.ndim != 2 or pose.shape[1] < 4 or pusher.ndim != 2 or pusher.shape[1] < 3:
        raise RecordedPushError(path, "poses need columns t, x, y, yaw and the pusher t, x, y")
    if not (np.all(np.isfinite(pose)) and np.all(np.isfinite(pusher))):
        raise RecordedPushError(path, "a pose or pusher position is not a finite number")
    keep_o = increasing(pose[:, 0], path, "object poses")
    keep_p = increasing(pusher[:, 0], path, "pusher path")
    dropped = len(pose) - len(keep_o) + len(pusher) - len(keep_p)
    pose, pusher = pose[keep_o], pusher[keep_p]
    yaw = np.unwrap(pose[:, 3])
    off = obj.centroid_offset_m if obj.centroid_offset_m is not None else np.zeros(2)
    x = pose[:, 1] + np.cos(yaw) * off[0] - np.sin(yaw) * off[1]
    y = pose[:, 2] + np.sin(yaw) * off[0] + np.cos(yaw) * off[1]
    t0 = min(pose[0, 0], pusher[0, 0])
    return RecordedPush(
        name=name,
        object_name=obj.name,
        path=Path(path),
        t_s=_frozen(pose[:, 0] - t0),
        x_m=_frozen(x),
        y_m=_frozen(y),
        yaw_rad=_frozen(yaw),
        pusher_t_s=_frozen(pusher[:, 0] - t0),
        pusher_x_m=_frozen(pusher[:, 1]),
        pusher_y_m=_frozen(pusher[:, 2]),
        speed_m_s=speed_m_s,
        push_angle_rad=push_angle_rad,
        samples_dropped=int(dropped),
        force=None if force is None else _force_rows(force, t0),
    )


def _force_rows(force: np.ndarray, t0: float) -> np.ndarray | None:
    """The force's rows (t from `t0`, fx, fy), keeping the finite ones whose time increases.
    The force serves `comexp-real force` only, so a bad stream never refuses the push: what
    is left of it is kept, None when fewer than two rows are."""
    force = np.asarray(force, dtype=float)
    if force.ndim != 2 or force.shape[1] < 3:
        return None
    force = force[np.all(np.isfinite(force[:, :3]), axis=1), :3]
    if len(force) == 0:
        return None
    t = force[:, 0]
    force = force[np.r_[True, t[1:] > np.maximum.accumulate(t)[:-1]]]
    if len(force) < 2:
        return None
    return _frozen(np.column_stack([force[:, 0] - t0, force[:, 1:3]]))


# --- the push's geometry: onset, contact, direction, turn -------------------------------------


def signed_gap(outline: np.ndarray, pts: np.ndarray, radius_m: float) -> np.ndarray:
    """Gap between a disc of `radius_m` about each point and the outline (negative: overlap,
    also when the point lies inside the outline)."""
    poly = shapely.Polygon(outline)
    d = shapely.distance(poly.exterior, shapely.points(pts))
    inside = shapely.contains_xy(poly, pts[:, 0], pts[:, 1])
    return np.where(inside, -d, d) - radius_m


def nearest_on_outline(outline: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The outline's point nearest to `p` and the inward unit normal of its edge (a CCW
    outline: the normal is left of the edge)."""
    a = np.asarray(outline, dtype=float)
    b = np.roll(a, -1, axis=0)
    e = b - a
    u = np.clip(((p - a) * e).sum(axis=1) / (e * e).sum(axis=1), 0.0, 1.0)
    q = a + u[:, None] * e
    k = int(np.argmin(np.hypot(*(q - p).T)))
    t = e[k] / np.hypot(*e[k])
    return q[k], np.array([-t[1], t[0]])


def in_object_frame(push: RecordedPush, t: np.ndarray, x: np.ndarray, y: np.ndarray):
    """World points (x, y) at times t in the object frame at those times (poses interpolated;
    the yaw is unwrapped, so linearly)."""
    px = np.interp(t, push.t_s, push.x_m)
    py = np.interp(t, push.t_s, push.y_m)
    yaw = np.interp(t, push.t_s, push.yaw_rad)
    c, s = np.cos(yaw), np.sin(yaw)
    dx, dy = x - px, y - py
    return np.column_stack([c * dx + s * dy, -s * dx + c * dy])


def onset_index(push: RecordedPush, outline: np.ndarray, onset_m: float = ONSET_M) -> int | None:
    """The first pose after which the object stays moved: some outline vertex farther than
    `onset_m` from where it was at the first pose (a rigid motion moves a vertex the most).
    None: the object never moved that much for good."""
    yaw = push.yaw_rad[:, None]
    vx, vy = outline[None, :, 0], outline[None, :, 1]
    wx = push.x_m[:, None] + np.cos(yaw) * vx - np.sin(yaw) * vy
    wy = push.y_m[:, None] + np.sin(yaw) * vx + np.cos(yaw) * vy
    moved = np.hypot(wx - wx[0], wy - wy[0]).max(axis=1) > onset_m
    still = np.flatnonzero(~moved)
    i = int(still[-1]) + 1 if len(still) else 0
    return i if i < len(moved) else None


def _pusher_span(push: RecordedPush) -> tuple[float, float, float]:
    """When the pusher starts and stops moving, and its mean speed in between."""
    xy = np.column_stack([push.pusher_x_m, push.pusher_y_m])
    t = push.pusher_t_s
    if np.hypot(*(xy - xy[0]).T).max() <= 2 * PUSHER_MOVES_M:
        raise RecordedPushError(push.path, "the pusher never moves")
    i0 = int(np.argmax(np.hypot(*(xy - xy[0]).T) > PUSHER_MOVES_M))
    i1 = int(np.argmax(np.hypot(*(xy - xy[-1]).T) <= PUSHER_MOVES_M))
    i1 = max(i1, i0 + 1)
    speed = float(np.hypot(*(xy[i1] - xy[i0]))) / max(float(t[i1] - t[i0]), 1e-9)
    return float(t[i0]), float(t[i1]), speed


def _travel_direction(push: RecordedPush, t_on: float, speed_m_s: float) -> np.ndarray:
    """The pusher's direction of travel at `t_on` (world, unit): its chord over
    `DIRECTION_WINDOW_M` of travel around then, or over the whole path if it stood still."""
    half = 0.5 * DIRECTION_WINDOW_M / max(speed_m_s, 1e-6)
    ts = np.array([t_on - half, t_on + half])
    x = np.interp(ts, push.pusher_t_s, push.pusher_x_m)
    y = np.interp(ts, push.pusher_t_s, push.pusher_y_m)
    d = np.array([x[1] - x[0], y[1] - y[0]])
    if np.hypot(*d) < 0.2 * DIRECTION_WINDOW_M:
        d = np.array(
            [push.pusher_x_m[-1] - push.pusher_x_m[0], push.pusher_y_m[-1] - push.pusher_y_m[0]]
        )
    return d / np.hypot(*d)


def push_contact(push: RecordedPush, obj: RecordedObject) -> PushContact:
    """The push's geometry for estimation (`PushContact`); an unknown pusher radius counts as
    0 (a point pusher: the gaps are then the axis' distances to the outline)."""
    outline = obj.outline_m
    radius = obj.pusher_radius_m or 0.0
    t_start, t_end, speed = _pusher_span(push)
    tips = in_object_frame(push, push.pusher_t_s, push.pusher_x_m, push.pusher_y_m)
    gaps = signed_gap(outline, tips, radius)
    common = dict(
        turn_deg=math.degrees(float(push.yaw_rad[-1] - push.yaw_rad[0])),
        t_start_s=t_start,
        t_end_s=t_end,
        speed_m_s=speed,
        start_overlap_m=float(-gaps[0]),
        closest_gap_m=float(gaps.min()),
    )
    i = onset_index(push, outline)
    if i is None:
        return PushContact(moved=False, **common)
    t_on = float(push.t_s[i])
    tip_world = np.array(
        [
            np.interp(t_on, push.pusher_t_s, push.pusher_x_m),
            np.interp(t_on, push.pusher_t_s, push.pusher_y_m),
        ]
    )
    tip = in_object_frame(push, np.array([t_on]), tip_world[:1], tip_world[1:])[0]
    contact, normal = nearest_on_outline(outline, tip)
    yaw = float(push.yaw_rad[i])
    d = _travel_direction(push, t_on, speed)
    direction = np.array(
        [math.cos(yaw) * d[0] + math.sin(yaw) * d[1], -math.sin(yaw) * d[0] + math.cos(yaw) * d[1]]
    )
    angle = math.atan2(
        normal[0] * direction[1] - normal[1] * direction[0], float(normal @ direction)
    )
    return PushContact(
        moved=True,
        onset_index=i,
        t_onset_s=t_on,
        contact_m=_frozen(contact),
        normal=_frozen(normal),
        direction=_frozen(direction),
        angle_to_normal_rad=angle,
        contact_gap_m=float(signed_gap(outline, tip[None], radius)[0]),
        **common,
    )


def check_push(push: RecordedPush, obj: RecordedObject) -> PushContact:
    """`push_contact`, refusing a push whose pusher never comes near the outline, starts deep
    inside it, or is far from it when the object starts moving: the outline is then in another
    frame than the poses (turned, shifted, mirrored), or the log is not of this object."""
    pc = push_contact(push, obj)
    hint = "is the outline in the frame of the poses (not turned, shifted or mirrored)?"
    if pc.closest_gap_m > MAX_CONTACT_GAP_M:
        raise RecordedPushError(
            push.path,
            f"the pusher never touches the object: it comes {pc.closest_gap_m * 1e3:.1f} mm "
            f"from the outline at the closest (more than {MAX_CONTACT_GAP_M * 1e3:.0f} mm); {hint}",
        )
    if pc.start_overlap_m > MAX_START_OVERLAP_M:
        raise RecordedPushError(
            push.path,
            f"the pusher starts {pc.start_overlap_m * 1e3:.1f} mm inside the outline (the "
            f"measurement noise allows {MAX_START_OVERLAP_M * 1e3:.0f} mm); {hint}",
        )
    if pc.contact_gap_m is not None and abs(pc.contact_gap_m) > MAX_CONTACT_GAP_M:
        where = "from" if pc.contact_gap_m > 0 else "inside"
        raise RecordedPushError(
            push.path,
            f"when the object starts moving the pusher is {abs(pc.contact_gap_m) * 1e3:.1f} mm "
            f"{where} the outline (more than {MAX_CONTACT_GAP_M * 1e3:.0f} mm); {hint}",
        )
    return pc


# --- the dataset layout: HDF5 per push, obj/<shape>_ext.npy -----------------------------------


def name_fields(path: Path) -> dict[str, str]:
    """The fields of a dataset file name, `motion_surface=abs_shape=hex_a=0_v=100_..._t=0.349`
    -> {"surface": "abs", "shape": "hex", ...}: split where an underscore starts `key=`."""
    parts = re.split(r"_(?=[A-Za-z]+=)", Path(path).stem)
    return dict(p.split("=", 1) for p in parts if "=" in p)


def _number(value: Any, where: Path, what: str, positive: bool = True) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise RecordedPushError(where, f"{what}: not a number: {value!r}") from None
    if not math.isfinite(v) or (positive and v <= 0):
        raise RecordedPushError(where, f"{what}: must be a finite number{' > 0' * positive}")
    return v


def _pair(value: Any, where: Path, what: str) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise RecordedPushError(where, f"{what}: expected [x, y] in metres, got {value!r}")
    return np.array([_number(v, where, what, positive=False) for v in value])


def _yaml(path: Path) -> dict[str, Any]:
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as e:
        raise RecordedPushError(path, f"cannot read it as YAML: {str(e).splitlines()[0]}") from None
    if not isinstance(data, dict):
        raise RecordedPushError(path, "expected a mapping of keys to values")
    return data


def dataset_metadata(root: Path) -> dict[str, Any]:
    """The dataset layout's parameters: `mit_push.yaml` (shipped), with DIR/objects.yaml's
    top-level keys over it and its `objects` entries merged in, name by name."""
    meta = _yaml(DATASET_DEFAULTS)
    own = root / "objects.yaml"
    source = DATASET_DEFAULTS
    if own.is_file():
        extra, source = _yaml(own), own
        unknown = set(extra) - set(DATASET_KEYS)
        objects = extra.pop("objects", None) or {}
        if not isinstance(objects, dict) or not all(isinstance(v, dict) for v in objects.values()):
            raise RecordedPushError(own, "objects: expected a mapping of names to mappings")
        for name, entry in objects.items():
            unknown |= {f"objects.{name}.{k}" for k in set(entry) - set(OBJECT_KEYS)}
        if unknown:
            raise RecordedPushError(own, f"unknown keys: {', '.join(sorted(unknown))}")
        meta = {**meta, **extra, "objects": {**meta.get("objects", {}), **objects}}
    return {**meta, "_source": source}


def _dataset_object(shape: str, outline_path: Path, meta: Mapping[str, Any]) -> RecordedObject:
    try:
        raw = np.load(outline_path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise RecordedPushError(outline_path, f"cannot read the outline: {e}") from None
    src = Path(meta["_source"])  # where the parameters come from, for their errors
    turn = math.radians(_number(meta.get("outline_turn_deg", 0.0), src, "outline_turn_deg", False))
    outline = _turned(raw, turn) if np.ndim(raw) == 2 else raw
    entry = (meta.get("objects") or {}).get(shape) or {}
    com = entry.get("true_com_m")
    com = None if com is None else _pair(com, src, f"{shape}: true_com_m")
    if com is None and meta.get("true_com") == "centroid":
        com = centroid(outline) if np.ndim(outline) == 2 and len(outline) >= 3 else None
    radius = entry.get("pusher_radius_m", meta.get("pusher_radius_m"))
    mass = entry.get("mass_kg")
    height = entry.get("height_m", meta.get("height_m"))
    return make_object(
        shape,
        outline,
        outline_path,
        true_com_m=com,
        mass_kg=None if mass is None else _number(mass, src, f"{shape}: mass_kg"),
        pusher_radius_m=None if radius is None else _number(radius, src, "pusher_radius_m"),
        height_m=None if height is None else _number(height, src, f"{shape}: height_m"),
    )


def _outline_path(h5: Path, root: Path, shape: str) -> Path:
    """obj/<shape>_ext.npy in the push's folder or the nearest folder above it, up to DIR."""
    folder = h5.parent
    while True:
        candidate = folder / "obj" / f"{shape}_ext.npy"
        if candidate.is_file() or folder == root or folder == folder.parent:
            return candidate
        folder = folder.parent


def _optional_array(f: h5py.File, name: str) -> np.ndarray | None:
    """The dataset `name` as floats, None when the file has none or it is not numbers (an
    optional stream never refuses the file)."""
    try:
        return np.asarray(f[name], dtype=float) if name in f else None
    except (OSError, TypeError, ValueError):  # h5py: OSError when it cannot convert
        return None


def _read_h5(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The file's object poses, pusher path and, when it has one, `ft_wrench` (t, fx, fy)."""
    try:
        with h5py.File(path, "r") as f:
            missing = [k for k in ("object_pose", "tip_pose") if k not in f]
            if missing:
                raise RecordedPushError(path, f"no {' or '.join(missing)} dataset in the file")
            pose = np.asarray(f["object_pose"], dtype=float)
            tip = np.asarray(f["tip_pose"], dtype=float)
            wrench = _optional_array(f, "ft_wrench")
    except (OSError, TypeError, KeyError) as e:
        raise RecordedPushError(path, f"cannot read it as HDF5: {str(e).splitlines()[0]}") from None
    if pose.ndim != 2 or pose.shape[1] < 4:
        raise RecordedPushError(path, f"object_pose has shape {pose.shape}, expected (n, 4)")
    if tip.ndim != 2 or tip.shape[1] < 3:
        raise RecordedPushError(path, f"tip_pose has shape {tip.shape}, expected (n, 3+)")
    return pose[:, :4], tip[:, :3], wrench  # a malformed ft_wrench: `_force_rows` drops it


def _read_dataset(root: Path, files: list[Path]) -> RecordedPushes:
    meta = dataset_metadata(root)
    objects: dict[str, RecordedObject] = {}
    pushes = []
    for path in files:
        fields = name_fields(path)
        shape = fields.get("shape")
        if not shape:
            raise RecordedPushError(path, "no shape=<name> field in the file name")
        if shape not in objects:
            outline_path = _outline_path(path, root, shape)
            if not outline_path.is_file():
                raise RecordedPushError(path, f"no outline for shape {shape!r} ({outline_path})")
            objects[shape] = _dataset_object(shape, outline_path, meta)
        speed = fields.get("v")
        angle = fields.get("t")
        pose, tip, wrench = _read_h5(path)
        pushes.append(
            make_push(
                path.stem,
                objects[shape],
                path,
                pose,
                tip,
                speed_m_s=None if speed is None else _number(speed, path, "v") / 1000.0,
                push_angle_rad=None if angle is None else _number(angle, path, "t", False),
                force=wrench,
            )
        )
    return RecordedPushes("dataset", objects, tuple(sorted(pushes, key=_push_order)))


def _push_order(p: RecordedPush) -> tuple[str, str]:
    return p.object_name, str(p.path)


# --- the plain layout: <object>/outline.csv, object.yaml, pushes/*.csv ------------------------


def read_csv(path: Path, columns: Sequence[str], optional: Sequence[str] = ()) -> np.ndarray:
    """The named columns of a CSV file with a header row, as (n, k) floats (other columns
    ignored; lines starting with # skipped), followed by the `optional` ones when the header
    has them: all of them or none. Missing columns, some optional ones without the others, a
    value that is not a finite number, or no rows: RecordedPushError."""
    try:
        with open(path, newline="") as f:
            lines = [ln for ln in f if ln.strip() and not ln.lstrip().startswith("#")]
    except OSError as e:
        raise RecordedPushError(path, f"cannot read it: {e.strerror or e}") from None
    rows = list(csv.reader(lines))
    if not rows:
        raise RecordedPushError(
            path, "empty file (expected a header row: " + ", ".join(columns) + ")"
        )
    header = [h.strip() for h in rows[0]]
    missing = [c for c in columns if c not in header]
    if missing:
        raise RecordedPushError(
            path, f"missing columns: {', '.join(missing)} (has: {', '.join(header)})"
        )
    given = [c for c in optional if c in header]
    if given and len(given) < len(optional):
        absent = [c for c in optional if c not in header]
        raise RecordedPushError(
            path, f"{given[0]} without {absent[0]}: give {' and '.join(optional)} together"
        )
    columns = tuple(columns) + (tuple(optional) if given else ())
    idx = [header.index(c) for c in columns]
    out = np.empty((len(rows) - 1, len(columns)))
    for r, row in enumerate(rows[1:]):
        for j, (k, name) in enumerate(zip(idx, columns, strict=True)):
            value = row[k].strip() if k < len(row) else ""
            try:
                out[r, j] = float(value)
            except ValueError:
                raise RecordedPushError(
                    path, f"row {r + 2}, column {name}: not a number: {value!r}"
                ) from None
            if not math.isfinite(out[r, j]):
                raise RecordedPushError(path, f"row {r + 2}, column {name}: not finite")
    if len(out) == 0:
        raise RecordedPushError(path, "no rows after the header")
    return out


def _plain_object(folder: Path) -> RecordedObject:
    outline_path = folder / "outline.csv"
    outline = read_csv(outline_path, ("x_m", "y_m"))
    meta: dict[str, Any] = {}
    meta_path = folder / "object.yaml"
    if meta_path.is_file():
        meta = _yaml(meta_path)
        unknown = set(meta) - set(OBJECT_KEYS)
        if unknown:
            raise RecordedPushError(
                meta_path,
                f"unknown keys: {', '.join(sorted(unknown))} (known: {', '.join(OBJECT_KEYS)})",
            )
    com, mass, radius, height = (meta.get(k) for k in OBJECT_KEYS)
    return make_object(
        folder.name,
        outline,
        outline_path,
        true_com_m=None if com is None else _pair(com, meta_path, "true_com_m"),
        mass_kg=None if mass is None else _number(mass, meta_path, "mass_kg"),
        pusher_radius_m=None if radius is None else _number(radius, meta_path, "pusher_radius_m"),
        height_m=None if height is None else _number(height, meta_path, "height_m"),
    )


def _read_plain(root: Path) -> RecordedPushes:
    if (root / "outline.csv").is_file():
        folders = [root]
    else:
        folders = sorted(p.parent for p in root.glob("*/outline.csv"))
    objects: dict[str, RecordedObject] = {}
    pushes = []
    for folder in folders:
        obj = objects[folder.name] = _plain_object(folder)
        files = sorted((folder / "pushes").glob("*.csv"))
        if not files:
            raise RecordedPushError(folder / "pushes", "no push logs (*.csv) for this object")
        for path in files:
            rows = read_csv(path, PLAIN_COLUMNS, optional=FORCE_COLUMNS)
            force = rows[:, [0, 6, 7]] if rows.shape[1] > len(PLAIN_COLUMNS) else None
            pushes.append(
                make_push(path.stem, obj, path, rows[:, :4], rows[:, [0, 4, 5]], force=force)
            )
    return RecordedPushes("plain", objects, tuple(pushes))


def read_pushes(root: Path | str) -> RecordedPushes:
    """Every recorded push under `root`, in either layout (module docstring), each checked
    against its outline (`check_push`). Any problem: RecordedPushError naming the file."""
    root = Path(root)
    if not root.is_dir():
        raise RecordedPushError(root, "no such folder")
    h5 = sorted(root.rglob("*.h5"))
    plain = (root / "outline.csv").is_file() or any(root.glob("*/outline.csv"))
    if h5 and plain:
        raise RecordedPushError(root, "holds both HDF5 pushes and <object>/outline.csv: one layout")
    if h5:
        rec = _read_dataset(root, h5)
    elif plain:
        rec = _read_plain(root)
    else:
        raise RecordedPushError(
            root, "no recorded pushes: no *.h5 files (dataset layout) nor <object>/outline.csv"
        )
    for push in rec.pushes:
        check_push(push, rec.objects[push.object_name])
    return rec


def _fmt(v: float) -> str:
    return repr(float(v))  # the shortest text that reads back as the same float


def write_plain_object(
    folder: Path | str,
    outline_m: np.ndarray,
    true_com_m: Sequence[float] | None = None,
    mass_kg: float | None = None,
    pusher_radius_m: float | None = None,
    height_m: float | None = None,
) -> Path:
    """Write an object of the plain layout (outline.csv, and object.yaml if anything else is
    known) into `folder`; its pushes go to `folder`/pushes/ (`write_plain_push`)."""
    folder = Path(folder)
    (folder / "pushes").mkdir(parents=True, exist_ok=True)
    lines = ["x_m,y_m"] + [f"{_fmt(x)},{_fmt(y)}" for x, y in np.asarray(outline_m, dtype=float)]
    (folder / "outline.csv").write_text("\n".join(lines) + "\n")
    meta: dict[str, Any] = {}
    if true_com_m is not None:
        meta["true_com_m"] = [float(v) for v in true_com_m]
    if mass_kg is not None:
        meta["mass_kg"] = float(mass_kg)
    if pusher_radius_m is not None:
        meta["pusher_radius_m"] = float(pusher_radius_m)
    if height_m is not None:
        meta["height_m"] = float(height_m)
    if meta:
        (folder / "object.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    return folder


def write_plain_push(path: Path | str, columns: Mapping[str, Sequence[float]]) -> Path:
    """Write one push of the plain layout: `columns` maps each of `PLAIN_COLUMNS` (and, for a
    recorded force, `FORCE_COLUMNS`) to its values (one row per time)."""
    path = Path(path)
    missing = [c for c in PLAIN_COLUMNS if c not in columns]
    if missing:
        raise ValueError(f"write_plain_push: missing columns {missing}")
    names = PLAIN_COLUMNS + tuple(c for c in FORCE_COLUMNS if c in columns)
    data = np.column_stack([np.asarray(columns[c], dtype=float) for c in names])
    lines = [",".join(names)] + [",".join(_fmt(v) for v in row) for row in data]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path
