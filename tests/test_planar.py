"""The planar reference model's own checks: pressure, stiction, convergence, speed of a step.

The shared physics contract (tests/test_contract.py) holds every backend to closed forms; these
tests check the pieces of the reference itself that the contract cannot see.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from physics_helpers import BATCH_CASES, push_on_view

from comexp.backends.floor_friction import WinklerPressure, footprint_samples
from comexp.backends.physics_settings import FrictionSettings, SlowSteps
from comexp.backends.planar_sim import PlanarSimulator
from comexp.method.frames import Pose2D
from comexp.sim.bodies import box_object, prism_object
from comexp.sim.contact import contact_push, pusher_contact_height_m
from comexp.sim.protocol import push
from comexp.sim.scene import GRAVITY_M_S2, FloorSpec, PusherSpec, PushStatus, SceneSpec, SimSettings

RECT = np.array([(-0.04, -0.025), (0.04, -0.025), (0.04, 0.025), (-0.04, 0.025)])


def test_samples_carry_the_polygons_area_and_centroid():
    tri = np.array([(-0.03, -0.02), (0.05, -0.01), (-0.01, 0.04)])
    for poly in (RECT, tri):
        pts, a = footprint_samples(poly, 300)
        import shapely

        ref = shapely.Polygon(poly)
        assert a.sum() == pytest.approx(ref.area, rel=1e-9)
        c = (a @ pts) / a.sum()
        assert c == pytest.approx(np.asarray(ref.centroid.coords[0]), abs=1e-9)


@pytest.mark.parametrize("c", [(0.0, 0.0), (0.01, -0.005), (0.03, 0.0), (-0.035, 0.02)])
def test_winkler_pressure_puts_its_centre_where_asked_and_pulls_nowhere(c):
    pts, a = footprint_samples(RECT, 400)
    com = np.array([0.005, -0.003])
    W = 1.962
    f = WinklerPressure(pts - com, a, W).forces(np.asarray(c, dtype=float))
    assert np.all(f >= 0.0)
    assert f.sum() == pytest.approx(W, rel=1e-9)
    assert (f @ (pts - com)) / W == pytest.approx(np.asarray(c), abs=1e-9)


def test_winkler_pressure_is_linear_inside_the_kern():
    """Inside the kern (a rhombus of half-diagonals L/6 for a rectangle) no sample is clipped
    and the pressure is exactly linear; beyond it part of the footprint carries nothing."""
    pts, a = footprint_samples(RECT, 400)
    W = 1.0
    inside = WinklerPressure(pts, a, W).forces(np.array([0.08 / 6 * 0.9, 0.0])) / a
    assert np.all(inside > 0)
    fit = np.polyfit(pts[:, 0], inside, 1)
    assert np.allclose(np.polyval(fit, pts[:, 0]), inside, rtol=1e-9)
    beyond = WinklerPressure(pts, a, W).forces(np.array([0.08 / 6 * 1.5, 0.0]))
    assert np.any(beyond == 0.0)


def _pushed_box(sim, mu, speed, lever=0.01, com=(0.0, 0.0)):
    scene = SceneSpec(FloorSpec(mu, mu), box_object(0.08, 0.05, 0.015, com_m=com, mu_pusher=0.5))
    sim.build(scene)
    return push(sim, contact_push((-0.04, lever), (1.0, 0.0), 0.03, speed, 0.005))


def test_an_object_at_rest_stays_exactly_at_rest():
    """Stiction without creep or chatter: once the friction can hold the object, its velocity
    is exactly zero and its pose does not move over a further second."""
    sim = PlanarSimulator()
    out = _pushed_box(sim, 1.0, 0.04)
    assert out.status is PushStatus.OK
    st0 = sim.object_state()
    sim.step(1.0)
    st1 = sim.object_state()
    assert st1.position_m == st0.position_m and st1.yaw_rad == st0.yaw_rad
    assert st1.linear_velocity_m_s == (0.0, 0.0, 0.0)
    assert st1.angular_velocity_rad_s == (0.0, 0.0, 0.0)


def test_a_slide_stops_without_reversing():
    """Backward-Euler friction: the speed falls to zero and stays there (no sign flip)."""
    sim = PlanarSimulator()
    sim.build(SceneSpec(FloorSpec(1.0, 1.0), box_object(0.08, 0.05, 0.015)))
    sim.set_object_velocity((0.2, 0.0, 0.0), (0.0, 0.0, 0.0))
    vs = []
    for _ in range(60):
        sim.step(0.001)
        vs.append(sim.object_state().linear_velocity_m_s[0])
    assert min(vs) >= 0.0
    assert vs[-1] == 0.0
    # stop time of a uniform deceleration mu g from 0.2 m/s: 20.4 ms, to a step
    t_stop = (next(i for i, v in enumerate(vs) if v == 0.0) + 1) * 1e-3
    assert t_stop == pytest.approx(0.2 / 9.81, abs=1.5e-3)


@pytest.mark.parametrize("speed", [0.4, 0.04])
def test_rotation_converges_in_the_grid_and_the_timestep(speed):
    """The reference's numerical settings are converged: 4x the samples, half the step or a
    step for each of the protocol's where the motion is slow (`SlowSteps` off) move a 1 cm
    lever-arm push's rotation by < 1% (mu 0.1 floor: the longest slides)."""
    base = PlanarSimulator()
    ref = _pushed_box(base, 0.1, speed).rotation_deg
    fine = PlanarSimulator(planar=replace(FrictionSettings(), samples=1600))
    rot_fine = _pushed_box(fine, 0.1, speed).rotation_deg
    half = PlanarSimulator(settings=replace(SimSettings(), timestep_s=0.0005))
    rot_half = _pushed_box(half, 0.1, speed).rotation_deg
    every = PlanarSimulator(slow_steps=replace(SlowSteps(), steps=1))
    rot_every = _pushed_box(every, 0.1, speed).rotation_deg
    assert abs(ref) > 5.0
    assert rot_fine == pytest.approx(ref, rel=0.01), (ref, rot_fine)
    assert rot_half == pytest.approx(ref, rel=0.01), (ref, rot_half)
    assert rot_every == pytest.approx(ref, rel=0.01), (ref, rot_every)


