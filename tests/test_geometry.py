"""Polygon geometry: area/centroid/moments against closed forms, convex decomposition."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
from shapely.geometry import MultiPoint, Polygon

from comexp.method.geometry import (
    centroid,
    convex_decomposition,
    douglas_peucker,
    is_convex,
    min_width,
    second_moments,
    signed_area,
    simplify,
)
from comexp.sim.bodies import box_object, prism_object

NONCONVEX = {
    "L": [(0, 0), (10, 0), (10, 4), (4, 4), (4, 8), (0, 8)],
    "T": [(-6, 2), (-6, -2), (-2, -2), (-2, -9), (2, -9), (2, -2), (6, -2), (6, 2)],
    "U": [(0, 0), (12, 0), (12, 9), (8, 9), (8, 4), (4, 4), (4, 9), (0, 9)],
    "cross": [
        (-2, -6),
        (2, -6),
        (2, -2),
        (6, -2),
        (6, 2),
        (2, 2),
        (2, 6),
        (-2, 6),
        (-2, 2),
        (-6, 2),
        (-6, -2),
        (-2, -2),
    ],
    "arrow": [(0, -2), (8, -2), (8, -4), (13, 0), (8, 4), (8, 2), (0, 2)],
    "comb": [
        (0, 0),
        (9, 0),
        (9, 6),
        (7, 6),
        (7, 2),
        (5.5, 2),
        (5.5, 6),
        (3.5, 6),
        (3.5, 2),
        (2, 2),
        (2, 6),
        (0, 6),
    ],
    "star": [
        (
            math.cos(math.pi / 2 + k * math.pi / 5) * (5 if k % 2 == 0 else 2),
            math.sin(math.pi / 2 + k * math.pi / 5) * (5 if k % 2 == 0 else 2),
        )
        for k in range(10)
    ],
    "collinear_T": [
        (-6, 2),
        (-6, -2),
        (-2, -2),
        (-2, -5),
        (-2, -9),
        (2, -9),
        (2, -2),
        (6, -2),
        (6, 2),
        (0, 2),
    ],
}
# minimum convex parts for the shapes whose optimum is obvious
OPTIMAL_PARTS = {"L": 2, "T": 2, "U": 3, "cross": 3, "arrow": 2, "collinear_T": 2}


def _check_decomposition(poly, parts, scale=1.0):
    target = Polygon(poly)
    assert len(parts) >= 1
    for part in parts:
        assert signed_area(part) > 0, "parts must be counter-clockwise"
        assert is_convex(part), "parts must be convex"
        assert Polygon(part).is_valid
    total = sum(signed_area(p) for p in parts)
    assert total == pytest.approx(target.area, rel=1e-9)  # no overlap, nothing missing
    union = shapely.union_all([Polygon(p) for p in parts])
    assert union.symmetric_difference(target).area <= 1e-9 * target.area * scale


@pytest.mark.parametrize("name", sorted(NONCONVEX))
@pytest.mark.parametrize("reverse", [False, True], ids=["ccw", "cw"])
def test_nonconvex_decomposition(name, reverse):
    poly = NONCONVEX[name][::-1] if reverse else NONCONVEX[name]
    assert not is_convex(poly)
    parts = convex_decomposition(poly)
    _check_decomposition(poly, parts)
    if name in OPTIMAL_PARTS:
        assert len(parts) == OPTIMAL_PARTS[name]
    # Hertel-Mehlhorn bound: at most 4x the minimum, which is >= (reflex vertices + 1) / 2 ...
    # and a triangulation has n - 2 triangles: few parts means fewer than that
    assert len(parts) < len(simplify(poly)) - 2


@pytest.mark.parametrize("scale", [1.0, 0.01])
def test_decomposition_is_unit_independent(scale):
    poly = np.asarray(NONCONVEX["U"], dtype=float) * scale
    parts = convex_decomposition(poly)
    assert len(parts) == 3
    _check_decomposition(poly, parts)


@pytest.mark.parametrize("seed", range(5))
def test_random_convex_polygon_is_one_part(seed):
    rng = np.random.default_rng(seed)
    hull = MultiPoint(rng.uniform(-5, 5, size=(20, 2))).convex_hull
    poly = np.asarray(hull.exterior.coords)[:-1][::-1]  # clockwise on purpose
    parts = convex_decomposition(poly)
    assert len(parts) == 1
    _check_decomposition(poly, parts)


@pytest.mark.parametrize("seed", range(5))
def test_random_star_shaped_polygon(seed):
    """Random radii around the origin: a simple, usually non-convex polygon."""
    rng = np.random.default_rng(100 + seed)
    n = 14
    ang = np.sort(rng.uniform(0, 2 * np.pi, n))
    r = rng.uniform(2, 6, n)
    poly = np.stack([r * np.cos(ang), r * np.sin(ang)], axis=1)
    assert Polygon(poly).is_valid
    parts = convex_decomposition(poly)
    _check_decomposition(poly, parts)


def test_area_centroid_moments_of_a_rectangle():
    rect = [(1, 1), (5, 1), (5, 3), (1, 3)]  # 4 x 2, centre (3, 2)
    assert signed_area(rect) == pytest.approx(8.0)
    assert signed_area(rect[::-1]) == pytest.approx(-8.0)
    assert centroid(rect) == pytest.approx([3.0, 2.0])
    jx, jy = second_moments(rect)
    assert jx == pytest.approx(4 * 2**3 / 12)
    assert jy == pytest.approx(2 * 4**3 / 12)


def _centroid_numpy(p: np.ndarray) -> np.ndarray:
    """The shoelace centroid in numpy, as `centroid` computed it before its kernel."""
    x, y = p[:, 0], p[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    a = 0.5 * np.sum(cross)
    return np.array([np.sum((x + xn) * cross), np.sum((y + yn) * cross)]) / (6.0 * a)


def test_the_compiled_centroid_has_the_numpy_form_s_bits():
    """`_centroid_kernel` sums as NumPy does (pairwise, in blocks of 128): every vertex
    count up to a block and beyond (the numpy form), star polygons at random offsets."""
    rng = np.random.default_rng(11)
    for n in [*range(3, 140), 200, 300]:
        for _ in range(8):
            t = np.sort(rng.uniform(0.0, 2.0 * np.pi, n))
            r = rng.uniform(0.02, 0.06, n)
            p = np.stack([r * np.cos(t), r * np.sin(t)], axis=1) + rng.normal(0.0, 0.1, 2)
            np.testing.assert_array_equal(centroid(p), _centroid_numpy(p))


def test_centroid_of_l_matches_shapely():
    poly = NONCONVEX["L"]
    c = Polygon(poly).centroid
    assert centroid(poly) == pytest.approx([c.x, c.y])


def test_min_width():
    assert min_width([(0, 0), (12, 0), (12, 4), (0, 4)]) == pytest.approx(4.0)
    # equilateral triangle: its height
    assert min_width([(0, 0), (10, 0), (5, 5 * math.sqrt(3))]) == pytest.approx(5 * math.sqrt(3))
    # rotated rectangle
    a = math.radians(30)
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    rect = np.array([(0, 0), (12, 0), (12, 4), (0, 4)], dtype=float) @ rot.T
    assert min_width(rect) == pytest.approx(4.0)


def test_simplify_drops_collinear_and_repeated_vertices():
    poly = [(0, 0), (2, 0), (4, 0), (4, 0), (4, 3), (0, 3)]
    assert len(simplify(poly)) == 4


def test_prism_object_recentres_and_decomposes():
    poly_cm = np.asarray(NONCONVEX["L"], dtype=float)
    obj = prism_object("L", poly_cm / 100.0, 0.02, (0.0, 0.0), izz_scale=10.0)
    assert centroid(obj.outline_m) == pytest.approx([0.0, 0.0], abs=1e-12)
    assert signed_area(obj.outline_m) > 0
    assert len(obj.convex_parts_m) == 2
    _check_decomposition(obj.outline_m, [np.asarray(p) for p in obj.convex_parts_m])
    assert obj.ixx_kg_m2 + obj.iyy_kg_m2 >= obj.izz_kg_m2 * (1 - 1e-12)


def test_box_object_inertia_is_the_textbook_value():
    b = box_object(0.08, 0.05, 0.03)
    assert b.izz_kg_m2 == pytest.approx(0.2 * (0.08**2 + 0.05**2) / 12)
    assert len(b.convex_parts_m) == 1


def test_pose_maps_points_ccw_and_back_and_reads_only_x_and_y():
    """`Pose2D.to_world` / `to_object` (filled in place since 5952407): a quarter turn takes
    object +x to world +y (counter-clockwise positive), the two are inverse on any (..., 2)
    batch, and points with more columns map by their x and y, as (..., 2) results."""
    from comexp.method.frames import Pose2D

    pose = Pose2D(0.1, -0.2, math.pi / 2)
    assert np.allclose(pose.to_world(np.array([1.0, 0.0])), [0.1, 0.8])
    pts = np.random.default_rng(3).normal(size=(4, 5, 2))
    assert np.allclose(pose.to_object(pose.to_world(pts)), pts)
    assert pose.to_world(pts).shape == (4, 5, 2)
    wide = np.concatenate([pts, np.ones((4, 5, 1))], axis=-1)
    assert np.array_equal(pose.to_world(wide), pose.to_world(pts))
    assert np.array_equal(pose.to_object(wide), pose.to_object(pts))


def _staircase(poly: list[tuple[float, float]], step: float) -> np.ndarray:
    """The polygon traced as a pixel outline would be: every edge cut into `step`-long pieces."""
    pts = []
    for a, b in zip(poly, poly[1:] + poly[:1], strict=True):
        n = max(1, round(math.dist(a, b) / step))
        pts += [tuple(np.add(a, np.subtract(b, a) * k / n)) for k in range(n)]
    return np.array(pts)


@pytest.mark.parametrize("name", ["L", "T", "U", "cross"])
def test_douglas_peucker_keeps_a_traced_polygons_corners(name):
    """A polygon cut into 0.1-long pieces comes back as its own corners."""
    poly = NONCONVEX[name]
    out = douglas_peucker(_staircase(poly, 0.1), 1e-6)
    assert sorted(map(tuple, np.round(out, 9))) == sorted(map(tuple, np.array(poly, float)))


@pytest.mark.parametrize("tol", [1e-4, 3e-4, 1e-3])
def test_douglas_peucker_stays_within_its_tolerance(tol):
    """A 5 cm circle of 400 vertices: far fewer kept, every dropped one within `tol` of the
    simplified outline."""
    t = np.linspace(0.0, 2 * math.pi, 400, endpoint=False)
    circle = 0.05 * np.c_[np.cos(t), np.sin(t)]
    out = douglas_peucker(circle, tol)
    assert 8 <= len(out) < len(circle) / 4
    boundary = Polygon(out).exterior
    assert max(boundary.distance(shapely.Point(p)) for p in circle) <= tol * (1 + 1e-9)
