"""MuJoCo backend: the scene as generated MJCF, a kinematically driven pusher, EGL depth camera.

Physics choices (measured and justified in docs/physics_mujoco.md):
- Every contact is an explicit `<pair>`: MuJoCo would otherwise combine the two geoms'
  friction by taking the max, and the floor's anisotropy (mu_x along world x, mu_y along world
  y) can only be expressed per pair. For the floor's horizontal normal MuJoCo's contact frame
  has its first tangent along world +y and its second along world -x (whatever the object's
  yaw), so the pair friction is "mu_y mu_x". condim 3: no torsional or rolling friction, which
  would add a spurious resisting torque to the object's rotation.
- The object touches the floor only through small spheres whose set is point-symmetric about
  the CoM (`_support_points`). MuJoCo regularises every contact with the same weight, so
  whenever friction is not saturated (impacts, slow slip) the contact forces act about the
  centre of the contact set, not the centre of pressure: with a uniform grid over the
  footprint that is the centroid, and a push through the CoM turned by 0.2-1.5 deg, always the
  same way. Raised spheres at the footprint's hull corners take over when the object tilts.
- The pusher is a capsule (its straight part is exactly the pusher cylinder): capsule-box
  contacts are analytic, cylinder contacts go through the general convex collider, whose
  errors depend on the object's yaw (a rotated box turned by up to 2.7 deg). Its contact with
  the object is softer than the floor's (`pusher_solref`), which lowers the 40 cm/s impact's
  lift of the object off the floor (it still lifts 1-4 mm on the mu 1 floor: docs/physics.md).
- The pusher is a heavy body on two slide joints whose position and velocity are set before
  every chunk of steps (kinematic): unlike a mocap body, the contact solver then sees the
  pusher's true velocity; being heavy, it coasts through a chunk at that velocity, so MuJoCo
  runs whole chunks without Python in between.
- Depth renderers (a GL context each, ~70 ms to create) are cached per object geometry.
"""

from __future__ import annotations

import functools
import math
import os
from collections import OrderedDict
from dataclasses import dataclass, field, replace

import numpy as np
import shapely
import shapely.affinity
import shapely.ops

os.environ.setdefault("MUJOCO_GL", "egl")
# Mesa's software rasteriser (llvmpipe, what EGL gives on a machine without a GPU) hands each
# render to worker threads; for our small depth renders the hand-off costs more CPU than it
# saves, and a study keeps every core busy with its own workers anyway. 0 = rasterise in the
# calling thread: the same pixels bit for bit (200 window and full renders over the 20
# objects compared), 0.66x the CPU per window render (measured at 9f588be with a script
# removed later, docs/performance.md). A GPU ignores it.
os.environ.setdefault("LP_NUM_THREADS", "0")

import mujoco  # noqa: E402

from comexp.backends.floor_friction import FootprintFriction  # noqa: E402
from comexp.backends.mujoco_steps import (  # noqa: E402
    PUSHER_SENSOR,
    PUSHER_SENSOR_MJCF,
    cos_tilt,
    push_chunks,
    push_steps,
    pusher_touching,
)
from comexp.backends.numba_kernels import DirectCall  # noqa: E402
from comexp.backends.physics_settings import (  # noqa: E402  # noqa: E402
    DEFAULT_CONTACT,
    FLOOR_FRICTION_CHOICES,
    MUJOCO,
    RENDERER_CHOICES,
    STILL_JUMPS,
    MujocoContactSettings,
)
from comexp.method.frames import DepthImage, Pose2D
from comexp.sim.protocol import ChunkStop, JumpsStillSteps, RunsChunks  # noqa: E402
from comexp.sim.scene import (
    GRAVITY_M_S2,
    FloorSpec,
    ObjectSpec,
    ObjectState,
    PushStatus,  # noqa: E402
    SceneSpec,
    SimSettings,
    tilt_deg,
)
from comexp.sim.simulator import Simulator  # noqa: E402
from comexp.sim.view import crop_camera, object_window_px  # noqa: E402

_PARK_XY_M = (3.0, 3.0)  # far outside the floor and the camera frustum
_NO_RECORD = np.zeros((0, 5))  # push_steps: no friction inputs recorded
_push_steps_call = DirectCall(push_steps)  # a chunk of the protocol's steps (`advance`)
_push_chunks_call = DirectCall(push_chunks)  # chunks of them (`advance_chunks`)
_UNSTABLE_WARNINGS = (
    mujoco.mjtWarning.mjWARN_BADQACC,
    mujoco.mjtWarning.mjWARN_BADQVEL,
    mujoco.mjtWarning.mjWARN_BADQPOS,
    mujoco.mjtWarning.mjWARN_CONTACTFULL,
    mujoco.mjtWarning.mjWARN_CNSTRFULL,
)
_UNSTABLE_WARNING_INDEX = np.array([int(w) for w in _UNSTABLE_WARNINGS])


# What "MuJoCo out of the box" means in docs/physics_mujoco.md (before/after measurements).
NAIVE_CONTACT = MujocoContactSettings(
    solref=(0.02, 1.0),
    solimp=(0.9, 0.95, 0.001, 0.5, 2.0),
    integrator="Euler",
    iterations=100,
    tolerance=1e-8,
    multiccd=False,
    use_box_geoms=False,
    solreffriction=(0.0, 0.0),
    support_spacing_m=0.0,
    build_settle_s=0.0,
    pusher_geom="cylinder",
)


def _fmt(*vals: float) -> str:
    return " ".join(repr(float(v)) for v in vals)


