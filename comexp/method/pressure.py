"""The floor's normal pressure under a rigid plate on a uniform elastic (Winkler) foundation:
linear over the footprint's samples, tensionless (clipped at zero), with a given centre.

One place for the referee (`comexp.backends.floor_friction`, which places the centre by moment
balance) and for the quasi-static model the `fit` estimator reads slow pushes with
(`comexp.method.quasi_static.pressure_weights`, the centre under a candidate CoM): where the
floor presses decides how its friction resists a twist, so the two must press alike. Clipping
a linear pressure at zero without solving again moves its centre back toward the footprint's
middle (a CoM at (4, 2) cm in a 10 x 6 cm box pressed as if at (1.9, 0.9) cm): the tensionless
problem is solved here instead.
"""

from __future__ import annotations

import numpy as np
import shapely
from numba import njit

# The loops over the footprint's samples are compiled as SIMD loops: their sums may be
# reassociated (summed in vector lanes) and multiply-adds fused, and a division follows IEEE
# (inf / NaN, which the protocol reports as `sim_unstable`) instead of raising, which is what
# kept LLVM from vectorising them. That changes the sums in their last bits only (a 400-sample
# Newton pass: 4.9 -> 1.3 us); one build on one CPU still gives the same bits every run.
sample_loop = njit(cache=True, fastmath={"reassoc", "contract"}, error_model="numpy")

COP_INSIDE_M = 1e-5  # how far inside the samples' hull a pressure centre is kept


@njit(cache=True)
def solve_spd3(H, r, out):
    """out = H^-1 r for a symmetric positive definite 3x3 H (LDL^T, no pivoting needed)."""
    d0 = H[0, 0]
    l10 = H[0, 1] / d0
    l20 = H[0, 2] / d0
    d1 = H[1, 1] - l10 * H[0, 1]
    l21 = (H[1, 2] - l20 * H[0, 1]) / d1
    d2 = H[2, 2] - l20 * H[0, 2] - l21 * l21 * d1
    y0 = r[0]
    y1 = r[1] - l10 * y0
    y2 = r[2] - l20 * y0 - l21 * y1
    out[2] = y2 / d2
    out[1] = y1 / d1 - l21 * out[2]
    out[0] = y0 / d0 - l10 * out[1] - l20 * out[2]


@sample_loop
def _winkler_kernel(dx, dy, a, W, cx, cy, coef):
    """Tensionless linear pressure: minimise the convex, C1, piecewise-quadratic
    Phi(alpha, beta) = sum a_k max(0, alpha + beta . d_k)^2 / 2 - W (alpha + beta . c), whose
    stationarity is the force and moment balance sum p_k a_k (1, d_k) = W (1, c) with
    p_k = max(0, alpha + beta . d_k). Damped Newton from `coef` (updated in place); its sums
    in scalars and its 3x3 solve in place (`solve_spd3`): nothing is allocated per pass."""
    n = dx.shape[0]
    g = np.empty(3)
    H = np.empty((3, 3))
    step = np.empty(3)
    for _ in range(100):
        phi = g0 = g1 = g2 = 0.0
        h00 = h01 = h02 = h11 = h12 = h22 = 0.0
        for k in range(n):
            p = coef[0] + coef[1] * dx[k] + coef[2] * dy[k]
            if p > 0.0:
                ak = a[k]
                akp = ak * p
                phi += 0.5 * akp * p
                g0 += akp
                g1 += akp * dx[k]
                g2 += akp * dy[k]
                h00 += ak
                h01 += ak * dx[k]
                h02 += ak * dy[k]
                h11 += ak * dx[k] * dx[k]
                h12 += ak * dx[k] * dy[k]
                h22 += ak * dy[k] * dy[k]
        phi -= W * (coef[0] + coef[1] * cx + coef[2] * cy)
        g[0], g[1], g[2] = g0 - W, g1 - W * cx, g2 - W * cy
        if abs(g[0]) <= 1e-12 * W and abs(g[1]) + abs(g[2]) <= 1e-15 * W:
            break
        H[0, 0], H[1, 1], H[2, 2] = h00 + 1e-18, h11 + 1e-18, h22 + 1e-18
        H[0, 1] = H[1, 0] = h01
        H[0, 2] = H[2, 0] = h02
        H[1, 2] = H[2, 1] = h12
        solve_spd3(H, g, step)
        for i in range(3):
            step[i] = -step[i]
        dec = -(g[0] * step[0] + g[1] * step[1] + g[2] * step[2])
        t = 1.0
        while t > 1e-10:
            c0, c1, c2 = coef[0] + t * step[0], coef[1] + t * step[1], coef[2] + t * step[2]
            phi1 = -W * (c0 + c1 * cx + c2 * cy)
            for k in range(n):
                p = c0 + c1 * dx[k] + c2 * dy[k]
                if p > 0.0:
                    phi1 += 0.5 * a[k] * p * p
            if phi1 <= phi - 0.25 * t * dec:
                break
            t *= 0.5
        for i in range(3):
            coef[i] += t * step[i]
        if dec < 1e-30 * W * W:
            break


