"""MuJoCo backend beyond the shared contract: symmetry of through-CoM pushes, stopping
distances, the built-in objects, the floor-support construction and renderer reuse.

Why these exist: MuJoCo's soft contacts act about the contact set's own centre whenever
friction is not saturated, and its general convex collider is not rotation-invariant; both
turned a push through the CoM by up to 1.5 deg (docs/physics_mujoco.md). These tests pin the
fixes (point-symmetric floor supports, capsule pusher) for mirrored and rotated set-ups.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely.geometry
from physics_helpers import BATCH_CASES, push_on_view

from comexp.experiment.objects import com_points, load_objects
from comexp.method.frames import Pose2D
from comexp.method.geometry import signed_area
from comexp.sim.bodies import box_object
from comexp.sim.contact import contact_push, pusher_contact_height_m
from comexp.sim.protocol import push
from comexp.sim.scene import GRAVITY_M_S2, FloorSpec, PusherSpec, PushStatus, SceneSpec

mujoco_sim = pytest.importorskip("comexp.backends.mujoco_sim")

THROUGH_COM_TARGET_DEG = 0.1
# floor mu 1 at 40 cm/s: the impact lifts the object off its supports for a few ms (soft
# contacts, docs/physics_mujoco.md "open problems"); measured residual 0.03-0.10 deg there,
# 0.7-4.6 deg before the fixes, at the exact starts; 1.92 deg at starts 0.1 um away (xfail)
THROUGH_COM_IMPACT_DEG = 0.25
# floor mu 0.1 at 40 cm/s: a sticking push through the CoM is unstable, and the long slide
# after it grows a 1e-7 seed; over 21 starts within 0.5 um / 5 urad of each set-up, 1 of 21
# turns more than 0.1 deg at yaw 0.7 (0.354 deg with every still step stepped, mujoco-6;
# 0.156 with them jumped, mujoco-7; medians 0.0013 / 0.0003 deg; at mujoco-8's last bits the
# three starts of the test turn at most 0.004 deg). Beyond the target there (xfail), the
# contract's bound still holds.
THROUGH_COM_CONTRACT_DEG = 0.5


@pytest.fixture(scope="module")
def sim():
    s = mujoco_sim.MujocoSimulator(renderer="engine")  # its own renderer is tested here
    yield s
    s.close()


def _push_through_com(sim, mu: float, speed: float, com: tuple[float, float], pose: Pose2D):
    """Push the box's -x face (object frame) along +x at the CoM's y, the box at `pose`."""
    obj = box_object(0.08, 0.05, 0.03, com_m=com, mu_pusher=1.0)
    scene = SceneSpec(FloorSpec(mu, mu), obj, initial_pose=pose)
    sim.build(scene)
    contact = pose.to_world(np.array([-0.04, com[1]]))
    normal = (math.cos(pose.yaw_rad), math.sin(pose.yaw_rad))
    return push(sim, contact_push(contact, normal, 0.03, speed, scene.pusher.radius_m))


@pytest.mark.parametrize(
    "com,yaw",
    [((0.015, -0.01), 0.0), ((0.015, 0.01), 0.7), ((-0.015, -0.01), 2.0)],
    ids=["mirrored", "yaw0.7", "near_face_yaw2"],
)
@pytest.mark.parametrize("mu,speed", [(1.0, 0.04), (1.0, 0.4), (0.1, 0.04), (0.1, 0.4)])
def test_push_through_com_mirrored_and_rotated(sim, com, yaw, mu, speed):
    """At the exact start and 0.1 um / 1 urad either side (see nearby_starts). Measured over
    5 starts up to 0.3 um away: |rotation| < 0.0005 deg except on mu 1 at 40 cm/s, where the
    mirrored and yaw0.7 set-ups turn 0.008 deg at the exact start but 1.92 deg at most nearby
    ones (bimodal: the known impact lift, docs/physics.md); near_face_yaw2 <= 0.003 deg."""
    from physics_helpers import nearby_starts

    rotations = []
    for start in nearby_starts(Pose2D(0.0, 0.0, yaw)):
        out = _push_through_com(sim, mu, speed, com, start)
        assert out.status is PushStatus.OK, out
        moved = math.hypot(
            out.pose_after.x_m - out.pose_before.x_m, out.pose_after.y_m - out.pose_before.y_m
        )
        assert moved > 0.02
        assert out.max_tilt_deg < 5.0
        rotations.append(out.rotation_deg)
    worst = max(abs(r) for r in rotations)
    impact = (mu, speed) == (1.0, 0.4)
    bound = THROUGH_COM_IMPACT_DEG if impact else THROUGH_COM_TARGET_DEG
    if impact and worst >= bound:
        pytest.xfail(f"impact lift on mu 1 (known, documented): {np.round(rotations, 3)} deg")
    if (mu, speed) == (0.1, 0.4) and worst >= bound:
        assert worst < THROUGH_COM_CONTRACT_DEG, f"rotated {np.round(rotations, 3)} deg"
        pytest.xfail(f"a seed grown in the slide (known, measured): {np.round(rotations, 3)} deg")
    assert worst < bound, f"rotated {np.round(rotations, 3)} deg"


def _slide_distance_m(sim, mu: float, v0: float) -> float:
    sim.build(SceneSpec(FloorSpec(mu, mu), box_object(0.08, 0.05, 0.03, mu_pusher=0.5)))
    x0 = sim.object_state().position_m[0]
    sim.set_object_velocity((v0, 0.0, 0.0), (0.0, 0.0, 0.0))
    for _ in range(200):
        sim.step(0.01)
        v = sim.object_state().linear_velocity_m_s
        if math.hypot(v[0], v[1]) < 1e-5:
            break
    return sim.object_state().position_m[0] - x0


@pytest.mark.parametrize("mu", [0.1, 1.0])
@pytest.mark.parametrize("v0", [0.4, 0.04])
def test_stopping_distance_is_coulomb(sim, mu, v0):
    """A slide from v0 stops after v0^2 / (2 mu g). The absolute allowance (0.1 mm, 1/28 of
    a camera pixel) covers MuJoCo's regularised friction below ~mu g / b (b = friction
    damping); a viscous tail would overshoot it many times over (measured 0.95 mm instead of
    0.08 mm with solreffriction 0.05)."""
    d = _slide_distance_m(sim, mu, v0)
    ideal = v0 * v0 / (2.0 * mu * GRAVITY_M_S2)
    assert abs(d - ideal) < max(0.03 * ideal, 1e-4), f"{d * 1e3:.3f} mm vs {ideal * 1e3:.3f} mm"


REPRESENTATIVE = ["triangle_equilateral_10", "ellipse_12x7", "l_shape", "u_shape", "cross_12"]


@pytest.mark.parametrize("name", REPRESENTATIVE)
def test_builtin_object_rests_renders_and_slides(sim, name):
    obj = load_objects([name])[name]
    com = com_points(obj, 1)[0]
    spec = obj.model(com, izz_scale=1.0, mu_pusher=0.5)
    scene = SceneSpec(FloorSpec(1.0, 1.0), spec, initial_pose=Pose2D(0.03, -0.02, 0.4))
    sim.build(scene)
    st = sim.object_state()
    assert st.tilt_deg < 0.5
    assert abs(st.position_m[2]) < 5e-4
    # the top face seen by the camera has the footprint's area
    img = sim.render_depth()
    cam = img.camera
    top = cam.position_m[2] - spec.height_m
    mask = img.depth_m < cam.position_m[2] - 0.5 * spec.height_m
    area = mask.sum() * cam.pixel_size_m(top) ** 2
    assert area == pytest.approx(abs(signed_area(spec.outline_m)), rel=0.06)
    # a slide stops after v0^2 / (2 mu g): the mean deceleration is mu g (the velocity is a
    # staircase of sub-mm hops at mu = 1, see docs/physics_mujoco.md, so no fit of v(t))
    v0 = 0.5
    x0 = sim.object_state().position_m[0]
    sim.set_object_velocity((v0, 0.0, 0.0), (0.0, 0.0, 0.0))
    sim.step(0.2)
    st = sim.object_state()
    ideal = v0 * v0 / (2.0 * GRAVITY_M_S2)
    assert st.position_m[0] - x0 == pytest.approx(ideal, rel=0.05)
    assert math.hypot(*st.linear_velocity_m_s[:2]) < 1e-3
    assert st.tilt_deg < 1.0


@pytest.mark.parametrize("floor_friction", ["native", "model"])
@pytest.mark.parametrize("name", ["l_shape", "triangle_right_11x7", "u_shape", "square_7"])
def test_floor_core_is_point_symmetric_about_the_com(name, floor_friction):
    """Either layout (native: the supports carry MuJoCo's friction; model: the weight only,
    coarser) is point-symmetric about the CoM, with a support by every tipping corner."""
    obj = load_objects([name])[name]
    spec = obj.model(com_points(obj, 1)[0], izz_scale=1.0, mu_pusher=0.5)
    layout = mujoco_sim._support_settings(mujoco_sim.DEFAULT_CONTACT, floor_friction)
    core, rim = mujoco_sim._support_points(spec.outline_m, spec.com_m, layout)
    c = np.asarray(spec.com_m)
    pts = np.asarray(core)
    assert len(pts) >= layout.support_min_points
    mirrored = 2.0 * c - pts
    gaps = np.min(np.linalg.norm(mirrored[:, None, :] - pts[None, :, :], axis=2), axis=1)
    assert gaps.max() < 1e-9  # every support has its mirror image: contact centre = CoM
    assert np.allclose(pts.mean(axis=0), c, atol=1e-9)
    hull = np.asarray(shapely.geometry.Polygon(spec.outline_m).convex_hull.exterior.coords)
    rim_a = np.asarray(rim)
    for v in hull[:-1]:  # every tipping corner has a support next to it
        assert np.min(np.linalg.norm(rim_a - v, axis=1)) < 6e-3  # acute corners: inset


def test_the_model_s_supports_are_coarser_than_native_s():
    """Under `floor_friction=model` the supports carry the weight only: 2 cm apart, halved
    down to 4 core points (mujoco-9), fewer than native's 1 cm and 8 on the study's objects."""
    objs = load_objects()
    counts = {}
    for ff in ("native", "model"):
        layout = mujoco_sim._support_settings(mujoco_sim.DEFAULT_CONTACT, ff)
        counts[ff] = []
        for obj in objs.values():
            spec = obj.model(com_points(obj, 1)[0], izz_scale=1.0, mu_pusher=0.5)
            counts[ff].append(
                len(mujoco_sim._support_points(spec.outline_m, spec.com_m, layout)[0])
            )
    assert all(m <= n for m, n in zip(counts["model"], counts["native"], strict=True))
    assert sum(counts["model"]) < 0.6 * sum(counts["native"])
    assert min(counts["model"]) >= 4
    naive = mujoco_sim.NAIVE_CONTACT  # no supports stays none
    assert mujoco_sim._support_settings(naive, "model") is naive


def test_renderer_is_reused_across_object_changes(sim):
    scenes = [
        SceneSpec(FloorSpec(0.5, 0.5), box_object(0.08, 0.05, 0.03)),
        SceneSpec(FloorSpec(0.5, 0.5), box_object(0.06, 0.06, 0.02)),
    ]
    sim.build(scenes[0])
    first = sim.render_depth().depth_m.copy()
    renderer = sim._renderers[sim._render_key].renderer
    sim.build(scenes[1])
    sim.render_depth()
    sim.build(scenes[0])
    again = sim.render_depth().depth_m
    assert sim._renderers[sim._render_key].renderer is renderer  # no new GL context
    assert np.array_equal(first, again)


def test_a_rebuild_at_another_pose_reuses_the_model_and_a_new_object_does_not(sim):
    """An episode's re-centring builds keep the scene's MJCF (the pose is not in it) and so
    the compiled model; the MJCF kept is the one a fresh writing gives, and another object
    (a CoM moved) compiles a new model. Each build puts the object at its pose."""
    from dataclasses import replace

    scene = SceneSpec(FloorSpec(0.5, 0.5), box_object(0.08, 0.05, 0.03, com_m=(0.01, 0.0)))
    sim.build(scene)
    model = sim.model
    moved = replace(scene, initial_pose=Pose2D(0.02, -0.01, 0.4))
    sim.build(moved)
    assert sim.model is model
    assert sim._xml == mujoco_sim.scene_mjcf(moved, sim.settings, sim.contact, sim.floor_friction)
    x, y, _ = sim.object_state().position_m
    assert (x, y, sim.object_state().yaw_rad) == pytest.approx((0.02, -0.01, 0.4), abs=1e-6)
    other = replace(scene, obj=box_object(0.08, 0.05, 0.03, com_m=(-0.01, 0.0)))
    sim.build(other)
    assert sim.model is not model
    assert sim._xml == mujoco_sim.scene_mjcf(other, sim.settings, sim.contact, sim.floor_friction)


@pytest.mark.parametrize("floor_friction", ["model", "native"])
def test_the_conditions_of_a_batch_share_kept_models(floor_friction):
    """Under `floor_friction=model` the floor's friction is not in the MJCF: scenes that
    differ in it alone share one compiled model (native: each has its own). The last
    `KEPT_MODELS` models are kept, and a push on a kept one is the push of a fresh
    simulator, to the bit."""
    from dataclasses import replace

    sim = mujoco_sim.MujocoSimulator(floor_friction=floor_friction)
    scene = _box_scene(0.3)
    other_floor = replace(scene, floor=FloorSpec(0.9, 0.2))
    other_pusher = replace(
        scene, obj=box_object(0.08, 0.05, 0.03, com_m=(0.01, -0.01), mu_pusher=0.9)
    )
    sim.build(scene)
    first = sim.model
    sim.build(other_pusher)
    assert sim.model is not first
    sim.build(other_floor)
    assert (sim.model is first) == (floor_friction == "model")
    contact = scene.initial_pose.to_world(np.array([-0.04, 0.012]))
    cmd = contact_push(contact, (math.cos(0.3), math.sin(0.3)), 0.03, 0.4, 0.005)
    kept = push(sim, cmd), sim.object_state()
    fresh = mujoco_sim.MujocoSimulator(floor_friction=floor_friction)
    fresh.build(other_floor)
    assert kept == (push(fresh, cmd), fresh.object_state())
    assert kept[0].contact_made and abs(kept[0].true_rotation_deg) > 1.0
    for k in range(mujoco_sim.KEPT_MODELS + 1):  # the oldest is dropped
        sim.build(replace(scene, obj=box_object(0.08, 0.05, 0.03, com_m=(0.0, 0.001 * k))))
    assert len(sim._models) == mujoco_sim.KEPT_MODELS
    sim.close()
    fresh.close()


def _box_scene(mu: float) -> SceneSpec:
    obj = box_object(0.08, 0.05, 0.03, com_m=(0.01, -0.01), mu_pusher=0.5)
    return SceneSpec(FloorSpec(mu, mu), obj, initial_pose=Pose2D(0.0, 0.0, 0.3))


def _box_push(sim, mu: float, speed: float):
    """An off-CoM push of `_box_scene` on its -x face (it turns and slides)."""
    scene = _box_scene(mu)
    sim.build(scene)
    contact = scene.initial_pose.to_world(np.array([-0.04, 0.012]))
    normal = (math.cos(0.3), math.sin(0.3))
    return push(sim, contact_push(contact, normal, 0.03, speed, 0.005))


@pytest.mark.parametrize("mu, speed", [(0.1, 0.4), (1.0, 0.04)])
def test_a_traced_push_is_the_untraced_push(sim, mu, speed):
    """With `floor_friction=model` a chunk of steps is one compiled call (mujoco_steps);
    traced, every step is its own call. The same push to the bit: nothing the loop carries
    from step to step (pusher path, touch flag, friction state) is lost between calls."""
    plain = _box_push(sim, mu, speed)
    assert plain.ok and plain.contact_made and abs(plain.true_rotation_deg) > 1.0
    sim.trace = []
    try:
        traced = _box_push(sim, mu, speed)
        assert len(sim.trace) == traced.steps
        assert sim.trace[-1] == sim.object_state()
    finally:
        sim.trace = None
    assert traced == plain


def test_the_compiled_loop_calls_libmujoco_without_making_it_global(sim):
    """mujoco_steps binds mj_step and mju_quat2Mat by address (llvm.add_symbol) to the
    library the bindings loaded, and leaves the process's global symbol scope as it was: a
    library loaded later cannot bind to libmujoco's symbols through it."""
    import ctypes

    from llvmlite import binding as llvm

    from comexp.backends import mujoco_steps

    assert _box_push(sim, 0.5, 0.4).contact_made  # the compiled loop ran
    lib = ctypes.CDLL(mujoco_steps._libmujoco())
    for name in mujoco_steps._C_FUNCTIONS:
        own = ctypes.cast(getattr(lib, name), ctypes.c_void_p).value
        assert llvm.address_of_symbol(name) == own
        with pytest.raises(AttributeError):
            getattr(ctypes.CDLL(None), name)


