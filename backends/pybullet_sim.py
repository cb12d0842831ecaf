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
- The pusher is a heavy (100 kg) free rigid sphere: before each step its velocity is set so
  that it reaches the commanded path point at the end of the step (zero lag in free space); it
  falls with gravity within a step like the resting object and is put back at its height before
  the next. Its inertia is a thin rod's along a horizontal axle across the push: it rolls freely
  in the vertical plane, so its contact has Coulomb friction in the floor's plane only, as in
  the model (`_pusher_urdf`, `_step_once`). It is only teleported when clear of the object.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import tempfile
from collections.abc import Sequence

import numpy as np

from comexp.backends.floor_friction import FootprintFriction
from comexp.backends.numba_kernels import DirectCall
from comexp.backends.physics_settings import (
    FLOOR_FRICTION_CHOICES,
    PYBULLET,
    PYBULLET_PUSHER_AXLE_INERTIA_M2,
    PYBULLET_PUSHER_MASS_KG,
    PYBULLET_SOLVER_ITERATIONS,
    RENDERER_CHOICES,
    STILL_JUMPS,
)
from comexp.method.frames import CameraSpec, DepthImage, Pose2D
from comexp.sim.contact import pusher_contact_height_m
from comexp.sim.protocol import JumpsStillSteps
from comexp.sim.scene import (
    GRAVITY_M_S2,
    FloorSpec,
    ObjectSpec,
    ObjectState,
    SceneSpec,
    SimSettings,
    tilt_deg,
)
from comexp.sim.simulator import PARK_XY_M, Simulator
from comexp.sim.view import crop_camera, object_window_px


def _import_pybullet_quietly():
    """pybullet prints its build time on stderr at import, from C: a driver that only needs
    this module's physics identity would break its one-line errors with it."""
    import sys

    sys.stderr.flush()
    saved, devnull = os.dup(2), os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        import pybullet

        return pybullet
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


pb = _import_pybullet_quietly()
# after the quiet import: the compiled steps' module imports pybullet too
from comexp.backends.pybullet_steps import client_handle, push_steps  # noqa: E402

_WORLD = pb.WORLD_FRAME
_ZERO3 = (0.0, 0.0, 0.0)  # (pybullet reads any sequence; this one is never written)
_NO_RECORD = np.zeros((0, 5))  # push_steps: no friction inputs recorded
_push_steps_call = DirectCall(push_steps)  # every chunk of the protocol's steps


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


