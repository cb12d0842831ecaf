"""The camera watches the push: the protocol's frame hook, the pusher mask, the frame-to-frame
tracker that unwraps large turns of symmetric outlines, `camera.fps`, `pushes.n_frames`."""

from __future__ import annotations

import math
import sqlite3
import sys
from dataclasses import replace

import numpy as np
import pytest
from hydra import compose, initialize_config_module

from comexp.episode.task import EpisodeSpec, build_scene
from comexp.experiment.config import ConfigError, make_simulator, prepare_job
from comexp.method.frames import Pose2D
from comexp.method.observation import (
    mask_pusher,
    object_mask,
    observe,
    observe_boundary,
    perceive_first,
)
from comexp.method.tracking import PoseTracker
from comexp.results.schema import SCHEMA_VERSION
from comexp.results.store import ResultsDB
from comexp.sim.contact import contact_push
from comexp.sim.protocol import Frame, at_rest, push

BOX_CM = ((-4.0, -2.5), (4.0, -2.5), (4.0, 2.5), (-4.0, 2.5))


def box_spec(backend: str = "planar", mu_pusher: float = 0.1) -> EpisodeSpec:
    return EpisodeSpec(
        backend=backend,
        floor="iso",
        mu_floor_x=0.1,
        mu_floor_y=0.1,
        mu_pusher=mu_pusher,
        speed_cm_s=40.0,
        izz_scale=1.0,
        object="box",
        outline_cm=BOX_CM,
        height_cm=3.0,
        com_index=0,
        com_cm=(0.0, 0.0),
    )


def _big_turn(sim, on_frame=None, interval_s: float = 0.0):
    """The 8 x 5 cm box on mu 0.1, pushed at 40 cm/s 2 cm off its CoM with mu_p 0.1: it turns
    by -121 deg in the planar model (measured), more than the rectangle's half-symmetry."""
    sim.build(replace(build_scene(box_spec()), initial_pose=Pose2D(0.0, 0.0, 0.0)))
    cmd = contact_push((-0.04, 0.02), (1.0, 0.0), 0.03, 0.4, 0.005)
    return push(sim, cmd, on_frame=on_frame, frame_interval_s=interval_s)


def test_frames_only_while_the_object_moves_and_the_physics_is_unchanged():
    sim = make_simulator("planar")
    plain = _big_turn(sim)
    seen: list[tuple[Frame, bool]] = []
    watched = _big_turn(sim, lambda f: seen.append((f, at_rest(sim.object_state(), sim.settings))))
    assert watched.n_frames == 0  # no interval: no frames
    watched = _big_turn(
        sim, lambda f: seen.append((f, at_rest(sim.object_state(), sim.settings))), 1 / 30
    )
    assert watched.n_frames == len(seen) > 5
    assert not any(rest for _, rest in seen)
    # frames hang on the protocol's checks: the push is step for step the same
    assert (watched.pose_after, watched.steps) == (plain.pose_after, plain.steps)
    times = [f.t_s for f, _ in seen]
    chunk_s = sim.check_every_steps * sim.settings.timestep_s
    assert all(
        1 / 30 - chunk_s - 1e-9 <= b - a <= 1 / 30 + chunk_s + 1e-9
        for a, b in zip(times, times[1:], strict=False)
    )
    # the object moves for less than the push: 0.65 s of protocol, frames while it moves
    assert len(seen) < watched.sim_time_s * 30
    # a push that misses the object never moves it: no frame
    sim.build(replace(build_scene(box_spec()), initial_pose=Pose2D(0.0, 0.0, 0.0)))
    missed = push(sim, contact_push((-0.04, 0.06), (1.0, 0.0), 0.03, 0.4, 0.005), seen.append, 0.01)
    assert missed.n_frames == 0 and not missed.contact_made


def test_true_rotation_is_unwrapped():
    sim = make_simulator("planar")
    out = _big_turn(sim)
    assert out.true_rotation_deg == pytest.approx(out.rotation_deg)  # -121 deg: no wrap
    assert out.true_rotation_deg < -90.0