def _axis_aligned_rect(poly: tuple[tuple[float, float], ...]) -> tuple[float, ...] | None:
    """(cx, cy, half_x, half_y) when the polygon is an axis-aligned rectangle, else None."""
    if len(poly) != 4:
        return None
    p = np.asarray(poly, dtype=float)
    xs, ys = np.unique(np.round(p[:, 0], 12)), np.unique(np.round(p[:, 1], 12))
    if len(xs) != 2 or len(ys) != 2:
        return None
    corners = {(round(x, 12), round(y, 12)) for x in xs for y in ys}
    if corners != {(round(x, 12), round(y, 12)) for x, y in p}:
        return None
    return (
        (xs[0] + xs[1]) / 2.0,
        (ys[0] + ys[1]) / 2.0,
        (xs[1] - xs[0]) / 2.0,
        (ys[1] - ys[0]) / 2.0,
    )


def scene_mjcf(
    scene: SceneSpec,
    settings: SimSettings,
    contact: MujocoContactSettings,
    floor_friction: str = "model",
) -> str:
    """The MJCF of a scene. Deterministic text: equal scenes give equal strings (cache key)."""
    obj, floor, pusher, cam = scene.obj, scene.floor, scene.pusher, scene.camera
    h = obj.height_m
    assets, obj_geoms = _object_geoms(obj, contact)
    supports = _support_geoms(obj, contact, floor_friction)
    obj_geoms += supports
    pairs = _contact_pairs(obj, floor, contact, floor_friction, len(supports))
    ix, iy, iz = obj.ixx_kg_m2, obj.iyy_kg_m2, obj.izz_kg_m2
    half = floor.size_m / 2.0
    pz = pusher.clearance_m + pusher.length_m / 2.0
    extent = cam.far_m  # depth is metric when extent * znear/zfar are the camera's near/far
    flags = '<flag multiccd="enable"/>' if contact.multiccd else ""
    return f"""<mujoco model="comexp_scene">
  <compiler angle="radian" inertiafromgeom="false"/>
  <option timestep="{settings.timestep_s / contact.substeps!r}" cone="{contact.cone}"
          gravity="0 0 {-GRAVITY_M_S2!r}"
          impratio="{contact.impratio!r}" noslip_iterations="{contact.noslip_iterations}"
          integrator="{contact.integrator}" iterations="{contact.iterations}"
          tolerance="{contact.tolerance!r}">{flags}</option>
  <statistic extent="{extent!r}" center="0 0 0"/>
  <visual>
    <map znear="{cam.near_m / extent!r}" zfar="{cam.far_m / extent!r}"/>
    <global offwidth="{max(cam.width_px, 64)}" offheight="{max(cam.height_px, 64)}"/>
  </visual>
  <default><geom contype="0" conaffinity="0"/></default>
  <asset>{"".join(assets)}</asset>
  <worldbody>
    <geom name="floor" type="box" size="{_fmt(half, half, floor.thickness_m / 2)}"
          pos="{_fmt(0.0, 0.0, -floor.thickness_m / 2)}" rgba="0.5 0.5 0.5 1"/>
    <camera name="top" pos="{_fmt(0.0, 0.0, cam.height_m)}" fovy="{cam.fov_deg!r}"/>
    <body name="object">
      <freejoint name="object"/>
      <inertial pos="{_fmt(obj.com_m[0], obj.com_m[1], h / 2)}" mass="{obj.mass_kg!r}"
                diaginertia="{_fmt(ix, iy, iz)}"/>
      {"".join(obj_geoms)}
    </body>
    <body name="pusher" pos="{_fmt(0.0, 0.0, pz)}">
      <joint name="pusher_x" type="slide" axis="1 0 0"/>
      <joint name="pusher_y" type="slide" axis="0 1 0"/>
      <inertial pos="0 0 0" mass="{contact.pusher_mass_kg!r}" diaginertia="1 1 1"/>
      <geom name="pusher" type="{contact.pusher_geom}"
            size="{_fmt(pusher.radius_m, pusher.length_m / 2)}" rgba="0.2 0.2 0.8 1"/>
    </body>
  </worldbody>
  <contact>{"".join(pairs)}</contact>
  {PUSHER_SENSOR_MJCF}
</mujoco>
"""


def _object_geoms(obj: ObjectSpec, contact: MujocoContactSettings) -> tuple[list[str], list[str]]:
    """The object's mesh assets and its geoms: a box for an axis-aligned rectangle part (when
    `use_box_geoms`), else the part's prism as a mesh."""
    h = obj.height_m
    assets, obj_geoms = [], []
    for i, part in enumerate(obj.convex_parts_m):
        rect = _axis_aligned_rect(part) if contact.use_box_geoms else None
        if rect is not None:
            cx, cy, hx, hy = rect
            obj_geoms.append(
                f'<geom name="obj{i}" type="box" size="{_fmt(hx, hy, h / 2)}" '
                f'pos="{_fmt(cx, cy, h / 2)}" rgba="0.8 0.3 0.2 1"/>'
            )
        else:
            verts = [(x, y, z) for z in (0.0, h) for x, y in part]
            vtxt = " ".join(_fmt(*v) for v in verts)
            assets.append(f'<mesh name="part{i}" vertex="{vtxt}"/>')
            obj_geoms.append(
                f'<geom name="obj{i}" type="mesh" mesh="part{i}" rgba="0.8 0.3 0.2 1"/>'
            )
    return assets, obj_geoms