def test_centre_of_pressure_moves_forward_by_mu_h_over_2_while_sliding():
    """A free slide on mu 1: the friction at the floor, the inertia at h/2: the pressure centre
    sits mu h / 2 ahead of the CoM (7.5 mm for a 1.5 cm prism)."""
    sim = PlanarSimulator()
    sim.build(SceneSpec(FloorSpec(1.0, 1.0), box_object(0.08, 0.05, 0.015)))
    sim.set_object_velocity((0.3, 0.0, 0.0), (0.0, 0.0, 0.0))
    sim.step(0.005)
    cop = sim._model.fr.cop
    assert cop[0] == pytest.approx(1.0 * 0.015 / 2, rel=0.01)
    assert abs(cop[1]) < 1e-6


def test_sustained_push_that_would_tip_reports_tipped():
    """A narrow tall block pushed on mu 1 at 3.2 cm height tips (mu z_p > half-width)."""
    sim = PlanarSimulator()
    tall = prism_object(
        "tall", [(-0.01, -0.01), (0.01, -0.01), (0.01, 0.01), (-0.01, 0.01)], 0.12, (0, 0)
    )
    sim.build(SceneSpec(FloorSpec(1.0, 1.0), tall))
    out = push(sim, contact_push((-0.01, 0.0), (1.0, 0.0), 0.03, 0.04, 0.005))
    assert out.status is PushStatus.TIPPED


def _block_pushed_through_its_com(d_m: float, speed: float, length_m: float = 0.03):
    """A 3 x 3 x 2 cm block on mu 1, its CoM d behind the leading edge, pushed along +x
    through the CoM; the push's outcome, the simulator and every step's tilt (deg)."""
    sim = PlanarSimulator()
    block = box_object(0.03, 0.03, 0.02, com_m=(0.015 - d_m, 0.0), mu_pusher=0.5)
    sim.build(SceneSpec(FloorSpec(1.0, 1.0), block))
    sim.trace = []
    out = push(sim, contact_push((-0.015, 0.0), (1.0, 0.0), length_m, speed, 0.005))
    tilts = np.array([s.tilt_deg for s in sim.trace])
    sim.trace = None
    return out, sim, block, tilts


def test_past_the_onset_a_block_pitches_about_its_leading_edge_as_the_moment_balance_says():
    """Quasi-static (4 cm/s) on mu 1 the pusher's force mu m g acts at z_p, normal to the
    face: with the CoM d = mu z_p - delta behind the leading edge and the face D behind it,
    the pitch about that edge follows, for small angles,
    I_e theta'' = m g (delta - (mu D - h) theta): from rest at 0 it swings to
    2 delta / (mu D - h) in pi / k, k = sqrt(m g (mu D - h) / I_e)."""
    delta_m, lean_m, h = 0.0005, 0.03, 0.01
    z_p = pusher_contact_height_m(PusherSpec(), 0.02)
    d = z_p - delta_m
    out, _, block, tilts = _block_pushed_through_its_com(d, 0.04)
    assert out.status is PushStatus.OK
    i_e = block.iyy_kg_m2 + block.mass_kg * (d**2 + h**2)
    k = math.sqrt(block.mass_kg * GRAVITY_M_S2 * (lean_m - h) / i_e)
    onset = int(np.flatnonzero(tilts > 0)[0])
    swing = tilts[onset : onset + int(2 * math.pi / k / 1e-3)]
    # measured 2.907 deg at 124 ms against 2.865 deg at 126.6 ms (the small-angle form; the
    # onset falls in a 5 ms slow step)
    assert swing.max() == pytest.approx(math.degrees(2 * delta_m / (lean_m - h)), rel=0.03)
    assert (int(np.argmax(swing)) + 1) * 1e-3 == pytest.approx(math.pi / k, abs=3e-3)


