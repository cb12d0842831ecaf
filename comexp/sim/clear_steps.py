"""How many of a pusher's next steps stay out of reach of an object at rest, compiled.

The push protocol advances such steps without its checks (`Simulator.steps_still`): each
check would see the same resting object. planar's compiled contact uses the same closest
point. Apart from `contact.py`, which the driver imports (a grid's push lines), so that the
driver loads no Numba.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def closest_on_polygon(qx, qy, poly):
    """Closest boundary point of a polygon to q, its distance, and whether q is inside."""
    n = poly.shape[0]
    best = np.inf
    bx = by = 0.0
    inside = False
    for i in range(n):
        ax, ay = poly[i, 0], poly[i, 1]
        cx, cy = poly[(i + 1) % n, 0], poly[(i + 1) % n, 1]
        ex, ey = cx - ax, cy - ay
        t = ((qx - ax) * ex + (qy - ay) * ey) / (ex * ex + ey * ey)
        t = min(1.0, max(0.0, t))
        px, py = ax + t * ex, ay + t * ey
        d = math.hypot(px - qx, py - qy)
        if d < best:
            best, bx, by = d, px, py
        if (ay > qy) != (cy > qy) and qx < ax + (qy - ay) * ex / ey:
            inside = not inside  # (the edge crosses q's row, so ey != 0 here)
    return bx, by, best, inside


@njit(cache=True)
def clear_steps(q0x, q0y, targets, poly, radius, margin):
    """The pusher starting at q0 outside the polygon by its radius: how many of the leading
    targets each lie farther from the polygon's boundary (less the radius) than the step to
    it is long plus `margin`, so that every point of each step's straight path is outside by
    `margin`. The count only decides which steps the protocol advances without its checks; a
    step it leaves out is checked as usual."""
    _, _, d, inside = closest_on_polygon(q0x, q0y, poly)
    if inside or d < radius:
        return 0
    px, py = q0x, q0y
    for i in range(targets.shape[0]):
        qx, qy = targets[i, 0], targets[i, 1]
        _, _, d, _ = closest_on_polygon(qx, qy, poly)
        if d - radius < math.hypot(qx - px, qy - py) + margin:
            return i
        px, py = qx, qy
    return targets.shape[0]