def _support_geoms(
    obj: ObjectSpec, contact: MujocoContactSettings, floor_friction: str = "model"
) -> tuple[str, ...]:
    """The object's floor supports as invisible sphere geoms (`_support_points`: the core,
    then the rim), laid out by `_support_settings`."""
    return _support_geoms_of(obj.outline_m, obj.com_m, _support_settings(contact, floor_friction))


def _support_settings(contact: MujocoContactSettings, floor_friction: str) -> MujocoContactSettings:
    """The settings the floor supports are laid out with: `support_spacing_m` and
    `support_min_points` where they carry MuJoCo's friction (`native`), the `_model` ones
    where they carry the weight only (`model`); no supports where `support_spacing_m` is 0."""
    if floor_friction != "model" or contact.support_spacing_m <= 0:
        return contact
    return replace(
        contact,
        support_spacing_m=contact.support_spacing_model_m,
        support_min_points=contact.support_min_points_model,
    )


@functools.lru_cache(maxsize=16)
def _support_geoms_of(
    outline: tuple[tuple[float, float], ...],
    com: tuple[float, float],
    contact: MujocoContactSettings,
) -> tuple[str, ...]:
    """`_support_geoms` of what it depends on: an object's outline and CoM, which the 8
    conditions of a worker's batch share (docs/performance.md), are laid out once."""
    core, rim = (
        _support_points(outline, com, contact) if contact.support_spacing_m > 0 else ([], [])
    )
    r_sup = contact.support_radius_m
    rim_z = r_sup + contact.rim_lift_m
    supports = [(x, y, r_sup) for x, y in core] + [(x, y, rim_z) for x, y in rim]
    return tuple(
        f'<geom name="sup{j}" type="sphere" size="{r_sup!r}" pos="{_fmt(x, y, z)}" '
        f'group="3" rgba="0 0 0 0"/>'
        for j, (x, y, z) in enumerate(supports)
    )


def _contact_pairs(
    obj: ObjectSpec,
    floor: FloorSpec,
    contact: MujocoContactSettings,
    floor_friction: str,
    n_supports: int,
) -> list[str]:
    """The explicit contact pairs: floor with each support (or each object part when there
    are no supports), and pusher with each object part, at exactly the configured friction."""
    n_parts = len(obj.convex_parts_m)
    solref, solimp = _fmt(*contact.solref), _fmt(*contact.solimp)
    sref = f'solref="{solref}" solimp="{solimp}" solreffriction="{_fmt(*contact.solreffriction)}"'
    pairs = []
    floor_geoms = [f"sup{j}" for j in range(n_supports)] or [f"obj{i}" for i in range(n_parts)]
    for g in floor_geoms:
        # first tangent of a horizontal floor contact = world y, second = world x (see header)
        condim = 3
        friction = f'friction="{_fmt(floor.mu_y, floor.mu_x, 0.0, 0.0, 0.0)}" '
        if floor_friction == "model":
            # normal support only: the footprint model supplies the friction, and the floor's
            # coefficients stay out of the MJCF (a condim 1 contact does not read them), so
            # scenes that differ in them share a compiled model (`_compiled_model`)
            condim, friction = 1, ""
        pairs.append(f'<pair geom1="floor" geom2="{g}" condim="{condim}" {friction}{sref}/>')
    psref = sref
    if contact.pusher_solref is not None:
        psref = sref.replace(f'solref="{solref}"', f'solref="{_fmt(*contact.pusher_solref)}"')
    for i in range(n_parts):
        pairs.append(
            f'<pair name="pusher{i}" geom1="pusher" geom2="obj{i}" condim="3" '
            f'friction="{_fmt(obj.mu_pusher, obj.mu_pusher, 0.0, 0.0, 0.0)}" '
            f"{psref}/>"
        )
    return pairs