def test_tracking_unwraps_a_big_turn_of_a_rectangle_that_two_images_alias():
    """Before and after only, the -121 deg turn of the rectangle is indistinguishable from
    +59 deg (its 180 deg symmetry): the wrong sign. Through 10 fps frames it is found."""
    sim = make_simulator("planar")
    sim.build(replace(build_scene(box_spec()), initial_pose=Pose2D(0.0, 0.0, 0.0)))
    perc, obs0 = perceive_first(sim.render_depth())
    two = PoseTracker(perc, obs0)
    tracked = PoseTracker(perc, obs0)
    tracked.begin_push()

    def on_frame(f: Frame) -> None:
        img = mask_pusher(f.image, f.pusher_xy_m, f.pusher_radius_m)
        tracked.track(observe_boundary(img, (tracked.last.x_m, tracked.last.y_m)), f.t_s)

    out = _big_turn(sim, on_frame, 0.1)
    after = observe(sim.render_depth())
    aliased = math.degrees(two.fit(after).pose.yaw_rad)
    unwrapped = math.degrees(tracked.fit(after).pose.yaw_rad)
    assert out.n_frames >= 3
    assert aliased == pytest.approx(out.true_rotation_deg + 180.0, abs=2.0)
    assert unwrapped == pytest.approx(out.true_rotation_deg, abs=2.0)


def test_a_still_object_is_reported_at_the_frames_it_is_not_rendered():
    """Every frame time of the push is either a rendered frame (object moving) or an
    `on_still` call (at rest): the tracker learns where the object stopped."""
    sim = make_simulator("planar")
    frames: list[float] = []
    still: list[float] = []
    out = _big_turn(sim, lambda f: frames.append(f.t_s), 1 / 30)
    plain_frames = list(frames)
    frames.clear()
    sim.build(replace(build_scene(box_spec()), initial_pose=Pose2D(0.0, 0.0, 0.0)))
    cmd = contact_push((-0.04, 0.02), (1.0, 0.0), 0.03, 0.4, 0.005)
    again = push(sim, cmd, lambda f: frames.append(f.t_s), 1 / 30, on_still=still.append)
    assert frames == plain_frames and again.steps == out.steps  # nothing else changes
    assert still and not set(still) & set(frames)
    ticks = sorted(frames + still)
    chunk_s = sim.check_every_steps * sim.settings.timestep_s
    assert ticks[0] <= 1 / 30 + chunk_s + 1e-9
    assert all(
        1 / 30 - chunk_s - 1e-9 <= b - a <= 1 / 30 + chunk_s + 1e-9
        for a, b in zip(ticks, ticks[1:], strict=False)
    )
    assert ticks[-1] >= out.sim_time_s - 1 / 30 - chunk_s - 1e-9


def test_after_a_still_frame_the_tracker_predicts_from_rest():
    sim = make_simulator("planar")
    sim.build(replace(build_scene(box_spec()), initial_pose=Pose2D(0.0, 0.0, 0.0)))
    perc, obs0 = perceive_first(sim.render_depth())
    tracker = PoseTracker(perc, obs0)
    tracker.begin_push()
    # two frames turning at 1 rad/s, as a push would give them
    tracker._history += [(0.1, 0.1)]
    tracker.last = replace(tracker.last, yaw_rad=0.1)
    assert tracker.predicted_yaw(0.3) == pytest.approx(0.3)
    tracker.hold(0.2)  # a frame at 0.2 s showed it at rest
    assert tracker.predicted_yaw(0.5) == pytest.approx(0.1)


