"""Algorithms 1 and 2 on synthetic regions with known answers (no simulator, no images)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely

from comexp.method.estimator import (
    ComEstimator,
    EstimatorSettings,
    ObservedPush,
    choose_contact,
    cross2,
    estimate_com,
    floor_force_direction,
    lever_arms,
    line_cuts_region,
    magnitude_misfit,
    magnitude_posterior,
    pca,
    reachable_contacts,
    refine_grid,
    score_contacts,
    update_region,
    weighted_pca,
)

PX = 0.0025  # metres per pixel of the synthetic grids
DEFAULT = EstimatorSettings()


def grid_in(poly: np.ndarray, spacing: float = PX) -> np.ndarray:
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0], spacing), np.arange(lo[1], hi[1], spacing))
    pts = np.stack([gx.ravel(), gy.ravel()], axis=1) + spacing / 2
    return pts[shapely.contains_xy(shapely.Polygon(poly), pts[:, 0], pts[:, 1])]


def rect(a: float, b: float) -> np.ndarray:
    return np.array([(-a, -b), (a, -b), (a, b), (-a, b)])


def edge_contacts(poly: np.ndarray, step: float = 0.004) -> tuple[np.ndarray, np.ndarray]:
    """Points along each edge of a CCW polygon with inward normals (corners skipped)."""
    P, N = [], []
    for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        e = b - a
        length = np.linalg.norm(e)
        t = e / length
        for s in np.arange(step, length - step / 2, step):
            P.append(a + s * t)
            N.append([-t[1], t[0]])
    return np.array(P), np.array(N)


def test_ccw_keeps_the_left_of_the_push_line():
    """Push north (+y) at x = 0: a CCW turn means the CoM is west (x < 0) of the line."""
    region = grid_in(rect(0.05, 0.03))
    P, N = np.array([0.0, -0.03]), np.array([0.0, 1.0])
    kept, decision = update_region(region, P, N, +5.0, DEFAULT, PX)
    assert decision == "ccw"
    assert (kept[:, 0] < 0).all() and len(kept) == (region[:, 0] < 0).sum()
    kept, decision = update_region(region, P, N, -5.0, DEFAULT, PX)
    assert decision == "cw" and (kept[:, 0] > 0).all()


def test_half_plane_sign_matches_the_moment():
    """For random pushes and CoMs, the kept side holds G iff the moment (P - G) x N has the
    sign of the rotation: the physics, not just a convention."""
    rng = np.random.default_rng(0)
    region = grid_in(rect(0.05, 0.03))
    for _ in range(50):
        G = rng.uniform([-0.04, -0.02], [0.04, 0.02])
        P = rng.uniform([-0.05, -0.03], [0.05, 0.03])
        ang = rng.uniform(-math.pi, math.pi)
        N = np.array([math.cos(ang), math.sin(ang)])
        moment = cross2(P - G, N)
        if abs(moment) < 1e-3:
            continue
        rot = 10.0 * math.copysign(1.0, moment)
        kept, _ = update_region(region, P, N, rot, DEFAULT, PX)
        # the kept half-plane is the one G is in
        assert cross2(N, G - P) * cross2(N, kept - P).mean() > 0


def test_band_rule_keeps_points_near_the_line():
    region = grid_in(rect(0.06, 0.03))
    P, N = np.array([0.0, -0.03]), np.array([0.0, 1.0])
    kept, decision = update_region(region, P, N, 0.5, DEFAULT, PX)
    assert decision == "band"
    bw = DEFAULT.C_bw_px * PX
    assert (np.abs(kept[:, 0]) < bw).all()
    assert len(kept) == (np.abs(region[:, 0]) < bw).sum()
    # below the threshold in either direction is the same band
    kept_neg, _ = update_region(region, P, N, -0.5, DEFAULT, PX)
    np.testing.assert_array_equal(kept, kept_neg)
    # the literal signed reading deletes only one side: d = (P_i - P) x N >= C_bw
    literal = EstimatorSettings(band_signed=True)
    kept_lit, _ = update_region(region, P, N, 0.5, literal, PX)
    d = cross2(kept_lit - P, N)
    assert (d < bw).all()  # here d = x: everything west of x = C_bw survives
    assert len(kept_lit) == (region[:, 0] < bw).sum() and kept_lit[:, 0].min() < -bw


def test_threshold_is_exclusive():
    region = grid_in(rect(0.06, 0.03))
    P, N = np.array([0.0, -0.03]), np.array([0.0, 1.0])
    assert update_region(region, P, N, 1.0, DEFAULT, PX)[1] == "band"
    assert update_region(region, P, N, 1.01, DEFAULT, PX)[1] == "ccw"


def test_contradiction_keeps_the_region():
    region = grid_in(rect(0.02, 0.02))
    P, N = np.array([0.1, -0.1]), np.array([0.0, 1.0])  # line east of the whole region
    kept, decision = update_region(region, P, N, -5.0, DEFAULT, PX)  # says: CoM is east
    assert decision == "cw-empty" and len(kept) == len(region)


def test_pca_main_axis():
    region = grid_in(rect(0.06, 0.015))
    c, V, lam = pca(region)
    assert c == pytest.approx([0.0, 0.0], abs=1e-3)
    assert abs(V[0, 0]) > 0.99 and lam[0] > 4 * lam[1]


def test_validity_requires_the_line_to_cut_the_region():
    region = grid_in(rect(0.02, 0.02))
    P = np.array([[0.0, -0.05], [0.05, -0.05]])
    N = np.array([[0.0, 1.0], [0.0, 1.0]])
    np.testing.assert_array_equal(line_cuts_region(region, P, N), [True, False])


@pytest.mark.parametrize("seed", range(4))
def test_the_compiled_cut_test_is_the_planes_of_sides(seed):
    """`line_cuts_region` (a compiled scan that stops at a line's first points on both
    sides) decides as the (lines x points) planes of sides it replaced, on random lines and
    on lines through region points of a grid (sides exactly zero)."""
    rng = np.random.default_rng(seed)
    region = grid_in(rect(0.05, 0.03)) if seed % 2 else rng.normal(size=(300, 2)) * 0.02
    P = np.concatenate([rng.normal(size=(40, 2)) * 0.1, region[rng.integers(0, len(region), 40)]])
    N = np.concatenate([rng.normal(size=(40, 2)), np.round(rng.normal(size=(40, 2)))])
    N[np.all(N == 0, axis=1)] = (1.0, 0.0)
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    dx = region[None, :, 0] - P[:, 0, None]
    dy = region[None, :, 1] - P[:, 1, None]
    side = N[:, 0, None] * dy - N[:, 1, None] * dx
    want = (side.max(axis=1) > 0) & (side.min(axis=1) < 0)
    assert 5 < want.sum() < len(P) - 5  # both answers occur
    np.testing.assert_array_equal(line_cuts_region(region, P, N), want)
    assert line_cuts_region(region[:0], P, N).tolist() == [False] * len(P)
    # a NaN point is on neither side: it neither makes nor spoils a cut
    with_nan = np.concatenate([region, [[np.nan, 0.0]]])
    np.testing.assert_array_equal(line_cuts_region(with_nan, P, N), want)


def test_scoring_prefers_a_cut_across_the_long_axis_through_the_centroid():
    """Elongated region along x: the best push crosses the long axis through the centroid."""
    poly = rect(0.06, 0.02)
    region = grid_in(poly)
    P, N = edge_contacts(poly)
    j = choose_contact(region, P, N, DEFAULT, PX)
    assert abs(N[j] @ [1.0, 0.0]) < 0.1, "push direction must be perpendicular to V1"
    assert abs(P[j][0]) < 0.005, "push line through the centroid"
    s = score_contacts(region, P, N, DEFAULT, PX)
    assert s[j] == pytest.approx(s.min())


def test_literal_signed_readings_prefer_the_wrong_pushes():
    """Signed d and signed cos reward lines far to one side / along the long axis."""
    poly = rect(0.06, 0.02)
    region = grid_in(poly)
    P, N = edge_contacts(poly)
    j = choose_contact(region, P, N, EstimatorSettings(d_signed=True, cos_signed=True), PX)
    off = abs(cross2(region.mean(axis=0) - P[j], N[j]))
    assert off > 0.005 or abs(N[j][0]) > 0.5


def test_unreachable_contacts_in_a_narrow_notch():
    """A U whose slot (6 mm) is narrower than the pusher (10 mm): the slot's floor and the
    inner walls cannot be reached; the outer walls can."""
    u = np.array(
        [(-0.03, 0), (0.03, 0), (0.03, 0.04), (0.003, 0.04), (0.003, 0.01), (-0.003, 0.01)]
        + [(-0.003, 0.04), (-0.03, 0.04)]
    )
    P = np.array([[0.0, 0.01], [0.003, 0.03], [0.03, 0.02], [0.0, 0.0]])
    N = np.array([[0.0, -1.0], [-1.0, 0.0], [-1.0, 0.0], [0.0, 1.0]])
    ok = reachable_contacts(u, P, N, pusher_radius_m=0.005)
    np.testing.assert_array_equal(ok, [False, False, True, True])
    # a thin pusher fits the slot floor
    assert reachable_contacts(u, P[:1], N[:1], pusher_radius_m=0.002)[0]


def _ideal_rotation(G, P, N, gain_deg_per_cm=4.0):
    """VT with the push along the normal: rotation follows the moment about G."""
    return float(gain_deg_per_cm * 100.0 * cross2(np.subtract(P, G), np.asarray(N)))


@pytest.mark.parametrize("seed", range(6))
def test_region_shrinks_around_the_true_com(seed):
    poly = rect(0.05, 0.03)
    rng = np.random.default_rng(seed)
    G = rng.uniform([-0.04, -0.02], [0.04, 0.02])
    P, N = edge_contacts(poly, step=0.003)
    est = ComEstimator(grid_in(poly), P, N, PX, DEFAULT, outline_m=poly, pusher_radius_m=0.005)
    sizes = [est.region_px]
    for _ in range(DEFAULT.n_push):
        push = est.next_push()
        assert push is not None
        decision = est.observe(*push, _ideal_rotation(G, *push))
        assert not decision.endswith("empty")
        sizes.append(est.region_px)
        d = np.min(np.linalg.norm(est.region - G, axis=1))
        assert d < 1.5 * PX, "the true CoM must stay in the region"
    assert sizes[-1] <= 0.3 * sizes[0]
    assert np.linalg.norm(est.estimate_m - G) < 0.01


def test_estimate_com_api_for_observed_pushes():
    """The real-robot entry point: a region and a list of observed pushes."""
    region = grid_in(rect(0.05, 0.03))
    G = np.array([0.02, -0.01])
    pushes = [
        ObservedPush((0.0, -0.03), (0.0, 1.0), _ideal_rotation(G, (0.0, -0.03), (0.0, 1.0))),
        ObservedPush((-0.05, 0.0), (1.0, 0.0), _ideal_rotation(G, (-0.05, 0.0), (1.0, 0.0))),
        ObservedPush((0.02, 0.03), (0.0, -1.0), _ideal_rotation(G, (0.02, 0.03), (0.0, -1.0))),
    ]
    final, estimate = estimate_com(region, pushes, pixel_m=PX)
    assert len(final) < len(region) / 3
    assert (final[:, 0] > 0).all() and (final[:, 1] < 0).all()
    assert np.linalg.norm(estimate - G) < 0.015


def test_settings_are_validated():
    with pytest.raises(ValueError, match="method"):
        EstimatorSettings(method="bayes")
    with pytest.raises(ValueError, match="mag_noise_deg"):
        EstimatorSettings(mag_noise_deg=0.0)
    with pytest.raises(ValueError, match="mag_noise_deg"):
        EstimatorSettings(mag_noise_deg=math.nan)
    with pytest.raises(ValueError, match="mag_rel_noise"):
        EstimatorSettings(mag_rel_noise=-0.1)
    assert EstimatorSettings().method == "paper"
    with pytest.raises(ValueError):
        EstimatorSettings(rotation_source="magic")
    with pytest.raises(ValueError):
        EstimatorSettings(d_metric="furlongs")
    with pytest.raises(ValueError):
        EstimatorSettings(C_bw_px=0)
    # the rules the config used to add on its own are the settings' now
    for bad in (dict(theta_T_deg=float("nan")), dict(w=(1.0, float("inf"))), dict(n_push=0)):
        with pytest.raises(ValueError):
            EstimatorSettings(**bad)


# --- method="magnitude" (beyond the paper) ----------------------------------------------------

MAG = EstimatorSettings(method="magnitude")
PENTAGON = np.array([(-0.05, -0.02), (0.03, -0.035), (0.055, 0.01), (0.01, 0.04), (-0.045, 0.025)])


def _pushes_through(region: np.ndarray, poly: np.ndarray, n: int, rng: np.random.Generator):
    """n contacts of the outline whose push lines cut the region (random, reproducible)."""
    P, N = edge_contacts(poly, step=0.003)
    ok = np.flatnonzero(line_cuts_region(region, P, N))
    j = rng.choice(ok, size=n, replace=False)
    return P[j], N[j]


def test_lever_arms_have_the_sign_of_the_rotation():
    G = np.array([[0.0, 0.0]])
    # push north (+y) east of G: the moment (P - G) x N is +x * +y > 0, CCW
    np.testing.assert_allclose(lever_arms(G, [[0.01, -0.03]], [[0.0, 1.0]]), [[0.01]])
    np.testing.assert_allclose(lever_arms(G, [[-0.02, -0.03]], [[0.0, 1.0]]), [[-0.02]])
    rot = _ideal_rotation(G[0], (0.01, -0.03), (0.0, 1.0))
    assert rot > 0  # and the stand-in physics of the paper tests agrees


@pytest.mark.parametrize("gain_deg_per_cm", [3.0, 40.0])
def test_magnitude_recovers_the_com_exactly_with_the_linear_model(gain_deg_per_cm):
    """rot = k (P - G) x N exactly: G has zero misfit and is the misfit's unique minimum among
    the region's points (default noise settings), and told that the data are exact (tiny noise
    floor, no relative error) the posterior mean lands on it, for a weak and a strong gain."""
    exact = EstimatorSettings(method="magnitude", mag_noise_deg=0.01, mag_rel_noise=0.0)
    region = grid_in(PENTAGON)
    rng = np.random.default_rng(1)
    for i in rng.choice(len(region), size=5, replace=False):
        G = region[i]
        P, N = _pushes_through(region, PENTAGON, 5, rng)
        rot = gain_deg_per_cm * 100.0 * lever_arms(G, P, N)[0]
        chi = magnitude_misfit(region, P, N, rot, MAG, region)
        assert chi[i] == pytest.approx(0.0, abs=1e-18)
        assert np.argmin(chi) == i and np.sort(chi)[1] > 1e-3
        pushes = [ObservedPush(tuple(p), tuple(n), r) for p, n, r in zip(P, N, rot, strict=True)]
        final, est = estimate_com(region, pushes, PX, exact)
        paper_final, _ = estimate_com(region, pushes, PX)
        np.testing.assert_array_equal(final, paper_final)  # same sign region as the paper
        assert np.linalg.norm(est - G) < 1e-6


def _saturating_rotation(G, P, N, rng, sat_deg=60.0, lever_m=0.01, noise_deg=0.3):
    """A monotone, non-linear law (tanh: ~linear below the lever, saturating at sat_deg above
    it) with 5% gain scatter between pushes and additive noise."""
    lev = float(cross2(np.subtract(P, G), np.asarray(N)))
    scale = 1.0 + 0.05 * rng.standard_normal()
    return float(sat_deg * scale * math.tanh(lev / lever_m) + noise_deg * rng.standard_normal())


def _run(settings, poly, G, seed):
    rng = np.random.default_rng(seed)
    P, N = edge_contacts(poly, step=0.003)
    est = ComEstimator(grid_in(poly), P, N, PX, settings, outline_m=poly, pusher_radius_m=0.005)
    for _ in range(settings.n_push):
        push = est.next_push()
        assert push is not None
        est.observe(*push, _saturating_rotation(G, *push, rng))
        assert np.min(np.linalg.norm(est.region - G, axis=1)) < 1.5 * PX  # G never cut off
    return float(np.linalg.norm(est.estimate_m - G))


@pytest.mark.parametrize("poly", [rect(0.05, 0.03), PENTAGON], ids=["rect", "pentagon"])
def test_magnitude_is_robust_to_a_saturating_law_and_noise(poly):
    """Episodes driven by ComEstimator (Alg. 1 on the posterior) under a tanh law with noise:
    the magnitude estimate is several times closer than the paper's on the same CoMs."""
    rng = np.random.default_rng(7)
    inner = shapely.Polygon(poly).buffer(-0.01)
    Gs = []
    while len(Gs) < 12:
        g = rng.uniform(poly.min(axis=0), poly.max(axis=0))
        if inner.contains(shapely.Point(g)):
            Gs.append(g)
    paper = [_run(DEFAULT, poly, G, s) for s, G in enumerate(Gs)]
    mag = [_run(MAG, poly, G, s) for s, G in enumerate(Gs)]
    assert np.mean(mag) < 0.4 * np.mean(paper)
    assert np.mean(mag) < 0.002 and max(mag) < 0.004


