"""The physics contract: one module, every backend, physics as the referee.

Closed forms where they exist (mu g deceleration along each floor axis, the elliptic law on
diagonal slides, spin-down under linear pressure centred under the CoM, no turn for a normal
push through the CoM), the planar backend as the truth where they don't (turn magnitudes, the
coupled slide-and-spin of a disc). Every backend passes all of it; a case an engine cannot
pass is marked xfail with its measured value and listed in docs/physics.md (two today:
MuJoCo's quasi-static tipping cases, the block past the onset and the tall block).
"""

from __future__ import annotations

import math
from functools import cache

import numpy as np
import pytest

from comexp.experiment.config import make_simulator
from comexp.experiment.objects import load_objects, object_names
from comexp.method.frames import Pose2D
from comexp.sim.bodies import box_object, prism_object
from comexp.sim.contact import contact_push
from comexp.sim.protocol import push
from comexp.sim.scene import GRAVITY_M_S2, FloorSpec, PushCommand, PushStatus, SceneSpec

BACKENDS = ["planar", "pybullet", "mujoco"]
PUSH_LENGTH_M = 0.03
H_BUILTIN = 0.015  # the built-in objects' height


@pytest.fixture(params=BACKENDS, scope="module")
def sim(request):
    s = make_simulator(request.param)
    yield s
    s.close()


@pytest.fixture(scope="module")
def planar():
    s = make_simulator("planar")
    yield s
    s.close()


def _disc(radius_m=0.05, n=32, com=(0.0, 0.0), height_m=H_BUILTIN, mu_pusher=0.5):
    a = 2 * np.pi * (np.arange(n) + 0.5) / n
    outline = np.stack([radius_m * np.cos(a), radius_m * np.sin(a)], axis=1)
    return prism_object("disc32", outline, height_m, com, mu_pusher=mu_pusher)


# --- sliding -------------------------------------------------------------------------------


def _slide_decel(sim, direction: np.ndarray, v0: float) -> tuple[np.ndarray, float]:
    """Launch at v0 along `direction`, return the mean acceleration vector over the slide
    (fit of velocity vs time while above 20% of v0) and the sideways drift (m)."""
    sim.set_object_velocity((v0 * direction[0], v0 * direction[1], 0.0), (0.0, 0.0, 0.0))
    p0 = np.array(sim.object_state().position_m[:2])
    dt = 0.002
    ts, vs = [], []
    for i in range(2000):
        sim.step(dt)
        v = np.array(sim.object_state().linear_velocity_m_s[:2])
        if float(v @ direction) < 0.2 * v0:
            break
        ts.append((i + 1) * dt)
        vs.append(v)
    ts_a, vs_a = np.array(ts), np.array(vs)
    keep = ts_a > 0.006  # skip the first contact transient of soft engines
    acc = np.array([np.polyfit(ts_a[keep], vs_a[keep, k], 1)[0] for k in range(2)])
    moved = np.array(sim.object_state().position_m[:2]) - p0
    side = float(moved[0] * direction[1] - moved[1] * direction[0])
    return acc, side


@pytest.mark.parametrize(
    "mu_x,mu_y",
    [(0.1, 0.1), (1.0, 1.0), (0.1, 1.0), (1.0, 0.1)],
    ids=["iso0.1", "iso1", "aniso_x0.1", "aniso_x1"],
)
@pytest.mark.parametrize("axis", [0, 1], ids=["x", "y"])
def test_sliding_deceleration_is_mu_g(sim, mu_x, mu_y, axis):
    mu = (mu_x, mu_y)[axis]
    sim.build(SceneSpec(FloorSpec(mu_x, mu_y), box_object(0.08, 0.05, 0.03)))
    sim.step(0.05)
    d = np.eye(2)[axis]
    acc, side = _slide_decel(sim, d, 0.6 if mu >= 1.0 else 0.3)
    decel = -float(acc @ d)
    assert decel == pytest.approx(mu * GRAVITY_M_S2, rel=0.03), f"{sim.name}: {decel:.4f}"
    assert abs(side) < 1e-3


def elliptic_acceleration(mu_x: float, mu_y: float, s: np.ndarray) -> np.ndarray:
    """The elliptic maximum-dissipation law: a = -g A^2 s / |A s|, A = diag(mu_x, mu_y)."""
    A = np.array([mu_x, mu_y])
    return -GRAVITY_M_S2 * A * A * s / float(np.linalg.norm(A * s))