def test_short_of_the_onset_a_block_stays_flat():
    """mu z_p 0.5 mm short of the CoM's distance to the edge: the floor holds it flat."""
    z_p = pusher_contact_height_m(PusherSpec(), 0.02)
    out, _, _, tilts = _block_pushed_through_its_com(z_p + 0.0005, 0.04)
    assert out.status is PushStatus.OK and tilts.max() == 0.0 and out.max_tilt_deg == 0.0


def test_a_pitched_block_lands_back_flat_and_at_rest():
    """Past the onset by 1 mm for a 3 cm push at 40 cm/s: it pitches several degrees (short
    of the 15 deg limit; measured 8.7), and once the push ends and the slide stops its weight
    sets it back flat (a plastic landing)."""
    z_p = pusher_contact_height_m(PusherSpec(), 0.02)
    out, sim, _, tilts = _block_pushed_through_its_com(z_p - 0.001, 0.4)
    assert out.status is PushStatus.OK and 0.5 < out.max_tilt_deg < 15.0
    assert out.max_tilt_deg == pytest.approx(tilts.max())
    for _ in range(200):
        sim.step(0.005)
    st = sim.object_state()
    assert st.tilt_deg == 0.0 and st.angular_velocity_rad_s == (0.0, 0.0, 0.0)


def test_the_same_episode_gives_the_same_numbers():
    a = _pushed_box(PlanarSimulator(), 0.1, 0.4)
    b = _pushed_box(PlanarSimulator(), 0.1, 0.4)
    assert a == b


def test_a_rebuilt_scene_is_a_new_one_to_the_bit():
    """`build` of the same object, floor and pusher at another pose (an episode re-centring
    its object) resets the last model instead of making one: what then happens is what
    happens on a new simulator, step by step. The first push is sustained on an anisotropic
    floor and leaves the friction's caches and warm starts set."""
    obj = box_object(0.08, 0.05, 0.015, com_m=(0.01, -0.005), mu_pusher=1.0)
    scene = SceneSpec(FloorSpec(0.2, 1.0), obj)
    again = replace(scene, initial_pose=Pose2D(0.02, -0.01, 0.7))
    second = contact_push((-0.04, 0.012), (1.0, 0.0), 0.02, 0.04, 0.005)

    used = PlanarSimulator()
    used.build(scene)
    first = push(used, contact_push((-0.04, 0.008), (1.0, 0.0), 0.03, 0.04, 0.005))
    assert first.ok and abs(first.rotation_deg) > 0.1
    model = used._model
    used.build(again)
    assert used._model is model  # reset, not made anew
    fresh = PlanarSimulator()
    fresh.build(again)
    a, b = used._model, fresh._model
    for state in ("ms", "fr.fs", "fr.normal", "fr.dxw", "fr.dyw", "geo.poly"):
        owner, _, name = state.rpartition(".")
        np.testing.assert_array_equal(
            getattr(getattr(a, owner) if owner else a, name),
            getattr(getattr(b, owner) if owner else b, name),
            err_msg=state,
        )
    used.trace, fresh.trace = [], []
    assert push(used, second) == push(fresh, second)
    assert used.trace == fresh.trace and len(used.trace) > 100


def test_the_object_state_is_the_model_s_at_every_read():
    """`object_state` is made once per state of the model (the protocol asks again between
    steps), and is the model's after whatever changed it: a velocity set, steps, a rebuilt
    scene (a reset model: the same object), the model's arrays written directly."""
    from comexp.backends.planar_sim import XI_W, _model_tilt, _object_state

    def made(sim: PlanarSimulator):
        m = sim._model
        st = m.ms[: XI_W + 1].tolist()
        return _object_state(m.com_xy, st[:2], st[2], st[3:], _model_tilt(m))

    obj = box_object(0.08, 0.05, 0.015, com_m=(0.01, -0.005), mu_pusher=0.5)
    scene = SceneSpec(FloorSpec(0.3, 0.3), obj, initial_pose=Pose2D(0.01, 0.0, 0.2))
    sim = PlanarSimulator()
    sim.build(scene)
    first = sim.object_state()
    assert sim.object_state() is first and first == made(sim)
    sim.set_object_velocity((0.05, 0.0, 0.0), (0.0, 0.0, 1.0))
    assert sim.object_state() == made(sim) != first
    assert sim.object_state().angular_velocity_rad_s[2] == 1.0
    sim.advance(np.repeat(np.array([[0.5, 0.5]]), 10, axis=0))  # steps, pusher far away
    assert sim.object_state() == made(sim) and sim.object_state().pose != first.pose
    sim.build(replace(scene, initial_pose=Pose2D(0.01, 0.0, 0.2)))  # reset to the start
    assert sim.object_state() == first
    sim._model.ms[1] += 0.01  # the CoM's y, written directly
    assert sim.object_state() == made(sim) != first