def test_magnitude_estimate_stays_in_the_sign_region():
    """The posterior lives on the sign-consistent points only, whatever the magnitudes say
    (here a huge and a tiny turn that fit no single gain well)."""
    region = grid_in(rect(0.05, 0.03))
    # CCW for a north push at x = 0: G is west (x < 0); CW for an east push at y = 0: G is
    # south (y < 0); CCW for a north push at x = 0.03: west of it (no new cut).
    pushes = [
        ObservedPush((0.0, -0.03), (0.0, 1.0), 2.0),
        ObservedPush((-0.05, 0.0), (1.0, 0.0), -60.0),
        ObservedPush((0.03, -0.03), (0.0, 1.0), 40.0),
    ]
    final, est = estimate_com(region, pushes, PX, MAG)
    assert (final[:, 0] < 0).all() and (final[:, 1] < 0).all()
    assert est[0] < 0 and est[1] < 0  # the signs' half-planes hold for the estimate itself
    hull = shapely.MultiPoint(final.tolist()).convex_hull  # within the region's cells
    assert hull.buffer(PX / 2 * math.sqrt(2)).contains(shapely.Point(est))
    P = np.array([p.contact_m for p in pushes])
    N = np.array([p.direction for p in pushes])
    rot = np.array([p.rotation_deg for p in pushes])
    w = magnitude_posterior(final, P, N, rot, MAG, region)
    assert w.shape == (len(final),) and w.sum() == pytest.approx(1.0) and (w >= 0).all()