@pytest.mark.parametrize("mu", [(1.0, 1.0), (0.1, 1.0), (1.0, 0.1)], ids=["iso1", "x0.1", "x1"])
@pytest.mark.parametrize("angle_deg", [30, 45, 60])
def test_diagonal_slide_follows_the_elliptic_law(sim, mu, angle_deg):
    """The initial deceleration of a slide at an angle to the floor's axes (the law is
    anisotropic: the deceleration is not along the slide, which then curves)."""
    sim.build(SceneSpec(FloorSpec(*mu), box_object(0.08, 0.05, 0.03)))
    sim.step(0.05)
    s = np.array([math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))])
    sim.set_object_velocity((0.3 * s[0], 0.3 * s[1], 0.0), (0.0, 0.0, 0.0))
    sim.step(0.002)  # past a soft engine's contact transient
    v0 = np.array(sim.object_state().linear_velocity_m_s[:2])
    sim.step(0.004)
    v1 = np.array(sim.object_state().linear_velocity_m_s[:2])
    acc = (v1 - v0) / 0.004
    # the slide curves (the law is anisotropic): compare at the window's mean slip direction
    mid = (v0 + v1) / 2.0
    want = elliptic_acceleration(*mu, mid / float(np.linalg.norm(mid)))
    err = float(np.linalg.norm(acc - want)) / float(np.linalg.norm(want))
    assert err < 0.05, f"{sim.name}: measured {np.round(acc, 3)} vs elliptic {np.round(want, 3)}"


# --- spin-down -----------------------------------------------------------------------------


def closed_form_spin_decel(shape: str, com: tuple[float, float], mu: float) -> float:
    """Angular deceleration (rad/s^2) of a prism spinning about its CoM under linear (Winkler)
    pressure centred under the CoM: mu * integral(p |r - G| dA) / Izz, by fine quadrature."""
    return mu * _spin_moment_per_mu(shape, com)


@cache
def _spin_moment_per_mu(shape: str, com: tuple[float, float]) -> float:
    """integral(p |r - G| dA) / Izz on 40,000 clipped cells (100x the model's samples; the
    clipped cells' quadrature error is O(h^2): 160,000 cells change it by < 2e-5 relative)."""
    from comexp.backends.floor_friction import WinklerPressure, footprint_samples

    obj = _spin_object(shape, com)
    pts, area = footprint_samples(np.asarray(obj.outline_m), 40_000)
    d = pts - np.asarray(obj.com_m)
    normal = WinklerPressure(d, area, obj.mass_kg * GRAVITY_M_S2).forces(np.zeros(2))
    return float(normal @ np.hypot(d[:, 0], d[:, 1])) / obj.izz_kg_m2


def _spin_object(shape: str, com: tuple[float, float]):
    if shape == "disc":
        return _disc(com=com)
    if shape == "square":
        return box_object(0.07, 0.07, H_BUILTIN, com_m=com)
    return box_object(0.08, 0.05, H_BUILTIN, com_m=com)


SPIN_CASES = [
    ("disc", (0.0, 0.0)),
    ("disc", (0.015, -0.01)),
    ("square", (0.0, 0.0)),
    ("square", (0.012, 0.01)),
    ("rect", (0.0, 0.0)),
    ("rect", (0.02, -0.008)),
]


def _spin_about_com(sim, obj, w0: float) -> None:
    st = sim.object_state()
    r = Pose2D(0.0, 0.0, st.yaw_rad).to_world(np.asarray(obj.com_m))
    sim.set_object_velocity((w0 * r[1], -w0 * r[0], 0.0), (0.0, 0.0, w0))


@pytest.mark.parametrize("mu", [0.1, 1.0])
@pytest.mark.parametrize("shape,com", SPIN_CASES, ids=[f"{s}-{c}" for s, c in SPIN_CASES])
def test_spin_down_matches_linear_pressure(sim, shape, com, mu):
    obj = _spin_object(shape, com)
    sim.build(SceneSpec(FloorSpec(mu, mu), obj))
    sim.step(0.05)
    alpha = closed_form_spin_decel(shape, com, mu)
    w0 = 0.03 * alpha  # stops in 30 ms ... 0.3 s
    _spin_about_com(sim, obj, w0)
    dt = 0.001
    ts, ws, t_stop = [], [], None
    for i in range(1, 3000):
        sim.step(dt)
        w = sim.object_state().angular_velocity_rad_s[2]
        if w > 0.2 * w0:
            ts.append(i * dt)
            ws.append(w)
        if abs(w) < 1e-3 * w0:
            t_stop = i * dt
            break
    assert t_stop is not None, f"{sim.name}: never stopped"
    decel = -float(np.polyfit(ts, ws, 1)[0])
    assert decel == pytest.approx(alpha, rel=0.10), f"{sim.name}: {decel:.1f} vs {alpha:.1f}"
    assert t_stop == pytest.approx(w0 / alpha, rel=0.10, abs=2e-3), f"{sim.name}: {t_stop:.3f} s"