def test_rendered_pose_matches_the_state():
    """The camera is the exact ray-cast of the prism at the model's pose."""
    from comexp.method.observation import observe

    sim = PlanarSimulator()
    out = _pushed_box(sim, 0.1, 0.4)
    assert out.ok
    obs = observe(sim.render_depth())
    pose = sim.object_state().pose
    centre = obs.points_m.mean(axis=0)
    assert math.hypot(centre[0] - pose.x_m, centre[1] - pose.y_m) < 1e-3


@pytest.mark.parametrize("slow_steps", [1, SlowSteps().steps])
def test_a_traced_push_is_the_untraced_push(slow_steps):
    """`advance` runs the steps in one compiled call; with a trace it records every model
    step's state, and the push it traces is the same push. With slow steps off that is one
    state per protocol step; on, the slow tail of the slide takes fewer."""
    slow = replace(SlowSteps(), steps=slow_steps)
    plain = _pushed_box(PlanarSimulator(slow_steps=slow), 0.1, 0.4)
    sim = PlanarSimulator(slow_steps=slow)
    sim.trace = []
    traced = _pushed_box(sim, 0.1, 0.4)
    assert traced == plain
    if slow_steps == 1:
        assert len(sim.trace) == traced.steps
    else:
        assert traced.steps / 2 < len(sim.trace) < traced.steps
    assert sim.trace[-1] == sim.object_state()
    yaws = [st.yaw_rad for st in sim.trace]
    assert yaws[0] == 0.0 and abs(yaws[-1]) > 0.05  # it turned, step by step


def test_engine_friction_impulse_holds_and_then_slides():
    """`FootprintFriction.impulse` (the engines' floor friction): a slow twist is cancelled
    exactly (static friction); a fast slide loses mu m g dt of momentum per step and moves the
    pressure centre forward."""
    from comexp.backends.floor_friction import FootprintFriction
    from comexp.sim.scene import PusherSpec

    obj = box_object(0.08, 0.05, 0.015)
    fr = FootprintFriction(obj, 0.5, 0.5, PusherSpec())
    slow = np.array([1e-4, 0.0, 1e-3])
    assert np.array_equal(fr.impulse(slow, 0.3, 1e-3, False), -fr.M * slow)
    fr = FootprintFriction(obj, 0.5, 0.5, PusherSpec())  # the weight's pressure again
    fast = np.array([0.3, 0.0, 0.0])
    imp = fr.impulse(fast, 0.0, 1e-3, False)
    assert imp[0] == pytest.approx(-0.5 * obj.mass_kg * 9.81 * 1e-3, rel=1e-6)
    assert abs(imp[1]) < 1e-12 and abs(imp[2]) < 1e-12
    assert fr.cop[0] == pytest.approx(0.5 * 0.015 / 2, rel=1e-6)


def test_impulse_of_a_twist_in_floats_is_the_kernels_to_the_bit():
    """`impulse_of_twist` (pybullet's per-step call, floats in and out) gives the bits of
    `impulse_kernel` on the twist's array, the kernel MuJoCo's compiled loop calls, and leaves
    the same pressure for the next step: at rest, sliding, spinning, pushed."""
    from comexp.backends.floor_friction import FootprintFriction, impulse_kernel
    from comexp.sim.scene import PusherSpec

    obj = box_object(0.08, 0.05, 0.015)
    a, b = (FootprintFriction(obj, 0.6, 0.3, PusherSpec()) for _ in range(2))
    twists = [(1e-4, 0.0, 1e-3, 0.3, False), (0.3, -0.05, 2.0, 0.7, False),
              (0.2, 0.1, -1.5, -2.0, True), (0.0, 0.0, 0.0, 1.0, True)]  # fmt: skip
    for vx, vy, wz, yaw, pushed in twists:
        xi = np.array([vx, vy, wz])
        want = impulse_kernel(a.geo, a.fs, a.normal, a.dxw, a.dyw, xi, yaw, 1e-3, pushed)
        assert b.impulse_of_twist(vx, vy, wz, yaw, 1e-3, pushed) == tuple(want.tolist())
        assert np.array_equal(a.fs, b.fs, equal_nan=True)
        assert np.array_equal(a.normal, b.normal)