def test_magnitude_without_pushes_is_the_centroid():
    region = grid_in(PENTAGON)
    final, est = estimate_com(region, [], PX, MAG)
    np.testing.assert_array_equal(final, region)
    np.testing.assert_allclose(est, region.mean(axis=0))


def test_refined_grid_tiles_the_cells():
    region = grid_in(rect(0.01, 0.01))
    fine = refine_grid(region, PX, 3)
    assert len(fine) == 9 * len(region)
    np.testing.assert_allclose(fine.mean(axis=0), region.mean(axis=0), atol=1e-12)
    d = np.linalg.norm(fine[:9] - region[0], axis=1)
    assert d.max() == pytest.approx(math.hypot(PX / 3, PX / 3))


def test_weighted_pca_follows_the_weights():
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    c, V, lam = weighted_pca(pts, np.array([1.0, 1.0, 0.0, 0.0]))
    np.testing.assert_allclose(c, [0.5, 0.0])
    assert abs(V[0, 0]) == pytest.approx(1.0) and lam[1] == pytest.approx(0.0)
    _, _, lam = weighted_pca(pts, np.array([1.0, 0, 0, 0]), floor_m=0.3)
    np.testing.assert_allclose(lam, [0.0075, 0.0075])  # a grid cell's own variance


def test_magnitude_pushes_cross_the_line_a_null_turn_found():
    """After a push whose line passes through the CoM (no turn), the posterior is a strip
    along that line; Algorithm 1 on the posterior then pushes across it, where the paper's
    region centroid would have it push the same line again."""
    poly = rect(0.05, 0.03)
    G = np.array([0.0, 0.004])
    P, N = edge_contacts(poly, step=0.003)
    est = ComEstimator(grid_in(poly), P, N, PX, MAG, outline_m=poly, pusher_radius_m=0.005)
    for p, n in (((0.001, -0.03), (0.0, 1.0)), ((-0.05, -0.01), (1.0, 0.0))):
        est.observe(p, n, _ideal_rotation(G, p, n, 20.0))
    est.observe((0.0, 0.03), (0.0, -1.0), 0.0)  # the line x = 0: through G
    p, n = est.next_push()
    assert abs(n[1]) < 0.5, "the next push crosses the vertical line"


