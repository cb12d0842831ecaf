"""The episode runner: on a kinematic stand-in simulator (fast, exact answers, every failure
path), then end-to-end on both physics backends."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import shapely

from comexp.episode.loop import run_episode
from comexp.episode.task import EpisodeSpec, build_scene
from comexp.experiment.config import make_simulator
from comexp.method.estimator import EstimatorSettings, cross2
from comexp.method.frames import DepthImage, Pose2D
from comexp.method.rendering import render_prism_depth
from comexp.sim.protocol import Frame, PushOutcome
from comexp.sim.scene import ObjectState, PushCommand, PushStatus, SceneSpec
from comexp.sim.simulator import Simulator

BOX_CM = ((-4.0, -2.5), (4.0, -2.5), (4.0, 2.5), (-4.0, 2.5))
TRI_CM = ((-3.67, -2.67), (5.33, -1.67), (-0.67, 4.33))  # area centroid at the origin
TRAP_CM = ((-5.0, -2.0), (5.0, -2.0), (2.5, 2.0), (-2.5, 2.0))


def spec_for(
    outline=BOX_CM, com=(1.5, 0.8), seed=0, backend="fake", speed=40.0, mu=1.0, fps=0.0, **est
) -> EpisodeSpec:
    """The images before and after each push only, unless `fps` is given."""
    return EpisodeSpec(
        camera_fps=fps,
        backend=backend,
        floor="iso",
        mu_floor_x=mu,
        mu_floor_y=mu,
        mu_pusher=0.5,
        speed_cm_s=speed,
        izz_scale=1.0,
        object="obj",
        outline_cm=outline,
        height_cm=3.0,
        com_index=0,
        com_cm=com,
        seed=seed,
        estimator=EstimatorSettings(**est),
    )


class KinematicSim(Simulator):
    """Voting-theorem kinematics: the object turns with the push's moment about the CoM and
    slides along the push; renders exact depth images. `fail_at` injects a failure."""

    name = "fake"

    def __init__(
        self,
        fail_at: int | None = None,
        status=PushStatus.TIPPED,
        raise_at=None,
        slide_m=0.02,
        deg_per_cm: float = 4.0,
        max_turn_deg: float = 30.0,
        moving_s: float = 0.4,
    ):
        super().__init__()
        self.fail_at, self.status, self.raise_at = fail_at, status, raise_at
        self.slide_m, self.n = slide_m, 0
        self.deg_per_cm, self.max_turn_deg, self.moving_s = deg_per_cm, max_turn_deg, moving_s

    def build(self, scene: SceneSpec) -> None:
        self._scene, self.pose = scene, scene.initial_pose  # `n` counts pushes across re-builds
        self.outline = np.array(scene.obj.outline_m)
        self.com = np.array(scene.obj.com_m)

    def render_depth(self) -> DepthImage:
        cam = self._scene.camera.model()
        return render_prism_depth(cam, self.outline, self._scene.obj.height_m, self.pose)

    def push(
        self,
        cmd: PushCommand,
        on_frame=None,
        frame_interval_s: float = 0.0,
        on_still=None,
        frame_wanted=None,
    ) -> PushOutcome:
        """The motion takes `moving_s` at a constant rate; with `on_frame`, frames every
        `frame_interval_s` while it moves (the protocol's frame hook; it never rests in
        between, so `on_still` is never called; the pusher drives it all along, so
        `frame_wanted` is asked with driving=True)."""
        k, self.n = self.n, self.n + 1
        if self.raise_at == k:
            raise RuntimeError("engine exploded")
        before = self.pose
        if self.fail_at == k:
            return PushOutcome(self.status, before, before, 0.1, 100, True, 0.0, 30.0)
        start = before.to_object(np.array(cmd.start_xy_m))
        d = Pose2D(0, 0, -before.yaw_rad).to_world(np.array(cmd.direction_xy))
        line = shapely.LineString([start, start + d * (cmd.travel_m + 0.1)])
        contact = shapely.intersects(shapely.Polygon(self.outline), line)
        moment_cm = 100.0 * float(cross2(start - self.com, d))
        cap = self.max_turn_deg
        rot = math.radians(np.clip(self.deg_per_cm * moment_cm, -cap, cap)) if contact else 0.0
        # rotate about the CoM, then slide 2 cm along the push
        g_w = before.to_world(self.com)
        shift = np.array(cmd.direction_xy) * self.slide_m if contact else np.zeros(2)

        def pose_at(f: float) -> Pose2D:
            yaw = before.yaw_rad + f * rot
            origin = g_w - Pose2D(0, 0, yaw).to_world(self.com) + f * shift
            return Pose2D(float(origin[0]), float(origin[1]), yaw)

        n_frames = 0
        if on_frame is not None and frame_interval_s > 0 and contact:
            for i in range(1, math.ceil(self.moving_s / frame_interval_s)):
                self.pose = pose_at(i * frame_interval_s / self.moving_s)
                if frame_wanted is not None and not frame_wanted(i * frame_interval_s, True):
                    continue
                on_frame(Frame(self.render_depth(), i * frame_interval_s, (0.0, 0.5), 0.005))
                n_frames += 1
        self.pose = pose_at(1.0)
        return PushOutcome(
            PushStatus.OK,
            before,
            self.pose,
            0.5,
            500,
            contact,
            0.0,
            0.0,
            n_frames,
            math.degrees(rot),
        )

    def object_state(self) -> ObjectState:
        p = self.pose
        return ObjectState((p.x_m, p.y_m, 0.015), 0.0, 0.0, p.yaw_rad, (0, 0, 0), (0, 0, 0))

    def set_object_velocity(self, linear_m_s, angular_rad_s) -> None:
        raise NotImplementedError

    # the protocol is replaced whole (`run_kinematic`), so its primitives are never called
    def place_pusher(self, xy) -> None:
        raise NotImplementedError

    def pusher_xy(self):
        raise NotImplementedError

    def advance(self, targets):
        raise NotImplementedError

    def step(self, duration_s: float) -> None:
        pass


def run_kinematic(spec: EpisodeSpec, sim: KinematicSim):
    """The episode loop on ideal kinematics: `KinematicSim.push` in the push protocol's place."""
    return run_episode(spec, sim, push=KinematicSim.push)


