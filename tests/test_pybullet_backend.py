"""pybullet-specific checks that the shared physics contract does not cover."""

from __future__ import annotations

import math

import numpy as np
import pybullet as pb
import pytest

from comexp.experiment.config import make_simulator
from comexp.method.frames import Pose2D
from comexp.sim.bodies import box_object, prism_object
from comexp.sim.contact import contact_push
from comexp.sim.protocol import push
from comexp.sim.scene import FloorSpec, PushCommand, PushStatus, SceneSpec


@pytest.fixture(scope="module")
def sim():
    s = make_simulator("pybullet", renderer="engine")  # its own renderer is tested here
    yield s
    s.close()


def test_inertia_and_com_come_from_the_spec_not_the_shape(sim):
    obj = box_object(0.08, 0.05, 0.03, com_m=(0.02, -0.01), izz_scale=10.0)
    sim.build(SceneSpec(FloorSpec(0.5, 0.5), obj))
    mass, _, inertia = pb.getDynamicsInfo(sim._object, -1, physicsClientId=sim._cid)[:3]
    assert mass == pytest.approx(obj.mass_kg)
    assert inertia == pytest.approx((obj.ixx_kg_m2, obj.iyy_kg_m2, obj.izz_kg_m2), rel=1e-6)
    com_world, _ = pb.getBasePositionAndOrientation(sim._object, physicsClientId=sim._cid)
    assert com_world[:2] == pytest.approx(obj.com_m, abs=1e-9)
    assert sim.object_state().position_m[:2] == pytest.approx((0.0, 0.0), abs=1e-9)


def test_object_rests_on_its_true_bottom(sim):
    """No collision margin: after settling the object frame sits on z = 0 within 0.1 mm."""
    sim.build(SceneSpec(FloorSpec(0.5, 0.5), box_object(0.06, 0.04, 0.02)))
    sim.step(0.2)
    st = sim.object_state()
    assert abs(st.position_m[2]) < 1e-4
    assert st.tilt_deg < 0.05


def test_velocity_hook_is_for_the_object_frame(sim):
    sim.build(SceneSpec(FloorSpec(0.0, 0.0), box_object(0.08, 0.05, 0.03, com_m=(0.02, 0.01))))
    sim.set_object_velocity((0.1, -0.05, 0.0), (0.0, 0.0, 0.3))
    st = sim.object_state()
    assert st.linear_velocity_m_s[:2] == pytest.approx((0.1, -0.05), abs=1e-9)
    assert st.angular_velocity_rad_s[2] == pytest.approx(0.3, abs=1e-9)


def test_nonconvex_object_from_several_parts(sim):
    """An L shape made of two boxes: one body, both parts visible and colliding."""
    outline = [(0, 0), (0.08, 0), (0.08, 0.03), (0.03, 0.03), (0.03, 0.08), (0, 0.08)]
    obj = prism_object("L", outline, 0.03, (0.0, 0.0))
    parts = obj.convex_parts_m
    if len(parts) < 2:
        pytest.skip("convex decomposition of non-convex outlines not available yet")
    sim.build(SceneSpec(FloorSpec(0.5, 0.5), obj))
    sim.step(0.1)
    assert sim.object_state().tilt_deg < 0.05
    img = sim.render_depth()
    top = np.abs(img.depth_m - (img.camera.position_m[2] - 0.03)) < 2e-3
    px = img.camera.pixel_size_m(img.camera.position_m[2] - 0.03)
    area = 0.08 * 0.03 + 0.03 * 0.05
    assert top.sum() * px * px == pytest.approx(area, rel=0.08)


def test_two_instances_coexist_and_agree():
    scene = SceneSpec(FloorSpec(1.0, 0.1), box_object(0.08, 0.05, 0.03, com_m=(0.01, -0.005)))
    cmd = contact_push((-0.04, 0.012), (1.0, 0.0), 0.03, 0.4, scene.pusher.radius_m)
    a, b = make_simulator("pybullet"), make_simulator("pybullet")
    try:
        outs = []
        for s in (a, b, a, b):
            s.build(scene)
            outs.append(push(s, cmd))
        assert all(o == outs[0] for o in outs)
        assert outs[0].ok and abs(outs[0].rotation_deg) > 1.0
    finally:
        a.close()
        b.close()


def test_pusher_is_parked_out_of_view_after_a_push(sim):
    scene = SceneSpec(FloorSpec(0.5, 0.5), box_object(0.08, 0.05, 0.03))
    sim.build(scene)
    empty = sim.render_depth().depth_m.copy()
    out = push(sim, contact_push((-0.04, 0.0), (1.0, 0.0), 0.03, 0.04, scene.pusher.radius_m))
    assert out.ok and out.contact_made
    xy = sim.pusher_xy()
    uv = scene.camera.model().world_to_pixel(xy[0], xy[1], 0.1)
    assert not (0 <= uv[0] < 224 and 0 <= uv[1] < 224)
    # the image only changed where the object moved: nothing of the pusher is left in view
    moved = np.abs(sim.render_depth().depth_m - empty) > 1e-3
    assert moved.sum() > 0
    v, u = np.nonzero(moved)
    world = scene.camera.model().pixel_to_world(u, v, np.full(u.shape, 1.0))
    assert np.all(np.abs(world[:, 1]) < 0.05)