def test_paper_path_is_unchanged():
    """`method="paper"` (the default) chooses the same pushes and gives the same estimate, to
    the last bit, as before `method` existed: values recorded with commit b32f6b0's
    estimator on this scenario."""
    G = np.array([0.0113, -0.0042])
    P, N = edge_contacts(PENTAGON, step=0.003)
    est = ComEstimator(
        grid_in(PENTAGON), P, N, PX, DEFAULT, outline_m=PENTAGON, pusher_radius_m=0.005
    )
    got = []
    for _ in range(5):
        p, n = est.next_push()
        rot = 60.0 * np.tanh(float(cross2(p - G, n)) / 0.01)
        got.append((p.tolist(), est.observe(p, n, rot), est.region_px))
    assert got == [
        ([-0.005770751587955515, -0.028292984077258346], "cw", 441),
        ([-0.04698776746934724, 0.007110092775874863], "cw", 216),
        ([0.004211417072573607, 0.03842129556524735], "cw", 112),
        ([-0.04897553493869448, -0.010779814448250283], "ccw", 54),
        ([0.03003849116986469, 0.02664100588675687], "ccw", 29),
    ]
    assert est.estimate_m.tolist() == [0.011508620689655216, -0.011077586206896533]
    assert est.posterior is None


def test_floor_force_direction():
    """Isotropic floor: the push direction itself. Anisotropic: turned towards the floor's
    friction direction for motion along the push (half way), within the pusher's cone, and
    not at all along the floor's axes."""
    n = np.array([math.sqrt(0.5), math.sqrt(0.5)])
    np.testing.assert_array_equal(floor_force_direction(n, 0.3, 0.5, 0.5, 1.0), n)
    for yaw in (0.0, math.pi / 2):  # pushing along a floor axis: no turn
        d = floor_force_direction([1.0, 0.0], yaw, 0.1, 1.0, 1.0)
        np.testing.assert_allclose(d, [1.0, 0.0], atol=1e-12)
    # 45 deg on mu_x = 0.1, mu_y = 1: friction along ~y, phi ~ +44 deg, half of it applied
    d = floor_force_direction(n, 0.0, 0.1, 1.0, 1.0)
    phi = math.degrees(math.atan2(d[1], d[0])) - 45.0
    assert phi == pytest.approx(0.5 * (math.degrees(math.atan(100.0)) - 45.0))
    # the pusher's friction cone bounds it: mu_p = 0.1 -> at most atan(0.1)
    d = floor_force_direction(n, 0.0, 0.1, 1.0, 0.1)
    assert math.degrees(math.atan2(d[1], d[0])) - 45.0 == pytest.approx(
        math.degrees(math.atan(0.1))
    )
    # the object's yaw counts: an object-frame north push at yaw -90 deg runs along world +x
    d = floor_force_direction([0.0, 1.0], -math.pi / 2, 0.1, 1.0, 1.0)  # world +x: an axis
    np.testing.assert_allclose(d, [0.0, 1.0], atol=1e-12)
    assert np.linalg.norm(floor_force_direction(n, 1.0, 1.0, 0.1, 0.5)) == pytest.approx(1.0)


def test_magnitude_uses_the_line_direction_and_the_paper_ignores_it():
    """A push whose force line is turned (anisotropic floor) splits the region along that line
    for `magnitude`; the paper's Algorithm 2 keeps using the push direction."""
    region = grid_in(rect(0.05, 0.03))
    turned = (math.sin(0.3), math.cos(0.3))  # north push, line turned 0.3 rad clockwise
    push = ObservedPush((0.0, -0.03), (0.0, 1.0), 5.0, line_direction=turned)
    paper_final, _ = estimate_com(region, [push], PX)
    np.testing.assert_array_equal(paper_final, region[region[:, 0] < 0])
    mag_final, _ = estimate_com(region, [push], PX, MAG)
    side = cross2(np.array(turned), mag_final - np.array([0.0, -0.03]))
    assert (side > 0).all() and len(mag_final) != len(paper_final)
    est = ComEstimator(region, *edge_contacts(rect(0.05, 0.03)), PX, MAG)
    est.observe(np.array([0.0, -0.03]), np.array([0.0, 1.0]), 5.0, np.array(turned))
    np.testing.assert_array_equal(est.region, mag_final)