def _support_points(
    outline: tuple[tuple[float, float], ...],
    com: tuple[float, float],
    contact: MujocoContactSettings,
) -> tuple[list[tuple[float, float]], list[tuple[float, float]]]:
    """Floor supports: a core grid that is point-symmetric about the CoM, and a raised rim.

    Core: grid points p = c + h (i + 1/2, j + 1/2) kept when both p and its mirror 2c - p lie
    in the footprint (inset by the sphere radius), i.e. a uniform pressure over the largest
    region of the footprint that is point-symmetric about the CoM c. MuJoCo's soft contact
    solution acts about the contact set's own centre whenever friction is not saturated
    (impact, slow slip, the first steps of a slide); with a point-symmetric set that centre is
    the CoM, so a push through the CoM cannot turn the object. (A full uniform grid centres
    it on the footprint centroid, and matching only the centroid is not enough: measured in
    docs/physics_mujoco.md.) The spacing is halved until the core has enough points; the
    core region's boundary is sampled too (in mirror pairs), so the supports reach the
    footprint's edges wherever the region does: a sliding object needs support out to its
    edges or it rocks (measured: decel 0.95 mu g instead of 1.00 without the boundary).

    Rim: the corners of the footprint's convex hull (inset), `rim_lift_m` above the floor:
    they carry no load at rest (and cost no contact rows) and take it when the object tilts
    beyond the core, so tipping happens about the true footprint and the object never sinks
    past its edge.
    """
    from shapely.geometry import Point, Polygon

    r = contact.support_radius_m
    poly = Polygon(outline)
    inner = poly.buffer(-1.5 * r, join_style="mitre")
    c = np.asarray(com, dtype=float)
    if not inner.contains(Point(c)):
        raise ValueError(f"CoM {tuple(com)} is not inside the footprint")
    x0, y0, x1, y1 = poly.bounds
    h = contact.support_spacing_m
    hull = np.asarray(poly.convex_hull.exterior.coords)[:-1]
    corners = []
    for v in hull:  # moved onto the inset footprint and a hair towards the CoM
        q = np.asarray(shapely.ops.nearest_points(inner, Point(v))[0].coords[0])
        q = q + (c - q) * 1e-6
        corners.append((float(q[0]), float(q[1])))
    core: list[tuple[float, float]] = []
    while True:
        n = int(math.ceil(max(x1 - x0, y1 - y0) / h)) + 1
        k = np.arange(-n, n) + 0.5
        gx, gy = np.meshgrid(k * h, k * h)
        g = np.stack([gx.ravel(), gy.ravel()], axis=1)
        p, q = c + g, c - g  # the condition below is symmetric in g <-> -g
        keep = shapely.contains_xy(inner, p[:, 0], p[:, 1]) & shapely.contains_xy(
            inner, q[:, 0], q[:, 1]
        )
        core = [(float(x), float(y)) for x, y in p[keep]]
        if len(core) >= contact.support_min_points or h < 4 * r:
            break
        h /= 2.0
    # the core region's edge, sampled every h from each corner, each sample with its mirror
    # image: the core reaches the footprint's edges where the footprint allows it (e.g. all
    # of a centred rectangle) and the set stays exactly point-symmetric
    mirrored = shapely.affinity.rotate(inner, 180.0, origin=(float(c[0]), float(c[1])))
    region = inner.intersection(mirrored)
    edge: list[np.ndarray] = []
    for part in getattr(region, "geoms", [region]):
        if part.geom_type != "Polygon" or part.is_empty:
            continue
        ring = np.asarray(part.exterior.coords)
        for a, b in zip(ring[:-1], ring[1:], strict=True):
            n_seg = max(1, int(math.ceil(float(np.hypot(*(b - a))) / h - 1e-9)))
            edge.extend(a + (b - a) * k / n_seg for k in range(n_seg))
    for v in edge:
        pair = (v, 2.0 * c - v)
        known = np.asarray(core).reshape(-1, 2)
        if all(known.size == 0 or np.min(np.hypot(*(known - q).T)) > 1e-6 for q in pair):
            core.extend((float(q[0]), float(q[1])) for q in pair)
    return core, corners  # rim: the hull corners (the tipping edges)


def _geometry_key(scene: SceneSpec, contact: MujocoContactSettings) -> tuple:
    """Everything that changes what the camera sees (not mass, inertia or friction)."""
    return (
        scene.obj.convex_parts_m,
        scene.obj.height_m,
        scene.floor.size_m,
        scene.floor.thickness_m,
        scene.pusher,
        scene.camera,
        contact.use_box_geoms,
    )


def _quat_to_rpy(q: np.ndarray) -> tuple[float, float, float]:
    """MuJoCo (w, x, y, z) quaternion -> roll, pitch, yaw (ZYX convention)."""
    w, x, y, z = q.tolist()
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def _tilt_deg_of_cos(c: float) -> float:
    """The tilt angle of `cos_tilt`'s cosine."""
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def _window_frustum(
    cam: mujoco.MjvGLCamera, width_px: int, height_px: int, u0: int, v0: int, w: int, h: int
) -> None:
    """Make a scene camera's frustum (as mjv_updateScene left it for the full width_px x
    height_px image) the off-centre frustum of the w x h window with top-left pixel (u0, v0).

    mjr_render calls glFrustum(center -+ halfwidth, bottom, top) at the near plane, halfwidth
    = frustum_width or, when 0, the viewport's aspect times the half height; the full image's
    pixels tile that rectangle, row 0 at the top after the read-back's flip. The window's
    frustum is its sub-rectangle, so its pixels are the full image's up to the rasteriser's
    sub-pixel snapping, which differs between the two viewports (measured over 1,532 frames of
    bench/tracking.py --compare-frames: median frame maximum < 1e-6 m, one edge pixel flipped
    in one frame; tests/test_tracking.py checks three poses to 2e-5 m, masks identical)."""
    top, bottom = float(cam.frustum_top), float(cam.frustum_bottom)
    half_w = float(cam.frustum_width) or 0.5 * width_px / height_px * (top - bottom)
    left = float(cam.frustum_center) - half_w
    px_w, px_h = 2.0 * half_w / width_px, (top - bottom) / height_px
    cam.frustum_center = left + (u0 + 0.5 * w) * px_w
    cam.frustum_width = 0.5 * w * px_w
    cam.frustum_top = top - v0 * px_h
    cam.frustum_bottom = top - (v0 + h) * px_h


@dataclass
class _Renderer:
    """The depth renderer of one object geometry (its own GL context and uploaded meshes)."""

    key: tuple
    model: mujoco.MjModel
    data: mujoco.MjData
    renderer: mujoco.Renderer
    cam_id: int = field(default=0)


KEPT_MODELS = 2  # compiled scene models a simulator keeps (`_compiled_model`)


