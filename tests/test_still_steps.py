"""The engines' still steps (`Simulator.steps_still`, `StillJumps`): an object at rest by the
settle rule, the pusher clear of it, is not stepped; time passes, the object's state is kept,
the pusher ends where the steps would leave it. planar's own still steps are in test_planar.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from comexp.backends.physics_settings import STILL_JUMPS
from comexp.experiment.config import make_simulator
from comexp.method.frames import Pose2D
from comexp.sim.bodies import box_object
from comexp.sim.clear_steps import clear_steps
from comexp.sim.contact import contact_push
from comexp.sim.protocol import push
from comexp.sim.scene import FloorSpec, SceneSpec

ENGINES = ["pybullet", "mujoco"]


@pytest.fixture(params=ENGINES, scope="module")
def sim(request):
    pytest.importorskip(f"comexp.backends.{request.param}_sim")
    s = make_simulator(request.param)
    yield s
    s.close()


def _box_scene(mu: float = 0.3, yaw: float = 0.4) -> SceneSpec:
    obj = box_object(0.08, 0.05, 0.03, com_m=(0.01, -0.005), mu_pusher=0.5)
    return SceneSpec(FloorSpec(mu, mu), obj, initial_pose=Pose2D(0.01, -0.02, yaw))


def _settled(sim, scene: SceneSpec) -> None:
    sim.build(scene)
    sim.step(0.3)  # a resting object: the settle rule holds


def _approach(sim, gap_m: float, n: int, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Pusher targets toward the object's -x face (object frame) from `gap_m` clear of it."""
    pose = sim.object_state().pose
    inward = np.array([math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)])
    face = pose.to_world(np.array([-0.04, 0.0]))
    start = face - inward * (sim.pusher_radius_m() + gap_m)
    sim.place_pusher(start)
    return start, start + step_m * np.arange(1, n + 1)[:, None] * inward


def test_the_count_is_the_clear_steps_of_a_resting_object(sim):
    """As many steps as stay clear by the margin beyond their length (`clear_steps`, the
    kernel planar uses too); none when the object moves or the pusher starts within reach."""
    _settled(sim, _box_scene())
    start, targets = _approach(sim, 0.01, 400, 4e-5)
    poly = sim.object_state().pose.to_world(sim.outline_m())
    r = sim.pusher_radius_m()
    expected = clear_steps(start[0], start[1], targets, poly, r, STILL_JUMPS.margin_m)
    assert 0 < expected < len(targets)  # it stops short of the object
    assert sim.steps_still(targets) == expected
    # the last counted step ends farther than the margin from the outline
    end = targets[expected - 1]
    gap = min(_segment_distance(end, poly[i], poly[(i + 1) % len(poly)]) for i in range(4))
    assert gap - r > STILL_JUMPS.margin_m
    sim.set_object_velocity((0.01, 0.0, 0.0), (0.0, 0.0, 0.0))  # 1 cm/s: not at rest
    assert sim.steps_still(targets) == 0
    _settled(sim, _box_scene())
    _, from_the_face = _approach(sim, 0.0, 10, 4e-5)  # within reach from the start
    assert sim.steps_still(from_the_face) == 0


def _segment_distance(p, a, b) -> float:
    ab = b - a
    t = min(1.0, max(0.0, float(np.dot(p - a, ab) / np.dot(ab, ab))))
    return float(np.hypot(*(a + t * ab - p)))


def test_a_jump_keeps_the_object_and_moves_the_pusher_without_stepping(sim, monkeypatch):
    _settled(sim, _box_scene())
    _, targets = _approach(sim, 0.01, 200, 4e-5)
    n = sim.steps_still(targets)
    before = sim.object_state()
    stepped: list[int] = []
    monkeypatch.setattr(sim, "advance", lambda t: stepped.append(len(t)) or (False, 0.0))
    assert sim.advance_still(targets[:n]) is False
    assert stepped == []  # the engine was not stepped
    assert sim.object_state() == before  # to the bit
    assert np.array_equal(sim.pusher_xy(), targets[n - 1])


