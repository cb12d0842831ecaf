"""Planar polygon geometry for the objects: area, centroid, second moments, convexity,
convex decomposition, and the rigid-body model of an extruded polygon."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from comexp.scene import ObjectSpec, Polygon2


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


def centroid(poly: Sequence[Sequence[float]]) -> np.ndarray:
    p = as_array(poly)
    x, y = p[:, 0], p[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    a = 0.5 * np.sum(cross)
    return np.array([np.sum((x + xn) * cross), np.sum((y + yn) * cross)]) / (6.0 * a)


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


def is_convex(poly: Sequence[Sequence[float]], tol: float = 1e-12) -> bool:
    p = as_array(poly)
    d1 = np.roll(p, -1, axis=0) - p
    d2 = np.roll(p, -2, axis=0) - np.roll(p, -1, axis=0)
    z = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    return bool(np.all(z >= -tol) or np.all(z <= tol))


def ccw(poly: Sequence[Sequence[float]]) -> np.ndarray:
    p = as_array(poly)
    return p if signed_area(p) > 0 else p[::-1].copy()


def convex_decomposition(poly: Sequence[Sequence[float]]) -> list[np.ndarray]:
    """Counter-clockwise convex polygons whose union is `poly` (a simple polygon)."""
    p = ccw(poly)
    if is_convex(p):
        return [p]
    raise NotImplementedError("non-convex decomposition not implemented yet")


def _to_tuple(poly: np.ndarray) -> Polygon2:
    return tuple((float(x), float(y)) for x, y in poly)


def prism_object(
    name: str,
    outline_m: Sequence[Sequence[float]],
    height_m: float,
    com_m: Sequence[float],
    mass_kg: float = 0.2,
    izz_scale: float = 1.0,
    mu_pusher: float = 0.5,
) -> ObjectSpec:
    """Rigid-body model of an extruded polygon.

    The outline is re-centred on its area centroid (the object frame's origin). Inertia: the
    uniform-density values about the centroid, used about the given CoM (the paper moves the CoM
    without changing the inertia), Izz multiplied by `izz_scale`; Ixx and Iyy are raised in
    proportion when needed so that the tensor stays physical (Ixx + Iyy >= Izz).
    """
    p = ccw(outline_m)
    p = p - centroid(p)
    area = signed_area(p)
    jx, jy = second_moments(p)
    ixx = mass_kg * (jx / area + height_m**2 / 12.0)
    iyy = mass_kg * (jy / area + height_m**2 / 12.0)
    izz = mass_kg * (jx + jy) / area * izz_scale
    if ixx + iyy < izz:
        k = izz / (ixx + iyy)
        ixx, iyy = ixx * k, iyy * k
    parts = tuple(_to_tuple(part) for part in convex_decomposition(p))
    return ObjectSpec(
        name=name,
        outline_m=_to_tuple(p),
        convex_parts_m=parts,
        height_m=float(height_m),
        com_m=(float(com_m[0]), float(com_m[1])),
        mass_kg=float(mass_kg),
        ixx_kg_m2=float(ixx),
        iyy_kg_m2=float(iyy),
        izz_kg_m2=float(izz),
        mu_pusher=float(mu_pusher),
    )


def box_object(
    length_m: float,
    width_m: float,
    height_m: float,
    com_m: Sequence[float] = (0.0, 0.0),
    **kwargs: float,
) -> ObjectSpec:
    """A rectangular block centred on its object frame (length along x)."""
    a, b = length_m / 2.0, width_m / 2.0
    outline = [(-a, -b), (a, -b), (a, b), (-a, b)]
    return prism_object("box", outline, height_m, com_m, **kwargs)