def test_recording_the_friction_inputs_changes_nothing(sim, monkeypatch):
    """`FootprintFriction.inputs` (bench/step_cost.py's replay) gets one row per step the
    engine takes and leaves the push as it was; the still steps it jumps compute none."""
    plain = _box_push(sim, 0.5, 0.4)
    rows: list = []
    real_build = sim.build

    def build(scene):
        rows.clear()
        real_build(scene)
        sim._fric.inputs = rows

    monkeypatch.setattr(sim, "build", build)
    recorded = _box_push(sim, 0.5, 0.4)
    assert recorded == plain
    assert 0 < len(rows) < recorded.steps  # the approach and the retract jumped
    assert any(p for *_, p in rows) and not all(p for *_, p in rows)  # touched, then not
    monkeypatch.setattr(sim, "still_jumps", None)  # every step stepped
    stepped = _box_push(sim, 0.5, 0.4)
    assert len(rows) == stepped.steps == recorded.steps


def test_the_touch_sensor_reads_the_contact_list(sim):
    """The compiled loop knows the pusher touches from a contact sensor; after every step of
    a push it says what MuJoCo's contact list says: a pusher contact at negative distance."""
    scene = _box_scene(0.3)
    sim.build(scene)
    m, d = sim.model, sim.data
    pusher = m.geom("pusher").id
    contact = scene.initial_pose.to_world(np.array([-0.04, 0.012]))
    n = np.array([math.cos(0.3), math.sin(0.3)])
    start = contact - n * 0.007
    sim.place_pusher(start)
    seen = set()
    for k in range(1, 120):  # 2 mm to the face, then 1.7 cm into it, at 0.16 m/s
        sim.advance((start + n * 1.6e-4 * k)[None, :])
        g, dist = d.contact.geom[: d.ncon], d.contact.dist[: d.ncon]
        listed = bool(np.any(((g[:, 0] == pusher) | (g[:, 1] == pusher)) & (dist < 0)))
        assert sim._pusher_touching() == listed, k
        seen.add(listed)
    assert seen == {False, True}


