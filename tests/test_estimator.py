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
    line_cuts_region,
    pca,
    reachable_contacts,
    score_contacts,
    update_region,
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