def test_blocked_start_leaves_the_scene_untouched(sim):
    scene = SceneSpec(
        FloorSpec(0.5, 0.5), box_object(0.08, 0.05, 0.03), initial_pose=Pose2D(0.05, 0.0, 0.3)
    )
    sim.build(scene)
    before = sim.object_state()
    # axis outside the footprint but within one radius of its edge: still overlaps
    edge_x = 0.05 + 0.04 * math.cos(0.3)
    out = push(sim, PushCommand((edge_x + 0.002, 0.0), (-1.0, 0.0), 0.03, 0.4))
    assert out.status is PushStatus.PATH_BLOCKED and out.steps == 0
    assert sim.object_state() == before


def test_free_rigid_pusher_keeps_its_height_and_orientation(sim):
    """The pusher is a heavy free body driven by velocity: gravity is cancelled and contact
    torques must not tilt it, or it would touch the floor or push at the wrong height (a
    sphere at the line contact's resultant height, `pusher_contact_height_m`)."""
    from comexp.sim.contact import pusher_contact_height_m

    scene = SceneSpec(FloorSpec(1.0, 1.0), box_object(0.08, 0.05, 0.03, mu_pusher=1.0))
    z0 = pusher_contact_height_m(scene.pusher, scene.obj.height_m)
    for speed in (0.4, 0.04):
        sim.build(scene)
        out = push(
            sim, contact_push((-0.04, 0.015), (1.0, 0.0), 0.03, speed, scene.pusher.radius_m)
        )
        assert out.ok and out.contact_made
        pos, quat = pb.getBasePositionAndOrientation(sim._pusher, physicsClientId=sim._cid)
        assert abs(pos[2] - z0) < 1e-6
        assert max(abs(a) for a in pb.getEulerFromQuaternion(quat)) < 1e-3


@pytest.mark.parametrize("mu_pusher", [0.5, 1.0])
def test_the_pusher_carries_none_of_the_objects_weight(sim, mu_pusher, monkeypatch):
    """While a pusher pushes 1 cm beside the CoM, the floor carries the whole weight: the model's
    pusher friction acts in the floor's plane only. (Bullet takes a contact's friction direction
    from the pre-solve slip, gravity included: a pusher held up against the object's in-step fall
    carried 39% of this box's weight, and tilted rect_8x5 by 1.14 deg.) Measured: 0.999-1.001
    of the weight after the impact's first three steps (which reach 0.978 and 1.017)."""
    obj = box_object(0.08, 0.05, 0.015, mu_pusher=mu_pusher)
    sim.build(SceneSpec(FloorSpec(1.0, 1.0), obj, initial_pose=Pose2D(0.0, 0.0, 0.3)))
    pose = Pose2D(0.0, 0.0, 0.3)
    contact = pose.to_world(np.array([-0.04, -0.01]))
    n = pose.to_world(np.array([1.0, 0.0])) - pose.to_world(np.zeros(2))
    cmd = contact_push(contact, n, 0.03, 0.4, 0.005)
    weight = obj.mass_kg * 9.81
    shares = []
    monkeypatch.setattr(sim, "_handle", None)  # stepped from Python, where steps can be watched
    original = sim._step_once

    def step():
        original()
        if pb.getContactPoints(sim._pusher, sim._object, physicsClientId=sim._cid):
            floor = pb.getContactPoints(sim._object, sim._floor, physicsClientId=sim._cid)
            shares.append(sum(p[9] for p in floor) / weight)

    sim._step_once = step
    try:
        out = push(sim, cmd)
    finally:
        del sim._step_once
    assert out.status is PushStatus.OK and len(shares) > 20
    after_impact = shares[3:]
    assert min(after_impact) > 0.99 and max(after_impact) < 1.01, (
        f"the floor carried {min(after_impact):.3f}..{max(after_impact):.3f} of the weight"
    )


def _box_push(sim, mu: float, speed: float):
    """An off-CoM push of an 8 x 5 cm box on its -x face (it turns and slides)."""
    obj = box_object(0.08, 0.05, 0.03, com_m=(0.01, -0.01), mu_pusher=0.5)
    pose = Pose2D(0.0, 0.0, 0.3)
    sim.build(SceneSpec(FloorSpec(mu, 0.5 * mu), obj, initial_pose=pose))
    contact = pose.to_world(np.array([-0.04, 0.012]))
    normal = (math.cos(0.3), math.sin(0.3))
    return push(sim, contact_push(contact, normal, 0.03, speed, 0.005))


