"""Planar polygon geometry for the objects: area, centroid, second moments, convexity,
convex decomposition, and the rigid-body model of an extruded polygon."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numba import njit


def as_array(poly: Sequence[Sequence[float]]) -> np.ndarray:
    a = np.asarray(poly, dtype=float)
    if a.ndim != 2 or a.shape[1] != 2 or len(a) < 3:
        raise ValueError("a polygon needs at least 3 (x, y) vertices")
    return a


def signed_area(poly: Sequence[Sequence[float]]) -> float:
    """Shoelace area; positive for counter-clockwise vertex order."""
    p = as_array(poly)
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def centroid(poly: Sequence[Sequence[float]], compiled: bool = True) -> np.ndarray:
    """Area centroid (shoelace). Every tracking frame asks for it (up to 64 vertices): up to
    `_SUM_BLOCK` vertices in one compiled pass (`_centroid_kernel`), with the bits of the
    numpy form below (tests/test_geometry.py). `compiled` False: the numpy form, for a caller
    that asks a few times only (the driver's objects: loading the compiled kernel costs a
    process ~0.2 s)."""
    p = as_array(poly)
    if compiled and len(p) <= _SUM_BLOCK:
        return np.array(_centroid_kernel(np.ascontiguousarray(p)))
    x, y = p[:, 0], p[:, 1]
    pn = np.concatenate((p[1:], p[:1]))  # the next vertices (np.roll's, without its overhead)
    xn, yn = pn[:, 0], pn[:, 1]
    cross = x * yn - xn * y
    a = 0.5 * np.sum(cross)
    return np.array([np.sum((x + xn) * cross), np.sum((y + yn) * cross)]) / (6.0 * a)


# NumPy sums up to this many float64 in one block of its pairwise summation (PW_BLOCKSIZE)
_SUM_BLOCK = 128


@njit(cache=True)
def _block_sum(a: np.ndarray) -> float:
    """`np.sum(a)` for len(a) <= `_SUM_BLOCK`, as NumPy adds float64 (below 8 in order, else
    8 running sums combined pairwise, then the rest in order), so that a compiled sum gives
    the bits of the numpy expression it replaces. (Longer arrays NumPy splits in halves.)"""
    n = a.shape[0]
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[i]
        return res
    r = a[:8].copy()
    i = 8
    while i < n - n % 8:
        for k in range(8):
            r[k] += a[i + k]
        i += 8
    res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    while i < n:
        res += a[i]
        i += 1
    return res


@njit(cache=True)
def _centroid_kernel(p: np.ndarray) -> tuple[float, float]:
    n = p.shape[0]
    cross, mx, my = np.empty(n), np.empty(n), np.empty(n)
    for i in range(n):
        j = i + 1 if i + 1 < n else 0
        x, y, xn, yn = p[i, 0], p[i, 1], p[j, 0], p[j, 1]
        c = x * yn - xn * y
        cross[i], mx[i], my[i] = c, (x + xn) * c, (y + yn) * c
    d = 6.0 * (0.5 * _block_sum(cross))
    return _block_sum(mx) / d, _block_sum(my) / d


def second_moments(poly: Sequence[Sequence[float]]) -> tuple[float, float]:
    """(Jx, Jy) = (integral of y^2 dA, integral of x^2 dA) about the polygon's own centroid."""
    p = as_array(poly)
    if signed_area(p) < 0:
        p = p[::-1]
    p = p - centroid(p)
    x, y = p[:, 0], p[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    jx = float(np.sum((y * y + y * yn + yn * yn) * cross) / 12.0)
    jy = float(np.sum((x * x + x * xn + xn * xn) * cross) / 12.0)
    return jx, jy


def _scale2(p: np.ndarray) -> float:
    """Squared size of a polygon: makes cross-product tolerances unit-independent."""
    span = float(np.max(np.ptp(p, axis=0)))
    return span * span if span > 0 else 1.0


def _turns(p: np.ndarray) -> np.ndarray:
    """z of (p[i] - p[i-1]) x (p[i+1] - p[i]) at every vertex i."""
    d_in = p - np.roll(p, 1, axis=0)
    d_out = np.roll(p, -1, axis=0) - p
    return d_in[:, 0] * d_out[:, 1] - d_in[:, 1] * d_out[:, 0]


def is_convex(poly: Sequence[Sequence[float]], tol: float = 1e-9) -> bool:
    """True when every corner turns the same way (collinear vertices allowed).

    `tol` is relative to the polygon's squared size, so the answer does not depend on units.
    """
    p = as_array(poly)
    z = _turns(p)
    t = tol * _scale2(p)
    return bool(np.all(z >= -t) or np.all(z <= t))


def ccw(poly: Sequence[Sequence[float]]) -> np.ndarray:
    p = as_array(poly)
    return p if signed_area(p) > 0 else p[::-1].copy()


def simplify(poly: Sequence[Sequence[float]], tol: float = 1e-9) -> np.ndarray:
    """Drop repeated and collinear vertices (they carry no shape, and break ear tests).

    A repeated vertex has a zero turn, so one test removes both kinds.
    """
    p = as_array(poly)
    t = tol * _scale2(p)
    while len(p) > 3:
        flat = np.abs(_turns(p)) <= t
        if not np.any(flat):
            break
        # one at a time: removing a vertex changes its neighbours' turns
        p = np.delete(p, int(np.argmax(flat)), axis=0)
    return p


def douglas_peucker(poly: Sequence[Sequence[float]], tol: float) -> np.ndarray:
    """The closed polygon's vertices that keep it within `tol` of the original (Ramer-Douglas-
    Peucker on the two chains between vertex 0 and the vertex farthest from it): a traced
    outline's pixel staircase, a hundred vertices, becomes its corners and curves."""
    p = as_array(poly)
    if len(p) <= 4:
        return p
    far = int(np.argmax(np.hypot(*(p - p[0]).T)))
    keep = np.zeros(len(p), dtype=bool)
    keep[[0, far]] = True
    stack = [(0, far), (far, len(p))]
    while stack:
        i, j = stack.pop()
        a, b = p[i], p[j % len(p)]
        if j - i < 2:
            continue
        seg = b - a
        rel = p[i + 1 : j] - a
        length = float(np.hypot(*seg))
        if length > 0:
            d = np.abs(seg[0] * rel[:, 1] - seg[1] * rel[:, 0]) / length
        else:
            d = np.hypot(*rel.T)
        k = int(np.argmax(d))
        if d[k] > tol:
            m = i + 1 + k
            keep[m] = True
            stack += [(i, m), (m, j)]
    return p[keep]


def _cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))


