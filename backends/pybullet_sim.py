"""pybullet backend: headless (DIRECT), one physics client per instance, deterministic.

Contact and solver choices (measured, see docs/physics_pybullet.md):
- Floor and object are loaded from generated URDF files with URDF_INITIALIZE_SAT_FEATURES:
  only then do the convex hulls get polyhedral features, so that floor-object contact is a full
  clipped face (4+ points, no collision margin). Shapes built with createCollisionShape ignore
  the flag in pybullet 3.2.7: the prism then rests on a GJK point manifold of 1-3 points, rocks
  (|w| ~ 1 rad/s while sliding) and floats 1-2 mm on the margins.
- Isotropic floor: a fixed rigid (maximal-coordinates) box, no anisotropicFriction. Its contact
  with the object goes through Bullet's rigid-body solver, whose first friction direction is
  each contact point's slip velocity: friction opposes sliding whatever the object's yaw.
  (A multibody floor uses world-fixed friction directions and projects the impulse onto the
  cone in a metric that depends on the contact point's position in world axes: the same push
  rotated by -4.5 .. +9 deg depending on the object's yaw.)
- Anisotropic floor: a fixed-base multibody box with anisotropicFriction = (mu_x, mu_y)/max:
  world-fixed friction directions are the only frame in which the scaling means mu_x along
  world x, mu_y along y (elliptic cone; diagonal slides: see docs/physics_pybullet.md).
- Pair friction is a product in pybullet: object lateralFriction = 1, floor = max(mu_x, mu_y),
  pusher = mu_pusher.
- The pusher is a heavy (100 kg) free rigid cylinder: before each step its velocity is set so
  that it reaches the commanded path point at the end of the step (zero lag in free space) and
  its weight is cancelled. Being a rigid body, its contact with the object also gets slip-aligned
  friction. It is only teleported when clear of the object.
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
import shutil
import tempfile
from collections.abc import Sequence

import numpy as np
import pybullet as pb

from comexp.scene import (
    GRAVITY_M_S2,
    DepthImage,
    ObjectSpec,
    ObjectState,
    Pose2D,
    PushCommand,
    SceneSpec,
    SimSettings,
)
from comexp.simulator import PushOutcome, PushStatus, Simulator, classify_state

# Pusher parking spot (world, m): beyond the floor edge and outside the camera's view at the
# pusher's top (half-width seen there ~0.29 m), and unreachable by an object still in view.
_PARK_XY_M = (0.0, 0.5)
# Retract distance after a push (m) before teleporting to the park position, and its speed.
_RETRACT_M = 0.006
_RETRACT_SPEED_M_S = 0.1
# Geometric clearance (m) between pusher surface and object footprint to count as "clear".
_CLEAR_M = 5e-4
# How often (steps) the shared failure classifier runs while stepping.
_CHECK_EVERY = 5
# Pusher mass (kg): 500x the object's, so contact impulses change its velocity by < 0.2 %
# of the object's change within a step; its velocity is re-imposed before every step.
_PUSHER_MASS_KG = 100.0


def _fmt(x: float) -> str:
    return repr(float(x))


def _prism_obj(part: Sequence[Sequence[float]], height_m: float) -> str:
    """Wavefront OBJ of a convex CCW polygon extruded from z=0 to z=height (outward faces)."""
    n = len(part)
    lines = [f"v {_fmt(x)} {_fmt(y)} 0.0" for x, y in part]
    lines += [f"v {_fmt(x)} {_fmt(y)} {_fmt(height_m)}" for x, y in part]
    faces = []
    for i in range(1, n - 1):  # bottom (seen from below: CW in xy -> normal -z)
        faces.append((1, i + 2, i + 1))
    for i in range(1, n - 1):  # top, CCW -> normal +z
        faces.append((n + 1, n + i + 1, n + i + 2))
    for i in range(n):
        j = (i + 1) % n
        faces.append((i + 1, j + 1, n + j + 1))
        faces.append((i + 1, n + j + 1, n + i + 1))
    lines += [f"f {a} {b} {c}" for a, b, c in faces]
    return "\n".join(lines) + "\n"


def _object_urdf(obj: ObjectSpec, mesh_files: Sequence[str]) -> str:
    cx, cy = obj.com_m
    geoms = "".join(
        f'<collision><geometry><mesh filename="{m}"/></geometry></collision>'
        f'<visual><geometry><mesh filename="{m}"/></geometry></visual>'
        for m in mesh_files
    )
    return (
        '<?xml version="1.0"?><robot name="object"><link name="base">'
        f'<inertial><origin xyz="{_fmt(cx)} {_fmt(cy)} {_fmt(obj.height_m / 2)}"/>'
        f'<mass value="{_fmt(obj.mass_kg)}"/>'
        f'<inertia ixx="{_fmt(obj.ixx_kg_m2)}" iyy="{_fmt(obj.iyy_kg_m2)}" '
        f'izz="{_fmt(obj.izz_kg_m2)}" ixy="0" ixz="0" iyz="0"/></inertial>'
        f"{geoms}</link></robot>"
    )


def _floor_urdf(size_m: float, thickness_m: float) -> str:
    box = f'<geometry><box size="{_fmt(size_m)} {_fmt(size_m)} {_fmt(thickness_m)}"/></geometry>'
    org = f'<origin xyz="0 0 {_fmt(-thickness_m / 2)}"/>'
    return (
        '<?xml version="1.0"?><robot name="floor"><link name="base">'
        '<inertial><mass value="0"/><inertia ixx="0" iyy="0" izz="0" ixy="0" ixz="0" iyz="0"/>'
        f"</inertial><collision>{org}{box}</collision><visual>{org}{box}</visual>"
        "</link></robot>"
    )


def _pusher_urdf(radius_m: float, length_m: float, mass_kg: float) -> str:
    """A free cylinder; its large inertia keeps contact torques from turning it in one step."""
    i = _fmt(mass_kg * 1.0)
    cyl = f'<geometry><cylinder radius="{_fmt(radius_m)}" length="{_fmt(length_m)}"/></geometry>'
    return (
        '<?xml version="1.0"?><robot name="pusher"><link name="tip">'
        f'<inertial><mass value="{_fmt(mass_kg)}"/>'
        f'<inertia ixx="{i}" iyy="{i}" izz="{i}" ixy="0" ixz="0" iyz="0"/>'
        f"</inertial><collision>{cyl}</collision></link></robot>"
    )


def _pixel_centred_projection(proj: Sequence[float], width_px: int, height_px: int) -> list[float]:
    """Shift an OpenGL projection (column-major) so the tiny renderer's pixels match the model.

    With the plain projection, ER_TINY_RENDERER puts the optical axis on column W/2 and row
    H/2 - 1 (measured: a box's top face came out +0.50 px right and 0.50 px up, ~1.4 mm at the
    floor), i.e. it samples pixel corners, not the centres of the CameraModel convention
    ((W-1)/2, (H-1)/2). Adding 1/W to P[2][0] and 1/H to P[2][1] moves the image half a pixel
    left and down; tests/test_physics.py checks the result to 0.25 px.
    """
    m = list(proj)
    m[8] += 1.0 / width_px
    m[9] += 1.0 / height_px
    return m


def _point_polygon_distance(pt: np.ndarray, poly: np.ndarray) -> float:
    """Signed distance from a point to a simple polygon's boundary (negative inside)."""
    a = poly
    b = np.roll(poly, -1, axis=0)
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", pt - a, ab) / np.einsum("ij,ij->i", ab, ab), 0.0, 1.0)
    d = float(np.min(np.linalg.norm(a + t[:, None] * ab - pt, axis=1)))
    # even-odd ray cast for inside
    x, y = pt
    inside = False
    for (x1, y1), (x2, y2) in zip(a, b, strict=True):
        if (y1 > y) != (y2 > y) and x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
            inside = not inside
    return -d if inside else d


