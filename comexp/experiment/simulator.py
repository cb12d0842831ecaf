"""The one simulator interface that perception, the estimator and the workers use.

A backend builds a scene from engine-independent dataclasses (`comexp.method.scene`), renders the
top-down depth image, executes straight pushes and lets the object come to rest. The true
object state is for evaluation, tests and failure detection only; the estimator never reads it
unless `rotation_source=oracle` is asked for.
"""

from __future__ import annotations

import enum
import importlib
import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from comexp.method.scene import (
    CameraModel,
    DepthImage,
    ObjectState,
    Pose2D,
    PushCommand,
    PusherSpec,
    SceneSpec,
    SimSettings,
    wrap_angle,
)

BACKENDS: dict[str, str] = {
    "planar": "comexp.backends.planar_sim:PlanarSimulator",
    "pybullet": "comexp.backends.pybullet_sim:PybulletSimulator",
    "mujoco": "comexp.backends.mujoco_sim:MujocoSimulator",
}
# How an engine gets the floor's friction: "model" applies the shared footprint model
# (backends/floor_friction.py) as a force each step, the engine's own object-floor friction off;
# "native" is the engine's own contact friction (kept to show the difference).
FLOOR_FRICTION_CHOICES = ("model", "native")
# How an engine makes its depth images (`camera.renderer`): "raycast" is the exact ray cast of
# the prism at the engine's pose (`comexp.method.perception.render_prism_depth`, planar's
# camera; no pusher in the image, which the tracker masks anyway); "engine" is the engine's own
# renderer (pybullet's tiny renderer, MuJoCo's GL on Mesa).
RENDERER_CHOICES = ("raycast", "engine")
# Pusher parking spot (world, m): beyond the floor edge and outside the camera's view at the
# pusher's top, unreachable by an object still in view.
PARK_XY_M = (0.0, 0.5)


class PushStatus(enum.StrEnum):
    OK = "ok"
    TIPPED = "tipped"
    LEFT_VIEW = "left_view"
    SIM_UNSTABLE = "sim_unstable"
    NOT_SETTLED = "not_settled"
    PATH_BLOCKED = "path_blocked"  # the pusher's start position overlaps the object


@dataclass(frozen=True)
class PushOutcome:
    status: PushStatus
    pose_before: Pose2D
    pose_after: Pose2D
    sim_time_s: float
    steps: int
    contact_made: bool
    max_pusher_lag_m: float  # worst |actual - commanded| pusher position during the push
    max_tilt_deg: float
    n_frames: int = 0  # tracking frames handed to `on_frame` (Simulator.push)
    # true CCW rotation over the push, unwrapped (summed from check to check, so a push may
    # turn more than half a turn); None from a simulator that does not follow it
    true_rotation_deg: float | None = None

    @property
    def ok(self) -> bool:
        return self.status is PushStatus.OK

    @property
    def rotation_deg(self) -> float:
        """True CCW rotation of the object during the push, wrapped to (-180, 180]."""
        return math.degrees(wrap_angle(self.pose_after.yaw_rad - self.pose_before.yaw_rad))


@dataclass(frozen=True)
class Frame:
    """A depth image taken during a push (`Simulator.push(on_frame=...)`).

    The pusher may be in it: the engines render their pusher, touching the object's side.
    Where it is (the pusher's axis, world m) and its radius are known to the robot, so the
    tracker can mask it (`comexp.method.perception.mask_pusher`). On the engines `image` is only
    the window around the object (`object_window_px`); its camera model says where it lies.
    """

    image: DepthImage
    t_s: float  # since the start of the push
    pusher_xy_m: tuple[float, float]
    pusher_radius_m: float


def outline_radius_m(outline_m: np.ndarray) -> float:
    """The largest distance of an outline corner from the object frame's origin."""
    o = np.asarray(outline_m, dtype=float)
    return float(np.sqrt(np.max(o[:, 0] * o[:, 0] + o[:, 1] * o[:, 1])))


