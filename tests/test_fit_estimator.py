"""The `fit` estimator: its quasi-static model against closed forms and the planar referee, the
estimator on the model's own paths, and in episodes."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from comexp.method.estimator import EstimatorSettings, outline_contacts, region_from_outline
from comexp.method.estimators import make_estimator
from comexp.method.fit_estimator import FIT_VERSION, FitEstimator, FitSettings
from comexp.method.frames import Pose2D
from comexp.method.motion_estimator import KnownNuisances, PushPath
from comexp.method.quasi_static import (
    MOMENT_ANGLES,
    ContactStep,
    PusherDrive,
    RolloutPush,
    _closest_near,
    _closest_on_outline,
    footprint_samples,
    moment_table,
    predict_step,
    pressure_weights,
    roll_out,
)

BOX = np.array([(-0.05, -0.03), (0.05, -0.03), (0.05, 0.03), (-0.05, 0.03)])
PIXEL_M = 0.0027
RADIUS_M = 0.005


def _step(P, N, v=0.04, tau=0.1, yaw=0.0) -> ContactStep:
    N = np.asarray(N, float) / np.linalg.norm(N)
    return ContactStep(np.asarray(P, float), N, v * N, yaw, tau, np.zeros(2), 0.0)


def _predict(G, step, ratio=1.0, axis=0.0, mu=1.0):
    samples = footprint_samples(BOX)
    G = np.atleast_2d(np.asarray(G, float))
    return predict_step(G, samples, pressure_weights(samples, G), ratio, axis, mu, step)


def test_a_push_through_the_com_does_not_turn_and_moves_with_the_pusher() -> None:
    G = (0.0, 0.0)
    d, turn = _predict(G, _step((-0.05, 0.0), (1.0, 0.0)))
    assert turn[0] == pytest.approx(0.0, abs=1e-12)
    assert d[0] == pytest.approx([0.04 * 0.1, 0.0], abs=1e-12)  # sticks: the pusher's travel


@pytest.mark.parametrize("offset", [0.01, -0.01, 0.025])
def test_it_turns_with_the_torque_counter_clockwise_positive(offset) -> None:
    """Pushing +x below the CoM (lever (P - G) x N > 0) turns the object CCW (positive)."""
    G = (0.0, offset)
    _, turn = _predict(G, _step((-0.05, 0.0), (1.0, 0.0)))
    lever = (-0.05 - 0.0) * 0.0 - (0.0 - offset) * 1.0
    assert np.sign(turn[0]) == np.sign(lever)


def test_a_sticking_contact_moves_with_the_pusher() -> None:
    """With a wide cone the contact point's velocity is the pusher's (J V = v_p)."""
    G = np.array([0.01, 0.012])
    P = np.array([-0.05, 0.0])
    step = _step(P, (1.0, 0.0), tau=1.0)
    d, turn = _predict(G, step, mu=10.0)
    # the contact point moves as the origin plus the turn about the origin
    v_contact = d[0] + turn[0] * np.array([-P[1], P[0]])
    assert v_contact == pytest.approx(step.push_velocity, abs=1e-9)


def test_a_frictionless_pusher_pushes_along_the_normal_and_slides() -> None:
    G = np.array([0.01, 0.012])
    P = np.array([-0.05, 0.0])
    step = _step(P, (1.0, 0.0), tau=1.0)
    d, turn = _predict(G, step, mu=0.0)
    v_contact = d[0] + turn[0] * np.array([-P[1], P[0]])
    assert v_contact[0] == pytest.approx(0.04, abs=1e-9)  # keeps up with the pusher
    assert abs(v_contact[1]) > 1e-4  # and slides along the face
    # on an isotropic floor a force along x moves the CoM along x (B_f is a multiple of I)
    v_G = d[0] + turn[0] * np.array([G[1], -G[0]]) * -1
    assert v_G[1] == pytest.approx(0.0, abs=1e-9)


def test_an_anisotropic_floor_turns_the_motion_toward_its_slippery_axis() -> None:
    """A push through the CoM at 45 deg to a floor slippery along x (ratio 10 across) moves
    the object more along x than along y (frictionless pusher: the force is the normal)."""
    G = (0.0, 0.0)
    N = np.array([1.0, 1.0]) / math.sqrt(2)
    d, _ = _predict(G, _step(-0.03 * N, N), ratio=10.0, axis=0.0, mu=0.0)
    assert d[0, 0] > 5 * d[0, 1] > 0


def _planar_slow_push(
    com_cm, mu_floor, P, N, izz=1.0, mu_pusher=0.5, speed_cm_s=4.0, mu_floor_y=None
):
    """A slow push on planar (4 cm/s unless said), the true poses every 1.33 mm of the
    pusher's travel (30 frames/s at 4 cm/s; object frame = the true one)."""
    from test_episode import spec_for

    from comexp.episode.task import build_scene, push_command
    from comexp.experiment.config import make_simulator
    from comexp.sim.protocol import push

    spec = spec_for(backend="planar", speed=speed_cm_s, mu=mu_floor, com=com_cm)
    spec = replace(spec, izz_scale=izz, mu_pusher=mu_pusher)
    if mu_floor_y is not None:  # anisotropic: mu_floor along x, this along y
        spec = replace(spec, floor="aniso", mu_floor_y=mu_floor_y)
    sim = make_simulator("planar")
    scene = build_scene(spec)
    sim.build(scene)
    true0 = sim.true_pose()
    cmd = push_command(spec, true0, P, N, scene.pusher.radius_m)
    frames: list[tuple[float, Pose2D]] = []
    push(
        sim,
        cmd,
        on_frame=lambda f: frames.append((f.t_s, sim.true_pose())),
        frame_interval_s=(1 / 30) * 0.04 / cmd.speed_m_s,
    )
    approach = float(np.hypot(*(true0.to_world(P) - cmd.start_xy_m)))
    t_contact = (approach - scene.pusher.radius_m) / cmd.speed_m_s
    outline = np.array(spec.outline_cm) / 100.0
    steps = PusherDrive(
        true0,
        tuple(t for t, _ in frames),
        tuple(p for _, p in frames),
        P,
        N,
        t_contact,
        cmd.travel_m / cmd.speed_m_s,
        cmd.speed_m_s,
        outline,
        scene.pusher.radius_m,
    ).steps(0.002)
    return spec, outline, steps