@dataclass
class _CompiledScene:
    """A scene's compiled model and data, the addresses the steps use, and its object's
    settled state (`MujocoSimulator._settle_at_origin`, made at its first build)."""

    model: mujoco.MjModel
    data: mujoco.MjData
    obj_qadr: int
    obj_vadr: int
    px_qadr: int
    px_vadr: int
    obj_body: int
    sensor_adr: int
    # MjData's buffers as numpy views (fixed for its life): the compiled step loop reads and
    # writes them in place (backends/mujoco_steps.py); the warning counters are read at
    # every check
    views: tuple[np.ndarray, ...]
    warning_numbers: np.ndarray
    settled: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    @classmethod
    def of(cls, xml: str) -> _CompiledScene:
        m = mujoco.MjModel.from_xml_string(xml)
        d = mujoco.MjData(m)
        return cls(
            m, d,
            int(m.jnt_qposadr[m.joint("object").id]), int(m.jnt_dofadr[m.joint("object").id]),
            int(m.jnt_qposadr[m.joint("pusher_x").id]), int(m.jnt_dofadr[m.joint("pusher_x").id]),
            m.body("object").id, int(m.sensor_adr[m.sensor(PUSHER_SENSOR).id]),
            (d.qpos, d.qvel, d.xipos, d.xfrc_applied, d.sensordata), d.warning.number,
        )  # fmt: skip