def _tracked_big_turn(
    step_deg: float, gap_s: float = 0.1, speed_m_s: float = 0.4, drive_mm: float = 0.0
):
    """The -121 deg turn (at 40 cm/s), tracked at 30 fps with the frame rule
    (`PoseTracker.wants_frame`, a frame while driving every `drive_mm` of the pusher's travel):
    the push's outcome, the final fit's yaw (deg), and each offered frame's (t_s, driving,
    rendered)."""
    sim = make_simulator("planar")
    sim.build(replace(build_scene(box_spec()), initial_pose=Pose2D(0.0, 0.0, 0.0)))
    perc, obs0 = perceive_first(sim.render_depth())
    tracker = PoseTracker(perc, obs0)
    tracker.begin_push()
    offered: list[list] = []

    def wanted(t_s: float, driving: bool) -> bool:
        take = tracker.wants_frame(t_s, driving, step_deg, gap_s, drive_mm / 1000 / speed_m_s)
        offered.append([t_s, driving, False])
        return take

    def on_frame(f: Frame) -> None:
        assert offered[-1][0] == f.t_s  # rendered right after it was asked for
        offered[-1][2] = True
        img = mask_pusher(f.image, f.pusher_xy_m, f.pusher_radius_m)
        tracker.track(observe_boundary(img, (tracker.last.x_m, tracker.last.y_m)), f.t_s)

    cmd = contact_push((-0.04, 0.02), (1.0, 0.0), 0.03, speed_m_s, 0.005)
    out = push(sim, cmd, on_frame, 1 / 30, on_still=tracker.hold, frame_wanted=wanted)
    return out, math.degrees(tracker.fit(observe(sim.render_depth())).pose.yaw_rad), offered, cmd


def test_once_the_pusher_stops_frames_are_tracked_where_the_turn_needs_them():
    every, yaw_every, offered_every, cmd = _tracked_big_turn(0.0)
    fewer, yaw_fewer, offered, _ = _tracked_big_turn(10.0)
    assert all(r for _, _, r in offered_every) and every.n_frames == len(offered_every)
    # watching never changes the physics
    assert (fewer.pose_after, fewer.steps) == (every.pose_after, every.steps)
    # "driving" = the pusher still on its path (travel / speed), and then every frame is taken
    path_s = cmd.travel_m / cmd.speed_m_s
    sim = make_simulator("planar")
    chunk_s = sim.check_every_steps * sim.settings.timestep_s
    assert all((t <= path_s + chunk_s) == d for t, d, _ in offered if abs(t - path_s) > chunk_s)
    assert all(r for _, d, r in offered if d)
    # after it, not every frame, never more than 0.1 s apart, and the turn is still unwrapped
    taken = [t for t, _, r in offered if r]
    assert every.n_frames > fewer.n_frames == len(taken) and not all(r for *_, r in offered)
    assert all(b - a <= 0.1 + 1e-9 for a, b in zip(taken, taken[1:], strict=False))
    assert yaw_fewer == pytest.approx(every.true_rotation_deg, abs=2.0)
    assert yaw_every == pytest.approx(every.true_rotation_deg, abs=2.0)


def test_while_driving_a_frame_comes_with_the_pushers_travel():
    """`track_drive_mm` (4 mm): at 40 cm/s the pusher travels that in 10 ms, less than a
    frame's 33 ms, so every driving frame is tracked (the same frames as without it); at
    4 cm/s a driving frame is tracked every 0.1 s, fewer frames, the same turn measured."""
    every, _, offered_every, _ = _tracked_big_turn(10.0)
    rule, _, offered_rule, _ = _tracked_big_turn(10.0, drive_mm=4.0)
    assert offered_rule == offered_every and rule == every
    slow_every, yaw_every, offered_every, _ = _tracked_big_turn(10.0, speed_m_s=0.04)
    slow, yaw, offered, _ = _tracked_big_turn(10.0, speed_m_s=0.04, drive_mm=4.0)
    assert (slow.pose_after, slow.steps) == (slow_every.pose_after, slow_every.steps)
    assert abs(slow.true_rotation_deg) > 15.0  # it turns, all the while the pusher drives
    driving = [t for t, d, r in offered if d and r]
    assert 0 < len(driving) < 0.5 * sum(1 for _, d, r in offered_every if d and r)
    assert all(b - a <= 0.1 + 1e-9 for a, b in zip(driving, driving[1:], strict=False))
    assert yaw == pytest.approx(yaw_every, abs=0.05)
    assert yaw == pytest.approx(slow.true_rotation_deg, abs=2.0)