@pytest.mark.parametrize("lever_m", [0.006, -0.012])
def test_the_model_follows_the_referee_on_a_slow_push(lever_m) -> None:
    """Planar, 4 cm/s, isotropic floor, Izz x 1: the model's turn summed over the push's
    intervals, each predicted from its observed middle pose at the true CoM, floor and pusher
    friction, against planar's (measured: 1.08x and 1.09x planar's turn)."""
    from test_episode import BOX_CM

    com_cm = (1.5, 0.8)
    outline = np.array(BOX_CM) / 100.0
    x_min = outline[:, 0].min()
    P = np.array([x_min, com_cm[1] / 100 - lever_m])
    spec, outline, steps = _planar_slow_push(com_cm, 0.5, P, np.array([1.0, 0.0]))
    assert len(steps) >= 10
    samples = footprint_samples(outline)
    G = np.array([com_cm]) / 100.0
    w = pressure_weights(samples, G)
    predicted = sum(predict_step(G, samples, w, 1.0, 0.0, spec.mu_pusher, s)[1][0] for s in steps)
    observed = sum(s.d_yaw for s in steps)
    assert np.sign(predicted) == np.sign(observed) == np.sign(lever_m)
    assert predicted == pytest.approx(observed, rel=0.15)


@pytest.mark.parametrize(
    ("mu_pusher", "speed_cm_s", "rel"),
    [(0.1, 4.0, 0.15), (1.0, 4.0, 0.15), (0.1, 0.4, 0.06)],
)
def test_the_model_follows_the_referee_on_a_slippery_floor(mu_pusher, speed_cm_s, rel) -> None:
    """Planar, floor mu 0.1, Izz x 1, lever 15 mm, the push's intervals after the first
    (which holds the impact): the model's turn against the referee's. Sticking (mu 1): 0.97x
    the model's turn. Slipping (mu 0.1): 1.14x at 4 cm/s, 1.05x at a tenth of the speed,
    where the object's inertia no longer carries its spin ahead of the quasi-static twist.
    (With the pressure clipped but not re-centred under the CoM, the slipping push measured
    1.25x at 4 cm/s and was read as inertia.)"""
    from test_episode import BOX_CM

    com_cm = (1.5, 0.8)
    outline = np.array(BOX_CM) / 100.0
    P = np.array([outline[:, 0].min(), com_cm[1] / 100 - 0.015])
    spec, outline, steps = _planar_slow_push(
        com_cm, 0.1, P, np.array([1.0, 0.0]), mu_pusher=mu_pusher, speed_cm_s=speed_cm_s
    )
    assert len(steps) >= 10
    samples = footprint_samples(outline)
    G = np.array([com_cm]) / 100.0
    w = pressure_weights(samples, G)
    steady = steps[1:]
    predicted = sum(predict_step(G, samples, w, 1.0, 0.0, mu_pusher, s)[1][0] for s in steady)
    observed = sum(s.d_yaw for s in steady)
    assert np.sign(predicted) == np.sign(observed) == 1.0
    assert predicted == pytest.approx(observed, rel=rel)