def test_kept_samples_are_the_fresh_ones_and_the_callers_own():
    """A rebuild reuses the footprint's samples (`samples_of`): the same numbers as a fresh
    clipping, and a copy each time, so that nothing a caller does reaches the next build."""
    from comexp.backends.floor_friction import samples_of

    pts, a = footprint_samples(RECT, 400)
    p1, a1 = samples_of(RECT, 400)
    assert np.array_equal(p1, pts) and np.array_equal(a1, a)
    p1[:] = 0.0
    p2, _ = samples_of(RECT, 400)
    assert np.array_equal(p2, pts)


class _CheckEveryChunk(PlanarSimulator):
    """planar without `steps_still`: the protocol checks every chunk, as before it existed."""

    def steps_still(self, targets):
        return 0


def _watched_push(sim, speed_m_s: float, lever_m: float):
    obj = box_object(0.08, 0.05, 0.03, com_m=(0.01, -0.005), mu_pusher=0.5)
    sim.build(SceneSpec(FloorSpec(0.3, 0.3), obj))
    cmd = contact_push((-0.04, -0.005 + lever_m), (1.0, 0.0), 0.03, speed_m_s, 0.005)
    frames, still = [], []
    out = push(
        sim,
        cmd,
        on_frame=lambda f: frames.append((f.t_s, f.pusher_xy_m)),
        frame_interval_s=1.0 / 30.0,
        on_still=still.append,
    )
    return out, frames, still


@pytest.mark.parametrize("speed_m_s", [0.04, 0.4])
def test_skipping_still_steps_changes_nothing_the_protocol_reports(speed_m_s):
    """The approach to a resting object, the rest of the hold and the retract run without
    their checks on planar: the outcome, the frames and the still times are those of checking
    every chunk, to the bit."""
    for lever_m in (0.0, 0.012):
        a = _watched_push(PlanarSimulator(), speed_m_s, lever_m)
        b = _watched_push(_CheckEveryChunk(), speed_m_s, lever_m)
        assert a == b
        assert a[2], "the push has still frames (the approach, the hold): the test sees them"


class _OneChunkAtATime(PlanarSimulator):
    """planar not running chunks in one call: the protocol runs and checks one per call."""

    def runs_chunks(self) -> bool:
        return False


@pytest.mark.parametrize("case", sorted(BATCH_CASES))
@pytest.mark.parametrize(("watch", "every"), [(True, 1), (True, 3), (False, 1)])
def test_chunks_run_in_one_call_report_what_chunks_run_one_by_one(case, watch, every):
    """planar runs the protocol's chunks up to the next frame it renders (or until its
    `ChunkStop`: near rest, near the view's edge, tilted) in one compiled call, past the due
    frames the tracker declines; the outcome, the frames, the still times and the state
    after are those of one chunk per call, to the bit."""
    floor, pose, start, speed, length = BATCH_CASES[case]
    obj = box_object(0.08, 0.05, 0.03, com_m=(0.01, -0.005), mu_pusher=0.5)
    cmd = contact_push(start, (1.0, 0.0), length, speed, 0.005)
    batched = PlanarSimulator()
    calls = []
    run_chunks = batched.advance_chunks
    batched.advance_chunks = lambda *a: calls.append(run_chunks(*a)) or calls[-1]
    a = push_on_view(batched, floor, obj, Pose2D(*pose), cmd, watch, every)
    b = push_on_view(_OneChunkAtATime(), floor, obj, Pose2D(*pose), cmd, watch, every)
    assert a == b
    if every > 1:  # past declined frames: longer calls than between two due frames (3.3)
        assert max(len(c) for c in calls) >= 5
    assert max(len(c) for c in calls) >= 3  # chunks did run in one call
    if case == "out of view":
        assert a[0].status is PushStatus.LEFT_VIEW
    if case == "part of a chunk":
        assert math.ceil(cmd.travel_m / (speed * 1e-3) - 1e-9) % 10 != 0


class _StopsEarly(PlanarSimulator):
    """planar running at most two chunks a call: a backend may stop after any chunk (the
    protocol then checks it in full), here right after frames the tracker declined."""

    def advance_chunks(self, targets, chunk, stop):
        return super().advance_chunks(targets[: 2 * chunk], chunk, stop)