def _slide_and_spin(sim, ratio: float, mu: float = 0.5) -> tuple[float, float, float]:
    """A disc launched with v0 and w0 (v0 / (w0 R) = ratio): (t_v, t_w, v/(wR) at the moment
    the speed has dropped to 10% of its start value)."""
    R = 0.05
    obj = _disc(radius_m=R)
    sim.build(SceneSpec(FloorSpec(mu, mu), obj))
    sim.step(0.05)
    v0 = 0.3
    w0 = v0 / (ratio * R)
    sim.set_object_velocity((v0, 0.0, 0.0), (0.0, 0.0, w0))
    dt = 0.001
    t_v = t_w = None
    eps_near = None
    e0 = math.hypot(v0, w0 * R)
    for i in range(1, 5000):
        sim.step(dt)
        st = sim.object_state()
        v = math.hypot(*st.linear_velocity_m_s[:2])
        w = abs(st.angular_velocity_rad_s[2])
        if eps_near is None and math.hypot(v, w * R) < 0.1 * e0:
            eps_near = v / max(w * R, 1e-12)
        if t_v is None and v < 1e-3 * v0:
            t_v = i * dt
        if t_w is None and w < 1e-3 * w0:
            t_w = i * dt
        if t_v is not None and t_w is not None:
            break
    assert t_v is not None and t_w is not None and eps_near is not None
    return t_v, t_w, eps_near


@pytest.mark.parametrize("ratio", [0.3, 1.0, 3.0])
def test_disc_stops_sliding_and_spinning_together(sim, planar, ratio):
    """Farkas et al., PRL 90, 248302 (2003): sliding and spinning of a flat disc end at the
    same moment, v / (w R) tending to a fixed ratio; the engines must follow the planar value."""
    t_v, t_w, eps = _slide_and_spin(sim, ratio)
    assert abs(t_v - t_w) < 0.05 * max(t_v, t_w) + 2e-3, f"{sim.name}: {t_v:.3f} vs {t_w:.3f} s"
    _, _, eps_ref = _slide_and_spin(planar, ratio)
    assert abs(eps - eps_ref) < 0.15, f"{sim.name}: v/(wR) {eps:.3f} vs planar {eps_ref:.3f}"


# --- pushes --------------------------------------------------------------------------------


def _object_push(sim, obj, mu_floor, yaw_rad, contact_obj, normal_obj, speed, shift=0.0):
    """The push at an object-frame contact and inward normal, object at `yaw_rad`; `shift`
    moves the start back along the push by that many metres (the impact moves in time)."""
    pose = Pose2D(0.01, -0.02, yaw_rad)
    sim.build(SceneSpec(FloorSpec(mu_floor, mu_floor), obj, initial_pose=pose))
    n_w = pose.to_world(np.asarray(normal_obj)) - pose.to_world(np.zeros(2))
    cmd = contact_push(pose.to_world(np.asarray(contact_obj)), n_w, PUSH_LENGTH_M, speed, 0.005)
    if shift:
        start = np.asarray(cmd.start_xy_m) - shift * n_w
        cmd = type(cmd)(tuple(start), cmd.direction_xy, cmd.travel_m + shift, cmd.speed_m_s)
    out = push(sim, cmd)
    assert out.status is PushStatus.OK and out.contact_made, out
    return out.rotation_deg


YAWS_DEG = (0.0, 17.0, 45.0, 73.0, 90.0, 128.0, 200.0, 311.0)


def _rect(com_cm=(1.5, 0.8), mu_pusher=0.5):
    return load_objects(["rect_8x5"])["rect_8x5"].model(com_cm, izz_scale=1.0, mu_pusher=mu_pusher)


@pytest.mark.parametrize("speed", [0.4, 0.04], ids=["40cm_s", "4cm_s"])
@pytest.mark.parametrize("mu_floor", [0.1, 1.0])
def test_same_push_at_any_yaw_turns_the_same(sim, mu_floor, speed):
    """The same object-frame push (8x5 cm, CoM (1.5, 0.8) cm, contact 1 cm beside the CoM
    line) at 8 yaws, non-multiples of 45 deg included."""
    obj = _rect()
    contact = (0.015 + 0.01, -0.025)
    rots = [
        _object_push(sim, obj, mu_floor, math.radians(y), contact, (0.0, 1.0), speed)
        for y in YAWS_DEG
    ]
    spread = max(rots) - min(rots)
    assert min(rots) > 0.0, f"{sim.name}: wrong way {np.round(rots, 2)}"
    assert spread < (1.5 if speed > 0.1 else 1.0), f"{sim.name}: {np.round(rots, 2)}"