def surely_in_view(x_m: float, y_m: float, radius_m: float, camera: CameraModel) -> bool:
    """True when a disc of `radius_m` about the floor point (x, y) projects well inside the
    image, so every outline corner within it does: the protocol checks the view every few
    steps, and this test (a few float operations) spares the exact per-corner projection
    (numpy on a handful of points, ~100x its cost) on nearly every check. False decides
    nothing: the exact test runs. Its margin (1e-6 px, 1e-9 relative on the radius) is far
    above the rounding of either computation, so the verdict is always the exact test's."""
    x0, y0, z0 = camera.position_m
    r = radius_m * (1.0 + 1e-9) + 1e-12
    kx, ky = camera.fx_px / z0, camera.fy_px / z0
    margin = 1e-6
    return (
        camera.cx_px + (x_m - r - x0) * kx >= margin
        and camera.cx_px + (x_m + r - x0) * kx <= camera.width_px - 1 - margin
        and camera.cy_px - (y_m + r - y0) * ky >= margin
        and camera.cy_px - (y_m - r - y0) * ky <= camera.height_px - 1 - margin
    )


def classify_state(
    state: ObjectState,
    outline_m: np.ndarray,
    camera: CameraModel,
    settings: SimSettings,
    radius_m: float | None = None,
) -> PushStatus | None:
    """Failure check shared by both backends; None when the state is healthy.

    Order matters: a non-finite state makes the other checks meaningless, and a tipped object
    is reported as tipped even if it then also leaves the view. `radius_m`
    (`outline_radius_m`, passed by a caller that checks one outline often) enables the cheap
    `surely_in_view` test before the exact one.
    """
    if not state.is_finite:
        return PushStatus.SIM_UNSTABLE
    if state.tilt_deg > settings.tip_limit_deg:
        return PushStatus.TIPPED
    x_m, y_m, _ = state.position_m
    if radius_m is not None and surely_in_view(x_m, y_m, radius_m, camera):
        return None
    corners = state.pose.to_world(outline_m)
    uv = camera.world_to_pixel(corners[:, 0], corners[:, 1], 0.0)
    inside = (
        (uv[:, 0] >= 0)
        & (uv[:, 0] <= camera.width_px - 1)
        & (uv[:, 1] >= 0)
        & (uv[:, 1] <= camera.height_px - 1)
    )
    if not bool(np.all(inside)):
        return PushStatus.LEFT_VIEW
    return None