@pytest.mark.parametrize("floor_friction", ["model", "native"])
def test_a_build_is_the_settle_at_its_pose(floor_friction):
    """A build places the object's settled state (settled once per model at the origin, yaw
    0) at the scene's pose: what settling there gives, to rounding, at any pose and yaw, on an
    anisotropic floor too; the settle is not trivial (the object sinks into its supports)."""
    from dataclasses import replace

    sim = mujoco_sim.MujocoSimulator(floor_friction=floor_friction)
    try:
        scene = replace(_box_scene(1.0), floor=FloorSpec(0.3, 0.9))
        for pose in (Pose2D(0.0, 0.0, 0.0), Pose2D(0.03, -0.02, 0.7), Pose2D(-0.1, 0.05, -2.9)):
            sim.build(replace(scene, initial_pose=pose))
            m, d = sim.model, sim.data
            q, v = sim._obj_qadr, sim._obj_vadr
            built = d.qpos[q : q + 7].copy(), d.qvel[v : v + 6].copy()
            mujoco = mujoco_sim.mujoco  # the steps a build took before: settle at the pose
            mujoco.mj_resetData(m, d)
            d.qpos[q : q + 3] = (pose.x_m, pose.y_m, 0.0)
            d.qpos[q + 3 : q + 7] = (math.cos(pose.yaw_rad / 2), 0, 0, math.sin(pose.yaw_rad / 2))
            sim._set_pusher(mujoco_sim._PARK_XY_M, (0.0, 0.0))
            mujoco.mj_forward(m, d)
            mujoco.mj_step(m, d, round(sim.contact.build_settle_s / sim.settings.timestep_s))
            assert d.qpos[q + 2] < -1e-7  # sunk into the supports' soft contacts (0.28 um)
            assert np.abs(built[0] - d.qpos[q : q + 7]).max() < 1e-12
            assert np.abs(built[1] - d.qvel[v : v + 6]).max() < 1e-14  # it sinks at 1e-11 m/s
    finally:
        sim.close()