@pytest.mark.parametrize("mu_floor", [0.1, 1.0])
def test_moment_of_impact_within_a_step_does_not_matter(sim, mu_floor):
    obj = _rect()
    speed = 0.4
    step_m = speed * sim.settings.timestep_s
    rots = [
        _object_push(sim, obj, mu_floor, 0.3, (0.025, -0.025), (0.0, 1.0), speed, f * step_m)
        for f in (0.0, 0.2, 0.4, 0.6, 0.8)
    ]
    assert max(rots) - min(rots) < 1.0, f"{sim.name}: {np.round(rots, 2)}"


def _through_com_contact(outline: np.ndarray, com: np.ndarray):
    """The longest edge whose foot of the perpendicular from the CoM lies well inside it (and
    CoM-foot inside the object): a normal push there has its line through the CoM."""
    import shapely

    poly = shapely.Polygon(outline)
    best = None
    for i in range(len(outline)):
        a, b = outline[i], outline[(i + 1) % len(outline)]
        length = float(np.linalg.norm(b - a))
        t = (b - a) / length
        s = float(np.dot(com - a, t))
        margin = min(0.008, 0.3 * length)
        if not margin < s < length - margin:
            continue
        foot = a + s * t
        inward = np.array([-t[1], t[0]])
        if not poly.buffer(1e-6).contains(shapely.LineString([foot + 1e-4 * inward, com])):
            continue
        if best is None or length > best[0]:
            best = (length, foot, inward)
    return None if best is None else (best[1], best[2])


# 2 CoMs of every built-in object at 2 yaws off the floor's axes; the default suite runs CoM 0
# at yaw 0.3, `-m slow` the rest (so the default suite stays within its time budget)
THROUGH_COM = [
    pytest.param(name, k, yaw, marks=[pytest.mark.slow] if k or yaw < 0 else [])
    for name in object_names()
    for k in range(2)
    for yaw in (0.3, -2.1)
]


def _builtin_spec(name: str, k: int, mu_pusher: float = 1.0):
    from comexp.experiment.objects import com_points

    obj = load_objects([name])[name]
    return obj.model(com_points(obj, 2)[k], izz_scale=1.0, mu_pusher=mu_pusher)


@pytest.mark.parametrize("speed", [0.4, 0.04], ids=["40cm_s", "4cm_s"])
@pytest.mark.parametrize("mu_floor", [0.1, 1.0])
@pytest.mark.parametrize("name,k,yaw", THROUGH_COM)
def test_normal_push_through_the_com_does_not_turn(sim, name, k, yaw, mu_floor, speed):
    """Every built-in object, 2 CoMs, 2 yaws off the floor's axes, a sticky pusher."""
    spec = _builtin_spec(name, k)
    found = _through_com_contact(np.asarray(spec.outline_m), np.asarray(spec.com_m))
    if found is None:
        pytest.skip(f"{name}: no edge with a normal through CoM {k}")
    foot, inward = found
    rot = _object_push(sim, spec, mu_floor, yaw, foot, inward, speed)
    assert abs(rot) < 0.5, f"{sim.name} {name} com {k} yaw {yaw}: {rot:.3f} deg"


LEVER_CASES = [("rect_8x5", 0), ("l_shape", 1), ("hexagon_r5", 0), ("t_shape", 0)]


def _lever_push(sim, name, k, lever_m, mu_floor, speed):
    spec = _builtin_spec(name, k, mu_pusher=0.5)
    found = _through_com_contact(np.asarray(spec.outline_m), np.asarray(spec.com_m))
    foot, inward = found
    along = np.array([inward[1], -inward[0]])  # along the edge: moment (P - G) x N = +lever
    contact = foot + lever_m * along
    return _object_push(sim, spec, mu_floor, 0.3, contact, inward, speed)