@pytest.mark.parametrize(
    ("mu_x", "mu_y", "mu_pusher", "along_y", "lever_m"),
    [
        (0.5, 0.5, 0.1, False, 0.015),
        (0.5, 0.5, 0.0, False, 0.015),
        (1.0, 1.0, 0.5, False, -0.012),
        (0.1, 0.1, 1.0, False, 0.015),
        (1.0, 1.0, 0.1, False, 0.015),
        (0.1, 1.0, 0.5, False, 0.015),
        (1.0, 0.1, 0.5, False, 0.015),
        (0.1, 1.0, 0.1, True, 0.01),
        pytest.param(
            1.0,
            0.1,
            1.0,
            True,
            0.01,
            marks=pytest.mark.xfail(
                strict=True,
                reason="measured 1.155x the reference's turn: pushed along the slippery axis "
                "with mu 1, the contact slides on the cone's edge at ~2% of the pusher's speed "
                "(referee 0.83, reference 1.01 mm/s) and the turn follows that slip; why the "
                "slips differ is not located",
            ),
        ),
    ],
)
def test_the_referee_follows_the_exact_quasi_static_solution(
    mu_x, mu_y, mu_pusher, along_y, lever_m
) -> None:
    """Planar at 0.4 cm/s (inertia negligible), the push's intervals after the first: the
    referee's turn against the exact quasi-static solution (`quasi_static_reference`: the
    footprint's friction summed sample by sample, the pressure moved by the pusher's force at
    its height) from the same poses, within 10% (measured 0.92x-1.01x). The `fit` model's
    ellipsoid, without the move, was 0.74x-1.87x on the same pushes."""
    from quasi_static_reference import turn_rate
    from test_episode import BOX_CM

    from comexp.sim.contact import pusher_contact_height_m
    from comexp.sim.scene import PusherSpec

    com_cm = (1.5, 0.8)
    outline = np.array(BOX_CM) / 100.0
    if along_y:
        P, N = np.array([com_cm[0] / 100 + lever_m, outline[:, 1].min()]), np.array([0.0, 1.0])
    else:
        P, N = np.array([outline[:, 0].min(), com_cm[1] / 100 - lever_m]), np.array([1.0, 0.0])
    spec, outline, steps = _planar_slow_push(
        com_cm, mu_x, P, N, mu_pusher=mu_pusher, speed_cm_s=0.4, mu_floor_y=mu_y
    )
    assert len(steps) >= 8
    samples = footprint_samples(outline, 256)
    G = np.array(com_cm) / 100.0
    ratio, axis = (mu_y / mu_x, 0.0) if mu_x <= mu_y else (mu_x / mu_y, math.pi / 2)
    lift = pusher_contact_height_m(PusherSpec(), spec.height_cm / 100)
    exact = sum(
        s.drive_s
        * turn_rate(
            samples,
            G,
            ratio,
            axis - s.yaw_rad,
            mu_pusher,
            s.contact,
            s.normal,
            s.push_velocity,
            lift,
            min(mu_x, mu_y),
        )  # fmt: skip
        for s in steps[1:]
    )
    observed = sum(s.d_yaw for s in steps[1:])
    assert np.sign(exact) == np.sign(observed)
    assert exact == pytest.approx(observed, rel=0.10)


@pytest.mark.parametrize(
    ("com", "beyond_samples"),
    [((0.0, 0.0), False), ((0.015, 0.008), False), ((0.04, 0.02), False), ((-0.048, 0.0), True)],
)
def test_the_models_pressure_is_centred_under_each_candidate_com(com, beyond_samples) -> None:
    """The floor's pressure under a candidate CoM: non-negative, summing to 1, its centre at
    the CoM, also where the linear pressure must be clipped (a CoM far off the middle). A
    CoM inside the outline but beyond the samples' hull gets the centre the samples can carry
    on the way toward their middle (the referee's rule). Clipping without solving again put
    the centre of a CoM at (4, 2) cm at (1.9, 0.9) cm."""
    samples = footprint_samples(BOX)
    com = np.array(com)
    lo, hi = samples.min(0), samples.max(0)
    assert np.all((lo < com) & (com < hi)) != beyond_samples  # the case is what it says
    w = pressure_weights(samples, com[None])[0]
    assert w.min() >= 0.0 and w.sum() == pytest.approx(1.0)
    centre = w @ samples
    if not beyond_samples:
        assert centre == pytest.approx(com, abs=1e-9)
        if abs(com[0]) > 0.03:
            assert (w == 0).any()  # the tensionless branch was taken
    else:  # drawn toward the samples' middle, just inside their hull
        middle = samples.mean(0)
        assert np.all((lo <= centre) & (centre <= hi))
        (ax, ay), (bx, by) = centre - middle, com - middle
        assert ax * by - ay * bx == pytest.approx(0.0, abs=1e-12)  # on the way to the middle
        assert 0 < (centre - middle) @ (com - middle) < (com - middle) @ (com - middle)
        # as far out as the samples carry, to the rule's 5% steps
        assert centre[0] <= lo[0] + 0.05 * np.linalg.norm(com - middle)


