"""The episode loop: runs an episode's task on a simulator, from the first image to the estimate.

Build, perceive, then n_push times choose a contact (Alg. 1), push, measure the rotation,
update the region (Alg. 2). What is pushed and what is scored is the task's
(`comexp.episode.task`: `EpisodeSpec`, `build_scene`, `push_command`, `Scoring`); this
module is the loop that runs it, with the experimenter's protocol between pushes (re-centring
an object that drifted off). The pushes go through the one push protocol
(`comexp.sim.protocol.push`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from comexp.episode.task import (
    EpisodeResult,
    EpisodeSpec,
    PushRecord,
    Scoring,
    build_scene,
    failed_result,
    push_command,
)
from comexp.episode.timing import NO_TIMER, Timer
from comexp.method.estimator import floor_force_direction
from comexp.method.estimators import make_estimator
from comexp.method.frames import Pose2D, wrap_angle
from comexp.method.motion_estimator import KnownNuisances, PushPath
from comexp.method.observation import (
    PerceptionError,
    mask_pusher,
    observe,
    observe_boundary,
    perceive_first,
)
from comexp.method.tracking import PoseTracker
from comexp.sim.protocol import Frame, PushOutcome, push
from comexp.sim.scene import PushCommand
from comexp.sim.simulator import Simulator


def needs_recentering(pose: Pose2D, recenter_beyond_cm: float) -> bool:
    """True when the object has drifted far enough that the next push could carry it out of the
    camera's view (see `EpisodeSpec.recenter_beyond_cm`)."""
    return recenter_beyond_cm > 0 and math.hypot(pose.x_m, pose.y_m) * 100.0 > recenter_beyond_cm


# an estimator's label of a push (`observe`'s return): the `pushes.decision` column's width
DECISION_MAX_CHARS = 16

# a push protocol: `comexp.sim.protocol.push`, or a test's ideal kinematics in its place
PushFn = Callable[..., PushOutcome]


def run_episode(
    spec: EpisodeSpec, sim: Simulator, push: PushFn = push, timer: Timer = NO_TIMER
) -> EpisodeResult:
    """One CoM estimation: build, perceive, then n_push times choose a contact (Alg. 1), push,
    measure the rotation, update the region (Alg. 2). Never raises: failures are results.

    The estimator works in its own frame (the first image's world frame, origin at the hull
    centroid). The true initial pose is used only at the end, to express the estimate and the
    push records in the object's own frame for evaluation; the true pose during the episode
    only with `rotation_source=oracle`. `timer` is told where the time goes
    (`comexp.episode.timing`: benchmarks).
    """
    loop = _EpisodeLoop(spec, sim, push, timer, time.perf_counter())
    try:
        return loop.run()
    except PerceptionError as exc:
        return loop.failed(exc.failure, str(exc))
    except Exception as exc:  # noqa: BLE001 - a sweep must survive any single episode
        return loop.failed("error", f"{type(exc).__name__}: {exc}")