@pytest.mark.parametrize("speed", [0.4, 0.04], ids=["40cm_s", "4cm_s"])
@pytest.mark.parametrize("mu_floor", [0.1, 1.0])
@pytest.mark.parametrize("name,k", LEVER_CASES, ids=[f"{n}-{k}" for n, k in LEVER_CASES])
def test_turn_follows_the_torque_and_the_reference(sim, planar, name, k, mu_floor, speed):
    """A lever arm >= 2 mm turns with the torque (CCW for a contact to the right of the line
    through the CoM, looking along the push); >= 5 mm: within 15% (4 cm/s) / 20% (40 cm/s) of
    the planar reference's rotation."""
    for lever in (0.002, -0.002):
        rot = _lever_push(sim, name, k, lever, mu_floor, speed)
        assert rot * math.copysign(1.0, lever) > 0.0, f"{sim.name}: lever {lever}: {rot:.2f}"
    tol = 0.20 if speed > 0.1 else 0.15
    for lever in (0.005, -0.01):
        rot = _lever_push(sim, name, k, lever, mu_floor, speed)
        # the reference's own case: the same deterministic push again would be `rot` itself
        ref = rot if sim.name == "planar" else _lever_push(planar, name, k, lever, mu_floor, speed)
        assert rot == pytest.approx(ref, rel=tol), f"{sim.name}: {rot:.2f} vs planar {ref:.2f}"


@pytest.mark.parametrize("name", ["rect_8x5", "hexagon_r5", "l_shape", "ellipse_12x7"])
def test_a_low_object_neither_lifts_nor_tilts(sim, name):
    """Every step of a 40 cm/s push on mu 1 (lever 1 cm): an object lower than its smallest
    width stays on the floor (lift <= 0.2 mm, tilt <= 0.5 deg)."""
    spec = _builtin_spec(name, 0, mu_pusher=1.0)
    foot, inward = _through_com_contact(np.asarray(spec.outline_m), np.asarray(spec.com_m))
    contact = foot + 0.01 * np.array([inward[1], -inward[0]])
    sim.trace = []
    try:
        _object_push(sim, spec, 1.0, 0.3, contact, inward, 0.4)
        states = sim.trace
    finally:
        sim.trace = None
    assert len(states) > 100
    z0 = 0.0
    lift = max(abs(s.position_m[2] - z0) for s in states)
    tilt = max(s.tilt_deg for s in states)
    assert lift <= 2e-4 and tilt <= 0.5, f"{sim.name}: lift {lift * 1e3:.2f} mm, tilt {tilt:.2f}"


@pytest.mark.parametrize("speed", [0.4, 0.04])
def test_a_tall_object_tips_and_the_push_says_so(sim, speed, request):
    """A 2 x 2 x 12 cm block pushed low on mu 1 (mu z_p 3.2 cm against a 1 cm half width).
    Quasi-static, MuJoCo's capsule keeps it up (measured: `ok`, 0.28 deg), as it keeps every
    block up at 4 cm/s (docs/physics.md, "Tipping")."""
    if sim.name == "mujoco" and speed < 0.1:
        request.applymarker(pytest.mark.xfail(strict=True, reason="measured ok, 0.28 deg"))
    tall = box_object(0.02, 0.02, 0.12, mu_pusher=1.0)
    scene = SceneSpec(FloorSpec(1.0, 1.0), tall)
    sim.build(scene)
    out = push(sim, contact_push((-0.01, 0.0), (1.0, 0.0), PUSH_LENGTH_M, speed, 0.005))
    assert out.status is PushStatus.TIPPED, (
        f"{sim.name}: {out.status.value}, {out.max_tilt_deg:.2f}"
    )


def _hexagon_flat_to_x(radius_m: float, height_m: float, com_x_m: float):
    a = np.radians(np.arange(6) * 60.0 + 30.0)  # flat faces across x, at +-apothem
    outline = np.stack([radius_m * np.cos(a), radius_m * np.sin(a)], axis=1)
    return prism_object("hexagon", outline, height_m, (com_x_m, 0.0), mu_pusher=0.5)


_HEX_APOTHEM_M = 0.02 * math.cos(math.radians(30.0))
# (object, the pushed face's x, the outcome on every backend), each pushed 3 cm along +x
# through its CoM on mu 1. The sustained moment balance's onset is a CoM mu z_p behind the
# leading edge (1.1 cm for the 2 cm block, 1.6 cm for the 3 cm hexagon); these cases lie
# outside the band where the backends' outcomes differ (docs/physics.md, "Tipping").
TIPPING_CASES = {
    "block_3x3x2_d1.3": (lambda: box_object(0.03, 0.03, 0.02, (0.002, 0.0)), -0.015, "ok"),
    "block_3x3x2_d0.5": (lambda: box_object(0.03, 0.03, 0.02, (0.010, 0.0)), -0.015, "tipped"),
    "hexagon_r2_h3_d1.6": (
        lambda: _hexagon_flat_to_x(0.02, 0.03, _HEX_APOTHEM_M - 0.016),
        -_HEX_APOTHEM_M,
        "ok",
    ),
    "hexagon_r2_h3_d0.6": (
        lambda: _hexagon_flat_to_x(0.02, 0.03, _HEX_APOTHEM_M - 0.006),
        -_HEX_APOTHEM_M,
        "tipped",
    ),
}


