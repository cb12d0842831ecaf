"""The push protocol, written once for every backend: a straight push driven on an engine's
primitives (`comexp.sim.simulator.Simulator`), its checks, and what it reports.

`push(sim, cmd)`: start clear of the object, drive the pusher along the push line at the
commanded speed, hold it until the object is at rest under one settle rule (`at_rest`), back
it off and park it, classify failures (`classify_state`), and, while the camera watches, hand
tracking frames over (`Frame`). `_PushRun` runs the three phases and the checks between
chunks of steps. An engine may offer the protocol's optional capabilities, each an interface
beside the protocol with the protocol's plain path as the default:
- `SkipsStillSteps` / `JumpsStillSteps`: steps that cannot move an object at rest are advanced
  without the checks (stepped, or an engine's jump);
- `RunsChunks`: several of the protocol's chunks in one call, stopping where the protocol's
  stop rule (`ChunkStop`; compiled once in `comexp.sim.stop_rule`) says a check could
  conclude anything.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from comexp.method.frames import CameraModel, DepthImage, Pose2D, wrap_angle
from comexp.sim.clear_steps import clear_steps
from comexp.sim.contact import pusher_clearance_m
from comexp.sim.scene import ObjectState, PushCommand, PushStatus, SimSettings
from comexp.sim.simulator import Simulator
from comexp.sim.view import outline_radius_m, surely_in_view, surely_in_view_box


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
    """A depth image taken during a push (`push(sim, cmd, on_frame=...)`).

    The pusher may be in it: the engines render their pusher, touching the object's side.
    Where it is (the pusher's axis, world m) and its radius are known to the robot, so the
    tracker can mask it (`comexp.method.observation.mask_pusher`). On the engines `image` is only
    the window around the object (`object_window_px`); its camera model says where it lies.
    """

    image: DepthImage
    t_s: float  # since the start of the push
    pusher_xy_m: tuple[float, float]
    pusher_radius_m: float


@dataclass(frozen=True)
class ChunkStop:
    """Where an engine that runs several of the protocol's chunks in one call
    (`RunsChunks.advance_chunks`) stops, so that the protocol's own check sees that chunk's
    state: after a chunk that leaves the state not finite, the object tilted (planar: not
    flat on the floor; an engine, whose object never is exactly: half way to `tip_limit_deg`),
    its frame's origin outside `box` (x_lo, x_hi, y_lo, y_hi: `surely_in_view_box`), the
    engine with a failure of its own (`engine_failure`), or, after the chunks `rest_after`
    marks, the object near rest (the origin's |v_x| + |v_y| below `rest_speed_m_s` and
    |omega_z| below `rest_spin_rad_s`: twice the settle limits, a superset of `at_rest`).
    Every chunk it does not stop after is one the check passes without a failure, a
    rendered frame or a rest. The rule itself is compiled once (`comexp.sim.stop_rule`), for
    every engine that runs chunks in compiled code."""

    box: tuple[float, float, float, float]
    rest_speed_m_s: float
    rest_spin_rad_s: float
    rest_after: np.ndarray  # bool, one per chunk of the call

    def rule(self) -> np.ndarray:
        """(x_lo, x_hi, y_lo, y_hi, rest speed, rest spin): `stop_rule.chunk_stops`' `rule`."""
        return np.array([*self.box, self.rest_speed_m_s, self.rest_spin_rad_s])


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


def push(
    sim: Simulator,
    cmd: PushCommand,
    on_frame: Callable[[Frame], None] | None = None,
    frame_interval_s: float = 0.0,
    on_still: Callable[[float], None] | None = None,
    frame_wanted: Callable[[float, bool], bool] | None = None,
) -> PushOutcome:
    """Execute the push on `sim`, let the object come to rest, clear and park the pusher,
    report.

    With `on_frame` and `frame_interval_s` > 0 the camera watches the push: at the first
    protocol check at or after every multiple of `frame_interval_s` since the push began,
    if the object is moving (not `at_rest`), a tracking frame is rendered and handed over;
    if it is at rest, nothing is rendered (a still object shows nothing new) and `on_still`
    gets the frame's time, so that a tracker knows the object stopped there.
    `frame_wanted(t_s, driving)`, if given, is asked before a moving frame is rendered
    (`driving`: the pusher is still moving along the push line); a frame it declines is
    neither rendered nor handed over, as a tracker that skips a camera frame never looks
    at it. It is a question without side effects: the protocol may ask it ahead, for the
    due frames up to the next one rendered (`_PushRun._batch`).
    Frames hang on the existing checks, so the steps an engine is asked for (`advance`
    calls) are the same with or without frames: watching never changes the physics. The
    rate is therefore `1 / frame_interval_s` on average, each frame up to one check
    (`check_every_steps` steps) late.

    The three phases (drive, settle, retract) and the checks between chunks of steps are
    `_PushRun`'s; this function starts the push and reports it.
    """
    camera = sim.camera_model()
    outline = sim.outline_m()
    before = sim.object_state()
    start = np.asarray(cmd.start_xy_m, dtype=float)
    direction = np.asarray(cmd.direction_xy, dtype=float)
    if pusher_clearance_m(start, before, outline, sim.pusher_radius_m()) < 0.0:
        return PushOutcome(
            PushStatus.PATH_BLOCKED, before.pose, before.pose, 0.0, 0, False, 0.0, before.tilt_deg
        )
    sim.place_pusher(start)
    run = _PushRun(sim, camera, outline, before, on_frame, frame_interval_s, on_still, frame_wanted)
    run.drive(cmd, start, direction)
    run.settle()
    run.retract(direction)
    return run.finish(before)


# --- optional capabilities of an engine ----------------------------------------------------


class SkipsStillSteps(ABC):
    """An engine that knows which of the pusher's next steps cannot move an object at rest:
    the protocol advances them without its checks (`_PushRun.skip_still`), each of which
    would see the same resting object. Without it, every chunk is checked."""

    @abstractmethod
    def steps_still(self, targets: np.ndarray) -> int:
        """How many of the pusher's next `targets` (one per step) surely leave the object as
        it is; 0: unknown, check every chunk. planar proves it on its exact state."""

    def advance_still(self, targets: np.ndarray) -> bool:
        """Advance steps `steps_still` counted; whether the pusher touched the object.
        Stepped, by default."""
        return self.advance(targets)[0]  # type: ignore[attr-defined]


class JumpsStillSteps(SkipsStillSteps):
    """An engine whose object never comes exactly to rest (it creeps and bobs at the
    contacts' numerical scale), and which jumps the still steps instead of stepping them.

    With `still_jumps` (`comexp.backends.physics_settings.StillJumps`), an object at rest by
    the settle rule (`at_rest`) and flat (tilted less than `max_tilt_deg`: not one falling
    back from a lift) counts as at rest, and the steps in which the pusher stays farther from
    its outline than the step is long plus `margin_m` (`clear_steps`, beyond the reach of any
    contact a step could make) are jumped: time passes, the object's state is kept, the
    pusher ends where stepping would leave it (`jump_pusher`). `still_jumps` None: every step
    is stepped (a comparison's baseline)."""

    still_jumps: Any

    @abstractmethod
    def jump_pusher(self, targets: np.ndarray) -> None:
        """Put the pusher where, and moving as, `advance(targets)` would leave it, without
        stepping; no contact."""

    def steps_still(self, targets: np.ndarray) -> int:
        sim: Any = self
        jumps = self.still_jumps
        if jumps is None:
            return 0
        st = sim.object_state()
        if not at_rest(st, sim.settings) or not st.tilt_deg < jumps.max_tilt_deg:
            return 0
        poly = st.pose.to_world(sim.outline_m())
        q = sim.pusher_xy()
        pts = np.ascontiguousarray(targets, dtype=np.float64).reshape(-1, 2)
        r = sim.pusher_radius_m()
        return clear_steps(float(q[0]), float(q[1]), pts, poly, r, jumps.margin_m)

    def advance_still(self, targets: np.ndarray) -> bool:
        sim: Any = self
        self.jump_pusher(targets)
        if sim.trace is not None:
            sim.trace.extend([sim.object_state()] * len(targets))
        return False


class RunsChunks(ABC):
    """An engine that runs several of the protocol's chunks in one call (its pusher is then on
    its target after every chunk), stopping after a chunk where the protocol's check could
    conclude anything (`ChunkStop`). Without it, one chunk a call."""

    def runs_chunks(self) -> bool:
        """Whether this instance runs chunks in one call (an engine may do so under some of
        its options only)."""
        return True

    @abstractmethod
    def advance_chunks(
        self, targets: np.ndarray, chunk: int, stop: ChunkStop
    ) -> list[tuple[bool, float, float]]:
        """Advance the whole chunks of `targets` (`chunk` steps each, every one exactly as an
        `advance` call of it), stopping after the first one whose state `stop` names; per
        chunk advanced, (touched, its tilt as `advance` returns it, the yaw
        `object_state().pose.yaw_rad` would then read; an engine's tilt also covers
        `object_state().tilt_deg`'s, which the protocol's check adds and `_passed` does
        not)."""


# settle: the most chunks `_PushRun.advance` is handed at once (a batching backend's call)
SETTLE_BATCH_CHUNKS = 64


class _PushRun:
    """One push under way (`Simulator.push`): the protocol's three phases and its checks.

    The pusher advances in chunks of `check_every_steps` steps; after each chunk the object's
    state is checked (failures, the turn so far, the settle rule) and, when due, a tracking
    frame is taken. A backend may run the chunks between two due frames in one call,
    stopping wherever a check could conclude anything (`advance`, `ChunkStop`). Steps that
    provably cannot move the object are advanced without checks (`skip_still`). The counters
    (steps, contact, turn, tilt, frames) become the outcome.
    """

    def __init__(
        self,
        sim: Simulator,
        camera: CameraModel,
        outline: np.ndarray,
        before: ObjectState,
        on_frame: Callable[[Frame], None] | None,
        frame_interval_s: float,
        on_still: Callable[[float], None] | None,
        frame_wanted: Callable[[float, bool], bool] | None,
    ) -> None:
        self.sim = sim
        self.s = sim.settings
        self.dt = self.s.timestep_s
        self.camera = camera
        self.outline = outline
        self.radius = outline_radius_m(outline)
        self.on_frame = on_frame
        self.frame_interval_s = frame_interval_s
        self.on_still = on_still
        self.frame_wanted = frame_wanted
        self.max_tilt = before.tilt_deg
        self.steps = 0
        self.contact = False
        self.lag = 0.0
        self.status: PushStatus | None = None
        self.chunk = max(1, int(sim.check_every_steps))
        self.watch = on_frame is not None and frame_interval_s > 0
        self.next_frame_s = frame_interval_s
        self.n_frames = 0
        self.last_yaw = before.pose.yaw_rad
        self.turned = 0.0
        self.box: tuple[float, float, float, float] | None = None  # `ChunkStop`'s, once asked
        self.end = np.zeros(2)  # where the pusher's path ends (`drive`), held while settling
        self._answers: dict[float, bool] = {}  # `frame_wanted`'s, by due time (`_wanted`)

    def _frame_due(self, t_s: float) -> bool:
        """A frame is due at `t_s`: if so, the next one is due a frame interval later."""
        if not self._due_at(t_s):
            return False
        self.next_frame_s = self._next_due(t_s)
        return True

    def _next_due(self, t_s: float) -> float:
        """When the frame after one due at `t_s` is due: the next multiple of the interval."""
        fi = self.frame_interval_s
        return (math.floor(t_s / fi + 1e-9) + 1) * fi

    def skip_still(self, targets: np.ndarray) -> int:
        """Advance the leading steps of `targets` that cannot move the object, in whole
        chunks, as one call (`SkipsStillSteps.advance_still`: stepped, or an engine's jump);
        the checks they span are those of an object at rest (no failure, no turn; a due frame
        is a still one). Returns how many were advanced (0 on an engine without the
        capability)."""
        sim, s, chunk = self.sim, self.s, self.chunk
        if not isinstance(sim, SkipsStillSteps):
            return 0
        n = min(sim.steps_still(targets), len(targets)) // chunk * chunk - chunk
        if n <= 0:
            return 0
        pose0 = sim.object_state().pose
        touched = sim.advance_still(targets[:n])
        after = sim.object_state()
        if touched or after.pose != pose0 or not at_rest(after, s):
            raise RuntimeError(f"{sim.name}: the object moved in steps declared still")
        self.contact = self.contact or touched
        for _ in range(n // chunk):
            self.steps += chunk
            t_s = self.steps * self.dt
            if self._frame_due(t_s) and self.on_still is not None:
                self._tell_still(t_s)
        return n

    def run(self, targets: np.ndarray, driving: bool = False) -> ObjectState:
        """Advance one chunk of steps, then check: failures, turn, tilt, a due frame."""
        touched, tilt = self.sim.advance(targets)
        return self._check(len(targets), touched, tilt, driving)

    def advance(
        self, targets: np.ndarray, driving: bool = False, near_rest: bool = False
    ) -> tuple[int, ObjectState]:
        """`run` the first chunk of `targets`; returns the steps advanced and the state.

        An engine that runs several chunks in one call (`RunsChunks`) runs the whole chunks up
        to the first one whose check may do more than bookkeeping (`_batch`) in one call,
        stopping early where its `ChunkStop` says (`near_rest`: near rest too, for the settle
        rule); the chunks it passes get the bookkeeping their checks would do (`_passed`),
        the last one the full check. The steps, and what the checks conclude, are those of
        one `run` after another (tests/test_planar.py)."""
        chunk = self.chunk
        batches = isinstance(self.sim, RunsChunks) and self.sim.runs_chunks()
        n = len(targets) // chunk if batches else 1
        k, declined = self._batch(n, driving)
        if k <= 1:  # one chunk, or a part of one (the end of a path)
            return len(targets[:chunk]), self.run(targets[:chunk], driving)
        rest = np.full(k, near_rest)
        rest[declined] = True
        if self.box is None:
            self.box = surely_in_view_box(self.radius, self.camera)
        stop = ChunkStop(
            self.box, 2.0 * self.s.settle_speed_m_s, 2.0 * self.s.settle_spin_rad_s, rest
        )
        done = self.sim.advance_chunks(targets[: k * chunk], chunk, stop)  # type: ignore[attr-defined]
        for touched, tilt, yaw in done[:-1]:
            self._passed(chunk, touched, tilt, yaw)
        touched, tilt, _ = done[-1]
        return len(done) * chunk, self._check(chunk, touched, tilt, driving)

    def _batch(self, n: int, driving: bool) -> tuple[int, list[int]]:
        """How many of the next `n` chunks go in one call: up to the first at which a frame
        is due, the last of them; while the pusher drives, past those the tracker declines
        (`frame_wanted`: a question without side effects, so it is asked ahead; the object
        moves with the pusher, so the frames asked are those the checks would ask; settling,
        it may stop before the next due frame and show nothing new). Also the chunks (0-based)
        at which a due frame is declined: passed unless the object is near rest there (at
        rest, the check tells the tracker so: `on_still`)."""
        declined: list[int] = []
        next_s = self.next_frame_s
        for k in range(1, n + 1):
            t_s = (self.steps + k * self.chunk) * self.dt
            if not self._due_at(t_s, next_s):
                continue
            if k == n or not driving or self._wanted(t_s, driving):
                return k, declined
            declined.append(k - 1)
            next_s = self._next_due(t_s)
        return n, declined

    def _passed(self, n: int, touched: bool, tilt: float, yaw: float) -> None:
        """A chunk the backend ran past (`advance`): the check's bookkeeping of a state that
        is finite, flat, surely in view and not at rest, where a due frame is declined."""
        self.steps += n
        self.contact = self.contact or touched
        self.turned += wrap_angle(yaw - self.last_yaw)
        self.last_yaw = yaw
        self.max_tilt = max(self.max_tilt, tilt, 0.0)
        self._frame_due(self.steps * self.dt)  # a declined frame: the next one's time

    def _due_at(self, t_s: float, next_s: float | None = None) -> bool:
        """`_frame_due`'s test, without its bookkeeping (`next_s`: the next frame's time, by
        default the push's own)."""
        next_s = self.next_frame_s if next_s is None else next_s
        return self.watch and t_s >= next_s - 1e-9

    def _check(self, n: int, touched: bool, tilt: float, driving: bool) -> ObjectState:
        """After a chunk of `n` steps: failures, turn, tilt, a due frame."""
        sim, s = self.sim, self.s
        self.steps += n
        self.contact = self.contact or touched
        st = sim.object_state()
        if st.is_finite:  # < half a turn between two checks (a few ms apart)
            self.turned += wrap_angle(st.pose.yaw_rad - self.last_yaw)
            self.last_yaw = st.pose.yaw_rad
        self.max_tilt = max(self.max_tilt, tilt, st.tilt_deg if st.is_finite else 0.0)
        self.status = sim.engine_failure() or classify_state(
            st, self.outline, self.camera, s, self.radius
        )
        t_s = self.steps * self.dt
        if self.status is None and self._frame_due(t_s):
            if at_rest(st, s):  # a still object shows nothing new: no frame
                if self.on_still is not None:
                    self._tell_still(t_s)
            elif self._wanted(t_s, driving):
                xy = sim.pusher_xy()
                frame = Frame(
                    sim.render_tracking_depth(),
                    t_s,
                    (float(xy[0]), float(xy[1])),
                    sim.pusher_radius_m(),
                )
                self.on_frame(frame)  # type: ignore[misc]
                self.n_frames += 1
                self._answers.clear()  # the tracker has seen more
        return st

    def _wanted(self, t_s: float, driving: bool) -> bool:
        """Whether the moving frame due at `t_s` is rendered: `frame_wanted`'s answer (every
        frame without it), asked once for each due frame (`_batch` asks ahead) until a frame
        or a rest tells the tracker more."""
        if self.frame_wanted is None:
            return True
        answer = self._answers.get(t_s)
        if answer is None:
            answer = self._answers[t_s] = self.frame_wanted(t_s, driving)
        return answer

    def _tell_still(self, t_s: float) -> None:
        self.on_still(t_s)  # type: ignore[misc]
        self._answers.clear()

    def drive(self, cmd: PushCommand, start: np.ndarray, direction: np.ndarray) -> None:
        """1) The straight path at the commanded speed, or the command's own path (a recorded
        push's); the pusher is where the path is at the end of each step."""
        dt = self.dt
        if cmd.path_xy_m is not None:
            path = np.asarray(cmd.path_xy_m, dtype=float)
        else:
            n_move = math.ceil(cmd.travel_m / (cmd.speed_m_s * dt) - 1e-9)
            travelled = np.minimum(cmd.speed_m_s * dt * np.arange(1, n_move + 1), cmd.travel_m)
            path = start + travelled[:, None] * direction  # the pusher at the end of every step
        self.end = path[-1]
        n_move = len(path)
        k = self.skip_still(path)
        while k < n_move and self.status is None:
            n, _ = self.advance(path[k:], driving=True)
            k += n
            dx, dy = (self.sim.pusher_xy() - path[k - 1]).tolist()
            self.lag = max(self.lag, math.hypot(dx, dy))

    def settle(self) -> None:
        """2) Hold the pusher still where the path ended; at rest = the object frame's floor
        point and yaw below the settle limits at every check for settle_hold_s."""
        if self.status is not None:
            return
        s, dt, chunk = self.s, self.dt, self.chunk
        hold_checks = max(1, math.ceil(s.settle_hold_s / (dt * chunk) - 1e-9))
        quiet = 0
        checks = max(1, math.ceil(s.max_settle_s / (dt * chunk)))
        held = np.repeat(self.end[None, :], chunk * min(checks, SETTLE_BATCH_CHUNKS), axis=0)
        while checks > 0:
            n, st = self.advance(held[: chunk * checks], near_rest=True)
            checks -= n // chunk
            if self.status is not None:
                return
            if n > chunk:  # the chunks passed were not at rest (`ChunkStop`)
                quiet = 0
            if at_rest(st, s):
                quiet += 1
                left = (hold_checks - quiet) * chunk
                if left > 0:  # checks that would see the same still object: skipped
                    quiet += self.skip_still(np.repeat(held[:1], left + chunk, axis=0)) // chunk
                if quiet >= hold_checks:
                    return
            else:
                quiet = 0
        self.status = PushStatus.NOT_SETTLED

    def retract(self, direction: np.ndarray) -> None:
        """3) Back off along the push line until clear (parking is `finish`'s)."""
        if self.status is not None:
            return
        s, dt, chunk = self.s, self.dt, self.chunk
        end = self.sim.pusher_xy()
        n_back = math.ceil(s.retract_m / (s.retract_speed_m_s * dt))
        back = np.minimum(s.retract_speed_m_s * dt * np.arange(1, n_back + 1), s.retract_m)
        i = 0
        while i < n_back:
            self.run(end - back[i : i + chunk, None] * direction)
            i += chunk
            if self.status is not None:
                break
            i += self.skip_still(end - back[i:, None] * direction)

    def finish(self, before: ObjectState) -> PushOutcome:
        """Classify the state at rest, park the pusher out of view once clear, report."""
        sim, s = self.sim, self.s
        after = sim.object_state()
        if after.is_finite:
            self.turned += wrap_angle(after.pose.yaw_rad - self.last_yaw)
        status = self.status
        if status is None or status is PushStatus.NOT_SETTLED:
            status = classify_state(after, self.outline, self.camera, s, self.radius) or status
        clearance = pusher_clearance_m(sim.pusher_xy(), after, self.outline, sim.pusher_radius_m())
        if clearance > s.clear_m:
            sim.place_pusher(sim.park_xy())
        max_tilt = max(self.max_tilt, after.tilt_deg) if after.is_finite else self.max_tilt
        return PushOutcome(
            status=status or PushStatus.OK,
            pose_before=before.pose,
            pose_after=after.pose if after.is_finite else before.pose,
            sim_time_s=self.steps * self.dt,
            steps=self.steps,
            contact_made=self.contact,
            max_pusher_lag_m=self.lag,
            max_tilt_deg=max_tilt,
            n_frames=self.n_frames,
            true_rotation_deg=math.degrees(self.turned),
        )
