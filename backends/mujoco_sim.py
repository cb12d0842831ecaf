"""MuJoCo backend: the scene as generated MJCF, a kinematically driven pusher, EGL depth camera.

Physics choices (measured and justified in docs/physics_mujoco.md):
- Every contact is an explicit `<pair>`: MuJoCo would otherwise combine the two geoms'
  friction by taking the max, and the floor's anisotropy (mu_x along world x, mu_y along world
  y) can only be expressed per pair. For the floor's horizontal normal MuJoCo's contact frame
  has its first tangent along world +y and its second along world -x (whatever the object's
  yaw), so the pair friction is "mu_y mu_x". condim 3: no torsional or rolling friction, which
  would add a spurious resisting torque to the object's rotation.
- Elliptic friction cones and a support polygon that is sampled by several contact points
  (box-box collisions, or multi-point convex collision for mesh parts): a single floor contact
  point under a sliding block cannot carry the shifting normal-force distribution, the block
  pitches about it (the "hop") and its friction acts at one point, which rotates a push through
  the CoM.
- The pusher is a heavy body on two slide joints whose position and velocity are prescribed
  every step (kinematic): unlike a mocap body, the contact solver then sees the pusher's true
  velocity, so the contact does not behave like a wall the object keeps bouncing off.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402

from comexp.scene import (  # noqa: E402
    GRAVITY_M_S2,
    DepthImage,
    ObjectState,
    PushCommand,
    SceneSpec,
    SimSettings,
)
from comexp.simulator import (  # noqa: E402
    PushOutcome,
    PushStatus,
    Simulator,
    classify_state,
)

_PARK_XY_M = (3.0, 3.0)  # far outside the floor and the camera frustum
_CHECK_EVERY = 10  # steps between failure checks while moving
_UNSTABLE_WARNINGS = (
    mujoco.mjtWarning.mjWARN_BADQACC,
    mujoco.mjtWarning.mjWARN_BADQVEL,
    mujoco.mjtWarning.mjWARN_BADQPOS,
    mujoco.mjtWarning.mjWARN_CONTACTFULL,
    mujoco.mjtWarning.mjWARN_CNSTRFULL,
)


@dataclass(frozen=True)
class MujocoContactSettings:
    """Solver and contact parameters; the defaults are the validated ones.

    `solref`/`solimp` apply to every contact pair. `multiccd` asks the convex collider for
    several contact points per mesh pair (MuJoCo >= 3.3 understands the flag; MuJoCo 4 has it
    on by default). `pusher_mass_kg` only has to dwarf the object's 0.2 kg: the pusher's state
    is overwritten every step, the mass just keeps the in-step reaction negligible.
    """

    solref: tuple[float, float] = (0.004, 1.0)
    solimp: tuple[float, float, float, float, float] = (0.95, 0.99, 0.0005, 0.5, 2.0)
    solreffriction: tuple[float, float] = (0.01, 1.0)  # (0, 0): friction rows use solref
    impratio: float = 1.0
    noslip_iterations: int = 0
    integrator: str = "implicitfast"
    iterations: int = 50
    tolerance: float = 1e-10
    multiccd: bool = True
    use_box_geoms: bool = True  # rectangles as primitive boxes (exact box-box collider)
    support_spacing_m: float = 0.01  # > 0: floor contact through a grid of small spheres
    support_radius_m: float = 0.001
    build_settle_s: float = 0.1
    substeps: int = 1  # physics steps per SimSettings.timestep_s (pusher command rate)
    pusher_mass_kg: float = 100.0


DEFAULT_CONTACT = MujocoContactSettings()
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


def scene_mjcf(scene: SceneSpec, settings: SimSettings, contact: MujocoContactSettings) -> str:
    """The MJCF of a scene. Deterministic text: equal scenes give equal strings (cache key)."""
    obj, floor, pusher, cam = scene.obj, scene.floor, scene.pusher, scene.camera
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
    n_parts = len(obj.convex_parts_m)
    supports = _support_points(obj.convex_parts_m, contact) if contact.support_spacing_m > 0 else []
    r_sup = contact.support_radius_m
    for j, (x, y) in enumerate(supports):
        obj_geoms.append(
            f'<geom name="sup{j}" type="sphere" size="{r_sup!r}" pos="{_fmt(x, y, r_sup)}" '
            f'group="3" rgba="0 0 0 0"/>'
        )
    solref, solimp = _fmt(*contact.solref), _fmt(*contact.solimp)
    sref = f'solref="{solref}" solimp="{solimp}" solreffriction="{_fmt(*contact.solreffriction)}"'
    pairs = []
    floor_geoms = [f"sup{j}" for j in range(len(supports))] or [f"obj{i}" for i in range(n_parts)]
    for g in floor_geoms:
        # first tangent of a horizontal floor contact = world y, second = world x (see header)
        pairs.append(
            f'<pair geom1="floor" geom2="{g}" condim="3" '
            f'friction="{_fmt(floor.mu_y, floor.mu_x, 0.0, 0.0, 0.0)}" '
            f"{sref}/>"
        )
    for i in range(n_parts):
        pairs.append(
            f'<pair geom1="pusher" geom2="obj{i}" condim="3" '
            f'friction="{_fmt(obj.mu_pusher, obj.mu_pusher, 0.0, 0.0, 0.0)}" '
            f"{sref}/>"
        )
    ix, iy, iz = obj.ixx_kg_m2, obj.iyy_kg_m2, obj.izz_kg_m2
    half = floor.size_m / 2.0
    pz = pusher.clearance_m + pusher.length_m / 2.0
    extent = cam.far_m  # depth is metric when extent * znear/zfar are the camera's near/far
    flags = '<flag multiccd="enable"/>' if contact.multiccd else ""
    return f"""<mujoco model="comexp_scene">
  <compiler angle="radian" inertiafromgeom="false"/>
  <option timestep="{settings.timestep_s / contact.substeps!r}" cone="elliptic"
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
      <geom name="pusher" type="cylinder" size="{_fmt(pusher.radius_m, pusher.length_m / 2)}"
            rgba="0.2 0.2 0.8 1"/>
    </body>
  </worldbody>
  <contact>{"".join(pairs)}</contact>