def test_a_pusher_that_touches_early_is_measured_and_timed() -> None:
    """The object moves with the pusher 1 mm ahead of where its disc should touch (pybullet's
    contact keeps that stand-off): the gaps' median is that offset, and with it the first
    interval starts when the object did and every interval's motion is the pusher's travel."""
    v, dt, t_contact, offset = 0.04, 0.1, 0.05, 0.001
    t_touch = t_contact - offset / v
    P, N = np.array([-0.05, 0.0]), np.array([1.0, 0.0])
    t_s = tuple(dt * (k + 1) for k in range(8))
    poses = tuple(Pose2D(max(0.0, v * (t - t_touch)), 0.0, 0.0) for t in t_s)
    drive = PusherDrive(Pose2D(0.0, 0.0, 0.0), t_s, poses, P, N, t_contact, 0.7, v, BOX, RADIUS_M)
    gaps = drive.gaps_m(0.005)
    assert len(gaps) == 7
    assert np.median(gaps) == pytest.approx(offset, abs=1e-9)
    nominal = drive.steps(0.002)
    timed = drive.steps(0.002, offset_m=float(np.median(gaps)))
    assert nominal[0].drive_s == pytest.approx(dt - t_contact)  # the object moved before
    assert timed[0].drive_s == pytest.approx(dt - t_touch)
    for step in timed:
        assert step.d_origin[0] == pytest.approx(v * step.drive_s, abs=1e-12)


def test_a_pusher_that_never_moves_drives_no_interval() -> None:
    """A push logged with speed 0 (a robot's log can say so): no interval, no division by it."""
    poses = (Pose2D(0.0, 0.0, 0.0),) * 3
    drive = PusherDrive(
        Pose2D(0.0, 0.0, 0.0),
        (0.1, 0.2, 0.3),
        poses,
        np.array([-0.05, 0.0]),
        np.array([1.0, 0.0]),
        0.05,
        0.3,
        0.0,
        BOX,
        RADIUS_M,
    )
    assert drive.steps(0.002, offset_m=0.001) == []


def _model_path(G, P, N, ratio, axis, mu, pose0, speed=0.04, travel=0.03, dt_frame=0.1):
    """A push's path integrated with the model itself (1 ms steps), frames every dt_frame."""
    samples = footprint_samples(BOX)
    Gm = np.atleast_2d(G)
    w = pressure_weights(samples, Gm)
    pose = pose0
    t, t_contact = 0.0, 0.0
    t_end = travel / speed
    ts, poses = [], []
    n_world = pose0.to_world(N) - pose0.to_world(np.zeros(2))
    start = pose0.to_world(P - RADIUS_M * N)
    h = 0.001
    next_frame = dt_frame
    while t < t_end - 1e-12:
        q = pose.to_object(start + n_world * speed * (t + h / 2))
        a, b = BOX, np.roll(BOX, -1, 0)
        ab = b - a
        s = np.clip(((q - a) * ab).sum(1) / (ab * ab).sum(1), 0, 1)
        pts = a + s[:, None] * ab
        i = int(np.argmin(np.hypot(*(pts - q).T)))
        normal = (pts[i] - q) / np.linalg.norm(pts[i] - q)
        c, sn = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
        v = np.array([c * n_world[0] + sn * n_world[1], -sn * n_world[0] + c * n_world[1]]) * speed
        step = ContactStep(pts[i], normal, v, pose.yaw_rad, h, np.zeros(2), 0.0)
        d, turn = predict_step(Gm, samples, w, ratio, axis, mu, step)
        pose = pose.compose(Pose2D(d[0, 0], d[0, 1], turn[0]))
        t += h
        if t >= next_frame - 1e-9:
            ts.append(t)
            poses.append(pose)
            next_frame += dt_frame
    return PushPath(pose0, tuple(ts), tuple(poses), pose, t_contact, speed, None, {}, t_end)