def test_a_batch_cut_short_after_a_declined_frame_asks_the_frames_one_by_one_would():
    """The frames a tracker is asked about do not depend on where a batch ends: past a
    declined frame the next one is due a frame interval later (`_passed`), not at the chunk
    where the batch happened to stop. Asked ahead, a frame may turn out still (the object at
    rest there: `on_still`, its answer unused); every other one is a frame one chunk per
    call asks about."""
    obj = box_object(0.08, 0.05, 0.03, com_m=(0.01, -0.005), mu_pusher=0.5)
    cmd = contact_push((-0.045, 0.012), (1.0, 0.0), 0.03, 0.04, 0.005)

    def run_push(sim):
        sim.build(SceneSpec(FloorSpec(0.1, 1.0), obj))
        asked, frames, still = [], [], []

        def wanted(t_s: float, driving: bool) -> bool:
            asked.append(t_s)
            return round(t_s * 30.0) % 4 == 0

        out = push(sim, cmd, lambda f: frames.append(f.t_s), 1 / 30, still.append, wanted)
        return out, frames, still, sorted(set(asked))

    early, one_by_one = run_push(_StopsEarly()), run_push(_OneChunkAtATime())
    assert early[:3] == one_by_one[:3]
    asked, asked_one_by_one, still = set(early[3]), set(one_by_one[3]), set(early[2])
    assert asked_one_by_one <= asked and asked - asked_one_by_one <= still
    assert len(asked_one_by_one) > 10


def test_a_tipping_block_s_chunks_run_in_one_call_as_one_by_one():
    """Past the tipping onset the object pitches, and a tall one tips over: the batch
    stops where the object leaves the floor flat (`ChunkStop`), and the outcome and state
    are those of one chunk per call."""
    d = pusher_contact_height_m(PusherSpec(), 0.02) - 0.0005  # past the onset, as above
    block = box_object(0.03, 0.03, 0.02, com_m=(0.015 - d, 0.0), mu_pusher=0.5)
    cmd = contact_push((-0.015, 0.0), (1.0, 0.0), 0.03, 0.04, 0.005)
    floor, pose = FloorSpec(1.0, 1.0), Pose2D(0.0, 0.0, 0.0)
    a = push_on_view(PlanarSimulator(), floor, block, pose, cmd, True)
    b = push_on_view(_OneChunkAtATime(), floor, block, pose, cmd, True)
    assert a == b and a[0].max_tilt_deg > 2.0
    # and one that tips over (the protocol's TIPPED at the chunk where it passes the limit)
    tall = prism_object("tall", [(-0.01, -0.01), (0.01, -0.01), (0.01, 0.01), (-0.01, 0.01)],
                        0.12, (0, 0))  # fmt: skip
    cmd = contact_push((-0.01, 0.0), (1.0, 0.0), 0.03, 0.04, 0.005)
    for watch in (True, False):
        a = push_on_view(PlanarSimulator(), floor, tall, pose, cmd, watch)
        b = push_on_view(_OneChunkAtATime(), floor, tall, pose, cmd, watch)
        assert a == b and a[0].status is PushStatus.TIPPED


def test_steps_declared_still_that_move_the_object_are_an_error():
    class Liar(PlanarSimulator):
        def steps_still(self, targets):
            return len(targets)  # claims even the steps that push the object

    with pytest.raises(RuntimeError, match="moved in steps declared still"):
        _watched_push(Liar(), 0.4, 0.0)