class _OneChunkAtATime(mujoco_sim.MujocoSimulator):
    """MuJoCo not running chunks in one call: the protocol runs and checks one per call."""

    def runs_chunks(self) -> bool:
        return False


@pytest.fixture(scope="module")
def batched_and_one_by_one():
    sims = mujoco_sim.MujocoSimulator(), _OneChunkAtATime()
    yield sims
    for s in sims:
        s.close()


@pytest.mark.parametrize("case", sorted(BATCH_CASES))
@pytest.mark.parametrize("every", [1, 3])
def test_chunks_run_in_one_call_report_what_chunks_run_one_by_one(
    batched_and_one_by_one, case, every
):
    """MuJoCo runs the protocol's chunks up to the next frame it renders (or until its stop
    rule: near rest, near the view's edge, tilted, a warning) in one compiled call
    (`push_chunks`), past the due frames the tracker declines; the outcome (its largest tilt
    too), the frames, the still times and the state after are those of one chunk per call,
    to the bit."""
    batched, one_by_one = batched_and_one_by_one
    floor, pose, start, speed, length = BATCH_CASES[case]
    obj = box_object(0.08, 0.05, 0.03, com_m=(0.01, -0.005), mu_pusher=0.5)
    cmd = contact_push(start, (1.0, 0.0), length, speed, 0.005)
    calls, below = [], []

    def run_chunks(*args):
        calls.append(type(batched).advance_chunks(batched, *args))
        # the last chunk's tilt covers the state's (as it does every passed chunk's)
        below.append(calls[-1][-1][1] < batched.object_state().tilt_deg)
        return calls[-1]

    batched.advance_chunks = run_chunks
    try:
        a = push_on_view(batched, floor, obj, Pose2D(*pose), cmd, True, every)
    finally:
        del batched.advance_chunks
    b = push_on_view(one_by_one, floor, obj, Pose2D(*pose), cmd, True, every)
    assert a == b
    assert not any(below)
    assert max(len(c) for c in calls) >= (5 if every > 1 else 3)  # chunks ran in one call
    assert a[0].max_tilt_deg > 0.0  # an engine's object is never exactly flat
    if case == "out of view":
        assert a[0].status is PushStatus.LEFT_VIEW