def test_the_frame_rule_takes_a_frame_at_the_predicted_step_or_the_gap():
    sim = make_simulator("planar")
    sim.build(replace(build_scene(box_spec()), initial_pose=Pose2D(0.0, 0.0, 0.0)))
    tracker = PoseTracker(*perceive_first(sim.render_depth()))
    tracker.begin_push()
    assert tracker.wants_frame(0.03, False, 10.0, 0.1)  # nothing to predict from yet
    tracker._history += [(0.1, 0.1)]  # 1 rad/s = 57.3 deg/s
    step_t = 0.1 + math.radians(10.0)  # when the predicted turn reaches 10 deg
    assert not tracker.wants_frame(step_t - 0.005, False, 10.0, 0.5)
    assert tracker.wants_frame(step_t + 0.005, False, 10.0, 0.5)
    assert tracker.wants_frame(0.2, False, 10.0, 0.1)  # the gap
    assert not tracker.wants_frame(0.19, False, 10.0, 0.1)
    assert tracker.wants_frame(0.11, True, 10.0, 0.5)  # the pusher drives: every frame
    assert tracker.wants_frame(0.11, True, 10.0, 0.5, 0.01)  # ... or once it travelled
    assert not tracker.wants_frame(0.105, True, 10.0, 0.5, 0.01)
    assert tracker.wants_frame(0.11, False, 0.0, 0.5)  # step 0: every frame
    tracker._history[-1] = (0.1, 0.0)  # not turning: only the gap asks for a frame
    assert not tracker.wants_frame(0.19, False, 10.0, 0.1)
    assert not tracker.wants_frame(0.19, True, 10.0, 0.1, 0.1)  # nor while driving slowly
    assert tracker.wants_frame(0.2, True, 10.0, 0.1, 0.1)


@pytest.mark.parametrize(
    "knob,value", [("track_step", -1.0), ("track_gap", 0.0), ("track_drive", -1.0)]
)
def test_frame_rule_knobs_are_checked(knob, value):
    with pytest.raises(ConfigError, match=f"estimator.{knob}"):
        prepare_job(_compose(f"estimator.{knob}={value}"))


# Pushes the planar study at 30 fps measured off by a whole symmetry angle (docs/method.md,
# "Tracking during the push"): episode 107 of the planar study (cross_12: push 3 measured -114
# deg, true -24; the object stopped between frames and was hit again, and the tracker
# extrapolated its rate over the gap) and 2895 (triangle_equilateral_10, 4 cm/s: push 0
# measured -101, true +19; the fit at rest took a symmetric copy fitting 0.13 px better).
ALIASED = [
    ("cross_12", 3, (0.9011461171091488, -4.880478143576314), 40.0, 1.0, 770808875),
    (
        "triangle_equilateral_10",
        2,
        (0.25854857691532285, -1.5231806672131067),
        4.0,
        10.0,
        1089580271,
    ),
]


@pytest.mark.parametrize(
    "name,com_index,com_cm,speed,izz,seed", ALIASED, ids=[a[0] for a in ALIASED]
)
def test_pushes_the_study_once_aliased_are_measured_right(
    name, com_index, com_cm, speed, izz, seed
):
    from comexp.episode.loop import run_episode
    from comexp.experiment.objects import load_objects

    spec = EpisodeSpec.for_object(
        load_objects()[name],
        com_index,
        com_cm,
        backend="planar",
        floor="iso",
        mu_floor_x=1.0,
        mu_floor_y=1.0,
        mu_pusher=0.1,
        speed_cm_s=speed,
        izz_scale=izz,
        seed=seed,
    )
    res = run_episode(spec, make_simulator("planar"))
    assert res.status == "ok" and res.n_pushes == 5
    for p in res.pushes:
        assert p.n_frames > 0
        assert abs(p.rotation_deg - p.rotation_true_deg) < 2.0, p


@pytest.mark.parametrize("backend", ["pybullet", "mujoco"])
def test_engines_render_the_pusher_and_the_mask_removes_exactly_it(backend):
    """The engines draw their pusher (a sphere / a capsule) in the depth image; touching the
    object it would join its blob. Masked by the known pusher position, the object's mask is
    the one without the pusher, pixel for pixel (measured: 12-18 pusher pixels, 0 left)."""
    sim = make_simulator(backend, floor_friction="model", renderer="engine")
    try:
        for pose, xy in [
            (Pose2D(-0.08, 0.02, 0.0), (-0.08 + 0.04 + 0.0052, 0.03)),
            (Pose2D(0.08, -0.06, 0.0), (0.08 - 0.04 - 0.0052, -0.06)),
        ]:
            sim.build(replace(build_scene(box_spec(backend)), initial_pose=pose))
            alone = object_mask(sim.render_depth())
            sim.place_pusher(xy)
            img = sim.render_depth()
            assert object_mask(img).sum() > alone.sum() + 5  # the pusher is drawn, joined
            masked = object_mask(mask_pusher(img, xy, sim.pusher_radius_m()))
            assert np.array_equal(masked, alone)
    finally:
        sim.close()


