"""The rigid body of an extruded polygon: its simulator model (`ObjectSpec`), inertia included,
made in one place for every scene (`prism_object`).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np

from comexp.method.frames import Polygon2
from comexp.method.geometry import ccw, centroid, convex_decomposition, second_moments, signed_area
from comexp.sim.scene import ObjectSpec


def _to_tuple(poly: np.ndarray) -> Polygon2:
    return tuple((float(x), float(y)) for x, y in poly)


@functools.lru_cache(maxsize=256)
def _convex_parts(outline: Polygon2) -> tuple[Polygon2, ...]:
    """`convex_decomposition` of a (centred) outline, kept per outline: every episode builds
    its object model afresh (`prism_object`), and the decomposition is ~90% of that (~2 ms)."""
    return tuple(_to_tuple(part) for part in convex_decomposition(np.array(outline)))


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
    # Raise to Ixx + Iyy = Izz (1 + 1e-6), not to exact equality: equality is lost to rounding in
    # the sum, and MuJoCo then refuses the body ("inertia must satisfy A + B >= C").
    min_sum = izz * (1.0 + 1e-6)
    if ixx + iyy < min_sum:
        k = min_sum / (ixx + iyy)
        ixx, iyy = ixx * k, iyy * k
    parts = _convex_parts(_to_tuple(p))
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