def test_a_tipping_block_s_chunks_run_in_one_call_as_one_by_one(batched_and_one_by_one):
    """Near the tipping onset the block pitches and settles back (chunks pass with their
    tilt), a tall one tips over at 40 cm/s: the batch stops once the tilt is half way to the
    protocol's limit, and the outcome and state are those of one chunk per call."""
    batched, one_by_one = batched_and_one_by_one
    d = pusher_contact_height_m(PusherSpec(), 0.02) - 0.0005
    block = box_object(0.03, 0.03, 0.02, com_m=(0.015 - d, 0.0), mu_pusher=0.5)
    cmd = contact_push((-0.015, 0.0), (1.0, 0.0), 0.03, 0.4, 0.005)
    floor, pose = FloorSpec(1.0, 1.0), Pose2D(0.0, 0.0, 0.0)
    a = push_on_view(batched, floor, block, pose, cmd, True)
    assert a == push_on_view(one_by_one, floor, block, pose, cmd, True)
    assert a[0].max_tilt_deg > 0.5
    tall = box_object(0.02, 0.02, 0.12, mu_pusher=1.0)  # the contract's (tests/test_contract.py)
    cmd = contact_push((-0.01, 0.0), (1.0, 0.0), 0.03, 0.4, 0.005)
    a = push_on_view(batched, floor, tall, pose, cmd, True)
    assert a == push_on_view(one_by_one, floor, tall, pose, cmd, True)
    assert a[0].status is PushStatus.TIPPED