@pytest.fixture()
def model_sim():
    s = make_simulator("pybullet")  # floor_friction=model: the compiled steps
    yield s
    s.close()


def test_the_compiled_steps_are_used_here(model_sim):
    """On Linux, with pybullet's wheel, Bullet's client handle is found and checked (its
    state query answers with the status the compiled steps expect), the C functions are bound
    to the module's own without making its library global, and the force flag is pybullet's
    world frame."""
    import ctypes

    from comexp.backends import pybullet_steps

    _box_push(model_sim, 0.5, 0.4)
    assert model_sim._handle is not None and pybullet_steps._BOUND
    assert pybullet_steps.EF_WORLD_FRAME == pb.WORLD_FRAME
    with pytest.raises(AttributeError):  # not in the process's global scope
        ctypes.CDLL(None).b3CanSubmitCommand  # noqa: B018


@pytest.mark.parametrize("mu, speed", [(0.1, 0.4), (1.0, 0.04)])
def test_the_compiled_steps_are_the_python_steps(model_sim, monkeypatch, mu, speed):
    """A chunk of steps in one compiled call (pybullet_steps.push_steps) sends Bullet the
    commands `_step_once` sends through pybullet's Python functions: the same push, its
    friction inputs and its end state to the bit, an impact and a slide (mu 0.1, 40 cm/s)
    and a sustained push (mu 1, 4 cm/s)."""
    runs = []
    for compiled in (True, False):
        if not compiled:
            monkeypatch.setattr(model_sim, "_handle", None)  # through pybullet's functions
        rows: list = []
        real_build = model_sim.build

        def build(scene, rows=rows, real_build=real_build):
            real_build(scene)
            model_sim._fric.inputs = rows

        monkeypatch.setattr(model_sim, "build", build)
        out = _box_push(model_sim, mu, speed)
        assert (model_sim._handle is not None) == compiled  # two paths compared, not one
        runs.append((out, rows, model_sim.object_state(), model_sim.pusher_xy().tolist()))
    (compiled, rows_c, end_c, q_c), (python, rows_p, end_p, q_p) = runs
    assert compiled.ok and compiled.contact_made and abs(compiled.true_rotation_deg) > 1.0
    assert compiled == python and end_c == end_p and q_c == q_p
    assert len(rows_c) > 100 and rows_c == rows_p


def test_the_yaw_is_pybullets_to_the_bit():
    """The compiled steps' yaw is getEulerFromQuaternion's, both branches near +-90 deg of
    pitch included."""
    from comexp.backends.pybullet_steps import yaw_of_quaternion

    rng = np.random.default_rng(7)
    quats = rng.normal(size=(3000, 4))
    pitched = [pb.getQuaternionFromEuler([0.3, s * (math.pi / 2 - e), 1.1]) for s in (1, -1)
               for e in (0.0, 1e-4, 1e-2)]  # fmt: skip
    for q in [*(quats / np.linalg.norm(quats, axis=1)[:, None]).tolist(), *pitched]:
        assert yaw_of_quaternion(*q) == pb.getEulerFromQuaternion(q)[2]


def test_without_the_handle_the_steps_run_from_python(monkeypatch):
    """A pybullet library whose client table cannot be found (a stripped or another build)
    leaves the backend on pybullet's Python functions, with the same push."""
    from comexp.backends import pybullet_steps

    with make_simulator("pybullet") as found:
        want = _box_push(found, 0.5, 0.4)
    monkeypatch.setattr(pybullet_steps, "_clients_table_address", lambda: None)
    with make_simulator("pybullet") as s:
        got = _box_push(s, 0.5, 0.4)
        assert s._handle is None
    assert got == want
    assert pybullet_steps._elf_symbol_values(__file__, {"b3CanSubmitCommand"}) == {}
    # the table is read only from the file the library was loaded from, as it is on disk
    import ctypes

    anchor = ctypes.cast(ctypes.CDLL(pb.__file__).b3CanSubmitCommand, ctypes.c_void_p).value
    assert pybullet_steps._mapped_from(pb.__file__, anchor)
    assert not pybullet_steps._mapped_from(__file__, anchor)


def test_a_failed_query_in_the_compiled_steps_raises(model_sim):
    """A state query Bullet refuses (here: no such body) stops the chunk with an error
    naming the step, as pybullet's own function raises."""
    _box_push(model_sim, 0.5, 0.4)
    real = model_sim._object
    model_sim._object = 999
    try:
        with pytest.raises(RuntimeError, match="failed at step 1"):
            model_sim._compiled_steps(np.zeros((3, 2)))
    finally:
        model_sim._object = real