@pytest.mark.parametrize(("ratio", "axis"), [(1.0, 0.0), (10.0, math.pi / 2)])
def test_the_estimator_recovers_the_com_from_the_models_own_paths(ratio, axis) -> None:
    """Slow pushes simulated with the model (isotropic, and anisotropic with the slippery axis
    along y): `fit` lands within its model grid's spacing (two pixels) of the CoM, closer than
    `motion` (measured: 3.2 and 2.4 mm; motion 13.1 mm on the first), and so it does when told
    the floor and the pusher's friction (`nuisance_source=oracle`)."""
    G = np.array([0.018, -0.009])
    region = region_from_outline(BOX, PIXEL_M)
    contacts, normals = outline_contacts(BOX)
    mu_xy = (1.0, 1.0) if ratio == 1.0 else (1.0, 0.1) if axis else (0.1, 1.0)
    told = KnownNuisances(mu_xy, 0.5, 2e-3)
    errors = {}
    for method in ("motion", "fit", "fit told"):
        est = make_estimator(
            region,
            contacts,
            normals,
            PIXEL_M,
            EstimatorSettings(method=method.split()[0]),
            outline_m=BOX,
            pusher_radius_m=RADIUS_M,
            nuisances=told if method.endswith("told") else None,
        )
        pose = Pose2D(0.0, 0.0, 0.3)
        for P, N in [
            ((-0.05, 0.01), (1, 0)),
            ((0.02, -0.03), (0, 1)),
            ((0.05, 0.0), (-1, 0)),
            ((-0.01, 0.03), (0, -1)),
        ]:
            P, N = np.array(P, float), np.array(N, float)
            path = _model_path(G, P, N, ratio, axis, 0.5, pose)
            est.observe_path(path)
            turn = math.degrees(path.pose_after.yaw_rad - pose.yaw_rad)
            est.observe(P, N, turn)
            pose = Pose2D(0.0, 0.0, path.pose_after.yaw_rad)
        errors[method] = float(np.hypot(*(est.estimate_m - G)))
    assert errors["fit"] < 2 * PIXEL_M
    assert errors["fit"] < errors["motion"]
    assert errors["fit told"] < 2 * PIXEL_M


def test_told_the_nuisances_fit_keeps_one_floor_and_pusher_friction() -> None:
    """`KnownNuisances`: the model's hypotheses are the told floor (here mu 0.1 along world y:
    the low-friction axis at pi/2, ratio 10) and pusher friction; the turn gains stay (they
    stand for the model's error)."""
    region = region_from_outline(BOX, PIXEL_M)
    contacts, normals = outline_contacts(BOX)
    told = KnownNuisances((1.0, 0.1), 0.25, 2e-3)
    est = FitEstimator(
        region, contacts, normals, PIXEL_M, outline_m=BOX, pusher_radius_m=RADIUS_M, nuisances=told
    )
    assert est.ratios.tolist() == [10.0] and est.axes.tolist() == [math.pi / 2]
    assert est.mu_p.tolist() == [0.25] and est.log_prior.tolist() == [0.0]
    assert est.motion.known_floor == (math.pi / 2, 10.0)
    assert len(est.gains) == len(FitSettings().turn_gains)


def test_fit_is_a_built_in_method_with_its_version_in_the_key() -> None:
    from test_episode import spec_for

    from comexp.experiment.grid import PINNED_VERSIONS
    from comexp.results.identity import canonical_json

    contacts, normals = outline_contacts(BOX)
    est = make_estimator(
        region_from_outline(BOX, PIXEL_M),
        contacts,
        normals,
        PIXEL_M,
        EstimatorSettings(method="fit"),
        outline_m=BOX,
        pusher_radius_m=RADIUS_M,
    )
    assert isinstance(est, FitEstimator)
    assert PINNED_VERSIONS["fit"] == FIT_VERSION
    spec = spec_for(method="fit", motion_version=FIT_VERSION)
    assert f'"motion_version":"{FIT_VERSION}"' in canonical_json(spec.estimator)


def test_in_an_episode_slow_pushes_use_the_model_and_fast_ones_are_motions() -> None:
    """Planar, 2 pushes: at 4 cm/s the decisions say the quasi-static intervals were used; at
    40 cm/s fit's estimate is motion's exactly."""
    from test_episode import spec_for

    from comexp.episode.loop import run_episode
    from comexp.experiment.config import make_simulator

    sim = make_simulator("planar")
    slow = spec_for(backend="planar", speed=4.0, fps=30.0, method="fit", n_push=2)
    res = run_episode(slow, sim)
    assert res.status == "ok", (res.failure, res.detail)
    assert all(p.decision.endswith("-qs") for p in res.pushes)
    fast = {
        m: run_episode(spec_for(backend="planar", speed=40.0, fps=30.0, method=m, n_push=2), sim)
        for m in ("motion", "fit")
    }
    assert fast["fit"].status == "ok"
    assert fast["fit"].est_com_cm == fast["motion"].est_com_cm