def _boundary_distance(pts: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Distance of each point (n x 2) from a polygon's boundary (numpy, all at once)."""
    a = poly[None, :, :]
    ab = np.roll(poly, -1, axis=0)[None, :, :] - a
    ap = pts[:, None, :] - a
    t = np.clip(np.sum(ap * ab, axis=2) / np.sum(ab * ab, axis=2), 0.0, 1.0)
    closest = a + t[:, :, None] * ab
    return np.min(np.hypot(*(pts[:, None, :] - closest).transpose(2, 0, 1)), axis=1)


@pytest.mark.parametrize("gap_m", [0.0005, 0.003, 0.012, 0.03])
@pytest.mark.parametrize("yaw", [0.0, 0.7])
def test_still_steps_are_counted_to_the_first_step_within_reach(gap_m, yaw):
    """`steps_still` (compiled, step by step) counts to the first step whose end lies
    closer to the outline than the step is long (plus the margin), as the whole path's
    distances computed at once say, and the whole path when no step comes near; none from a
    start within reach."""
    from comexp.backends.planar_sim import _STILL_MARGIN_M

    sim = PlanarSimulator()
    obj = box_object(0.08, 0.05, 0.03, com_m=(0.01, -0.005), mu_pusher=0.5)
    sim.build(SceneSpec(FloorSpec(0.3, 0.3), obj, initial_pose=Pose2D(0.0, 0.0, yaw)))
    radius = sim._scene.pusher.radius_m
    poly = sim.object_state().pose.to_world(sim.outline_m())
    reach = float(np.max(np.hypot(*poly.T)))  # a start beyond the outline along -x
    start = np.array([-reach - radius - gap_m, 0.0])
    sim.place_pusher(start)
    step_m = 0.04 * sim.settings.timestep_s
    gap = _boundary_distance(start[None, :], poly)[0] - radius
    for travel_m in (gap + 0.01, 0.5 * gap):
        n = math.ceil(travel_m / step_m)
        targets = start + np.minimum(step_m * np.arange(1, n + 1), travel_m)[:, None] * [1.0, 0.0]
        pts = np.concatenate([start[None, :], targets])
        clear = _boundary_distance(targets, poly) - radius
        bad = np.flatnonzero(clear < np.hypot(*np.diff(pts, axis=0).T) + _STILL_MARGIN_M)
        expected = int(bad[0]) if len(bad) else n
        assert sim.steps_still(targets) == expected
        assert (expected < n) == (travel_m > gap)  # reaches the object, or stops short
    inside = np.array(sim.object_state().position_m[:2])  # deep inside: far from the edges
    assert _boundary_distance(inside[None, :], poly)[0] > 3 * radius
    sim.place_pusher(inside)
    assert sim.steps_still(inside + step_m * np.arange(1, 10)[:, None] * [1.0, 0.0]) == 0


def test_a_warm_started_tensionless_pressure_is_the_cold_one():
    """`pressure_kernel` starts the tensionless solve beyond the kern from the last one's
    coefficients: the same convex problem, so the same forces as a cold start, however far
    the last pressure centre was."""
    from comexp.backends.floor_friction import pressure_kernel

    pts, a = footprint_samples(RECT, 400)
    W = 1.962
    wp = WinklerPressure(pts, a, W)
    r = np.hypot(wp._dx, wp._dy)
    args = (wp._dx, wp._dy, a, r, W, wp._m)
    cold, hot = np.empty(len(a)), np.empty(len(a))
    for c_last, c in [((0.025, 0.0), (0.0252, 0.001)), ((-0.03, 0.012), (0.03, -0.012))]:
        warm = np.full(3, np.nan)
        pressure_kernel(*args, *c_last, warm, hot)
        assert not np.isnan(warm).any()  # beyond the kern: a tensionless solution to reuse
        sums = pressure_kernel(*args, *c, np.full(3, np.nan), cold)
        pressure_kernel(*args, *c, warm, hot)
        assert np.any(cold == 0.0)
        assert np.abs(hot - cold).max() <= 1e-9 * W
        # the sums it returns are those of the forces it wrote (the holding limits' inputs)
        assert sums == pytest.approx((cold.sum(), (cold * r).sum()), rel=1e-12)
    inside = np.full(3, 1.0)
    pressure_kernel(*args, 0.0, 0.0, inside, cold)
    assert np.isnan(inside[0])  # inside the kern: nothing to reuse (the flag)


@pytest.mark.parametrize("speed", [0.04, 0.4])
def test_the_push_solve_converges_to_the_tight_solvers_answer(speed):
    """The constrained solve's start (the incoming twist) and its line search (backtracking to
    the quadratic's minimiser) change the path, not the minimiser: a lever-arm push turns
    within the Newton tolerance's own error of the same push solved to 1e-19 J. Bound: the
    largest default-vs-tight difference on bench/planar_speed.py's 36 lever-arm pushes,
    0.043 deg (l_shape, mu 1, 5 mm, 4 cm/s), with a 50% margin across CPUs; a solver that
    stopped short or converged elsewhere turns by degrees."""
    from comexp.experiment.objects import com_point, load_objects

    od = load_objects(["l_shape"])["l_shape"]
    spec = od.model(com_point(od, 0), izz_scale=1.0, mu_pusher=0.5)
    scene = SceneSpec(FloorSpec(1.0, 1.0), spec)
    x0 = np.asarray(spec.outline_m)[:, 0].min()
    cmd = contact_push((x0, spec.com_m[1] + 0.005), (1.0, 0.0), 0.03, speed, 0.005)
    turns = []
    for planar in (FrictionSettings(), FrictionSettings(newton_tol=1e-19, max_newton=200)):
        sim = PlanarSimulator(planar=planar)
        sim.build(scene)
        out = push(sim, cmd)
        assert out.status == PushStatus.OK
        turns.append(out.rotation_deg)
    assert abs(turns[0]) > 5.0
    assert turns[0] == pytest.approx(turns[1], abs=0.065)


def _free_solve_first(geo, normal, xi_hat, dxw, dyw, dt, con, vq, mu_p, lam0):
    """`_solve_with_pusher` as it was before `planar-9`: the free solve always first, the
    plane's solve (`_plane_solve`) only when the free one would leave the pusher inside."""
    from comexp.backends.floor_friction import minimise_kernel
    from comexp.backends.planar_sim import _plane_solve

    nx, ny, rx, ry, gap = con
    a = np.array([nx, ny, rx * ny - ry * nx])
    b = (vq[0] * nx + vq[1] * ny) - max(gap, 0.0) / dt
    tau = np.array([-ny, nx, rx * nx + ry * ny])
    r0 = -vq[0] * ny + vq[1] * nx
    free, _ = minimise_kernel(
        xi_hat, xi_hat, geo.M, normal, dxw, dyw, geo.mu_x, geo.mu_y, dt, geo.eps, 0.0, tau, 0.0,
        True, a, b, False, geo.tol, geo.itmax,
    )  # fmt: skip
    if a @ free >= b:
        return free, 0.0, 0.0, False
    xi, lam, t_imp = _plane_solve(geo, normal, True, xi_hat, dxw, dyw, dt, a, b, tau, r0, mu_p,
                                  lam0)  # fmt: skip
    return xi, lam, t_imp, True


def test_the_plane_first_solve_makes_the_free_first_solve_s_choices():
    """`planar-9` solves a sustained push on the contact plane first and skips the free solve
    only when the frictionless plane's multiplier proves the free minimiser infeasible: bit
    for bit the old order's answers, on random sustained pushes (two anisotropic floors and
    an isotropic one, pusher mu 1, 1 and 5 ms steps). The sweep holds pushes the pusher's
    friction alone holds (the plane's solve pushes, the free solve separates), where skipping
    on the plane's push alone answers otherwise."""
    from comexp.backends.floor_friction import offsets_kernel
    from comexp.backends.planar_sim import PlanarModel, _plane_solve, _solve_with_pusher

    rng = np.random.default_rng(0)
    held_by_friction = 0
    obj = box_object(0.08, 0.05, 0.02, com_m=(0.01, -0.005), mu_pusher=1.0)
    for mu_x, mu_y in ((0.1, 1.0), (1.0, 0.1), (0.3, 0.3)):
        m = PlanarModel(obj, mu_x, mu_y, FrictionSettings(), PusherSpec())
        fr, geo = m.fr, m.fr.geo
        for k in range(3000):
            offsets_kernel(geo, fr.fs, rng.uniform(-math.pi, math.pi), fr.dxw, fr.dyw)
            th = rng.uniform(0.0, 2.0 * math.pi)
            nx, ny = math.cos(th), math.sin(th)
            rx, ry = -0.04 * nx + rng.normal(scale=0.02), -0.04 * ny + rng.normal(scale=0.02)
            con = (nx, ny, rx, ry, 0.0)
            v = rng.uniform(0.005, 0.05)
            xi_hat = np.array([v * nx, v * ny, 0.0]) + rng.normal(scale=(0.01, 0.01, 0.5))
            vq = (v + rng.normal(scale=0.01)) * np.array([nx, ny]) + rng.normal(scale=0.01, size=2)
            dt = 0.005 if k % 2 else 0.001
            lam0 = 10.0 ** rng.uniform(-6.0, -2.0)
            args = (geo, fr.normal, xi_hat, fr.dxw, fr.dyw, dt, con, vq, 1.0, lam0)
            *want, pushed = _free_solve_first(*args)
            got = _solve_with_pusher(geo, fr.normal, True, xi_hat, fr.dxw, fr.dyw, dt, con,
                                     float(vq[0]), float(vq[1]), 1.0, lam0)  # fmt: skip
            np.testing.assert_array_equal(got[0], want[0])
            assert got[1:] == tuple(want[1:])
            if not pushed:
                a = np.array([nx, ny, rx * ny - ry * nx])
                tau = np.array([-ny, nx, rx * nx + ry * ny])
                b, r0 = vq[0] * nx + vq[1] * ny, -vq[0] * ny + vq[1] * nx
                plane = _plane_solve(geo, fr.normal, True, xi_hat, fr.dxw, fr.dyw, dt, a, b,
                                     tau, r0, 1.0, lam0)  # fmt: skip
                held_by_friction += plane[1] > 0.0
    assert held_by_friction >= 3  # 8 with this seed


@pytest.mark.parametrize("com_x_m", [0.0499, 0.05, 0.06])
def test_a_com_beyond_the_footprint_is_refused_at_build(com_x_m):
    """A CoM on or past the outline's edge (a forward-model fit's candidate, a user's CoM)
    has no pressure that holds the object up: the build refuses it in one line instead of
    the pressure centre's search stepping towards it for ever (a replay ran for minutes)."""
    sim = PlanarSimulator()
    scene = SceneSpec(FloorSpec(0.3, 0.3), box_object(0.1, 0.06, 0.02, com_m=(com_x_m, 0.0)))
    with pytest.raises(ValueError, match="not inside the footprint's support"):
        sim.build(scene)
    sim.build(replace(scene, obj=box_object(0.1, 0.06, 0.02, com_m=(0.045, 0.0))))