# Seeds 0-7 of every case below. One episode's error is a draw from a spread, and symmetric
# outlines give exact ties between contacts that floating point breaks either way: with
# OpenBLAS's AVX2 kernels instead of AVX-512 (OPENBLAS_CORETYPE=Haswell), the box with CoM
# (-2, -1) at seed 7 takes the mirror-image first push and ends at 1.020 cm instead of
# 0.864 cm. Measured over seeds 0-23 of all 8 cases, natively and with the CPU features
# disabled (`git show c5b8989:bench/emulate_cpu.sh` avx2 | sse): one episode's error
# 0.077-1.141 cm, the mean of
# 8 consecutive seeds <= 0.752 cm (seeds 0-7: <= 0.582 cm); rotation error per episode:
# median <= 0.771 deg, max <= 1.688 deg.
IDEAL_SEEDS = range(8)
IDEAL_MEAN_ERROR_CM = 0.9  # measured <= 0.752 (any 8 consecutive seeds); margin 0.15 cm
IDEAL_MAX_ERROR_CM = 1.5  # measured <= 1.141 (24 seeds); margin 0.36 cm


@pytest.mark.parametrize("source", ["vision", "oracle"])
@pytest.mark.parametrize(
    "outline,com",
    [(BOX_CM, (1.5, 0.8)), (BOX_CM, (-2.0, -1.0)), (TRI_CM, (0.5, -0.5)), (TRAP_CM, (-1, 0.5))],
)
def test_episode_on_ideal_kinematics_finds_the_com(outline, com, source):
    errors = []
    for seed in IDEAL_SEEDS:
        res = run_kinematic(
            spec_for(outline, com, seed=seed, rotation_source=source), KinematicSim()
        )
        assert res.status == "ok", (seed, res.detail)
        assert res.n_pushes == 5 and len(res.pushes) == 5
        errors.append(res.error_cm)
        _check_push_records(res, outline, com)
    assert np.mean(errors) < IDEAL_MEAN_ERROR_CM, np.round(errors, 3)
    assert max(errors) < IDEAL_MAX_ERROR_CM, np.round(errors, 3)