def test_a_batch_stops_at_each_of_its_rules(batched_and_one_by_one):
    """The compiled stop rule on a built scene at rest (`mujoco_steps._stops`, the protocol's
    `stop_rule.chunk_stops` on MuJoCo's state): nothing stops it but the rest rule where it
    is asked; a coordinate not finite, one unstable warning more than at the build, a tilt
    past the cosine, the origin outside the box each stop it."""
    from comexp.backends.mujoco_steps import _stops

    sim = batched_and_one_by_one[0]
    sim.build(SceneSpec(FloorSpec(0.5, 0.5), box_object(0.08, 0.05, 0.03, com_m=(0.01, 0.0))))
    qpos, qvel = sim.data.qpos.copy(), sim.data.qvel.copy()
    warnings = sim._warning_numbers.copy()
    index = mujoco_sim._UNSTABLE_WARNING_INDEX
    rule = np.array((-1.0, 1.0, -1.0, 1.0, 1e-3, 1e-3))
    tilt = math.cos(math.radians(7.5))

    def stops(qpos=qpos, qvel=qvel, min_cos=1.0, rule=rule, rest=False, warnings=warnings):
        return _stops(qpos, qvel, sim._obj_qadr, sim._obj_vadr, min_cos, tilt, rule, rest,
                      warnings, index, sim._warnings0, np.empty(9))  # fmt: skip

    assert not stops() and stops(rest=True)
    moving = qvel.copy()
    moving[sim._obj_vadr + 5] = 0.01  # spinning about its own z: not near rest
    assert not stops(qvel=moving, rest=True)
    for arr, i in ((qpos, sim._obj_qadr + 4), (qvel, sim._obj_vadr + 1)):
        bad = arr.copy()
        bad[i] = math.nan
        assert stops(**{"qpos" if arr is qpos else "qvel": bad})
    warned = warnings.copy()
    warned[index[-1]] += 1
    assert stops(warnings=warned)
    assert stops(min_cos=math.cos(math.radians(8.0)))
    assert stops(rule=np.array((0.5, 1.0, *rule[2:])))