@pytest.mark.parametrize("speed_m_s", [0.04, 0.4])
def test_a_push_with_its_still_steps_jumped_is_the_stepped_push(sim, monkeypatch, speed_m_s):
    """The same push with every still step stepped: the same outcome, the turn within the
    creep of a resting engine object (here 1e-12 deg on pybullet, 0.007 - 0.022 on MuJoCo;
    over a job's pushes the median is 1e-5 deg, `bench/episode_profile.py --still-jumps`), in
    17 - 22% fewer engine steps."""
    scene = _box_scene(0.3)
    outline = np.asarray(scene.obj.outline_m)
    contact = scene.initial_pose.to_world(np.array([outline[:, 0].min(), 0.012]))
    yaw = scene.initial_pose.yaw_rad
    cmd = contact_push(contact, (math.cos(yaw), math.sin(yaw)), 0.03, speed_m_s, 0.005)
    real_advance = sim.advance

    def run_push(jumps: bool):
        monkeypatch.setattr(sim, "still_jumps", STILL_JUMPS if jumps else None)
        steps: list[int] = []
        monkeypatch.setattr(sim, "advance", lambda t: steps.append(len(t)) or real_advance(t))
        _settled(sim, scene)
        out = push(sim, cmd)
        return out, sum(steps)

    (jumped, n_jumped), (stepped, n_stepped) = run_push(True), run_push(False)
    assert jumped.ok and stepped.ok and jumped.contact_made
    assert jumped.true_rotation_deg == pytest.approx(stepped.true_rotation_deg, abs=0.1)
    assert abs(jumped.true_rotation_deg) > 1.0  # a lever push: it turns
    assert n_jumped < 0.9 * n_stepped
    assert abs(jumped.steps - stepped.steps) <= 0.1 * stepped.steps


def test_no_jump_from_a_tilted_object(sim, monkeypatch):
    """An object still on the floor but tilted beyond `max_tilt_deg` may be falling back from
    a lift: its steps are stepped. (MuJoCo's 3 cm hexagon after a 40 cm/s push on mu 1 had its
    hold jumped at 0.75 deg before the guard.)"""
    import dataclasses

    _settled(sim, _box_scene())
    _, targets = _approach(sim, 0.01, 200, 4e-5)
    flat = sim.object_state()
    assert flat.tilt_deg < STILL_JUMPS.max_tilt_deg and sim.steps_still(targets) > 0
    for tilt_deg, jumps in ((0.5 * STILL_JUMPS.max_tilt_deg, True), (0.2, False), (0.75, False)):
        tilted = dataclasses.replace(flat, roll_rad=math.radians(tilt_deg))
        monkeypatch.setattr(sim, "object_state", lambda st=tilted: st)
        assert (sim.steps_still(targets) > 0) is jumps, tilt_deg


def test_the_signed_distance_is_shapelys_on_every_builtin_outline():
    """`point_polygon_distance` (the protocol's clearance: the compiled closest point) is
    shapely's distance to the boundary, negative inside, on every built-in outline, with
    points inside, outside, on the extended edges' lines and near the vertices."""
    import shapely

    from comexp.experiment.objects import load_objects
    from comexp.sim.contact import point_polygon_distance

    rng = np.random.default_rng(3)
    for name, obj in load_objects().items():
        poly = np.array(obj.outline_cm, dtype=float) / 100.0
        shape = shapely.Polygon(poly)
        pts = np.concatenate(
            [
                rng.uniform(poly.min(0) - 0.03, poly.max(0) + 0.03, size=(200, 2)),
                poly + rng.normal(scale=1e-3, size=poly.shape),  # near every vertex
            ]
        )
        for x, y in pts:
            ref = shape.exterior.distance(shapely.Point(x, y))
            ref = -ref if shape.contains(shapely.Point(x, y)) else ref
            assert point_polygon_distance((x, y), poly) == pytest.approx(ref, abs=1e-12), name