class _EpisodeLoop:
    """One run of `run_episode`: the pushes so far, the simulated time, the notes, and the
    estimator frame's current pose (`frame`) beside the object's true one (`true_prev`)."""

    def __init__(
        self, spec: EpisodeSpec, sim: Simulator, push: PushFn, timer: Timer, t0: float
    ) -> None:
        self.spec = spec
        self.sim = sim
        self.push = push
        self.timer = timer
        self.settings = spec.estimator
        self.t0 = t0
        self.pushes: list[PushRecord] = []
        self.sim_time = 0.0
        self.details: list[str] = []
        self.path: list[tuple[float, Pose2D]] = []  # (t_s, pose) per tracked frame of a push

    def failed(self, reason: str, detail: str = "") -> EpisodeResult:
        wall_s = time.perf_counter() - self.t0
        return failed_result(self.spec, reason, detail, self.pushes, wall_s, self.sim_time)

    def run(self) -> EpisodeResult:
        spec, sim, settings, phase = self.spec, self.sim, self.settings, self.timer.phase
        with phase("build"):
            self.scene = build_scene(spec)
            sim.build(self.scene)
            true0 = sim.true_pose()
            perc, obs0 = perceive_first(sim.render_depth(), settings.contact_spacing_px)
        self.scoring = Scoring.at_first_image(spec, true0, perc.frame_pose)
        self.est = make_estimator(
            perc.region_m,
            perc.contacts_m,
            perc.contact_normals,
            perc.pixel_m,
            settings,
            outline_m=perc.outline_m,
            pusher_radius_m=self.scene.pusher.radius_m,
            nuisances=self._known_nuisances(),
        )
        self.tracker = PoseTracker(perc, obs0) if settings.rotation_source == "vision" else None
        self.frame = perc.frame_pose  # current estimate of the estimator frame's pose in the world
        self.true_prev = true0
        for k in range(settings.n_push):
            with phase("choose"):
                choice = self.est.next_push()
            if choice is None:
                if k == 0:
                    return self.failed("no_valid_contact", "no reachable push line cuts the region")
                self.details.append(f"stopped after {k} pushes: no valid contact")
                break
            P, N = choice
            failure = self._push(k, P, N)
            if failure is not None:
                return failure
        wall_s = time.perf_counter() - self.t0
        detail = "; ".join(self.details)
        return self.scoring.result(self.est.estimate_m, self.pushes, wall_s, self.sim_time, detail)

    def _known_nuisances(self) -> KnownNuisances | None:
        """The scene's floor, pusher friction and Izz / m about the CoM, for an estimator told
        them (`nuisance_source=oracle`: evaluation); None otherwise."""
        if self.settings.nuisance_source != "oracle":
            return None
        spec, obj = self.spec, self.scene.obj
        return KnownNuisances(
            (spec.mu_floor_x, spec.mu_floor_y), spec.mu_pusher, obj.izz_kg_m2 / obj.mass_kg
        )

    def _push(self, k: int, P: np.ndarray, N: np.ndarray) -> EpisodeResult | None:
        """Push `k` through contact P along N (estimator frame), measure the turn, update the
        region and record the push; the failed result if the push failed."""
        spec = self.spec
        cmd = push_command(spec, self.frame, P, N, self.scene.pusher.radius_m)
        with self.timer.phase("push"):
            out, used = self._watched_push(cmd)
        self.sim_time += out.sim_time_s
        if not out.ok:
            return self.failed(out.status.value, f"push {k}: {out.status.value}")
        if not out.contact_made:
            self.details.append(f"push {k}: pusher missed the object")
        with self.timer.phase("measure"):
            new_frame, true_now, rot, rot_true, recentred = self._measure(k, out, used)
        with self.timer.phase("estimate"):
            decision = self._estimate(P, N, cmd, new_frame, rot, recentred)
        self.frame, self.true_prev = new_frame, true_now
        region = getattr(self.est, "region_m", None)  # an estimator that shows its region
        record = self.scoring.record(
            k, P, N, rot, rot_true, decision, self.est.region_px, used, region
        )
        self.pushes.append(record)
        return None

    def _estimate(
        self,
        P: np.ndarray,
        N: np.ndarray,
        cmd: PushCommand,
        new_frame: Pose2D,
        rot: float,
        recentred: bool,
    ) -> str:
        """The estimator takes the push (its path first, if it reads paths); its decision."""
        spec, settings = self.spec, self.settings
        line = None
        if settings.method == "magnitude" and settings.mag_floor_model:
            # the robot knows its floor and pusher; the yaw is the estimator's own (vision)
            line = floor_force_direction(
                N, self.frame.yaw_rad, spec.mu_floor_x, spec.mu_floor_y, spec.mu_pusher
            )
        observe_path = getattr(self.est, "observe_path", None)
        if observe_path is not None:  # estimators that use the path of the push (motion)
            speed_m_s = spec.speed_cm_s / 100.0
            approach_m = float(np.hypot(*(self.frame.to_world(P) - cmd.start_xy_m)))
            observe_path(
                PushPath(
                    pose_before=self.frame,
                    t_s=tuple(t for t, _ in self.path),
                    poses=tuple(p for _, p in self.path),
                    pose_after=new_frame,
                    t_contact_s=(approach_m - self.scene.pusher.radius_m) / speed_m_s,
                    speed_m_s=speed_m_s,
                    rotation_deg=rot,
                    t_end_s=cmd.travel_m / cmd.speed_m_s,
                    extra={"recentred": True} if recentred else {},
                )
            )
        decision = self.est.observe(P, N, rot, line)
        if not isinstance(decision, str) or not 0 < len(decision) <= DECISION_MAX_CHARS:
            raise TypeError(
                f"{type(self.est).__name__}.observe must return a label of 1-"
                f"{DECISION_MAX_CHARS} characters (stored as the push's decision), "
                f"got {decision!r}"
            )
        return decision

    def _watched_push(self, cmd: PushCommand) -> tuple[PushOutcome, int]:
        """The push, with the tracker following it through camera frames when it watches
        (vision, `camera.fps` > 0); returns the outcome and the frames the tracker used.
        With `rotation_source=oracle` an estimator that uses the path (`observe_path`) gets the
        true poses at every camera frame instead: the path without vision's errors."""
        tracker, settings = self.tracker, self.settings
        self.path.clear()
        if not self.spec.camera_fps > 0:
            return self.push(self.sim, cmd), 0
        if tracker is None:
            if not hasattr(self.est, "observe_path"):
                return self.push(self.sim, cmd), 0
            # the estimator frame moves rigidly with the object: carried by the true pose
            offset = self.true_prev.relative(self.frame)

            def on_true_frame(f: Frame) -> None:
                self.path.append((f.t_s, self.sim.true_pose().compose(offset)))

            interval_s = 1.0 / self.spec.camera_fps
            return self.push(self.sim, cmd, on_frame=on_true_frame, frame_interval_s=interval_s), 0
        used = 0
        tracker.begin_push()

        def on_frame(f: Frame) -> None:
            nonlocal used
            with self.timer.phase("track"):
                img = mask_pusher(f.image, f.pusher_xy_m, f.pusher_radius_m)
                last = tracker.last
                try:
                    view = observe_boundary(img, (last.x_m, last.y_m))
                except PerceptionError:
                    return  # a frame that shows no object is not used
                tracker.track(view, f.t_s)
            self.path.append((f.t_s, tracker.last))
            used += 1

        # while driving, a frame once the pusher has travelled track_drive_mm since the last
        drive_gap_s = settings.track_drive_mm / 1000.0 / cmd.speed_m_s
        out = self.push(
            self.sim,
            cmd,
            on_frame=on_frame,
            frame_interval_s=1.0 / self.spec.camera_fps,
            on_still=tracker.hold,
            frame_wanted=lambda t_s, driving: tracker.wants_frame(
                t_s, driving, settings.track_step_deg, settings.track_gap_s, drive_gap_s
            ),
        )
        return out, used

    def _measure(
        self, k: int, out: PushOutcome, used: int
    ) -> tuple[Pose2D, Pose2D, float, float, bool]:
        """After push `k`: re-centre the object if it drifted off, then the estimator frame's
        new pose, the true pose, the measured and true turns (deg) and whether it re-centred."""
        sim = self.sim
        true_now = sim.true_pose()
        rot_true = out.true_rotation_deg
        if rot_true is None:  # a simulator that does not track it: wrapped
            rot_true = math.degrees(wrap_angle(true_now.yaw_rad - self.true_prev.yaw_rad))
        recentred = needs_recentering(true_now, self.spec.recenter_beyond_cm)
        if recentred:
            sim.build(replace(self.scene, initial_pose=Pose2D(0.0, 0.0, true_now.yaw_rad)))
            # Placement keeps the yaw, so it adds no rotation; the next image (vision) or the
            # placed true pose (oracle) carries the estimator frame along.
            true_now = sim.true_pose()
            self.details.append(f"re-centred after push {k}")
        if self.tracker is not None:
            new_frame = self.tracker.fit(observe(sim.render_depth())).pose
            # the tracker's yaw is unwrapped: through frames it may turn beyond half a turn
            turn = new_frame.yaw_rad - self.frame.yaw_rad
            rot = math.degrees(turn if used else wrap_angle(turn))
        else:  # oracle: carry the frame with the true rigid motion
            new_frame = true_now.compose(self.true_prev.relative(self.frame))
            rot = rot_true
        return new_frame, true_now, rot, rot_true, recentred