@sample_loop
def _pressure_into(dx, dy, a, r, coef, out, clip):
    """out_k = a_k max(0, alpha + beta . d_k) (`clip`) or a_k (alpha + beta . d_k); returns
    the smallest pressure and the sums of out_k and out_k r_k (the holding force's and
    torque's, `_update_holding`), in one pass over the samples."""
    p_min = np.inf
    tot = mom = 0.0
    for k in range(dx.shape[0]):
        p = coef[0] + (dx[k] * coef[1] + dy[k] * coef[2])
        p_min = min(p_min, p)
        f = a[k] * p
        if clip and p <= 0.0:
            f = 0.0
        out[k] = f
        tot += f
        mom += f * r[k]
    return p_min, tot, mom


@njit(cache=True)
def pressure_kernel(dx, dy, a, r, W, wm, cx, cy, warm, out):
    """Normal force of each sample for a centre of pressure (cx, cy), into `out`: one 3x3
    solve inside the kern, where no sample is clipped; the tensionless problem beyond it.
    Returns the sums of the forces and of their moments |d_k| out_k (`_update_holding`).

    `warm` (3, updated in place) holds the last tensionless solution's coefficients, NaN when
    the last call was inside the kern: a pressure centre that moves beyond the kern from step
    to step starts its Newton solve there (1-2 iterations instead of ~7 from the kern's
    linear solution; the same convex problem and stopping rule)."""
    rhs = np.empty(3)
    coef = np.empty(3)
    rhs[0], rhs[1], rhs[2] = W, W * cx, W * cy
    solve_spd3(wm, rhs, coef)
    p_min, tot, mom = _pressure_into(dx, dy, a, r, coef, out, False)
    if p_min >= 0.0:
        warm[0] = np.nan
        return tot, mom
    if not np.isnan(warm[0]):
        coef[:] = warm
    _winkler_kernel(dx, dy, a, W, cx, cy, coef)
    warm[:] = coef
    _, tot, mom = _pressure_into(dx, dy, a, r, coef, out, True)
    return tot, mom


class WinklerPressure:
    """Linear, tensionless pressure over the area samples with a given centre of pressure.

    p_k = max(0, alpha + beta . d_k) (d_k: sample offset from the CoM) with sum p_k a_k = W and
    sum p_k a_k d_k = W c: the pressure of a rigid plate on a uniform elastic foundation.
    Inside the footprint's kern no sample is clipped and this is one 3x3 solve; outside it,
    the convex problem of `_winkler_kernel`.
    """

    def __init__(self, d: np.ndarray, a: np.ndarray, weight_n: float) -> None:
        self.d, self.a, self.W = d, a, weight_n
        self._dx = np.ascontiguousarray(d[:, 0])
        self._dy = np.ascontiguousarray(d[:, 1])
        s0, s1, s2 = a.sum(), a @ d, (d * a[:, None]).T @ d
        self._m = np.array(
            [[s0, s1[0], s1[1]], [s1[0], s2[0, 0], s2[0, 1]], [s1[1], s2[1, 0], s2[1, 1]]]
        )

    def forces(self, c: np.ndarray) -> np.ndarray:
        """Normal force of each sample (N) for a centre of pressure at c (offset from the CoM)."""
        out = np.empty(self.a.shape[0])
        r = np.hypot(self._dx, self._dy)
        pressure_kernel(
            self._dx, self._dy, self.a, r, self.W, self._m, float(c[0]), float(c[1]),
            np.full(3, np.nan), out,
        )  # fmt: skip
        return out


@njit(cache=True)
def inside_hull(hull_n, hull_o, cx, cy):
    """(cx, cy) scaled toward the origin until it lies `COP_INSIDE_M` inside the convex hull
    n . x <= o (`half_planes`): a pressure centre the samples can carry."""
    k = 1.0
    while k > 0:
        worst = -np.inf
        for i in range(hull_o.shape[0]):
            v = hull_n[i, 0] * (k * cx) + hull_n[i, 1] * (k * cy)
            worst = max(worst, v - hull_o[i])
        if worst <= -COP_INSIDE_M:
            break
        k *= 0.95
    return k * cx, k * cy


def half_planes(hull: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Outward unit normals n and offsets o of a convex polygon: inside is n . x <= o."""
    if shapely.Polygon(hull).exterior.is_ccw is False:
        hull = hull[::-1]
    e = np.roll(hull, -1, axis=0) - hull
    n = np.stack([e[:, 1], -e[:, 0]], axis=1) / np.hypot(e[:, 0], e[:, 1])[:, None]
    return n, np.einsum("ij,ij->i", n, hull)


def centred_pressure(samples: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(n_centres, n_samples) normal forces of equal-area `samples`, summing to 1 per centre:
    the tensionless linear pressure whose centre is each of `centres` (a centre beyond the
    samples' convex hull is drawn toward their middle until inside, as the referee keeps it)."""
    samples = np.asarray(samples, dtype=float)
    centres = np.atleast_2d(np.asarray(centres, dtype=float))
    middle = samples.mean(0)
    d = samples - middle
    hull = np.asarray(shapely.MultiPoint(d).convex_hull.exterior.coords)[:-1]
    hull_n, hull_o = half_planes(hull)
    pressure = WinklerPressure(d, np.ones(len(d)), 1.0)
    out = np.empty((len(centres), len(samples)))
    for i, g in enumerate(centres - middle):
        cx, cy = inside_hull(hull_n, hull_o, float(g[0]), float(g[1]))
        out[i] = pressure.forces(np.array([cx, cy]))
    return out / out.sum(1, keepdims=True)