def test_magnitude_method_in_episodes_beats_the_paper_on_ideal_kinematics():
    """`estimator.method=magnitude` driven by `run_episode` (vision, the stand-in physics: a
    turn proportional to the moment, capped): measured mean 0.209 cm against the paper's
    0.458 over these 32 episodes."""
    cases = [
        (BOX_CM, (1.5, 0.8)),
        (BOX_CM, (-2.0, -1.0)),
        (TRI_CM, (0.5, -0.5)),
        (TRAP_CM, (-1, 0.5)),
    ]
    errors = {}
    for method in ("paper", "magnitude"):
        runs = [
            run_kinematic(spec_for(o, c, seed=s, method=method), KinematicSim())
            for o, c in cases
            for s in IDEAL_SEEDS
        ]
        assert all(r.status == "ok" and r.n_pushes == 5 for r in runs), method
        errors[method] = float(np.mean([r.error_cm for r in runs]))
    assert errors["magnitude"] < 0.6 * errors["paper"], errors


def _check_push_records(res, outline, com) -> None:
    """Push records are in the object's own frame: the contact lies on the outline, the push
    direction points into the object and the measured rotation has the moment's sign."""
    poly = shapely.Polygon(outline)
    for p in res.pushes:
        c = np.array([p.contact_x_cm, p.contact_y_cm])
        # a contour pixel's centre (up to ~0.7 px inside), plus the tracked pose's error, from
        # the true outline: measured <= 0.435 cm (1.6 px of 0.268 cm; triangle, seed 11) over
        # seeds 0-23 of these cases; margin 0.115 cm
        assert poly.exterior.distance(shapely.Point(c)) < 0.55, (res.spec.seed, p)
        inside = c + 0.5 * np.array([p.dir_x, p.dir_y])
        assert poly.contains(shapely.Point(inside))
        # the sign of the measured rotation is the sign of the moment about the true CoM
        moment = cross2(c - np.array(com), np.array([p.dir_x, p.dir_y]))
        if abs(p.rotation_true_deg) > 1.0:
            assert np.sign(p.rotation_true_deg) == np.sign(moment)
        assert p.decision in ("ccw", "cw", "band")
    # vision: a binary 224 px mask resolves the yaw to ~0.1-1 deg; the worst case, edges
    # along the pixel grid (this box at ~92 deg), reaches ~1.5 deg (docs/method.md); measured
    # over the seeds above: median <= 0.771 deg, max <= 1.688 deg
    rot_err = [abs(p.rotation_deg - p.rotation_true_deg) for p in res.pushes]
    assert np.median(rot_err) < 1.0 and max(rot_err) < 2.0, (res.spec.seed, rot_err)
    sizes = [p.region_px for p in res.pushes]
    assert sizes == sorted(sizes, reverse=True)


def test_episode_is_deterministic_and_seed_sets_the_yaw():
    a = run_kinematic(spec_for(seed=3), KinematicSim())
    b = run_kinematic(spec_for(seed=3), KinematicSim())
    assert a.est_com_cm == b.est_com_cm and a.pushes == b.pushes
    ya = build_scene(spec_for(seed=3)).initial_pose.yaw_rad
    yb = build_scene(spec_for(seed=4)).initial_pose.yaw_rad
    assert ya != yb and -math.pi <= ya < math.pi