def _ear_clip(p: np.ndarray, start: int, tol: float) -> list[list[int]]:
    """Triangulate a CCW simple polygon without collinear vertices by ear clipping.

    Ears are searched from vertex `start` on, so different starts give different
    triangulations (the merge step below picks the best). A candidate ear is rejected if any
    other vertex lies inside or on its triangle, which also rejects diagonals that touch
    the boundary.
    """
    n = len(p)
    idx = [(start + i) % n for i in range(n)]
    tris: list[list[int]] = []
    while len(idx) > 3:
        m = len(idx)
        for k in range(m):
            a, b, c = idx[k - 1], idx[k], idx[(k + 1) % m]
            if _cross(p[a], p[b], p[c]) <= tol:
                continue  # reflex (or flat) corner: not an ear
            blocked = False
            for j in idx:
                if j in (a, b, c):
                    continue
                q = p[j]
                if (
                    _cross(p[a], p[b], q) >= -tol
                    and _cross(p[b], p[c], q) >= -tol
                    and _cross(p[c], p[a], q) >= -tol
                ):
                    blocked = True
                    break
            if not blocked:
                tris.append([a, b, c])
                idx.pop(k)
                break
        else:
            raise ValueError("ear clipping found no ear: the polygon is not simple")
    tris.append(idx)
    return tris


def _merge(part1: list[int], part2: list[int], a: int, b: int) -> list[int]:
    """Union of two CCW index polygons sharing the edge a->b (in part1) / b->a (in part2)."""
    i = part1.index(b)
    r1 = part1[i:] + part1[:i]  # b ... a
    j = part2.index(a)
    r2 = part2[j:] + part2[:j]  # a ... b
    return r1 + r2[1:-1]


def _edges(part: list[int]) -> list[tuple[int, int]]:
    return [(part[k], part[(k + 1) % len(part)]) for k in range(len(part))]


def _hertel_mehlhorn(p: np.ndarray, tris: list[list[int]]) -> list[list[int]]:
    """Greedily remove diagonals between parts while the merged part stays convex.

    Hertel-Mehlhorn: the result has at most 4x the minimum number of convex parts.
    """
    parts = [list(t) for t in tris]
    merged = True
    while merged:
        merged = False
        owner = {}
        for pi, part in enumerate(parts):
            for e in _edges(part):
                owner[e] = pi
        for pi, part in enumerate(parts):
            for a, b in _edges(part):
                pj = owner.get((b, a))
                if pj is None or pj == pi:
                    continue
                cand = _merge(part, parts[pj], a, b)
                if is_convex(p[cand]):
                    parts[pi] = cand
                    del parts[pj]
                    merged = True
                    break
            if merged:
                break
    return parts


def convex_decomposition(poly: Sequence[Sequence[float]], max_starts: int = 16) -> list[np.ndarray]:
    """Counter-clockwise convex polygons whose union is `poly` (a simple polygon).

    Engines collide with convex shapes only, and every extra part costs contact work, so we
    want few parts: triangulate by ear clipping from up to `max_starts` different start
    vertices, merge each triangulation greedily (Hertel-Mehlhorn), keep the one with the
    fewest parts. Parts share only edges (no overlap), so their areas add up to the polygon's.
    """
    p = simplify(ccw(poly))
    if is_convex(p):
        return [p]
    n = len(p)
    tol = 1e-9 * _scale2(p)
    best: list[list[int]] | None = None
    for start in sorted({(k * n) // min(n, max_starts) for k in range(min(n, max_starts))}):
        parts = _hertel_mehlhorn(p, _ear_clip(p, start, tol))
        if best is None or len(parts) < len(best):
            best = parts
    assert best is not None
    return [simplify(p[part]) for part in best]


def min_width(poly: Sequence[Sequence[float]]) -> float:
    """Smallest caliper width of the polygon's convex hull (the object's thinnest extent).

    The minimum over directions is reached with one caliper flush with a hull edge.
    """
    from shapely.geometry import MultiPoint

    hull = np.asarray(MultiPoint([tuple(q) for q in as_array(poly)]).convex_hull.exterior.coords)
    hull = hull[:-1]
    best = np.inf
    for k in range(len(hull)):
        e = hull[(k + 1) % len(hull)] - hull[k]
        ne = np.hypot(*e)
        if ne == 0:
            continue
        nrm = np.array([-e[1], e[0]]) / ne
        proj = (hull - hull[k]) @ nrm
        best = min(best, float(np.ptp(proj)))
    return best