@pytest.mark.parametrize(("ratio", "axis"), [(1.0, 0.0), (10.0, math.pi / 2)])
def test_after_a_slow_push_on_an_anisotropic_floor_it_pushes_for_information(ratio, axis) -> None:
    """After one slow push simulated with the model: on the anisotropic floor the next push is
    the valid one whose predicted outcome spreads most across the likeliest CoMs; on the
    isotropic floor it is Algorithm 1's (motion's choice on the same posterior)."""
    from comexp.method.motion_estimator import MotionEstimator

    G = np.array([0.018, -0.009])
    contacts, normals = outline_contacts(BOX)
    est = make_estimator(
        region_from_outline(BOX, PIXEL_M), contacts, normals, PIXEL_M,
        EstimatorSettings(method="fit"), outline_m=BOX, pusher_radius_m=RADIUS_M,
    )  # fmt: skip
    P, N = np.array([-0.05, 0.01]), np.array([1.0, 0.0])
    path = _model_path(G, P, N, ratio, axis, 0.5, Pose2D(0.0, 0.0, 0.3))
    est.observe_path(path)
    est.observe(P, N, math.degrees(path.pose_after.yaw_rad - 0.3))
    chosen = est.next_push()
    assert chosen is not None
    algorithm_1 = MotionEstimator.next_push(est)
    from comexp.method.estimator import line_cuts_region

    valid = np.flatnonzero(est.allowed)
    valid = valid[line_cuts_region(est.region(), est.contacts[valid], est.normals[valid])]
    score = est._information(valid)
    if ratio == 1.0:
        assert score is None
        assert np.array_equal(chosen[0], algorithm_1[0])
    else:
        best = valid[int(np.argmax(score))]
        assert np.array_equal(chosen[0], est.contacts[best])
        assert score.max() > 2 * np.median(score)  # the pushes differ in what they tell


def test_a_robot_s_own_pushes_in_the_world_frame() -> None:
    """`estimate_com_fit` on `MotionPush`es (world frame, the object placed anywhere): the
    estimate the episode-side estimator gives on the same pushes in the object frame."""
    from comexp.method.fit_estimator import estimate_com_fit
    from comexp.method.motion_estimator import MotionPush

    G = np.array([0.018, -0.009])
    pose = Pose2D(0.12, -0.07, 0.3)
    pushes = []
    for P, N in [((-0.05, 0.01), (1, 0)), ((0.02, -0.03), (0, 1)), ((0.05, 0.0), (-1, 0))]:
        P, N = np.array(P, float), np.array(N, float)
        path = _model_path(G, P, N, 10.0, math.pi / 2, 0.5, pose)
        c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
        pushes.append(
            MotionPush(
                tuple(pose.to_world(P)), (c * N[0] - s * N[1], s * N[0] + c * N[1]), pose,
                path.t_s, path.poses, path.pose_after, path.t_contact_s,
                speed_m_s=path.speed_m_s, t_end_s=path.t_end_s,
            )
        )  # fmt: skip
        pose = path.pose_after
    est = estimate_com_fit(BOX, pushes, PIXEL_M, RADIUS_M)
    assert np.hypot(*(est.com_object_m - G)) < 2 * PIXEL_M
    assert est.com_world_m == pytest.approx(pushes[0].pose_before.to_world(est.com_object_m))


# --- the rollout reading ----------------------------------------------------------------------


ORIGIN = Pose2D(0.0, 0.0, 0.0)


def _rollout_push(P, N, pose0=ORIGIN, travel=0.03, speed=0.04, frames=()):
    """A slow push of BOX whose disc touches P (object frame) at t = 0, driving along the
    inward normal N for `travel`."""
    N = np.asarray(N, float) / np.linalg.norm(N)
    world_n = pose0.to_world(N) - pose0.to_world(np.zeros(2))
    return RolloutPush(
        np.array([pose0.x_m, pose0.y_m, pose0.yaw_rad]),
        pose0.to_world(np.asarray(P, float) - RADIUS_M * N),
        world_n,
        speed,
        travel / speed,
        RADIUS_M,
        np.asarray(frames, float),
        np.zeros((len(frames), 3)),
        np.zeros(3),
    )


def _roll(G, push, ratio=1.0, axis=0.0, mu=0.5, step_m=0.001):
    samples = footprint_samples(BOX)
    return roll_out(push, BOX, samples, np.asarray(G, float), ratio, axis, mu, step_m)


def test_a_rollout_through_the_com_does_not_turn_and_moves_with_the_pusher() -> None:
    """Pushed through the CoM the object translates along the push by the pusher's travel
    (less at most one step of the integration) and does not turn."""
    push = _rollout_push((-0.05, 0.0), (1.0, 0.0), pose0=Pose2D(0.1, 0.2, 0.4))
    x, y, yaw = _roll((0.0, 0.0), push)[-1]
    moved = np.array([x - 0.1, y - 0.2])
    along = np.array([math.cos(0.4), math.sin(0.4)])
    assert yaw == pytest.approx(0.4, abs=1e-9)
    assert moved @ along == pytest.approx(0.03, abs=0.001)
    assert abs(moved[0] * along[1] - moved[1] * along[0]) < 1e-9