def _tipping_push(sim, case: str, speed: float):
    make, face_x, expected = TIPPING_CASES[case]
    sim.build(SceneSpec(FloorSpec(1.0, 1.0), make()))
    out = push(sim, contact_push((face_x, 0.0), (1.0, 0.0), PUSH_LENGTH_M, speed, 0.005))
    return out, expected


@pytest.mark.parametrize("case", list(TIPPING_CASES))
def test_a_dynamic_push_tips_over_exactly_when_the_referee_says(sim, case):
    """40 cm/s: every backend gives the same outcome; one that stays up ends flat again."""
    out, expected = _tipping_push(sim, case, 0.4)
    assert out.status.value == expected, f"{sim.name}: {out.status.value}, {out.max_tilt_deg:.2f}"
    if expected == "ok":
        for _ in range(100):
            sim.step(0.005)
        assert sim.object_state().tilt_deg < 0.5


@pytest.mark.parametrize("case", ["block_3x3x2_d1.3", "block_3x3x2_d0.5"])
def test_a_quasi_static_push_tips_over_exactly_when_the_referee_says(sim, case, request):
    """4 cm/s. MuJoCo's capsule keeps the block up (measured: `ok`, 0.63 deg): as the face
    leans, its contact drops to the lowest point of the overlap, where the referee (and
    pybullet's sphere) keep the line load's resultant at mid-overlap (docs/physics.md)."""
    if sim.name == "mujoco" and case == "block_3x3x2_d0.5":
        request.applymarker(pytest.mark.xfail(strict=True, reason="measured ok, 0.63 deg"))
    out, expected = _tipping_push(sim, case, 0.04)
    assert out.status.value == expected, f"{sim.name}: {out.status.value}, {out.max_tilt_deg:.2f}"


# --- protocol, camera, determinism, failures --------------------------------------------------


def _box(com=(0.0, 0.0), mu_pusher=0.5, izz_scale=1.0, size=(0.08, 0.05, 0.03)):
    return box_object(*size, com_m=com, mu_pusher=mu_pusher, izz_scale=izz_scale)


def _push_left_face(sim, scene: SceneSpec, y_contact: float, speed: float):
    """Push the box's -x face at height y (world) along +x; returns the outcome."""
    half_len = max(p[0] for p in scene.obj.outline_m)
    contact = (scene.initial_pose.x_m - half_len, scene.initial_pose.y_m + y_contact)
    cmd = contact_push(contact, (1.0, 0.0), PUSH_LENGTH_M, speed, scene.pusher.radius_m)
    return push(sim, cmd)


def test_iso_floor_free_slide_does_not_depend_on_yaw(sim):
    """The same object-frame velocity and spin give the same object-frame motion at any yaw."""
    obj = _box(com=(0.015, 0.008))
    results = []
    for yaw_deg in (0, 30, 45, 90, -160):
        pose = Pose2D(0.0, 0.0, math.radians(yaw_deg))
        sim.build(SceneSpec(FloorSpec(1.0, 1.0), obj, initial_pose=pose))
        sim.step(0.05)
        p0 = sim.true_pose()
        v = pose.to_world(np.array([0.3, 0.4])) - np.array([pose.x_m, pose.y_m])
        sim.set_object_velocity((float(v[0]), float(v[1]), 0.0), (0.0, 0.0, 3.0))
        sim.step(0.5)
        p1 = sim.true_pose()
        d = p0.to_object(np.array([p1.x_m, p1.y_m]))
        results.append((d[0], d[1], math.degrees(p1.yaw_rad - p0.yaw_rad)))
    r = np.array(results)
    spread = r.max(axis=0) - r.min(axis=0)
    assert spread[0] < 5e-4 and spread[1] < 5e-4, f"{sim.name}: {r}"
    assert spread[2] < 0.5, f"{sim.name}: yaw change per start yaw {r[:, 2]}"