class PybulletSimulator(Simulator):
    """pybullet implementation of the simulator interface (see the module docstring)."""

    name = "pybullet"

    def __init__(self, settings: SimSettings | None = None) -> None:
        super().__init__(settings)
        self._cid = pb.connect(pb.DIRECT)
        self._dir = tempfile.mkdtemp(prefix="comexp_pybullet_")
        self._scene: SceneSpec | None = None
        self._floor = -1
        self._pusher = -1
        self._object = -1
        self._com_local = np.zeros(3)
        self._outline = np.zeros((0, 2))
        self._view: list[float] = []
        self._proj: list[float] = []
        self._steps_total = 0
        self._pusher_target = (0.0, 0.0)
        self._pusher_z = 0.0

    # --- construction ---------------------------------------------------------------------
    def _file(self, name: str, text: str) -> str:
        path = os.path.join(self._dir, name)
        if not os.path.exists(path):
            tmp = path + ".tmp"
            with open(tmp, "w") as f:
                f.write(text)
            os.replace(tmp, path)
        return path

    def _hashed_file(self, stem: str, ext: str, text: str) -> str:
        digest = hashlib.sha1(text.encode()).hexdigest()[:16]
        return self._file(f"{stem}_{digest}.{ext}", text)

    def _object_urdf_path(self, obj: ObjectSpec) -> str:
        meshes = [
            os.path.basename(self._hashed_file("part", "obj", _prism_obj(part, obj.height_m)))
            for part in obj.convex_parts_m
        ]
        return self._hashed_file("object", "urdf", _object_urdf(obj, meshes))

    def build(self, scene: SceneSpec) -> None:
        """Reset the whole world and load floor, pusher and object.

        A full reset (rather than keeping floor and pusher) is what makes repeated builds
        bit-identical: no solver warm-start, contact cache or body-id order survives; it costs
        about a millisecond (docs/physics_pybullet.md).
        """
        c = self._cid
        s = self.settings
        pb.resetSimulation(physicsClientId=c)
        pb.setGravity(0.0, 0.0, -GRAVITY_M_S2, physicsClientId=c)
        pb.setPhysicsEngineParameter(
            fixedTimeStep=s.timestep_s,
            numSubSteps=0,
            numSolverIterations=50,
            enableConeFriction=1,
            enableSAT=1,
            deterministicOverlappingPairs=1,
            physicsClientId=c,
        )
        flags = pb.URDF_INITIALIZE_SAT_FEATURES | pb.URDF_USE_INERTIA_FROM_FILE
        fl = scene.floor
        floor_path = self._hashed_file("floor", "urdf", _floor_urdf(fl.size_m, fl.thickness_m))
        # Isotropic floor: a rigid body, so that the floor-object contact goes through the
        # rigid-body solver, whose first friction direction follows each point's slip velocity
        # (friction opposes sliding whatever the object's yaw). Anisotropic floor: a multibody,
        # whose contacts use friction directions fixed to the world axes, the only frame in
        # which Bullet's anisotropicFriction scaling means "mu_x along x, mu_y along y".
        self._floor = pb.loadURDF(
            floor_path,
            useFixedBase=True,
            useMaximalCoordinates=fl.isotropic,
            flags=flags,
            physicsClientId=c,
        )
        mu_max = max(fl.mu_x, fl.mu_y)
        floor_dyn: dict[str, object] = {}
        if not fl.isotropic:  # never set on iso floors: see docs/physics_pybullet.md
            floor_dyn["anisotropicFriction"] = [fl.mu_x / mu_max, fl.mu_y / mu_max, 1.0]
        pb.changeDynamics(
            self._floor,
            -1,
            lateralFriction=mu_max,
            restitution=0.0,
            rollingFriction=0.0,
            spinningFriction=0.0,
            physicsClientId=c,
            **floor_dyn,
        )

        pu = scene.pusher
        self._pusher_z = pu.clearance_m + pu.length_m / 2.0
        pusher_path = self._hashed_file(
            "pusher", "urdf", _pusher_urdf(pu.radius_m, pu.length_m, _PUSHER_MASS_KG)
        )
        self._pusher = pb.loadURDF(
            pusher_path,
            basePosition=[_PARK_XY_M[0], _PARK_XY_M[1], self._pusher_z],
            useMaximalCoordinates=True,
            flags=flags,
            physicsClientId=c,
        )
        pb.changeDynamics(
            self._pusher,
            -1,
            lateralFriction=scene.obj.mu_pusher,
            restitution=0.0,
            rollingFriction=0.0,
            spinningFriction=0.0,
            linearDamping=0.0,
            angularDamping=0.0,
            activationState=pb.ACTIVATION_STATE_DISABLE_SLEEPING,
            physicsClientId=c,
        )
        pb.setCollisionFilterPair(self._pusher, self._floor, -1, -1, 0, physicsClientId=c)
        self._teleport_pusher(_PARK_XY_M)

        obj = scene.obj
        self._com_local = np.array([obj.com_m[0], obj.com_m[1], obj.height_m / 2.0])
        self._outline = np.asarray(obj.outline_m, dtype=float)
        pose = scene.initial_pose
        self._object = pb.loadURDF(
            self._object_urdf_path(obj),
            basePosition=[pose.x_m, pose.y_m, 0.0],
            baseOrientation=pb.getQuaternionFromEuler([0.0, 0.0, pose.yaw_rad]),
            useMaximalCoordinates=True,
            flags=flags,
            physicsClientId=c,
        )
        pb.changeDynamics(
            self._object,
            -1,
            lateralFriction=1.0,
            restitution=0.0,
            rollingFriction=0.0,
            spinningFriction=0.0,
            linearDamping=0.0,
            angularDamping=0.0,
            activationState=pb.ACTIVATION_STATE_DISABLE_SLEEPING,
            physicsClientId=c,
        )
        self._scene = scene
        cam = scene.camera
        self._view = pb.computeViewMatrix(
            cameraEyePosition=[0.0, 0.0, cam.height_m],
            cameraTargetPosition=[0.0, 0.0, 0.0],
            cameraUpVector=[0.0, 1.0, 0.0],
            physicsClientId=c,
        )
        self._proj = _pixel_centred_projection(
            pb.computeProjectionMatrixFOV(
                fov=cam.fov_deg,
                aspect=cam.width_px / cam.height_px,
                nearVal=cam.near_m,
                farVal=cam.far_m,
                physicsClientId=c,
            ),
            cam.width_px,
            cam.height_px,
        )

    # --- pusher ---------------------------------------------------------------------------
    def _step_once(self) -> None:
        """One engine step with the pusher driven onto its target.

        The pusher is a heavy free rigid body: before every step its velocity is set to reach
        the target at the end of the step and its weight is cancelled, so it follows the path
        with no lag in free space and is barely slowed by a 0.2 kg object (mass ratio 500).
        """
        c = self._cid
        pos, _ = pb.getBasePositionAndOrientation(self._pusher, physicsClientId=c)
        inv_dt = 1.0 / self.settings.timestep_s
        tx, ty = self._pusher_target
        vel = [(tx - pos[0]) * inv_dt, (ty - pos[1]) * inv_dt, (self._pusher_z - pos[2]) * inv_dt]
        pb.resetBaseVelocity(self._pusher, vel, [0.0, 0.0, 0.0], physicsClientId=c)
        pb.applyExternalForce(
            self._pusher,
            -1,
            [0.0, 0.0, _PUSHER_MASS_KG * GRAVITY_M_S2],
            pos,
            pb.WORLD_FRAME,
            physicsClientId=c,
        )
        pb.stepSimulation(physicsClientId=c)

    def _teleport_pusher(self, xy: Sequence[float]) -> None:
        c = self._cid
        pos = [float(xy[0]), float(xy[1]), self._pusher_z]
        pb.resetBasePositionAndOrientation(self._pusher, pos, [0, 0, 0, 1], physicsClientId=c)
        pb.resetBaseVelocity(self._pusher, [0, 0, 0], [0, 0, 0], physicsClientId=c)
        self._pusher_target = (pos[0], pos[1])

    def _command_pusher(self, xy: Sequence[float]) -> None:
        self._pusher_target = (float(xy[0]), float(xy[1]))

    def _pusher_xy(self) -> np.ndarray:
        pos, _ = pb.getBasePositionAndOrientation(self._pusher, physicsClientId=self._cid)
        return np.array(pos[:2])

    def _pusher_clearance_m(self, xy: Sequence[float], state: ObjectState) -> float:
        """Gap between the pusher's surface and the object's footprint (negative = overlap)."""
        poly = state.pose.to_world(self._outline)
        assert self._scene is not None
        return _point_polygon_distance(np.asarray(xy, float), poly) - self._scene.pusher.radius_m

    # --- queries --------------------------------------------------------------------------
    def _require_scene(self) -> SceneSpec:
        if self._scene is None:
            raise RuntimeError("build() a scene first")
        return self._scene

    def object_state(self) -> ObjectState:
        self._require_scene()
        c = self._cid
        com, quat = pb.getBasePositionAndOrientation(self._object, physicsClientId=c)
        v_com, w = pb.getBaseVelocity(self._object, physicsClientId=c)
        rot = np.array(pb.getMatrixFromQuaternion(quat)).reshape(3, 3)
        r = rot @ self._com_local  # origin -> CoM, world
        origin = np.asarray(com) - r
        v = np.asarray(v_com) - np.cross(np.asarray(w), r)
        roll, pitch, yaw = pb.getEulerFromQuaternion(quat)
        return ObjectState(
            position_m=(float(origin[0]), float(origin[1]), float(origin[2])),
            roll_rad=float(roll),
            pitch_rad=float(pitch),
            yaw_rad=float(yaw),
            linear_velocity_m_s=(float(v[0]), float(v[1]), float(v[2])),
            angular_velocity_rad_s=(float(w[0]), float(w[1]), float(w[2])),
        )

    def render_depth(self) -> DepthImage:
        scene = self._require_scene()
        cam = scene.camera
        _, _, _, depth_buf, _ = pb.getCameraImage(
            cam.width_px,
            cam.height_px,
            viewMatrix=self._view,
            projectionMatrix=self._proj,
            renderer=pb.ER_TINY_RENDERER,
            flags=pb.ER_NO_SEGMENTATION_MASK,
            physicsClientId=self._cid,
        )
        zb = np.asarray(depth_buf, dtype=np.float64).reshape(cam.height_px, cam.width_px)
        near, far = cam.near_m, cam.far_m
        depth = far * near / (far - (far - near) * zb)
        return DepthImage(depth_m=depth.astype(np.float32), camera=cam.model())

    # --- test hooks -----------------------------------------------------------------------
    def set_object_velocity(
        self, linear_m_s: tuple[float, float, float], angular_rad_s: tuple[float, float, float]
    ) -> None:
        self._require_scene()
        _, quat = pb.getBasePositionAndOrientation(self._object, physicsClientId=self._cid)
        rot = np.array(pb.getMatrixFromQuaternion(quat)).reshape(3, 3)
        w = np.asarray(angular_rad_s, dtype=float)
        v_com = np.asarray(linear_m_s, dtype=float) + np.cross(w, rot @ self._com_local)
        pb.resetBaseVelocity(self._object, v_com.tolist(), w.tolist(), physicsClientId=self._cid)

    def step(self, duration_s: float) -> None:
        self._require_scene()
        n = max(0, round(duration_s / self.settings.timestep_s))
        self._command_pusher(self._pusher_xy())
        for _ in range(n):
            self._step_once()

    def _planar_rest(self, s: SimSettings) -> bool:
        """Is the object's planar motion (what the camera and the estimator see) at rest?

        Judged on the horizontal velocity of the footprint point under the CoM and on the yaw
        rate. Not on the full 3D velocity: a prism with a many-sided footprint (ellipse, disc,
        hexagon) rocks by ~0.02 deg at rest in pybullet, because the floor contact keeps only 4
        of its bottom corners and which 4 changes from step to step; that rocking moves the CoM
        by mm/s (vertically and, at CoM height, sideways) and used to end pushes `not_settled`.
        """
        v, w = pb.getBaseVelocity(self._object, physicsClientId=self._cid)
        c = self._com_local[2]  # CoM height: the floor point under it moves at v - w x (0,0,c)
        vx, vy = v[0] - c * w[1], v[1] + c * w[0]
        return math.hypot(vx, vy) < s.settle_speed_m_s and abs(w[2]) < s.settle_spin_rad_s

    # --- push -----------------------------------------------------------------------------
    def push(self, cmd: PushCommand) -> PushOutcome:
        scene = self._require_scene()
        s = self.settings
        dt = s.timestep_s
        c = self._cid
        camera = scene.camera.model()
        before = self.object_state()
        start = np.asarray(cmd.start_xy_m, dtype=float)
        direction = np.asarray(cmd.direction_xy, dtype=float)
        max_tilt = before.tilt_deg
        if self._pusher_clearance_m(start, before) < 0.0:
            return PushOutcome(
                PushStatus.PATH_BLOCKED, before.pose, before.pose, 0.0, 0, False, 0.0, max_tilt
            )

        steps = 0
        contact = False
        lag = 0.0
        status: PushStatus | None = None
        self._teleport_pusher(start)

        def advance() -> ObjectState | None:
            """One step; returns the state when it was checked for failures."""
            nonlocal steps, contact, status, max_tilt
            self._step_once()
            steps += 1
            if not contact and pb.getContactPoints(self._pusher, self._object, physicsClientId=c):
                contact = True
            if steps % _CHECK_EVERY == 0:
                st = self.object_state()
                max_tilt = max(max_tilt, st.tilt_deg) if st.is_finite else max_tilt
                status = classify_state(st, self._outline, camera, s)
                return st
            return None

        # 1) the straight path at the commanded speed. The motor (kp = kd = 1, target velocity
        #    0) reaches its target in one step, so the target of each step is where the path is
        #    at the end of that step: the pusher follows the path with no lag in free space.
        n_move = math.ceil(cmd.travel_m / (cmd.speed_m_s * dt) - 1e-9)
        for k in range(1, n_move + 1):
            travelled = min(cmd.speed_m_s * k * dt, cmd.travel_m)
            target = start + direction * travelled
            self._command_pusher(target)
            advance()
            lag = max(lag, float(np.linalg.norm(self._pusher_xy() - target)))
            if status is not None:
                break

        # 2) hold the pusher still and let the object come to rest.
        if status is None:
            hold_steps = max(1, round(s.settle_hold_s / dt))
            quiet = 0
            for _ in range(max(1, round(s.max_settle_s / dt))):
                advance()
                if status is not None:
                    break
                if self._planar_rest(s):
                    quiet += 1
                    if quiet >= hold_steps:
                        break
                else:
                    quiet = 0
            else:
                status = PushStatus.NOT_SETTLED

        # 3) back off along the push line until clear, then park out of view.
        if status is None:
            pos = self._pusher_xy()
            n_back = math.ceil(_RETRACT_M / (_RETRACT_SPEED_M_S * dt))
            for k in range(1, n_back + 1):
                target = pos - direction * min(_RETRACT_SPEED_M_S * k * dt, _RETRACT_M)
                self._command_pusher(target)
                advance()
                if status is not None:
                    break
        after = self.object_state()
        if status is None or status is PushStatus.NOT_SETTLED:
            final = classify_state(after, self._outline, camera, s)
            status = final or status
        if self._pusher_clearance_m(self._pusher_xy(), after) > _CLEAR_M:
            self._teleport_pusher(_PARK_XY_M)
        max_tilt = max(max_tilt, after.tilt_deg) if after.is_finite else max_tilt
        self._steps_total += steps
        return PushOutcome(
            status=status or PushStatus.OK,
            pose_before=before.pose,
            pose_after=after.pose if after.is_finite else before.pose,
            sim_time_s=steps * dt,
            steps=steps,
            contact_made=contact,
            max_pusher_lag_m=lag,
            max_tilt_deg=max_tilt,
        )

    def true_pose(self) -> Pose2D:
        return self.object_state().pose

    def close(self) -> None:
        if self._cid >= 0:
            try:
                pb.disconnect(physicsClientId=self._cid)
            finally:
                self._cid = -1
                shutil.rmtree(self._dir, ignore_errors=True)

    def __del__(self) -> None:  # best effort: never leak a physics server or temp dir
        with contextlib.suppress(Exception):
            self.close()