def _pusher_urdf(radius_m: float, mass_kg: float) -> str:
    """The pusher as a free sphere of the pusher's radius, centred at the height of the line
    contact's resultant (see `pusher_contact_height_m`): Bullet reduces the line contact of a
    vertical cylinder or capsule with a vertical face to 1-3 points at arbitrary heights (near
    the face's top at impact, measured 13.8 of 15 mm), whose moment tilts a low object by ~1 deg;
    a sphere touches at one point, where the resultant is.

    Its inertia is a thin rod's along the body x axis (the "axle", kept horizontal and across
    the push, see `_orient_pusher`): about the axle it rolls freely, so its contact carries no
    vertical friction (the model's pusher friction acts in the floor's plane only; with Bullet's
    vertical friction a sticky pusher lifted a low object's pushed side and tilted it 1.14 deg),
    while about the other axes a large inertia keeps contact torques from turning it."""
    i_axle = _fmt(mass_kg * PYBULLET_PUSHER_AXLE_INERTIA_M2)
    i = _fmt(mass_kg * 1.0)
    geom = f'<geometry><sphere radius="{_fmt(radius_m)}"/></geometry>'
    return (
        '<?xml version="1.0"?><robot name="pusher"><link name="tip">'
        f'<inertial><mass value="{_fmt(mass_kg)}"/>'
        f'<inertia ixx="{i_axle}" iyy="{i}" izz="{i}" ixy="0" ixz="0" iyz="0"/>'
        f"</inertial><collision>{geom}</collision></link></robot>"
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


def _window_projection(
    proj: Sequence[float], width_px: int, height_px: int, u0: int, v0: int, w: int, h: int
) -> list[float]:
    """The projection (column-major) whose w x h image is exactly the window of the full
    width_px x height_px image with top-left pixel (u0, v0): an off-centre frustum.

    The viewport maps NDC x in [-1, 1] to the image's columns and y to its rows (rows grow
    downward); asking pixel u' of the window to be pixel u0 + u' of the full image gives
    x' = x W/w + (W - 2 u0 - w)/w and y' = y H/h + (h - H + 2 v0)/h. With clip w = -z_eye
    (row 3 of a perspective matrix) that is row0' = row0 W/w + row3 (W - 2 u0 - w)/w, likewise
    row 1; depth (row 2) is unchanged. Pixels equal the full image's window to float rounding
    (measured over 1,577 frames of bench/tracking.py --compare-frames: depth within 1.1e-5 m,
    no mask pixel differs; tests/test_tracking.py checks three poses to 1e-6 m).
    """
    m = list(proj)
    sx, bx = width_px / w, (width_px - 2 * u0 - w) / w
    sy, by = height_px / h, (h - height_px + 2 * v0) / h
    for col in range(4):
        row3 = proj[col * 4 + 3]
        m[col * 4 + 0] = sx * proj[col * 4 + 0] + bx * row3
        m[col * 4 + 1] = sy * proj[col * 4 + 1] + by * row3
    return m


# The backend's revision and settings live in backends/physics_settings.py: bump the
# revision there when a change here changes results.
PHYSICS_VERSION, ENGINE_DISTRIBUTION, PHYSICS_SETTINGS = PYBULLET


class PybulletSimulator(JumpsStillSteps, Simulator):
    """pybullet implementation of the simulator interface (see the module docstring)."""

    name = "pybullet"
    still_jumps = STILL_JUMPS  # still steps jumped, not stepped

    def __init__(
        self,
        settings: SimSettings | None = None,
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
        self._cid = pb.connect(pb.DIRECT)
        self._dir = tempfile.mkdtemp(prefix="comexp_pybullet_")
        self._scene: SceneSpec | None = None
        self._floor = -1
        self._pusher = -1
        self._object = -1
        self._com_local = np.zeros(3)
        self._view: list[float] = []
        self._proj: list[float] = []
        self._pusher_target = (0.0, 0.0)
        self._pusher_z = 0.0
        # Bullet's client handle for the compiled steps (`pybullet_steps`), found at the first
        # build; None: step through pybullet's Python functions
        self._handle: int | None = None
        self._handle_checked = False
        self._slots = np.zeros(2, dtype=np.int64)  # the compiled steps' C out-parameters

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
        about a millisecond (docs/physics_pybullet.md). The bodies are loaded in this order
        (floor, pusher, object): body ids, hence the engine's results, depend on it.
        """
        c = self._cid
        s = self.settings
        pb.resetSimulation(physicsClientId=c)
        pb.setGravity(0.0, 0.0, -GRAVITY_M_S2, physicsClientId=c)
        pb.setPhysicsEngineParameter(
            fixedTimeStep=s.timestep_s,
            numSubSteps=0,
            numSolverIterations=PYBULLET_SOLVER_ITERATIONS,
            enableConeFriction=1,
            enableSAT=1,
            deterministicOverlappingPairs=1,
            physicsClientId=c,
        )
        flags = pb.URDF_INITIALIZE_SAT_FEATURES | pb.URDF_USE_INERTIA_FROM_FILE
        self._load_floor(scene.floor, flags)
        self._load_pusher(scene, flags)
        self._load_object(scene.obj, scene.initial_pose, flags)
        if not self._handle_checked:  # one client for this simulator's life: one handle
            self._handle_checked = True
            self._handle = client_handle(c, self._object)
        self._scene = scene
        self._pushed = False
        fl = scene.floor
        self._fric = (
            FootprintFriction(scene.obj, fl.mu_x, fl.mu_y, scene.pusher)
            if self.floor_friction == "model"
            else None
        )
        self._set_camera(scene.camera)

    def _load_floor(self, fl: FloorSpec, flags: int) -> None:
        """The floor box and its friction (none with the footprint model: it supplies it)."""
        c = self._cid
        floor_path = self._hashed_file("floor", "urdf", _floor_urdf(fl.size_m, fl.thickness_m))
        # Isotropic floor: a rigid body, so that the floor-object contact goes through the
        # rigid-body solver, whose first friction direction follows each point's slip velocity
        # (friction opposes sliding whatever the object's yaw). Anisotropic floor: a multibody,
        # whose contacts use friction directions fixed to the world axes, the only frame in
        # which Bullet's anisotropicFriction scaling means "mu_x along x, mu_y along y".
        self._floor = pb.loadURDF(
            floor_path,
            useFixedBase=True,
            useMaximalCoordinates=fl.isotropic or self.floor_friction == "model",
            flags=flags,
            physicsClientId=c,
        )
        mu_max = max(fl.mu_x, fl.mu_y)
        floor_dyn: dict[str, object] = {}
        model = self.floor_friction == "model"
        if model:
            mu_max = 0.0  # the footprint model supplies the floor's friction (_step_once)
        elif not fl.isotropic:  # never set on iso floors: see docs/physics_pybullet.md
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

    def _load_pusher(self, scene: SceneSpec, flags: int) -> None:
        """The pusher at its contact height, parked; it never touches the floor."""
        c = self._cid
        pu = scene.pusher
        self._pusher_z = pusher_contact_height_m(pu, scene.obj.height_m)
        pusher_path = self._hashed_file(
            "pusher", "urdf", _pusher_urdf(pu.radius_m, PYBULLET_PUSHER_MASS_KG)
        )
        self._pusher = pb.loadURDF(
            pusher_path,
            basePosition=[PARK_XY_M[0], PARK_XY_M[1], self._pusher_z],
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
        self._teleport_pusher(PARK_XY_M)

    def _load_object(self, obj: ObjectSpec, pose: Pose2D, flags: int) -> None:
        """The object at its initial pose, resting on the floor."""
        c = self._cid
        self._com_local = np.array([obj.com_m[0], obj.com_m[1], obj.height_m / 2.0])
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

    def _set_camera(self, cam: CameraSpec) -> None:
        """The top-down camera's view and projection matrices."""
        c = self._cid
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
        the target at the end of the step, so it follows the path with no lag in free space and
        is barely slowed by a 0.2 kg object (mass ratio 500). It falls under gravity within the
        step like the object resting on the floor, and is put back at its height before the
        next: Bullet takes a contact's friction direction from the relative velocity before the
        solve, gravity included, so a pusher held up against the object's in-step fall g dt saw
        a vertical slip that its friction fought: it carried up to 39% of a low box's weight
        (tests/test_pybullet_backend.py).
        """
        c, pusher, z = self._cid, self._pusher, self._pusher_z
        pos, quat = pb.getBasePositionAndOrientation(pusher, physicsClientId=c)
        if pos[2] != z:
            pos = (pos[0], pos[1], z)
            pb.resetBasePositionAndOrientation(pusher, pos, quat, physicsClientId=c)
        inv_dt = 1.0 / self.settings.timestep_s
        tx, ty = self._pusher_target
        vel = [(tx - pos[0]) * inv_dt, (ty - pos[1]) * inv_dt, 0.0]
        pb.resetBaseVelocity(pusher, vel, _ZERO3, physicsClientId=c)
        if self._fric is not None:
            self._apply_floor_friction()
            pb.stepSimulation(physicsClientId=c)
            self._pushed = bool(pb.getContactPoints(pusher, self._object, physicsClientId=c))
        else:
            pb.stepSimulation(physicsClientId=c)

    def _apply_floor_friction(self) -> None:
        """`floor_friction=model`: the floor's friction for this step from the footprint model
        (backends/floor_friction.py), applied at the floor under the CoM, with Bullet's own
        object-floor friction off; Bullet keeps the normal contact, the pusher and the
        integration."""
        c, obj = self._cid, self._object
        com, quat = pb.getBasePositionAndOrientation(obj, physicsClientId=c)
        v, w = pb.getBaseVelocity(obj, physicsClientId=c)
        yaw = pb.getEulerFromQuaternion(quat)[2]
        dt = self.settings.timestep_s
        ix, iy, iz = self._fric.impulse_of_twist(v[0], v[1], w[2], yaw, dt, self._pushed)
        if ix == 0.0 and iy == 0.0 and iz == 0.0:
            return
        pb.applyExternalForce(
            obj, -1, [ix / dt, iy / dt, 0.0], [com[0], com[1], 0.0], _WORLD, physicsClientId=c
        )
        pb.applyExternalTorque(obj, -1, [0.0, 0.0, iz / dt], _WORLD, physicsClientId=c)

    def _teleport_pusher(self, xy: Sequence[float]) -> None:
        c = self._cid
        pos = [float(xy[0]), float(xy[1]), self._pusher_z]
        pb.resetBasePositionAndOrientation(self._pusher, pos, [0, 0, 0, 1], physicsClientId=c)
        pb.resetBaseVelocity(self._pusher, [0, 0, 0], [0, 0, 0], physicsClientId=c)
        self._pusher_target = (pos[0], pos[1])

    def _orient_pusher(self, toward_xy: Sequence[float]) -> None:
        """Turn the pusher's axle (body x) horizontal and across its coming travel, when it is
        not already: rolling about the axle then frees the contact's vertical slip only."""
        c = self._cid
        pos, quat = pb.getBasePositionAndOrientation(self._pusher, physicsClientId=c)
        d = np.array([toward_xy[0] - pos[0], toward_xy[1] - pos[1]])
        norm = float(np.hypot(d[0], d[1]))
        if norm < 1e-9:
            return
        axle = pb.getMatrixFromQuaternion(quat)[0::3]  # body x in world (first column)
        if abs(axle[0] * d[0] + axle[1] * d[1]) < 1e-6 * norm and abs(axle[2]) < 1e-6:
            return
        yaw = float(np.arctan2(d[1], d[0])) + np.pi / 2.0
        q = pb.getQuaternionFromEuler([0.0, 0.0, yaw])
        pb.resetBasePositionAndOrientation(self._pusher, pos, q, physicsClientId=c)

    def pusher_xy(self) -> np.ndarray:
        pos, _ = pb.getBasePositionAndOrientation(self._pusher, physicsClientId=self._cid)
        return np.array(pos[:2])

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
        r0, r1, r2 = (rot @ self._com_local).tolist()  # origin -> CoM, world
        w0, w1, w2 = w
        roll, pitch, yaw = pb.getEulerFromQuaternion(quat)
        # origin = com - r, v = v_com - w x r: the operations of np.cross, in scalars
        return ObjectState(
            position_m=(com[0] - r0, com[1] - r1, com[2] - r2),
            roll_rad=float(roll),
            pitch_rad=float(pitch),
            yaw_rad=float(yaw),
            linear_velocity_m_s=(
                v_com[0] - (w1 * r2 - w2 * r1),
                v_com[1] - (w2 * r0 - w0 * r2),
                v_com[2] - (w0 * r1 - w1 * r0),
            ),
            angular_velocity_rad_s=(float(w0), float(w1), float(w2)),
        )

    def render_depth(self) -> DepthImage:
        scene = self._require_scene()
        if self.renderer == "raycast":
            return self.raycast_depth()
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

    def render_tracking_depth(self) -> DepthImage:
        """Only the window the object covers (`object_window_px`, ~2,000 of the 224 x 224
        pixels): the tiny renderer's cost scales with the pixel count (CPU per tracking frame,
        bench/tracking.py: window 0.9 - 1.0 ms, full image 9.6 - 10.8 ms), and a tracking frame
        needs the object only."""
        scene = self._require_scene()
        if self.renderer == "raycast":
            return self.raycast_tracking_depth()
        cam = scene.camera
        model = cam.model()
        win = object_window_px(model, scene.obj.outline_m, scene.obj.height_m, self.object_state())
        if win is None:
            return self.render_depth()
        u0, v0, w, h = win
        proj = _window_projection(self._proj, cam.width_px, cam.height_px, u0, v0, w, h)
        _, _, _, depth_buf, _ = pb.getCameraImage(
            w,
            h,
            viewMatrix=self._view,
            projectionMatrix=proj,
            renderer=pb.ER_TINY_RENDERER,
            flags=pb.ER_NO_SEGMENTATION_MASK,
            physicsClientId=self._cid,
        )
        zb = np.asarray(depth_buf, dtype=np.float64).reshape(h, w)
        near, far = cam.near_m, cam.far_m
        depth = far * near / (far - (far - near) * zb)
        return DepthImage(depth_m=depth.astype(np.float32), camera=crop_camera(model, *win))

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

    # --- protocol primitives (comexp.simulator.Simulator.push) ------------------------------
    def place_pusher(self, xy) -> None:
        self._teleport_pusher(xy)

    def advance(self, targets: np.ndarray) -> tuple[bool, float]:
        """The steps of `_step_once`, one per target: with `floor_friction=model` and no
        `trace`, a whole chunk in one compiled call (`pybullet_steps.push_steps`: the same
        Bullet commands with the same numbers, the same bits), else from Python."""
        self._require_scene()
        c = self._cid
        self._orient_pusher(targets[-1])
        if self._fric is not None and self.trace is None and self._handle is not None:
            touched = self._compiled_steps(targets)
        else:
            touched = self._python_steps(targets)
        # the tilt alone (the protocol reads the whole state itself right after)
        _, quat = pb.getBasePositionAndOrientation(self._object, physicsClientId=c)
        roll, pitch, _ = pb.getEulerFromQuaternion(quat)
        return touched, tilt_deg(roll, pitch)

    def _python_steps(self, targets: np.ndarray) -> bool:
        c = self._cid
        touched = False
        model, trace = self._fric is not None, self.trace
        for target in np.asarray(targets, dtype=float).tolist():
            self._pusher_target = target  # where `_step_once` drives the pusher
            self._step_once()
            if not touched:
                # with the friction model, _step_once has just asked Bullet the same question
                touched = (
                    self._pushed
                    if model
                    else bool(pb.getContactPoints(self._pusher, self._object, physicsClientId=c))
                )
            if trace is not None:
                trace.append(self.object_state())
        return touched

    def _compiled_steps(self, targets: np.ndarray) -> bool:
        f = self._fric
        pts = np.ascontiguousarray(targets, dtype=np.float64).reshape(-1, 2)
        record = _NO_RECORD if f.inputs is None else np.zeros((len(pts), 5))
        status, touched, pushed = _push_steps_call(
            self._handle, self._pusher, self._object, self._pusher_z, pts,
            self.settings.timestep_s, f.geo, f.fs, f.normal, f.dxw, f.dyw, self._pushed,
            record, self._slots,
        )  # fmt: skip
        if status:
            raise RuntimeError(f"pybullet: a state or contact query failed at step {-status}")
        self._pushed = bool(pushed)
        if len(pts):
            self._pusher_target = (float(pts[-1, 0]), float(pts[-1, 1]))
        if f.inputs is not None:
            f.inputs.extend((x, y, w, yaw, bool(p)) for x, y, w, yaw, p in record.tolist())
        return bool(touched)

    def jump_pusher(self, targets: np.ndarray) -> None:
        """The pusher on its last target at its height, at rest, its axle as it was: the next
        `_step_once` sets the velocity that reaches its next target."""
        c = self._cid
        _, quat = pb.getBasePositionAndOrientation(self._pusher, physicsClientId=c)
        pos = (float(targets[-1][0]), float(targets[-1][1]), self._pusher_z)
        pb.resetBasePositionAndOrientation(self._pusher, pos, quat, physicsClientId=c)
        pb.resetBaseVelocity(self._pusher, _ZERO3, _ZERO3, physicsClientId=c)
        self._pusher_target = (pos[0], pos[1])
        self._pushed = False

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