</mujoco>
"""


def _support_points(
    parts: tuple[tuple[tuple[float, float], ...], ...], contact: MujocoContactSettings
) -> list[tuple[float, float]]:
    """Floor-contact points sampling the footprint: every part's vertices (inset by the sphere
    radius) plus a regular grid inside it, so that the pressure distribution under the object
    is resolved by many soft contacts instead of 1-4 collider points."""
    r, h = contact.support_radius_m, contact.support_spacing_m
    pts: list[tuple[float, float]] = []
    for part in parts:
        p = np.asarray(part, dtype=float)
        c = p.mean(axis=0)
        for v in p:
            d = c - v
            pts.append(tuple(v + d / np.linalg.norm(d) * r * 1.5))
        lo, hi = p.min(axis=0), p.max(axis=0)
        xs = np.arange(lo[0] + h / 2, hi[0], h)
        ys = np.arange(lo[1] + h / 2, hi[1], h)
        a, b = p, np.roll(p, -1, axis=0)
        for x in xs:
            for y in ys:
                cross = (b[:, 0] - a[:, 0]) * (y - a[:, 1]) - (b[:, 1] - a[:, 1]) * (x - a[:, 0])
                edge = np.hypot(b[:, 0] - a[:, 0], b[:, 1] - a[:, 1])
                if np.all(cross / edge > r * 1.5):  # inside the CCW convex part, off its edges
                    pts.append((float(x), float(y)))
    return [(float(x), float(y)) for x, y in pts]


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
    w, x, y, z = (float(v) for v in q)
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def _tilt_deg(q: np.ndarray) -> float:
    """Angle between the body's z axis and world z, from the quaternion alone (cheap)."""
    c = 1.0 - 2.0 * (float(q[1]) ** 2 + float(q[2]) ** 2)
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def _point_polygon_distance(p: np.ndarray, poly: np.ndarray) -> float:
    """Distance from a point to a closed polygon; 0 inside (even-odd rule)."""
    a, b = poly, np.roll(poly, -1, axis=0)
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.einsum("ij,ij->i", ab, ab), 0.0, 1.0)
    d = float(np.min(np.linalg.norm(a + t[:, None] * ab - p, axis=1)))
    crosses = (a[:, 1] > p[1]) != (b[:, 1] > p[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = a[:, 0] + (p[1] - a[:, 1]) * ab[:, 0] / ab[:, 1]
    inside = int(np.sum(crosses & (p[0] < x_at))) % 2 == 1
    return 0.0 if inside else d


@dataclass
class _Renderer:
    """One depth renderer per object geometry: GL contexts are expensive (~50-100 ms), so it
    is kept while only mass, inertia or friction change between builds."""

    key: tuple
    model: mujoco.MjModel
    data: mujoco.MjData
    renderer: mujoco.Renderer
    cam_id: int = field(default=0)


class MujocoSimulator(Simulator):
    name = "mujoco"

    def __init__(
        self, settings: SimSettings | None = None, contact: MujocoContactSettings | None = None
    ) -> None:
        super().__init__(settings)
        self.contact = contact or DEFAULT_CONTACT
        self._xml: str | None = None
        self.model: mujoco.MjModel | None = None
        self.data: mujoco.MjData | None = None
        self._scene: SceneSpec | None = None
        self._render: _Renderer | None = None
        self._outline = np.zeros((0, 2))

    # --- scene ---------------------------------------------------------------------------
    def build(self, scene: SceneSpec) -> None:
        xml = scene_mjcf(scene, self.settings, self.contact)
        if xml != self._xml:  # compiling is deterministic, so reuse == recompile bitwise
            self.model = mujoco.MjModel.from_xml_string(xml)
            self.data = mujoco.MjData(self.model)
            self._xml = xml
            m = self.model
            self._obj_qadr = int(m.jnt_qposadr[m.joint("object").id])
            self._obj_vadr = int(m.jnt_dofadr[m.joint("object").id])
            self._px_qadr = int(m.jnt_qposadr[m.joint("pusher_x").id])
            self._px_vadr = int(m.jnt_dofadr[m.joint("pusher_x").id])
            self._pusher_body = m.body("pusher").id
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        pose = scene.initial_pose
        q = self._obj_qadr
        d.qpos[q : q + 3] = (pose.x_m, pose.y_m, 0.0)
        d.qpos[q + 3 : q + 7] = (math.cos(pose.yaw_rad / 2), 0.0, 0.0, math.sin(pose.yaw_rad / 2))
        self._set_pusher(_PARK_XY_M, (0.0, 0.0))
        mujoco.mj_forward(m, d)
        self._scene = scene
        self.step(self.contact.build_settle_s)  # "resting on the floor": contacts at equilibrium
        d.time = 0.0
        self._outline = np.asarray(scene.obj.outline_m, dtype=float)
        self._warnings0 = self._warning_count()
        self._render_key = _geometry_key(scene, self.contact)

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
        rot = np.empty(9)
        mujoco.mju_quat2Mat(rot, quat)
        w_world = rot.reshape(3, 3) @ d.qvel[v + 3 : v + 6]  # free joint: angular vel is local
        return ObjectState(
            position_m=tuple(float(x) for x in d.qpos[q : q + 3]),
            roll_rad=roll,
            pitch_rad=pitch,
            yaw_rad=yaw,
            linear_velocity_m_s=tuple(float(x) for x in d.qvel[v : v + 3]),
            angular_velocity_rad_s=tuple(float(x) for x in w_world),
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

    def step(self, duration_s: float) -> None:
        m, d = self._require()
        n = max(0, round(duration_s / self.settings.timestep_s))
        hold = (float(d.qpos[self._px_qadr]), float(d.qpos[self._px_qadr + 1]))
        for _ in range(n):
            self._set_pusher(hold, (0.0, 0.0))
            mujoco.mj_step(m, d, self.contact.substeps)
        self._set_pusher(hold, (0.0, 0.0))

    # --- pusher --------------------------------------------------------------------------
    def _set_pusher(self, xy: tuple[float, float], vel_xy: tuple[float, float]) -> None:
        d = self.data
        d.qpos[self._px_qadr : self._px_qadr + 2] = xy
        d.qvel[self._px_vadr : self._px_vadr + 2] = vel_xy

    def _pusher_xy(self) -> np.ndarray:
        return np.array(self.data.qpos[self._px_qadr : self._px_qadr + 2])

    def _warning_count(self) -> int:
        d = self.data
        return sum(int(d.warning[w].number) for w in _UNSTABLE_WARNINGS)

    def _health(self) -> PushStatus | None:
        if self._warning_count() > self._warnings0:
            return PushStatus.SIM_UNSTABLE
        return classify_state(
            self.object_state(), self._outline, self._scene.camera.model(), self.settings
        )

    def push(self, cmd: PushCommand) -> PushOutcome:
        m, d = self._require()
        s = self.settings
        dt = s.timestep_s
        pose_before = self.true_pose()
        start = np.asarray(cmd.start_xy_m, dtype=float)
        direction = np.asarray(cmd.direction_xy, dtype=float)
        outline_w = pose_before.to_world(self._outline)
        clear = _point_polygon_distance(start, outline_w) > self._scene.pusher.radius_m

        def outcome(status: PushStatus, steps: int, lag: float, tilt: float, contact: bool):
            self._set_pusher(_PARK_XY_M, (0.0, 0.0))
            mujoco.mj_forward(m, d)
            return PushOutcome(
                status=status,
                pose_before=pose_before,
                pose_after=self.true_pose(),
                sim_time_s=steps * dt,
                steps=steps,
                contact_made=contact,
                max_pusher_lag_m=lag,
                max_tilt_deg=tilt,
            )

        if not clear:
            return outcome(PushStatus.PATH_BLOCKED, 0, 0.0, _tilt_deg(self._obj_quat()), False)

        n_move = math.ceil(cmd.travel_m / (cmd.speed_m_s * dt) - 1e-9)
        lag = tilt = 0.0
        contact = False
        steps = 0
        pusher_geom = m.geom("pusher").id
        # move: before each step the pusher sits on the commanded path with the commanded
        # velocity; after the step its integrated position is compared with the path
        for k in range(1, n_move + 1):
            s0 = min((k - 1) * cmd.speed_m_s * dt, cmd.travel_m)
            s1 = min(k * cmd.speed_m_s * dt, cmd.travel_m)
            v = tuple(direction * ((s1 - s0) / dt))
            self._set_pusher(tuple(start + direction * s0), v)
            mujoco.mj_step(m, d, self.contact.substeps)
            steps += 1
            lag = max(lag, float(np.linalg.norm(self._pusher_xy() - (start + direction * s1))))
            tilt = max(tilt, _tilt_deg(self._obj_quat()))
            if not contact:
                contact = self._pusher_touching(pusher_geom)
            if k % _CHECK_EVERY == 0 or k == n_move:
                bad = self._health()
                if bad is not None:
                    return outcome(bad, steps, lag, tilt, contact)
        end = tuple(start + direction * cmd.travel_m)
        # settle: the pusher stays where it stopped while the object comes to rest
        hold_needed = max(1, round(s.settle_hold_s / dt))
        calm = 0
        max_settle = round(s.max_settle_s / dt)
        for k in range(1, max_settle + 1):
            self._set_pusher(end, (0.0, 0.0))
            mujoco.mj_step(m, d, self.contact.substeps)
            steps += 1
            tilt = max(tilt, _tilt_deg(self._obj_quat()))
            if not contact:
                contact = self._pusher_touching(pusher_geom)
            vv = d.qvel[self._obj_vadr : self._obj_vadr + 6]
            if math.hypot(vv[0], vv[1], vv[2]) < s.settle_speed_m_s and (
                math.sqrt(vv[3] ** 2 + vv[4] ** 2 + vv[5] ** 2) < s.settle_spin_rad_s
            ):
                calm += 1
            else:
                calm = 0
            if k % _CHECK_EVERY == 0 or calm >= hold_needed:
                bad = self._health()
                if bad is not None:
                    return outcome(bad, steps, lag, tilt, contact)
            if calm >= hold_needed:
                return outcome(PushStatus.OK, steps, lag, tilt, contact)
        return outcome(PushStatus.NOT_SETTLED, steps, lag, tilt, contact)

    def _obj_quat(self) -> np.ndarray:
        q = self._obj_qadr
        return self.data.qpos[q + 3 : q + 7]

    def _pusher_touching(self, pusher_geom: int) -> bool:
        d = self.data
        for i in range(d.ncon):
            c = d.contact[i]
            if (c.geom1 == pusher_geom or c.geom2 == pusher_geom) and c.dist < 0:
                return True
        return False

    # --- camera --------------------------------------------------------------------------
    def render_depth(self) -> DepthImage:
        _, d = self._require()
        r = self._renderer()
        r.data.qpos[:] = d.qpos
        mujoco.mj_kinematics(r.model, r.data)
        mujoco.mj_camlight(r.model, r.data)
        r.renderer.update_scene(r.data, camera=r.cam_id)
        depth = np.asarray(r.renderer.render(), dtype=np.float32).copy()
        return DepthImage(depth_m=depth, camera=self._scene.camera.model())

    def _renderer(self) -> _Renderer:
        """The depth renderer for the current geometry, created on first use (physics-only
        users never open a GL context) and kept across builds with the same geometry."""
        if self._render is not None and self._render.key == self._render_key:
            return self._render
        self._close_renderer()
        rmodel = mujoco.MjModel.from_xml_string(self._xml)
        cam = self._scene.camera
        r = mujoco.Renderer(
            rmodel, height=cam.height_px, width=cam.width_px, max_geom=rmodel.ngeom + 16
        )
        r.enable_depth_rendering()
        self._render = _Renderer(
            self._render_key, rmodel, mujoco.MjData(rmodel), r, rmodel.camera("top").id
        )
        return self._render

    def _close_renderer(self) -> None:
        if self._render is not None:
            self._render.renderer.close()
            self._render = None

    def close(self) -> None:
        self._close_renderer()
        self.model = self.data = None
        self._xml = None


__all__ = ["DEFAULT_CONTACT", "NAIVE_CONTACT", "MujocoContactSettings", "MujocoSimulator"]