def test_pusher_tracks_commanded_path(sim):
    scene = SceneSpec(FloorSpec(0.5, 0.5), _box())
    sim.build(scene)
    for speed in (0.4, 0.04):
        out = _push_left_face(sim, scene, 0.0, speed)
        assert out.status is PushStatus.OK
        assert out.max_pusher_lag_m <= speed * sim.settings.timestep_s * 1.05 + 1e-6


def test_camera_maps_known_pose_to_pixels(sim):
    pose = Pose2D(0.08, -0.11, math.radians(30))
    obj = _box()
    sim.build(SceneSpec(FloorSpec(0.5, 0.5), obj, initial_pose=pose))
    img = sim.render_depth()
    cam = img.camera
    depth = img.depth_m
    assert depth.shape == (224, 224)
    floor_depth = cam.position_m[2]
    # metric depth: floor and object top at their true distances
    corner_floor = depth[112, 5]
    assert corner_floor == pytest.approx(floor_depth, abs=2e-3)
    mask = depth < floor_depth - 0.005
    top = depth[mask].min()
    assert top == pytest.approx(floor_depth - obj.height_m, abs=2e-3)
    # the top face's pixels are centred where the model projects the object's centre
    top_face = np.abs(depth - top) < 2e-3
    v, u = np.nonzero(top_face)
    expected = cam.world_to_pixel(pose.x_m, pose.y_m, obj.height_m)
    assert abs(u.mean() - expected[0]) < 1.0 and abs(v.mean() - expected[1]) < 1.0
    # sign conventions: +x is to the right of centre, +y is above centre (smaller row)
    assert u.mean() > cam.cx_px and v.mean() > cam.cy_px
    # area: top face pixels x pixel area ~ footprint area
    px = cam.pixel_size_m(top)
    area = top_face.sum() * px * px
    assert area == pytest.approx(0.08 * 0.05, rel=0.06)


@pytest.mark.parametrize(
    "pose",
    [Pose2D(0.0, 0.0, 0.0), Pose2D(0.08, -0.11, 0.52), Pose2D(-0.13, 0.07, -1.31)],
    ids=["centre", "right_low", "left_high"],
)
def test_camera_has_no_half_pixel_offset(sim, pose):
    """Pixel centres sit at integer coordinates: the top face's pixel centroid is where the
    returned CameraModel projects the object's centre, to a quarter of a pixel (~0.7 mm)."""
    obj = _box()
    sim.build(SceneSpec(FloorSpec(0.5, 0.5), obj, initial_pose=pose))
    img = sim.render_depth()
    top = float(img.depth_m.min())
    v, u = np.nonzero(np.abs(img.depth_m - top) < 2e-3)
    expected = img.camera.world_to_pixel(pose.x_m, pose.y_m, obj.height_m)
    du, dv = u.mean() - expected[0], v.mean() - expected[1]
    assert abs(du) < 0.25 and abs(dv) < 0.25, f"{sim.name}: offset ({du:+.3f}, {dv:+.3f}) px"


def test_many_sided_object_at_rest_settles_at_once(sim):
    """Regression (not_settled): a 28-sided ellipse prism at rest, pusher passing far away.

    pybullet keeps 4 of its bottom corners in the floor contact and rocks it by ~0.02 deg; the
    old 3D settle test then waited 0.83 s here, and 5 s (not_settled) in longer episodes.
    """
    from comexp.episode.task import EpisodeSpec, build_scene
    from comexp.experiment.objects import com_points, load_objects

    obj = next(o for o in load_objects().values() if o.name == "ellipse_12x7")
    spec = EpisodeSpec.for_object(
        obj,
        0,
        com_points(obj, 2)[0],
        backend=sim.name,
        floor="iso",
        mu_floor_x=1.0,
        mu_floor_y=1.0,
        mu_pusher=0.5,
        speed_cm_s=4.0,
        izz_scale=1.0,
    )
    sim.build(build_scene(spec))
    out = push(sim, PushCommand((0.2, 0.2), (1.0, 0.0), 0.01, 0.04))
    assert out.status is PushStatus.OK and not out.contact_made
    # 0.25 s travel + 0.05 s hold + 0.06 s retract (pybullet: 0.36 s); longer = rest missed
    assert out.sim_time_s < 0.4, f"{sim.name}: took {out.sim_time_s:.2f} s to settle"
    assert out.max_tilt_deg < 0.5


def test_same_scene_and_push_are_bit_identical(sim):
    def run():
        scene = SceneSpec(FloorSpec(1.0, 0.1), _box(com=(0.01, -0.005)))
        sim.build(scene)
        out = _push_left_face(sim, scene, 0.012, 0.4)
        return out, sim.render_depth().depth_m.copy()

    a, da = run()
    b, db = run()
    assert a == b
    assert np.array_equal(da, db)