class Simulator(ABC):
    """One engine instance behind the shared push protocol.

    `build` may be called many times (scene reuse is the backend's job). The protocol of a push
    (`push`: start clear, move along the normal for the travel, stop, wait for rest under one
    settle rule, clear the pusher, classify failures) is written once, here; an engine
    implements only the primitives below it (place and drive the pusher, advance, read the
    state), so that a cross-engine comparison compares physics, not protocols.
    """

    name: str = ""
    # steps advanced between two failure / rest checks (an engine-specific need: MuJoCo runs a
    # chunk of steps in C between Python checks); part of the protocol's settings
    check_every_steps: int = 5

    def __init__(self, settings: SimSettings | None = None) -> None:
        self.settings = settings or SimSettings()
        # when a list, every step's ObjectState is appended to it (physics tests: lift, tilt)
        self.trace: list[ObjectState] | None = None

    @abstractmethod
    def build(self, scene: SceneSpec) -> None:
        """(Re)create floor, object at `scene.initial_pose` resting on the floor, the pusher
        parked out of the camera's view, and the camera."""

    @abstractmethod
    def render_depth(self) -> DepthImage:
        """Top-down metric depth image of the current scene (pusher parked, out of view)."""

    @abstractmethod
    def object_state(self) -> ObjectState:
        """True state of the object frame: evaluation and tests only."""

    # --- protocol primitives -------------------------------------------------------------
    @abstractmethod
    def _place_pusher(self, xy: np.ndarray | Sequence[float]) -> None:
        """Put the pusher at rest at a world point (only called where it is clear of the
        object: the start of a push, the parking spot)."""

    @abstractmethod
    def _pusher_xy(self) -> np.ndarray:
        """The pusher axis' actual world position."""

    @abstractmethod
    def _advance(self, targets: np.ndarray) -> tuple[bool, float]:
        """Run len(targets) steps; the pusher reaches targets[i] (world, m) at the end of
        step i, moving straight between them. Returns (pusher touched the object during these
        steps, max tilt in deg over them). Appends every step's state to `trace` if set."""

    def render_tracking_depth(self) -> DepthImage:
        """The depth image of a tracking frame taken during a push; an engine may override it
        with a cheaper renderer that keeps the camera's projection: the engines render only
        the window of the image the object can cover (`object_window_px`), returned with the
        camera model of that window (`crop_camera`), so its pixels map to the same world points
        as the full image's."""
        return self.render_depth()

    def _raycast_depth(self) -> DepthImage:
        """The exact ray-cast depth image of the prism at the true pose (`camera.renderer=
        raycast`): an engine's alternative to its own renderer, the same pixels as planar's."""
        from comexp.method.perception import render_prism_depth

        scene = self._scene_or_fail()
        return render_prism_depth(
            self._camera_model(), self._outline_m(), scene.obj.height_m, self.object_state().pose
        )

    def _steps_still(self, targets: np.ndarray) -> int:
        """How many of the pusher's next `targets` (one per step) surely leave the object
        exactly as it is: a backend that can prove it (the object exactly at rest, nothing
        able to reach it within those steps) returns a count, and the protocol advances them
        without its checks (each would see the same state). 0: unknown, check every chunk."""
        return 0

    def _engine_failure(self) -> PushStatus | None:
        """An engine's own sign of trouble (e.g. solver warnings); None when healthy."""
        return None

    def _park_xy(self) -> tuple[float, float]:
        return PARK_XY_M

    # --- the push protocol ---------------------------------------------------------------
    def push(
        self,
        cmd: PushCommand,
        on_frame: Callable[[Frame], None] | None = None,
        frame_interval_s: float = 0.0,
        on_still: Callable[[float], None] | None = None,
        frame_wanted: Callable[[float, bool], bool] | None = None,
    ) -> PushOutcome:
        """Execute the push, let the object come to rest, clear and park the pusher, report.

        With `on_frame` and `frame_interval_s` > 0 the camera watches the push: at the first
        protocol check at or after every multiple of `frame_interval_s` since the push began,
        if the object is moving (not `at_rest`), a tracking frame is rendered and handed over;
        if it is at rest, nothing is rendered (a still object shows nothing new) and `on_still`
        gets the frame's time, so that a tracker knows the object stopped there.
        `frame_wanted(t_s, driving)`, if given, is asked before a moving frame is rendered
        (`driving`: the pusher is still moving along the push line); a frame it declines is
        neither rendered nor handed over, as a tracker that skips a camera frame never looks
        at it.
        Frames hang on the existing checks, so the steps an engine is asked for (`_advance`
        calls) are the same with or without frames: watching never changes the physics. The
        rate is therefore `1 / frame_interval_s` on average, each frame up to one check
        (`check_every_steps` steps) late.
        """
        s = self.settings
        dt = s.timestep_s
        camera = self._camera_model()
        outline = self._outline_m()
        radius = outline_radius_m(outline)
        before = self.object_state()
        start = np.asarray(cmd.start_xy_m, dtype=float)
        direction = np.asarray(cmd.direction_xy, dtype=float)
        max_tilt = before.tilt_deg
        if pusher_clearance_m(start, before, outline, self._pusher_radius_m()) < 0.0:
            return PushOutcome(
                PushStatus.PATH_BLOCKED, before.pose, before.pose, 0.0, 0, False, 0.0, max_tilt
            )
        self._place_pusher(start)
        steps = 0
        contact = False
        lag = 0.0
        status: PushStatus | None = None
        chunk = max(1, int(self.check_every_steps))
        watch = on_frame is not None and frame_interval_s > 0
        next_frame_s = frame_interval_s
        n_frames = 0
        last_yaw = before.pose.yaw_rad
        turned = 0.0

        def skip_still(targets: np.ndarray) -> int:
            """Advance the leading steps of `targets` that cannot move the object, in whole
            chunks, as one call; the checks they span are those of an object at rest (no
            failure, no turn; a due frame is a still one). Returns how many were advanced."""
            nonlocal steps, contact, next_frame_s
            n = min(self._steps_still(targets), len(targets)) // chunk * chunk - chunk
            if n <= 0:
                return 0
            pose0 = self.object_state().pose
            touched, _ = self._advance(targets[:n])
            after = self.object_state()
            if touched or after.pose != pose0 or not at_rest(after, s):
                raise RuntimeError(f"{self.name}: the object moved in steps declared still")
            contact = contact or touched
            for _ in range(n // chunk):
                steps += chunk
                t_s = steps * dt
                if watch and t_s >= next_frame_s - 1e-9:
                    next_frame_s = (
                        math.floor(t_s / frame_interval_s + 1e-9) + 1
                    ) * frame_interval_s
                    if on_still is not None:
                        on_still(t_s)
            return n

        def run(targets: np.ndarray, driving: bool = False) -> ObjectState:
            nonlocal steps, contact, status, max_tilt, next_frame_s, n_frames, last_yaw, turned
            touched, tilt = self._advance(targets)
            steps += len(targets)
            contact = contact or touched
            st = self.object_state()
            if st.is_finite:  # < half a turn between two checks (a few ms apart)
                turned += wrap_angle(st.pose.yaw_rad - last_yaw)
                last_yaw = st.pose.yaw_rad
            max_tilt = max(max_tilt, tilt, st.tilt_deg if st.is_finite else 0.0)
            status = self._engine_failure() or classify_state(st, outline, camera, s, radius)
            t_s = steps * dt
            if watch and status is None and t_s >= next_frame_s - 1e-9:
                next_frame_s = (math.floor(t_s / frame_interval_s + 1e-9) + 1) * frame_interval_s
                if at_rest(st, s):  # a still object shows nothing new: no frame
                    if on_still is not None:
                        on_still(t_s)
                elif frame_wanted is None or frame_wanted(t_s, driving):
                    xy = self._pusher_xy()
                    frame = Frame(
                        self.render_tracking_depth(),
                        t_s,
                        (float(xy[0]), float(xy[1])),
                        self._pusher_radius_m(),
                    )
                    on_frame(frame)  # type: ignore[misc]
                    n_frames += 1
            return st

        # 1) the straight path at the commanded speed; the pusher is where the path is at the
        #    end of each step
        n_move = math.ceil(cmd.travel_m / (cmd.speed_m_s * dt) - 1e-9)
        travelled = np.minimum(cmd.speed_m_s * dt * np.arange(1, n_move + 1), cmd.travel_m)
        k = skip_still(start + travelled[:, None] * direction)
        while k < n_move and status is None:
            n = min(chunk, n_move - k)
            travelled = np.minimum(cmd.speed_m_s * dt * np.arange(k + 1, k + n + 1), cmd.travel_m)
            targets = start + travelled[:, None] * direction
            run(targets, driving=True)
            k += n
            lag = max(lag, float(np.linalg.norm(self._pusher_xy() - targets[-1])))
        # 2) hold the pusher still; at rest = the object frame's floor point and yaw below the
        #    settle limits at every check for settle_hold_s
        if status is None:
            hold_checks = max(1, math.ceil(s.settle_hold_s / (dt * chunk) - 1e-9))
            quiet = 0
            held = np.repeat(start[None, :] + cmd.travel_m * direction[None, :], chunk, axis=0)
            for _ in range(max(1, math.ceil(s.max_settle_s / (dt * chunk)))):
                st = run(held)
                if status is not None:
                    break
                if at_rest(st, s):
                    quiet += 1
                    left = (hold_checks - quiet) * chunk
                    if left > 0:  # checks that would see the same still object: skipped
                        quiet += skip_still(np.repeat(held[:1], left + chunk, axis=0)) // chunk
                    if quiet >= hold_checks:
                        break
                else:
                    quiet = 0
            else:
                status = PushStatus.NOT_SETTLED
        # 3) back off along the push line until clear, then park out of view
        if status is None:
            end = self._pusher_xy()
            n_back = math.ceil(s.retract_m / (s.retract_speed_m_s * dt))
            back = np.minimum(s.retract_speed_m_s * dt * np.arange(1, n_back + 1), s.retract_m)
            i = 0
            while i < n_back:
                run(end - back[i : i + chunk, None] * direction)
                i += chunk
                if status is not None:
                    break
                i += skip_still(end - back[i:, None] * direction)
        after = self.object_state()
        if after.is_finite:
            turned += wrap_angle(after.pose.yaw_rad - last_yaw)
        if status is None or status is PushStatus.NOT_SETTLED:
            status = classify_state(after, outline, camera, s, radius) or status
        if pusher_clearance_m(self._pusher_xy(), after, outline, self._pusher_radius_m()) > (
            s.clear_m
        ):
            self._place_pusher(self._park_xy())
        max_tilt = max(max_tilt, after.tilt_deg) if after.is_finite else max_tilt
        return PushOutcome(
            status=status or PushStatus.OK,
            pose_before=before.pose,
            pose_after=after.pose if after.is_finite else before.pose,
            sim_time_s=steps * dt,
            steps=steps,
            contact_made=contact,
            max_pusher_lag_m=lag,
            max_tilt_deg=max_tilt,
            n_frames=n_frames,
            true_rotation_deg=math.degrees(turned),
        )

    # the scene the protocol needs (every backend keeps the SceneSpec it built)
    def _scene_or_fail(self) -> SceneSpec:
        scene = getattr(self, "_scene", None)
        if scene is None:
            raise RuntimeError("build() a scene first")
        return scene

    def _camera_model(self) -> CameraModel:
        return self._scene_or_fail().camera.model()

    def _outline_m(self) -> np.ndarray:
        return np.asarray(self._scene_or_fail().obj.outline_m, dtype=float)

    def _pusher_radius_m(self) -> float:
        return self._scene_or_fail().pusher.radius_m

    def true_pose(self) -> Pose2D:
        return self.object_state().pose

    # --- test hooks: used by physics validation, never by the estimator ---------------------
    @abstractmethod
    def set_object_velocity(
        self, linear_m_s: tuple[float, float, float], angular_rad_s: tuple[float, float, float]
    ) -> None:
        """Overwrite the object's velocity (world frame; linear = the object frame origin's)."""

    def step(self, duration_s: float) -> None:
        """Advance the simulation by `duration_s` (rounded to whole steps), pusher held still."""
        self._scene_or_fail()
        n = max(0, round(duration_s / self.settings.timestep_s))
        if n:
            self._advance(np.repeat(self._pusher_xy()[None, :], n, axis=0))

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release engine resources."""

    def __enter__(self) -> Simulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def object_window_px(
    camera: CameraModel,
    outline_m: np.ndarray,
    height_m: float,
    state: ObjectState,
    margin_px: int = 2,
) -> tuple[int, int, int, int] | None:
    """The window (u0, v0, width, height) of the image that holds every pixel the object can
    cover, `margin_px` wider each side, clipped to the image; None when it is off the image.

    Why it is enough: the object is a union of convex prisms, so its image lies inside the
    convex hull of the projections of its 2 n corners (bottom and top outline), placed by the
    full 3-D state (tilted or lifted objects included). Tracking frames need only this window
    (`Simulator.render_tracking_depth`): the pusher is masked away anyway.
    """
    outline = np.asarray(outline_m, dtype=float)
    n = len(outline)
    local = np.zeros((2 * n, 3))
    local[:, :2] = np.concatenate([outline, outline])
    local[n:, 2] = height_m
    cr, sr = math.cos(state.roll_rad), math.sin(state.roll_rad)
    cp, sp = math.cos(state.pitch_rad), math.sin(state.pitch_rad)
    cy, sy = math.cos(state.yaw_rad), math.sin(state.yaw_rad)
    rot = np.array(  # ZYX: R = Rz(yaw) Ry(pitch) Rx(roll), the engines' convention
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )
    world = local @ rot.T + np.asarray(state.position_m, dtype=float)
    uv = camera.world_to_pixel(world[:, 0], world[:, 1], world[:, 2])
    u0 = max(int(np.floor(uv[:, 0].min())) - margin_px, 0)
    u1 = min(int(np.ceil(uv[:, 0].max())) + margin_px, camera.width_px - 1)
    v0 = max(int(np.floor(uv[:, 1].min())) - margin_px, 0)
    v1 = min(int(np.ceil(uv[:, 1].max())) + margin_px, camera.height_px - 1)
    if u1 < u0 or v1 < v0:
        return None
    return u0, v0, u1 - u0 + 1, v1 - v0 + 1


def crop_camera(
    camera: CameraModel, u0: int, v0: int, width_px: int, height_px: int
) -> CameraModel:
    """The camera model of the window of `camera`'s image whose top-left pixel is (u0, v0):
    the same camera (pose, focal lengths), the principal point moved by the offset, so that
    pixel (u, v) of the window back-projects to the world point of pixel (u0 + u, v0 + v)."""
    return replace(
        camera,
        width_px=width_px,
        height_px=height_px,
        cx_px=camera.cx_px - u0,
        cy_px=camera.cy_px - v0,
    )


def at_rest(state: ObjectState, s: SimSettings) -> bool:
    """The one settle rule: what the camera and the estimator see is at rest, i.e. the object
    frame's origin (a point of the bottom face) moves slower than `settle_speed_m_s` across
    the floor and the object turns slower than `settle_spin_rad_s` about z.

    Not on the full 3-D velocity: a many-sided prism rocks by ~0.02 deg at rest in pybullet
    (its floor contact keeps 4 bottom corners, which 4 changes from step to step); that
    rocking moves the CoM by mm/s and would never count as rest.
    """
    v = state.linear_velocity_m_s
    return (
        math.hypot(v[0], v[1]) < s.settle_speed_m_s
        and abs(state.angular_velocity_rad_s[2]) < s.settle_spin_rad_s
    )


def point_polygon_distance(pt: np.ndarray, poly: np.ndarray) -> float:
    """Signed distance from a point to a simple polygon's boundary (negative inside)."""
    a = poly
    ab = np.roll(poly, -1, axis=0) - a
    t = np.clip(np.einsum("ij,ij->i", pt - a, ab) / np.einsum("ij,ij->i", ab, ab), 0.0, 1.0)
    d = float(np.min(np.hypot(*(a + t[:, None] * ab - pt).T)))
    crosses = (a[:, 1] > pt[1]) != (np.roll(a[:, 1], -1) > pt[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = a[:, 0] + (pt[1] - a[:, 1]) * ab[:, 0] / ab[:, 1]
    inside = int(np.sum(crosses & (pt[0] < x_at))) % 2 == 1
    return -d if inside else d


def pusher_contact_height_m(pusher: PusherSpec, object_height_m: float) -> float:
    """Height of the resultant of the pusher's line contact with an object's vertical side:
    the middle of their overlap (the pusher spans clearance .. clearance + length)."""
    top = min(object_height_m, pusher.clearance_m + pusher.length_m)
    return 0.5 * (pusher.clearance_m + top)


def pusher_clearance_m(
    xy: np.ndarray | Sequence[float], state: ObjectState, outline_m: np.ndarray, radius_m: float
) -> float:
    """Gap between the pusher's surface and the object's footprint (negative = overlap)."""
    poly = state.pose.to_world(outline_m)
    return point_polygon_distance(np.asarray(xy, dtype=float), poly) - radius_m


def physics_identity(
    name: str, settings: SimSettings | None = None, options: dict | None = None
) -> str:
    """What determines an episode's physics on backend `name`, as one short string: the
    backend's model revision (`PHYSICS_VERSION` in its module, bumped by any change that
    changes results), the engine's version, and a hash of the backend's settings and of the
    push protocol's. It is part of every episode's identity (`EpisodeSpec.physics`), so a
    database is never resumed across physics versions and no report pools two of them."""
    import hashlib
    from importlib import metadata

    try:
        module_name = BACKENDS[name].split(":")[0]
    except KeyError:
        raise ValueError(f"unknown backend {name!r}; choose one of {backend_names()}") from None
    module = importlib.import_module(module_name)
    engine = getattr(module, "ENGINE_DISTRIBUTION", None)
    engine_v = metadata.version(engine) if engine else "none"
    # the engine's own renderer is what every row had before `camera.renderer` existed: it is
    # left out, so that those rows keep their identity
    opts = {k: v for k, v in (options or {}).items() if (k, v) != ("renderer", "engine")}
    text = repr((module.PHYSICS_SETTINGS, settings or SimSettings(), sorted(opts.items())))
    digest = hashlib.sha256(text.encode()).hexdigest()[:10]
    return f"{name}/{module.PHYSICS_VERSION}/{engine or 'numpy'}-{engine_v}/{digest}"


def backend_names() -> list[str]:
    return sorted(BACKENDS)


def make_simulator(name: str, settings: SimSettings | None = None, **options) -> Simulator:
    """Create a backend by name (`planar`, `pybullet`, `mujoco`); engines are imported lazily.
    `options` are the backend's own (e.g. `floor_friction` for the engines)."""
    try:
        target = BACKENDS[name]
    except KeyError:
        raise ValueError(f"unknown backend {name!r}; choose one of {backend_names()}") from None
    module_name, cls_name = target.split(":")
    cls = getattr(importlib.import_module(module_name), cls_name)
    return cls(settings, **options)


def contact_push(
    contact_xy_m: tuple[float, float] | np.ndarray,
    inward_normal_xy: tuple[float, float] | np.ndarray,
    push_length_m: float,
    speed_m_s: float,
    pusher_radius_m: float,
    approach_gap_m: float = 0.01,
) -> PushCommand:
    """The push that drives the pusher's surface `push_length_m` past a contact point along
    the inward normal, starting `approach_gap_m` clear of it (world frame)."""
    n = np.asarray(inward_normal_xy, dtype=float)
    n = n / np.linalg.norm(n)
    c = np.asarray(contact_xy_m, dtype=float)
    start = c - n * (pusher_radius_m + approach_gap_m)
    return PushCommand(
        start_xy_m=(float(start[0]), float(start[1])),
        direction_xy=(float(n[0]), float(n[1])),
        travel_m=approach_gap_m + push_length_m,
        speed_m_s=speed_m_s,
    )