@pytest.mark.parametrize(
    "status",
    [PushStatus.TIPPED, PushStatus.LEFT_VIEW, PushStatus.SIM_UNSTABLE, PushStatus.NOT_SETTLED],
)
def test_push_failures_become_results(status):
    res = run_kinematic(spec_for(), KinematicSim(fail_at=2, status=status))
    assert res.status == "failed" and res.failure == status.value
    assert res.n_pushes == 2 and res.error_cm is None


def test_object_is_recentred_before_it_can_leave_the_view():
    """Long slides (a 40 cm/s push on the mu 0.1 floor) would carry the object out of the
    camera's view within 5 pushes; the protocol puts it back at the centre, yaw unchanged."""
    far = run_kinematic(spec_for(seed=5), KinematicSim(slide_m=0.12))
    assert "re-centred" in far.detail
    assert far.status == "ok" and far.n_pushes == 5, far.detail
    assert far.error_cm < 1.0  # 0.599 cm; seeds 0-23: <= 0.741 cm, every one re-centred
    lost = run_kinematic(
        replace(spec_for(seed=5), recenter_beyond_cm=0.0), KinematicSim(slide_m=0.12)
    )
    assert lost.status == "failed" and lost.failure == "left_view", lost.detail


def test_frames_unwrap_big_turns_of_a_symmetric_outline():
    """The box (180 deg symmetry) turning by up to 150 deg per push: from the images before
    and after only, a turn beyond 90 deg reads as its symmetric copy, of the wrong sign; with
    frames during the push (10 fps over the 0.4 s motion: 3 frames) every turn is found.
    Seed 1 (measured): 4 of 5 pushes turn by 92-150 deg."""
    sim = dict(deg_per_cm=100.0, max_turn_deg=150.0)
    two = run_kinematic(spec_for(seed=1), KinematicSim(**sim))
    big = [p for p in two.pushes if abs(p.rotation_true_deg) > 90]
    assert big and all(p.n_frames == 0 for p in two.pushes)
    for p in big:  # aliased by the symmetry: off by 180 deg, the other sign
        assert abs(abs(p.rotation_deg - p.rotation_true_deg) - 180.0) < 2.0
        assert np.sign(p.rotation_deg) != np.sign(p.rotation_true_deg)
    watched = run_kinematic(replace(spec_for(seed=1), camera_fps=10.0), KinematicSim(**sim))
    assert watched.status == "ok", watched.detail
    assert any(abs(p.rotation_true_deg) > 90 for p in watched.pushes)
    for p in watched.pushes:
        assert abs(p.rotation_deg - p.rotation_true_deg) < 2.0, p
        assert p.n_frames == (3 if abs(p.rotation_true_deg) > 0 else 0)
    # the aliased signs mislead the estimator: measured 4.75 cm, tracked 0.22 cm
    assert watched.error_cm < 1.0 < two.error_cm
    oracle = run_kinematic(
        replace(spec_for(seed=1, rotation_source="oracle"), camera_fps=10.0), KinematicSim(**sim)
    )
    assert all(p.n_frames == 0 for p in oracle.pushes)  # the oracle needs no frames
    assert [p.rotation_deg for p in oracle.pushes] == [p.rotation_true_deg for p in oracle.pushes]


def test_frame_counts_are_stored(tmp_path):
    from comexp.results.store import ResultsDB

    sim = KinematicSim(deg_per_cm=100.0, max_turn_deg=150.0)
    res = run_kinematic(replace(spec_for(seed=1), camera_fps=10.0), sim)
    with ResultsDB(tmp_path / "r.db") as db:
        db.add_results(None, [res])
        (row,) = db.episodes()
        stored = db.pushes(row["id"])
    assert [p["n_frames"] for p in stored] == [p.n_frames for p in res.pushes]
    assert [p["rotation_true_deg"] for p in stored] == [p.rotation_true_deg for p in res.pushes]
    assert any(p["n_frames"] > 0 for p in stored)