@pytest.mark.parametrize("offset", [0.01, -0.01])
def test_a_rollout_turns_with_the_torque_counter_clockwise_positive(offset) -> None:
    """Pushing +x at y = 0 with the CoM above (lever (P - G) x N > 0) turns it CCW."""
    yaw = _roll((0.0, offset), _rollout_push((-0.05, 0.0), (1.0, 0.0)))[-1, 2]
    assert np.sign(yaw) == np.sign(offset) and abs(yaw) > math.radians(1.0)


@pytest.mark.parametrize(("ratio", "axis", "mu"), [(1.0, 0.0, 0.5), (10.0, math.pi / 2, 0.25)])
def test_the_rollout_integrates_the_interval_model(ratio, axis, mu) -> None:
    """The compiled rollout (moment tabulated over the floor's axis, 1 mm steps, the overlap
    taken back each step) against the interval model's own finer integration (`_model_path`:
    exact moment, 1 ms steps = 0.04 mm): the same poses along the push and at its end."""
    G = np.array([0.018, -0.009])
    P, N = np.array([-0.05, 0.01]), np.array([1.0, 0.0])
    pose0 = Pose2D(0.0, 0.0, 0.3)
    path = _model_path(G, P, N, ratio, axis, mu, pose0)
    push = _rollout_push(P, N, pose0=pose0, frames=path.t_s)
    rolled = _roll(G, push, ratio, axis, mu)
    seen = np.array([(p.x_m, p.y_m, p.yaw_rad) for p in (*path.poses, path.pose_after)])
    turn = seen[-1, 2] - 0.3
    assert abs(turn) > math.radians(5)  # a push that turns
    # measured: 0.02 mm and 0.4% of the turn (isotropic), 0.42 mm and 2.0% (anisotropic);
    # a fifth of the step, a fifth of that
    assert np.hypot(*(rolled[:, :2] - seen[:, :2]).T).max() < 6e-4
    assert np.abs(rolled[:, 2] - seen[:, 2]).max() < 0.03 * abs(turn)


def _estimate_on_model_paths(ratio, axis, fit):
    G = np.array([0.018, -0.009])
    region = region_from_outline(BOX, PIXEL_M)
    contacts, normals = outline_contacts(BOX)
    est = FitEstimator(
        region, contacts, normals, PIXEL_M, outline_m=BOX, pusher_radius_m=RADIUS_M, fit=fit
    )
    pose = Pose2D(0.0, 0.0, 0.3)
    for P, N in [((-0.05, 0.01), (1, 0)), ((0.02, -0.03), (0, 1)), ((0.05, 0.0), (-1, 0))]:
        P, N = np.array(P, float), np.array(N, float)
        path = _model_path(G, P, N, ratio, axis, 0.5, pose)
        est.observe_path(path)
        est.observe(P, N, math.degrees(path.pose_after.yaw_rad - pose.yaw_rad))
        pose = Pose2D(0.0, 0.0, path.pose_after.yaw_rad)
    return est, float(np.hypot(*(est.estimate_m - G)))


@pytest.mark.parametrize(("ratio", "axis"), [(1.0, 0.0), (10.0, math.pi / 2)])
def test_the_rollout_refines_the_estimate_on_the_models_own_paths(ratio, axis) -> None:
    """Three slow pushes simulated with the model. On the anisotropic floor the rollout reading
    moves the estimate (only the estimate: the posterior the pushes were chosen by is the
    intervals'), lands within one grid spacing of the CoM, and its cost stays that of the
    screening plus the kept hypotheses at the grid points holding the posterior; on the
    isotropic floor the intervals' estimate stands and nothing is rolled out."""
    fs = FitSettings()
    with_rollout, error = _estimate_on_model_paths(ratio, axis, fs)
    without, _ = _estimate_on_model_paths(ratio, axis, replace(fs, rollout=False))
    assert with_rollout.weights == pytest.approx(without.weights)
    assert without.rollouts_run == 0
    assert error < 2 * PIXEL_M
    if ratio == 1.0:
        assert with_rollout.rollouts_run == 0
        assert with_rollout.estimate_m == pytest.approx(without.estimate_m)
        return
    assert with_rollout.rollouts_run > 0
    assert not np.allclose(with_rollout.estimate_m, without.estimate_m)
    nh = len(with_rollout.ratios) * len(with_rollout.mu_p)
    screening = 3 * fs.rollout_screen_points * nh
    assert with_rollout.rollouts_run <= screening + 3 * fs.rollout_hypotheses * len(
        with_rollout.coarse
    )


