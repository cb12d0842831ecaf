"""The camera watches the push: the protocol's frame hook, the pusher mask, the frame-to-frame
tracker that unwraps large turns of symmetric outlines, `camera.fps`, `pushes.n_frames`."""

from __future__ import annotations

import math
import sqlite3
from dataclasses import replace

import numpy as np
import pytest
from hydra import compose, initialize_config_module

from comexp.experiment.config import ConfigError, prepare_job
from comexp.experiment.episode import EpisodeSpec, build_scene
from comexp.experiment.simulator import Frame, at_rest, contact_push, make_simulator
from comexp.method.perception import (
    PoseTracker,
    mask_pusher,
    object_mask,
    observe,
    observe_boundary,
    perceive_first,
)
from comexp.method.scene import Pose2D
from comexp.results.schema import SCHEMA_VERSION
from comexp.results.store import ResultsDB

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
    return sim.push(cmd, on_frame=on_frame, frame_interval_s=interval_s)


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
    missed = sim.push(contact_push((-0.04, 0.06), (1.0, 0.0), 0.03, 0.4, 0.005), seen.append, 0.01)
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


@pytest.mark.parametrize("backend", ["pybullet", "mujoco"])
def test_engines_render_the_pusher_and_the_mask_removes_exactly_it(backend):
    """The engines draw their pusher (a sphere / a capsule) in the depth image; touching the
    object it would join its blob. Masked by the known pusher position, the object's mask is
    the one without the pusher, pixel for pixel (measured: 12-18 pusher pixels, 0 left)."""
    sim = make_simulator(backend, floor_friction="model")
    try:
        for pose, xy in [
            (Pose2D(-0.08, 0.02, 0.0), (-0.08 + 0.04 + 0.0052, 0.03)),
            (Pose2D(0.08, -0.06, 0.0), (0.08 - 0.04 - 0.0052, -0.06)),
        ]:
            sim.build(replace(build_scene(box_spec(backend)), initial_pose=pose))
            alone = object_mask(sim.render_depth())
            sim._place_pusher(xy)
            img = sim.render_depth()
            assert object_mask(img).sum() > alone.sum() + 5  # the pusher is drawn, joined
            masked = object_mask(mask_pusher(img, xy, sim._pusher_radius_m()))
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


def test_an_older_schema_is_refused_in_one_line(tmp_path):
    path = tmp_path / "old.db"
    ResultsDB(path).close()
    with sqlite3.connect(path) as con:
        con.execute("UPDATE comexp_meta SET value = '3' WHERE key = 'schema'")
    with pytest.raises(ValueError) as info:
        ResultsDB(path)
    msg = str(info.value)
    assert f"schema version 3, this comexp writes {SCHEMA_VERSION}" in msg and "\n" not in msg
    assert SCHEMA_VERSION == 4