def _compose(*overrides: str):
    with initialize_config_module("comexp.conf", version_base="1.3"):
        return compose("config", overrides=list(overrides), return_hydra_config=True)


@pytest.mark.parametrize("fps", ["-1", "31", "nan"])
def test_camera_fps_is_bounded_by_a_commodity_camera(fps):
    with pytest.raises(ConfigError) as info:
        prepare_job(_compose(f"camera.fps={fps}"))
    msg = str(info.value)
    assert "camera.fps" in msg and "\n" not in msg


def test_camera_fps_reaches_every_episode():
    from comexp.experiment.grid import expand_grid

    job = prepare_job(
        _compose("camera.fps=15", "grid.objects=[rect_8x5]", "grid.coms_per_object=1")
    )
    specs = expand_grid(job.cfg, job.objects, estimator=job.estimator)
    assert {s.camera_fps for s in specs} == {15.0}
    job0 = prepare_job(
        _compose("camera.fps=0", "grid.objects=[rect_8x5]", "grid.coms_per_object=1")
    )
    from comexp.results.identity import episode_key

    specs0 = expand_grid(job0.cfg, job0.objects, estimator=job0.estimator)
    assert episode_key(specs[0]) != episode_key(specs0[0])  # fps is part of the identity


def test_an_older_schema_is_upgraded_in_one_line(tmp_path):
    """Schema 4 added pushes.n_frames; an older file is upgraded when a job opens it (every
    earlier layout: tests/test_migrations.py)."""
    path = tmp_path / "old.db"
    ResultsDB(path).close()
    with sqlite3.connect(path) as con:
        con.execute("UPDATE comexp_meta SET value = '3' WHERE key = 'schema'")
    with ResultsDB(path) as db:
        msg = db.schema_note
    assert msg is not None and "schema version 3 upgraded" in msg and "\n" not in msg
    assert SCHEMA_VERSION >= 4


def _tilt(sim, pose: Pose2D, tilt_deg: float) -> None:
    """Put the object at `pose`, tilted about world x and lifted by 5 mm (engine state only:
    a pose no push reaches on purpose, the hardest case for the tracking window)."""
    a = math.radians(tilt_deg)
    if sim.name == "pybullet":
        pb = sys.modules["comexp.backends.pybullet_sim"].pb
        com, _ = pb.getBasePositionAndOrientation(sim._object, physicsClientId=sim._cid)
        quat = pb.getQuaternionFromEuler([a, 0.0, pose.yaw_rad])
        rot = np.array(pb.getMatrixFromQuaternion(quat)).reshape(3, 3)
        pos = np.array([pose.x_m, pose.y_m, 0.005]) + rot @ sim._com_local
        pb.resetBasePositionAndOrientation(sim._object, pos, quat, physicsClientId=sim._cid)
    else:
        q = sim._obj_qadr
        cy, sy = math.cos(pose.yaw_rad / 2), math.sin(pose.yaw_rad / 2)
        cx, sx = math.cos(a / 2), math.sin(a / 2)
        sim.data.qpos[q : q + 3] = (pose.x_m, pose.y_m, 0.005)
        sim.data.qpos[q + 3 : q + 7] = (cy * cx, cy * sx, sy * sx, sy * cx)  # Rz(yaw) Rx(a)
    assert sim.object_state().tilt_deg == pytest.approx(tilt_deg, abs=1e-6)