def test_exceptions_become_error_results():
    res = run_kinematic(spec_for(), KinematicSim(raise_at=1))
    assert res.status == "failed" and res.failure == "error"
    assert "engine exploded" in res.detail


def test_no_valid_contact_is_a_result(monkeypatch):
    import comexp.method.estimator as est

    # every contact unreachable (as for a pusher too fat for the object)
    monkeypatch.setattr(est, "reachable_contacts", lambda o, P, N, r, **k: np.zeros(len(P), bool))
    res = run_kinematic(spec_for(), KinematicSim())
    assert res.status == "failed" and res.failure == "no_valid_contact"


# --- end to end on the physics backends --------------------------------------------------

E2E = [(BOX_CM, (1.5, 0.8), 0), (TRI_CM, (0.5, -0.5), 1), (TRAP_CM, (-1.5, 0.5), 2)]


@pytest.mark.parametrize("backend", ["pybullet", "mujoco"])
def test_end_to_end_dynamic_pushing(backend):
    sim = make_simulator(backend)
    try:
        results = [
            run_episode(spec_for(o, c, seed=s, backend=backend, speed=40.0), sim) for o, c, s in E2E
        ]
    finally:
        sim.close()
    for r in results:
        assert r.status == "ok", (r.failure, r.detail)
        assert r.n_pushes == 5
        # simulated, not wall-clock, time (wall time on a shared machine says nothing): every
        # push came to rest promptly. Measured 1.03-1.31 s per episode (5 pushes) over 8
        # seeds of each case on both engines; a push that creeps on for seconds towards the
        # 5 s settle limit, as rocking footprints did (docs/physics_pybullet.md), exceeds it.
        assert r.sim_time_s < 2.0, (r.spec.object, r.sim_time_s)
    # measured over 8 seeds of each case, both engines, CPU features on and off
    # (git show c5b8989:bench/emulate_cpu.sh): the mean of the 3 <= 0.676 cm, one episode
    # <= 1.062 cm
    errors = [r.error_cm for r in results]
    assert np.mean(errors) < 1.0, errors
    assert max(errors) < 2.0, errors


def test_spec_for_object_copies_the_object_definition():
    from comexp.experiment.objects import load_objects

    obj = load_objects(["l_shape"])["l_shape"]
    spec = EpisodeSpec.for_object(
        obj,
        3,
        (0.5, -0.25),
        backend="pybullet",
        floor="iso",
        mu_floor_x=1.0,
        mu_floor_y=1.0,
        mu_pusher=0.5,
        speed_cm_s=40,
        izz_scale=1.0,
    )
    assert (spec.object, spec.com_index, spec.com_cm) == ("l_shape", 3, (0.5, -0.25))
    assert spec.outline_cm == tuple(tuple(p) for p in obj.outline_cm)
    assert spec.height_cm == obj.height_cm
    hash(spec)  # frozen and hashable: plain tuples of floats, no lists


def test_a_recentred_push_is_flagged_in_its_path(monkeypatch):
    """The estimator that reads each push's path learns which pushes were followed by a
    re-centring (their pose at rest is the placed one, not where the slide ended)."""
    from comexp.method.motion_estimator import MotionEstimator

    flags: list[bool] = []
    original = MotionEstimator.observe_path

    def spy(self, path):
        flags.append(bool(path.extra.get("recentred")))
        return original(self, path)

    monkeypatch.setattr(MotionEstimator, "observe_path", spy)
    res = run_kinematic(spec_for(seed=5, method="motion"), KinematicSim(slide_m=0.12))
    assert res.status == "ok", res.detail
    assert len(flags) == res.n_pushes and any(flags)
    assert sum(flags) == res.detail.count("re-centred")