def test_leaving_the_view_is_reported(sim):
    scene = SceneSpec(FloorSpec(0.1, 0.1), _box(), initial_pose=Pose2D(0.24, 0.0, 0.0))
    sim.build(scene)
    out = _push_left_face(sim, scene, 0.0, 0.4)
    assert out.status is PushStatus.LEFT_VIEW


def test_the_view_shortcut_changes_no_outcome(sim, monkeypatch):
    """`surely_in_view` only spares the exact check: the same pushes (one of them leaving the
    view) give the same outcomes, to the bit, with it switched off."""
    from comexp.sim import protocol as simulator_mod

    def pushes():
        outs = []
        for pose in (Pose2D(0.0, 0.0, 0.4), Pose2D(0.24, 0.0, 0.0)):
            scene = SceneSpec(FloorSpec(0.1, 0.1), _box(com=(0.01, -0.005)), initial_pose=pose)
            sim.build(scene)
            outs.append(_push_left_face(sim, scene, 0.012, 0.4))
        return outs

    with_shortcut = pushes()
    assert with_shortcut[1].status is PushStatus.LEFT_VIEW
    monkeypatch.setattr(simulator_mod, "surely_in_view", lambda *a: False)
    assert pushes() == with_shortcut


def test_surely_in_view_never_contradicts_the_exact_check():
    """Random objects, poses over and beyond the image's edge: whenever the cheap test says
    "inside", every corner projects inside, and the verdict with it is the verdict without."""
    from comexp.method.frames import CameraSpec
    from comexp.sim.protocol import classify_state
    from comexp.sim.scene import ObjectState, SimSettings
    from comexp.sim.view import outline_radius_m, surely_in_view

    camera, settings = CameraSpec().model(), SimSettings()
    rng = np.random.default_rng(7)
    said_inside = 0
    for _ in range(3000):
        n = int(rng.integers(3, 12))
        a = np.sort(rng.uniform(0, 2 * np.pi, n))
        outline = np.stack([np.cos(a), np.sin(a)], axis=1) * rng.uniform(0.01, 0.08, (n, 1))
        state = ObjectState(
            (float(rng.uniform(-0.4, 0.4)), float(rng.uniform(-0.4, 0.4)), 0.0),
            0.0, 0.0, float(rng.uniform(-np.pi, np.pi)), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0),
        )  # fmt: skip
        r = outline_radius_m(outline)
        exact = classify_state(state, outline, camera, settings)
        assert classify_state(state, outline, camera, settings, r) == exact
        if surely_in_view(state.position_m[0], state.position_m[1], r, camera):
            said_inside += 1
            assert exact is None
    assert 500 < said_inside < 2900  # both verdicts were exercised
    assert surely_in_view(0.0, 0.0, 0.05, camera)


def test_inside_the_sure_view_box_the_view_is_sure():
    """`surely_in_view_box`: an origin inside the box is surely in view, one a little outside
    it (beyond its inset) is not: the box is the cheap test's own region, inset."""
    from comexp.method.frames import CameraSpec
    from comexp.sim.view import surely_in_view, surely_in_view_box

    camera = CameraSpec().model()
    rng = np.random.default_rng(3)
    for r in rng.uniform(0.01, 0.09, 50):
        x_lo, x_hi, y_lo, y_hi = surely_in_view_box(float(r), camera, inset_m=1e-4)
        assert x_lo < 0.0 < x_hi and y_lo < 0.0 < y_hi
        xs, ys = rng.uniform(x_lo, x_hi, 200), rng.uniform(y_lo, y_hi, 200)
        corners = [(x, y) for x in (x_lo, x_hi) for y in (y_lo, y_hi)]
        for x, y in [*zip(xs, ys, strict=True), *corners]:
            assert surely_in_view(float(x), float(y), float(r), camera)
        for x, y in (
            (x_lo - 2e-4, 0.0),
            (x_hi + 2e-4, 0.0),
            (0.0, y_lo - 2e-4),
            (0.0, y_hi + 2e-4),
        ):
            assert not surely_in_view(x, y, float(r), camera)


def test_start_overlapping_object_is_refused(sim):
    scene = SceneSpec(FloorSpec(0.5, 0.5), _box())
    sim.build(scene)
    before = sim.true_pose()
    out = push(sim, PushCommand((0.0, 0.0), (1.0, 0.0), 0.03, 0.4))
    assert out.status is PushStatus.PATH_BLOCKED
    assert sim.true_pose() == before