@pytest.mark.parametrize("backend", ["pybullet", "mujoco"])
def test_engine_tracking_frames_are_the_object_window_of_the_full_image(backend):
    """`render_tracking_depth` renders only the window around the object (an off-centre
    frustum): its pixels are the full image's window (pybullet to float rounding, MuJoCo to
    the depth buffer's precision: measured 2.4e-7 / 4.4e-6 m), it holds the whole object
    (also tilted and lifted, at the image's edge where the window is clipped) and the pusher
    where it overlaps, and it costs a few % of the pixels. The full image is unchanged."""
    tol_m = {"pybullet": 1e-6, "mujoco": 2e-5}[backend]
    sim = make_simulator(backend, floor_friction="model", renderer="engine")
    try:
        cases = [
            (Pose2D(0.05, -0.03, 0.4), 0.0, (0.05 - 0.04 * math.cos(0.4) - 0.006, -0.045)),
            (Pose2D(-0.275, 0.275, -1.0), 0.0, None),  # cut by the image's corner
            (Pose2D(0.12, 0.08, 2.0), 12.0, None),
        ]
        for pose, tilt_deg, pusher_xy in cases:
            sim.build(replace(build_scene(box_spec(backend)), initial_pose=pose))
            if tilt_deg:
                _tilt(sim, pose, tilt_deg)
            if pusher_xy is not None:
                sim.place_pusher(pusher_xy)
            full = sim.render_depth()
            crop = sim.render_tracking_depth()
            fc, cc = full.camera, crop.camera
            u0, v0 = round(fc.cx_px - cc.cx_px), round(fc.cy_px - cc.cy_px)
            h, w = crop.depth_m.shape
            assert (cc.width_px, cc.height_px) == (w, h)
            assert (cc.fx_px, cc.fy_px, cc.position_m) == (fc.fx_px, fc.fy_px, fc.position_m)
            assert w * h < 0.1 * fc.width_px * fc.height_px
            window = full.depth_m[v0 : v0 + h, u0 : u0 + w]
            assert np.max(np.abs(crop.depth_m - window)) < tol_m
            above = full.depth_m < fc.position_m[2] - 0.004
            assert np.array_equal(
                crop.depth_m < cc.position_m[2] - 0.004, above[v0 : v0 + h, u0 : u0 + w]
            )
            if pusher_xy is None:  # nothing of the object outside the window
                assert above.sum() == above[v0 : v0 + h, u0 : u0 + w].sum() > 100
            else:  # the pusher is in the window where it touches the object
                assert (
                    object_mask(crop).sum() > object_mask(mask_pusher(crop, pusher_xy, 0.005)).sum()
                )
            if pose.x_m < -0.15:  # clipped at the image's top-left corner
                assert (u0, v0) == (0, 0)
            assert np.array_equal(sim.render_depth().depth_m, full.depth_m)
    finally:
        sim.close()


@pytest.mark.parametrize("backend", ["pybullet", "mujoco"])
def test_engine_tracking_frames_have_the_method_s_geometry(backend):
    """Through the window's camera model a tracking frame is metric and in the method's frames
    (docs/method.md): an object at +y lies in the image's upper half (rows grow downward), and
    a CCW turn about +z is tracked as a positive yaw, at the true position."""
    sim = make_simulator(backend, floor_friction="model", renderer="engine")
    try:
        sim.build(replace(build_scene(box_spec(backend)), initial_pose=Pose2D(0.0, 0.0, 0.0)))
        perc, obs0 = perceive_first(sim.render_depth())
        tracker = PoseTracker(perc, obs0)
        tracker.begin_push()
        moved = Pose2D(0.03, 0.06, math.radians(25.0))
        sim.build(replace(build_scene(box_spec(backend)), initial_pose=moved))
        crop = sim.render_tracking_depth()
        cy_px = sim.camera_model().cy_px
        v0 = cy_px - crop.camera.cy_px  # the window's top row in the full image
        assert v0 + crop.depth_m.shape[0] < cy_px  # +y: above the centre
        view = observe_boundary(crop, (0.0, 0.0))
        assert np.allclose(view.centroid_m, (moved.x_m, moved.y_m), atol=1.5e-3)
        fit = tracker.track(view, 0.1)
        assert math.degrees(fit.pose.yaw_rad) == pytest.approx(25.0, abs=1.0)
        assert (fit.pose.x_m, fit.pose.y_m) == pytest.approx((moved.x_m, moved.y_m), abs=1.5e-3)
    finally:
        sim.close()