class MujocoSimulator(JumpsStillSteps, RunsChunks, Simulator):
    name = "mujoco"
    still_jumps = STILL_JUMPS  # still steps jumped, not stepped

    def __init__(
        self,
        settings: SimSettings | None = None,
        contact: MujocoContactSettings | None = None,
        floor_friction: str = "model",
        renderer: str = "raycast",
    ) -> None:
        super().__init__(settings)
        if floor_friction not in FLOOR_FRICTION_CHOICES:
            raise ValueError(f"floor_friction must be one of {FLOOR_FRICTION_CHOICES}")
        if renderer not in RENDERER_CHOICES:
            raise ValueError(f"renderer must be one of {RENDERER_CHOICES}")
        self.floor_friction = floor_friction
        self.renderer = renderer
        self._fric: FootprintFriction | None = None
        self._pushed = False
        self.contact = contact or DEFAULT_CONTACT
        self._xml: str | None = None  # the MJCF the model was compiled from
        self._xml_key: tuple | None = None  # what `_scene_xml` was written of
        self._models: OrderedDict[str, _CompiledScene] = OrderedDict()  # by MJCF
        self._scene_xml = ""
        self.model: mujoco.MjModel | None = None
        self.data: mujoco.MjData | None = None
        self._settled: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._scene: SceneSpec | None = None
        self._renderers: OrderedDict[tuple, _Renderer] = OrderedDict()
        self._rot_buffer = np.empty(9)  # object_state's rotation matrix, filled in place

    # --- scene ---------------------------------------------------------------------------
    def build(self, scene: SceneSpec) -> None:
        # what the MJCF is made of (all frozen): not the pose, which is set below, so an
        # episode's re-centring builds reuse its text without writing it again
        key = (scene.floor, scene.obj, scene.pusher, scene.camera, self.settings, self.contact,
               self.floor_friction)  # fmt: skip
        if key != self._xml_key:
            self._xml_key = key
            self._scene_xml = scene_mjcf(scene, self.settings, self.contact, self.floor_friction)
        xml = self._scene_xml
        if xml != self._xml:
            self._use(self._compiled_model(xml))
            self._xml = xml
        fl = scene.floor
        self._fric = (
            FootprintFriction(scene.obj, fl.mu_x, fl.mu_y, scene.pusher)
            if self.floor_friction == "model"
            else None
        )
        self._com_local = np.array([scene.obj.com_m[0], scene.obj.com_m[1], scene.obj.height_m / 2])
        self._pushed = False
        compiled = self._models[xml]
        if compiled.settled is None:  # this model's object settled at the origin, yaw 0
            compiled.settled = self._settle_at_origin()
        self._settled = compiled.settled
        self._place_settled(scene.initial_pose)
        self._scene = scene
        self._warnings0 = self._warning_count()
        self._render_key = _geometry_key(scene, self.contact)

    def _compiled_model(self, xml: str) -> _CompiledScene:
        """The model of `xml`, compiled or (one of the last `KEPT_MODELS`) kept: compiling is
        deterministic, so reuse == recompile bitwise, and a build resets its data
        (`_place_settled`). An episode's conditions alternate between models that differ in
        the object's Izz and the pusher's friction only (the floor's friction is not in the
        MJCF under `floor_friction=model`), so a worker's batch of them compiles and settles
        each once."""
        compiled = self._models.pop(xml, None) or _CompiledScene.of(xml)
        self._models[xml] = compiled  # the most recent last
        while len(self._models) > KEPT_MODELS:
            self._models.popitem(last=False)
        return compiled

    def _use(self, c: _CompiledScene) -> None:
        self.model, self.data = c.model, c.data
        self._obj_qadr, self._obj_vadr = c.obj_qadr, c.obj_vadr
        self._px_qadr, self._px_vadr = c.px_qadr, c.px_vadr
        self._obj_body, self._sensor_adr = c.obj_body, c.sensor_adr
        self._views, self._warning_numbers = c.views, c.warning_numbers

    def _settle_at_origin(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The object "resting on the floor", contacts at equilibrium: placed flat at the
        origin with yaw 0, stepped `build_settle_s` with the pusher parked. Returns its free
        joint's qpos and qvel and the data's qacc_warmstart (the solver's start)."""
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        q, v = self._obj_qadr, self._obj_vadr
        d.qpos[q : q + 7] = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
        self._set_pusher(_PARK_XY_M, (0.0, 0.0))
        mujoco.mj_forward(m, d)
        n_settle = round(self.contact.build_settle_s / self.settings.timestep_s)
        mujoco.mj_step(m, d, n_settle * self.contact.substeps)
        return d.qpos[q : q + 7].copy(), d.qvel[v : v + 6].copy(), d.qacc_warmstart.copy()

    def _place_settled(self, pose: Pose2D) -> None:
        """The settled state (`_settle_at_origin`) moved rigidly to `pose`. Settling, the
        object only sinks into its supports on a flat, level floor (nothing moves it along the
        floor: no applied friction, no slip), so settling at any pose is this one translated
        and turned about z, to rounding; a build pays the settle's steps once per model, not
        at every re-centring. Free joint: position and linear velocity (and acceleration) in
        world axes, angular velocity in body axes."""
        m, d = self.model, self.data
        qpos0, qvel0, warm0 = self._settled
        mujoco.mj_resetData(m, d)
        q, v = self._obj_qadr, self._obj_vadr
        c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
        x, y, z = qpos0[:3].tolist()
        d.qpos[q : q + 3] = (pose.x_m + (c * x - s * y), pose.y_m + (s * x + c * y), z)
        turn = np.array((math.cos(pose.yaw_rad / 2), 0.0, 0.0, math.sin(pose.yaw_rad / 2)))
        mujoco.mju_mulQuat(d.qpos[q + 3 : q + 7], turn, qpos0[3:7])
        d.qvel[v : v + 6] = qvel0
        d.qacc_warmstart[:] = warm0
        for arr in (d.qvel, d.qacc_warmstart):
            ax, ay = arr[v], arr[v + 1]
            arr[v], arr[v + 1] = c * ax - s * ay, s * ax + c * ay
        self._set_pusher(_PARK_XY_M, (0.0, 0.0))
        mujoco.mj_forward(m, d)

    def _require(self) -> tuple[mujoco.MjModel, mujoco.MjData]:
        if self.model is None or self.data is None:
            raise RuntimeError("build() a scene first")
        return self.model, self.data

    # --- state ---------------------------------------------------------------------------
    def object_state(self) -> ObjectState:
        _, d = self._require()
        q, v = self._obj_qadr, self._obj_vadr
        quat = d.qpos[q + 3 : q + 7]
        roll, pitch, yaw = _quat_to_rpy(quat)
        rot = self._rot_buffer
        mujoco.mju_quat2Mat(rot, quat)
        w_world = rot.reshape(3, 3) @ d.qvel[v + 3 : v + 6]  # free joint: angular vel is local
        return ObjectState(
            position_m=tuple(d.qpos[q : q + 3].tolist()),
            roll_rad=roll,
            pitch_rad=pitch,
            yaw_rad=yaw,
            linear_velocity_m_s=tuple(d.qvel[v : v + 3].tolist()),
            angular_velocity_rad_s=tuple(w_world.tolist()),
        )

    def set_object_velocity(
        self, linear_m_s: tuple[float, float, float], angular_rad_s: tuple[float, float, float]
    ) -> None:
        _, d = self._require()
        q, v = self._obj_qadr, self._obj_vadr
        rot = np.empty(9)
        mujoco.mju_quat2Mat(rot, d.qpos[q + 3 : q + 7])
        d.qvel[v : v + 3] = linear_m_s
        d.qvel[v + 3 : v + 6] = rot.reshape(3, 3).T @ np.asarray(angular_rad_s, dtype=float)

    # --- pusher --------------------------------------------------------------------------
    def _set_pusher(self, xy: tuple[float, float], vel_xy: tuple[float, float]) -> None:
        d = self.data
        d.qpos[self._px_qadr : self._px_qadr + 2] = xy
        d.qvel[self._px_vadr : self._px_vadr + 2] = vel_xy

    def pusher_xy(self) -> np.ndarray:
        return np.array(self.data.qpos[self._px_qadr : self._px_qadr + 2])

    def _warning_count(self) -> int:
        return int(self._warning_numbers[_UNSTABLE_WARNING_INDEX].sum())

    # --- protocol primitives (comexp.simulator.Simulator.push) ------------------------------
    def place_pusher(self, xy) -> None:
        m, d = self._require()
        self._set_pusher((float(xy[0]), float(xy[1])), (0.0, 0.0))
        mujoco.mj_forward(m, d)

    def park_xy(self) -> tuple[float, float]:
        return _PARK_XY_M

    def engine_failure(self) -> PushStatus | None:
        return PushStatus.SIM_UNSTABLE if self._warning_count() > self._warnings0 else None

    def advance(self, targets: np.ndarray) -> tuple[bool, float]:
        """The pusher follows `targets`, one per step, kinematically: before every step (or run
        of steps) it is put exactly on the commanded path at the commanded velocity, and being
        heavy it coasts through the step at that velocity (the object's reaction changes it by
        < 1e-7 m/s per chunk).

        `floor_friction=model`: the whole chunk is one compiled call (`push_steps`: the
        friction force of every step, mj_step, the touch test). `native`: runs of steps at one
        constant pusher velocity go to MuJoCo as one `mj_step(m, d, n)`. With `trace` set,
        steps go one at a time and every step's state is recorded."""
        m, d = self._require()
        sub = self.contact.substeps
        targets = np.asarray(targets, dtype=float)
        starts, vel = self._pusher_path(targets)
        touched = False
        min_cos = 1.0
        i = 0
        n_all = len(targets)
        while i < n_all:
            j = n_all if self.trace is None else i + 1
            if self._fric is not None:
                t, self._pushed, c = self._friction_steps(m, d, starts[i:j], vel[i:j])
            else:
                if self.trace is None:
                    # equal within rounding: the path's per-step increments differ in the
                    # last bits, and splitting a run there (with its pusher reset) changed a
                    # mu 1 impact's rotation by 1.9 deg (measured): one run per constant
                    # commanded velocity
                    j = i + 1
                    while j < n_all and np.allclose(vel[j], vel[i], rtol=1e-9, atol=1e-12):
                        j += 1
                self._set_pusher(
                    (float(starts[i, 0]), float(starts[i, 1])), (float(vel[i, 0]), float(vel[i, 1]))
                )
                mujoco.mj_step(m, d, (j - i) * sub)
                t = self._pushed = self._pusher_touching()
                q = self._obj_quat()
                c = float(cos_tilt(float(q[1]), float(q[2])))
            touched = touched or t
            min_cos = min(min_cos, c)
            if self.trace is not None:
                self.trace.append(self.object_state())
            i = j
        last = targets[-1] if n_all else self.pusher_xy()
        self._set_pusher(
            (float(last[0]), float(last[1])),
            (float(vel[-1, 0]), float(vel[-1, 1])) if n_all else (0.0, 0.0),
        )
        return touched, _tilt_deg_of_cos(min_cos)

    def runs_chunks(self) -> bool:
        """Under the footprint model the compiled steps run several of the protocol's chunks
        in one call (`push_chunks`); MuJoCo's own friction steps one chunk a call."""
        return self.floor_friction == "model"

    def advance_chunks(
        self, targets: np.ndarray, chunk: int, stop: ChunkStop
    ) -> list[tuple[bool, float, float]]:
        """`advance` chunk after chunk in one compiled call (`push_chunks`), stopping after
        the first chunk whose state `stop` names, or whose tilt is half way to the protocol's
        `tip_limit_deg` (an engine's object is never exactly flat), or that raised an unstable
        warning (`engine_failure`). The steps are those of `advance` on each chunk: the
        pusher put on its path before every step, on its last target after the call. A
        chunk's tilt is the larger of `advance`'s and its state's (`ObjectState.tilt_deg`,
        which the protocol's check would add); the yaw as `object_state` reads it. A traced
        run (`trace`) goes one chunk at a time."""
        if self.trace is not None:
            touched, tilt = self.advance(targets[:chunk])
            return [(touched, tilt, self.object_state().pose.yaw_rad)]
        m, d = self._require()
        n = len(targets) // chunk
        targets = np.asarray(targets[: n * chunk], dtype=float)
        starts, vels = self._pusher_path(targets)  # each chunk's as `advance` makes it
        rule = stop.rule()
        min_cos_tilt = math.cos(math.radians(self.settings.tip_limit_deg / 2.0))
        rest = np.ascontiguousarray(stop.rest_after[:n], dtype=np.bool_)
        args, record = self._loop_args(m, d, starts, vels)
        out = np.empty((n, 7))
        done = _push_chunks_call(
            *args, chunk, rule, min_cos_tilt, rest, self._warning_numbers,
            _UNSTABLE_WARNING_INDEX, self._warnings0, out,
        )  # fmt: skip
        self._keep_inputs(record[: done * chunk])
        self._pushed = bool(out[done - 1, 2])
        last, vel = targets[done * chunk - 1], vels[done * chunk - 1]
        self._set_pusher((float(last[0]), float(last[1])), (float(vel[0]), float(vel[1])))
        ran = []
        for row in out[:done]:
            roll, pitch, yaw = _quat_to_rpy(row[3:7])
            tilt = max(_tilt_deg_of_cos(float(row[1])), tilt_deg(roll, pitch))
            ran.append((bool(row[0]), tilt, yaw))
        return ran

    def jump_pusher(self, targets: np.ndarray) -> None:
        """The pusher on its last target at its last step's velocity, as `advance` leaves it
        (`push_steps` puts it on its path before every step anyway)."""
        prev = self.pusher_xy() if len(targets) < 2 else targets[-2]
        last, dt = targets[-1], self.settings.timestep_s
        vel = ((last[0] - prev[0]) / dt, (last[1] - prev[1]) / dt)
        self._set_pusher((float(last[0]), float(last[1])), (float(vel[0]), float(vel[1])))
        self._pushed = False

    def _friction_steps(
        self, m: mujoco.MjModel, d: mujoco.MjData, starts: np.ndarray, vels: np.ndarray
    ) -> tuple[bool, bool, float]:
        """`push_steps` on this scene: the floor's friction from the footprint model
        (backends/floor_friction.py) as a force at the floor under the CoM, every step;
        MuJoCo's floor contacts are normal-only (condim 1), so its soft friction cone cannot
        raise the normal force. Returns (touched, touching now, least cosine of the tilt)."""
        args, record = self._loop_args(m, d, starts, vels)
        out = _push_steps_call(*args)
        self._keep_inputs(record)
        return out

    def _pusher_path(self, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where each step of `targets` starts (the pusher now, then each target before its
        own) and the velocity that reaches its target within the step."""
        path = np.concatenate((self.pusher_xy()[None, :], targets))
        return path[:-1], (path[1:] - path[:-1]) / self.settings.timestep_s

    def _loop_args(
        self, m: mujoco.MjModel, d: mujoco.MjData, starts: np.ndarray, vels: np.ndarray
    ) -> tuple[tuple, np.ndarray]:
        """The arguments `push_steps` takes (and `push_chunks` begins with) on this scene, and
        the array their `record` fills (no rows unless `FootprintFriction.inputs` records)."""
        qpos, qvel, xipos, xfrc, sensordata = self._views
        f = self._fric
        record = _NO_RECORD if f.inputs is None else np.zeros((len(starts), 5))
        args = (
            m._address, d._address, self.contact.substeps, qpos, qvel, xipos, xfrc,
            sensordata, self._sensor_adr, self._obj_qadr, self._obj_vadr, self._px_qadr,
            self._px_vadr, self._obj_body, self._com_local, starts, vels, f.geo, f.fs,
            f.normal, f.dxw, f.dyw, self.settings.timestep_s, self._pushed, record,
        )  # fmt: skip
        return args, record

    def _keep_inputs(self, record: np.ndarray) -> None:
        """The friction inputs the steps recorded, onto `FootprintFriction.inputs`."""
        inputs = self._fric.inputs
        if inputs is not None:
            inputs.extend((x, y, w, yaw, bool(p)) for x, y, w, yaw, p in record.tolist())

    def _obj_quat(self) -> np.ndarray:
        q = self._obj_qadr
        return self.data.qpos[q + 3 : q + 7]

    def _pusher_touching(self) -> bool:
        """The pusher penetrates the object in the contacts of the last step (its sensor)."""
        return bool(pusher_touching(self._views[4], self._sensor_adr))

    # --- camera --------------------------------------------------------------------------
    def render_depth(self) -> DepthImage:
        _, d = self._require()
        if self.renderer == "raycast":
            return self.raycast_depth()
        r = self._renderer()
        r.data.qpos[:] = d.qpos
        mujoco.mj_kinematics(r.model, r.data)
        mujoco.mj_camlight(r.model, r.data)
        r.renderer.update_scene(r.data, camera=r.cam_id)
        depth = np.asarray(r.renderer.render(), dtype=np.float32).copy()
        return DepthImage(depth_m=depth, camera=self._scene.camera.model())

    def render_tracking_depth(self) -> DepthImage:
        """Only the window the object covers (`object_window_px`): an off-centre frustum
        (`_window_frustum`) rendered into a viewport of the window's size in the same GL
        context and offscreen buffer, read back with mujoco.Renderer's own depth conversion
        (CPU per tracking frame, bench/tracking.py: window 1.0 - 1.4 ms, full image 2.1 - 2.6 ms;
        the rest is fixed cost: scene update, read-back)."""
        _, d = self._require()
        if self.renderer == "raycast":
            return self.raycast_tracking_depth()
        scene = self._scene
        model = scene.camera.model()
        win = object_window_px(model, scene.obj.outline_m, scene.obj.height_m, self.object_state())
        if win is None:
            return self.render_depth()
        u0, v0, w, h = win
        r = self._renderer()
        r.data.qpos[:] = d.qpos
        mujoco.mj_kinematics(r.model, r.data)
        mujoco.mj_camlight(r.model, r.data)
        rr = r.renderer
        rr.update_scene(r.data, camera=r.cam_id)
        for i in range(len(rr.scene.camera)):  # both eyes of the (mono) scene: mjr averages
            _window_frustum(rr.scene.camera[i], model.width_px, model.height_px, u0, v0, w, h)
        # mujoco.Renderer has no public viewport: its rect and size are swapped for this
        # render (read by render() for the viewport, the read-back and the output shape)
        saved = rr._rect, rr._width, rr._height
        rr._rect, rr._width, rr._height = mujoco.MjrRect(0, 0, w, h), w, h
        try:
            depth = np.asarray(rr.render(), dtype=np.float32).copy()
        finally:
            rr._rect, rr._width, rr._height = saved
        if depth.shape != (h, w):  # the private fields above changed meaning
            raise RuntimeError(f"MuJoCo rendered {depth.shape} for a {h} x {w} window")
        return DepthImage(depth_m=depth, camera=crop_camera(model, *win))

    def _renderer(self) -> _Renderer:
        """The depth renderer for the current geometry, created on first use (physics-only
        users never open a GL context). A new GL renderer costs ~70 ms (context ~30 ms, mesh
        upload ~40 ms), so renderers are kept in a least-recently-used cache keyed by the
        geometry (`max_renderers`); the grid runs each object's episodes together, so a small
        cache pays it about once per object and job."""
        hit = self._renderers.get(self._render_key)
        if hit is not None:
            self._renderers.move_to_end(self._render_key)
            return hit
        rmodel = mujoco.MjModel.from_xml_string(self._xml)
        cam = self._scene.camera
        r = mujoco.Renderer(
            rmodel, height=cam.height_px, width=cam.width_px, max_geom=rmodel.ngeom + 16
        )
        r.enable_depth_rendering()
        new = _Renderer(self._render_key, rmodel, mujoco.MjData(rmodel), r, rmodel.camera("top").id)
        self._renderers[self._render_key] = new
        while len(self._renderers) > self.contact.max_renderers:
            _, old = self._renderers.popitem(last=False)
            old.renderer.close()
        return new

    def _close_renderer(self) -> None:
        while self._renderers:
            _, old = self._renderers.popitem()
            old.renderer.close()

    def close(self) -> None:
        self._close_renderer()
        self.model = self.data = None
        self._xml = None
        self._models.clear()


# The backend's revision and settings live in backends/physics_settings.py: bump the
# revision there when a change here changes results.
PHYSICS_VERSION, ENGINE_DISTRIBUTION, PHYSICS_SETTINGS = MUJOCO

__all__ = ["DEFAULT_CONTACT", "NAIVE_CONTACT", "MujocoContactSettings", "MujocoSimulator"]