def test_the_moment_table_is_built_only_where_the_rollout_runs() -> None:
    """`_tabulate` fills the rows the rollouts used, each what the whole table would hold."""
    est, _ = _estimate_on_model_paths(10.0, math.pi / 2, FitSettings())
    rows = np.flatnonzero(est._tabulated)
    assert 0 < len(rows) < len(est.coarse) / 2  # measured: 13 of 228
    whole = moment_table(
        est.samples, est.pressure, est.coarse, np.unique(est.ratios), MOMENT_ANGLES
    )
    assert est._table[rows] == pytest.approx(whole[rows], rel=0, abs=0)


def test_the_rollouts_contact_search_is_the_full_search() -> None:
    """The rollout searches the outline near its last full search while the triangle
    inequality proves nothing else is closer (`quasi_static._closest_near`): on a traced U
    (1 mm edges, a notch whose far arm a local search can mistake for the closest), along
    300 random straight pusher paths in 1 mm steps, inside the outline and out, it returns
    the full search's closest point, distance and inside-ness every time."""
    u = [(0, 0), (0.12, 0), (0.12, 0.09), (0.08, 0.09), (0.08, 0.04), (0.04, 0.04), (0.04, 0.09)]
    corners = [*u, (0, 0.09)]
    traced = []
    for a, b in zip(corners, corners[1:] + corners[:1], strict=True):
        n = round(math.dist(a, b) / 0.001)
        traced += [np.add(a, np.subtract(b, a) * k / n) for k in range(n)]
    outline = np.array(traced)
    rng = np.random.default_rng(0)
    for _ in range(300):
        q0 = rng.uniform([-0.03, -0.03], [0.15, 0.12])
        d = rng.normal(size=2)
        d /= np.linalg.norm(d)
        anchor = np.array([0.0, 0.0, -1.0, 0.0, 0.0])
        for k in range(80):
            q = q0 + d * 0.001 * k
            x, y, dist, inside = _closest_near(q[0], q[1], outline, anchor, np.empty(len(outline)))
            point, full_dist, full_inside = _closest_on_outline(q, outline)
            assert (x, y) == pytest.approx(tuple(point), abs=1e-12)
            assert dist == pytest.approx(full_dist, abs=1e-12) and inside == full_inside


def _closest_reference(q: np.ndarray, outline: np.ndarray) -> tuple[np.ndarray, float, bool]:
    """The outline's closest point, its distance and inside-ness, vectorised over the edges
    (the NumPy search `_closest_on_outline` was until it was compiled)."""
    a, b = outline, np.roll(outline, -1, axis=0)
    ab = b - a
    t = np.clip(((q - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-30), 0.0, 1.0)
    pts = a + t[:, None] * ab
    d = np.hypot(*(pts - q).T)
    i = int(np.argmin(d))
    cross = (a[:, 1] > q[1]) != (b[:, 1] > q[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = a[:, 0] + (q[1] - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
    return pts[i], float(d[i]), bool(np.count_nonzero(cross & (q[0] < x_at)) % 2)


def test_the_compiled_contact_search_is_the_vectorised_one() -> None:
    """`_closest_on_outline` (compiled: the interval reading's contact, the footprint's
    samples, the rollout's full search) gives exactly what the vectorised search over every
    edge gives: on a concave and a convex outline, 2,000 points inside, out and on vertices'
    rows (the even-odd rule's ties), and the footprint's samples are those inside."""
    outlines = [
        np.array(
            [
                (0, 0),
                (0.12, 0),
                (0.12, 0.09),
                (0.08, 0.09),
                (0.08, 0.04),
                (0.04, 0.04),
                (0.04, 0.09),
                (0, 0.09),
            ],
            dtype=float,
        ),
        np.array(
            [(0.05 * math.cos(a), 0.03 * math.sin(a)) for a in np.linspace(0, math.tau, 41)[:-1]]
        ),
    ]
    rng = np.random.default_rng(3)
    for outline in outlines:
        lo, hi = outline.min(0) - 0.02, outline.max(0) + 0.02
        qs = rng.uniform(lo, hi, size=(2000, 2))
        qs[:200, 1] = outline[rng.integers(0, len(outline), 200), 1]  # on a vertex's row
        for q in qs:
            point, dist, inside = _closest_on_outline(q, outline)
            ref_point, ref_dist, ref_inside = _closest_reference(q, outline)
            assert tuple(point) == tuple(ref_point) and dist == ref_dist and inside == ref_inside
        samples = footprint_samples(outline)
        assert len(samples) >= 32 and all(_closest_reference(s, outline)[2] for s in samples)
