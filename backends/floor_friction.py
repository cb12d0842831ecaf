"""The floor's Coulomb friction over a prism's footprint: the model every backend shares.

- The footprint is sampled by the cells of a regular grid clipped to the polygon; each sample
  carries the normal force of its area.
- The normal pressure is that of a rigid plate on a uniform elastic (Winkler) foundation
  (`comexp.method.pressure`, which the `fit` estimator's model shares):
  linear, tensionless (clipped at zero), its centre of pressure placed by moment balance.
- Anisotropic floors follow the elliptic maximum-dissipation law: the friction force of a
  sample with slip u lies in the ellipse |(f_x / mu_x, f_y / mu_y)| <= N and dissipates the
  most, f = -N A^2 u / |A u|, A = diag(mu_x, mu_y) along the floor's axes.
- A step's friction is solved at the velocity level, implicitly (backward Euler): the
  end-of-step twist minimises the kinetic-energy change plus the step's frictional
  dissipation, a convex problem in 3 variables (damped Newton, Numba-compiled kernels). An
  object the friction can hold is exactly at rest: no creep, no chatter.

`backend=planar` solves this together with its pusher contact (backends/planar_sim.py); the
engines, with `floor_friction=model`, apply `impulse_kernel`'s impulse as an external force
each step (MuJoCo inside its compiled loop, pybullet through
`FootprintFriction.impulse_of_twist`), their own object-floor friction off (docs/physics.md).
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np
import shapely
from numba import njit

from comexp.backends.numba_kernels import DirectCall
from comexp.backends.physics_settings import FrictionSettings  # with every backend's settings
from comexp.method.pressure import (  # the Winkler pressure: shared with the fit model
    COP_INSIDE_M,
    WinklerPressure,
    half_planes,
    inside_hull,
    pressure_kernel,
    sample_loop,
    solve_spd3,
)
from comexp.sim.contact import pusher_contact_height_m
from comexp.sim.scene import GRAVITY_M_S2, ObjectSpec, PusherSpec


@njit(cache=True)
def objective_kernel(xi, xi_hat, M, w, dx, dy, mx, my, dt, eps, k, tau, r0, floor):
    """Value, gradient and Hessian of one step's convex objective at the twist xi.

    0.5 |xi - xi_hat|_M^2 + dt sum_k w_k |A u_k| + k |tau . xi - r0|: kinetic energy change,
    the floor's frictional dissipation over the step (u_k = v + omega x d_k the slip of sample
    k, A = diag(mu_x, mu_y), w_k its normal force), and the pusher's tangential friction
    (k = mu_p times the normal impulse). Norms are smoothed below `eps` (m/s).
    """
    g = np.zeros(3)
    H = np.zeros((3, 3))
    f = _objective_into(xi, xi_hat, M, w, dx, dy, mx, my, dt, eps, k, tau, r0, floor, g, H)
    return f, g, H


@sample_loop
def _objective_into(xi, xi_hat, M, w, dx, dy, mx, my, dt, eps, k, tau, r0, floor, g, H):
    """`objective_kernel` into preallocated g and H (the Newton loop's hot path): the sums
    over the samples run in scalars, the slip norm's Hessian with one division."""
    f = 0.0
    for i in range(3):
        dv = xi[i] - xi_hat[i]
        f += 0.5 * M[i] * dv * dv
        g[i] = M[i] * dv
        for m in range(3):
            H[i, m] = 0.0
        H[i, i] = M[i]
    e2 = eps * eps
    if floor:
        x0, x1, x2 = xi[0], xi[1], xi[2]
        acc = g0 = g1 = g2 = 0.0
        hxx = hyy = hxy = hxw = hyw = hww = 0.0
        for j in range(w.shape[0]):
            djx, djy = dx[j], dy[j]
            gx = mx * (x0 - x2 * djy)
            gy = my * (x1 + x2 * djx)
            s2 = gx * gx + gy * gy + e2
            s = math.sqrt(s2)
            acc += w[j] * s
            ws = dt * w[j] / s
            q = ws / s2
            ax = ws * gx * mx
            ay = ws * gy * my
            g0 += ax
            g1 += ay
            g2 += ay * djx - ax * djy
            exx = q * (gy * gy + e2)
            eyy = q * (gx * gx + e2)
            exy = -q * gx * gy
            b2x = -mx * djy
            b2y = my * djx
            hxx += exx
            hyy += eyy
            hxy += exy
            hxw += exx * b2x + exy * b2y
            hyw += exy * b2x + eyy * b2y
            hww += b2x * b2x * exx + 2.0 * b2x * b2y * exy + b2y * b2y * eyy
        f += dt * acc
        g[0] += g0
        g[1] += g1
        g[2] += g2
        H[0, 0] += mx * mx * hxx
        H[1, 1] += my * my * hyy
        H[0, 1] += mx * my * hxy
        H[0, 2] += mx * hxw
        H[1, 2] += my * hyw
        H[2, 2] += hww
        H[1, 0] = H[0, 1]
        H[2, 0] = H[0, 2]
        H[2, 1] = H[1, 2]
    if k > 0.0:
        r = tau[0] * xi[0] + tau[1] * xi[1] + tau[2] * xi[2] - r0
        s = math.sqrt(r * r + e2)
        f += k * s
        c = k * e2 / (s * s * s)
        for i in range(3):
            g[i] += k * r / s * tau[i]
            for m in range(3):
                H[i, m] += c * tau[i] * tau[m]
    return f


@sample_loop
def value_kernel(xi, xi_hat, M, w, dx, dy, mx, my, dt, eps, k, tau, r0, floor):
    """The value of `objective_kernel` alone (line search)."""
    f = 0.0
    for i in range(3):
        dv = xi[i] - xi_hat[i]
        f += 0.5 * M[i] * dv * dv
    e2 = eps * eps
    if floor:
        acc = 0.0
        for j in range(w.shape[0]):
            gx = mx * (xi[0] - xi[2] * dy[j])
            gy = my * (xi[1] + xi[2] * dx[j])
            acc += w[j] * math.sqrt(gx * gx + gy * gy + e2)
        f += dt * acc
    if k > 0.0:
        r = tau[0] * xi[0] + tau[1] * xi[1] + tau[2] * xi[2] - r0
        f += k * math.sqrt(r * r + e2)
    return f


@njit(cache=True)
def _line_search(
    xi, step, t, f, dec, trial, xi_hat, M, w, dx, dy, mx, my, dt, eps, k, tau, r0, floor, g1, H1
):
    """`minimise_kernel`'s backtracking from t along `step`: each trial evaluated with its
    gradient and Hessian (into g1, H1). Returns t, the objective there and whether the
    trial was accepted (else t fell below 1e-12 and was not evaluated)."""
    while t > 1e-12:
        for i in range(3):
            trial[i] = xi[i] + t * step[i]
        f1 = _objective_into(
            trial, xi_hat, M, w, dx, dy, mx, my, dt, eps, k, tau, r0, floor, g1, H1
        )
        if f1 <= f - 0.25 * t * dec:
            return t, f1, True
        # the quadratic through f, its slope -dec at 0 and f1 at t: its minimiser,
        # kept within [t / 10, t / 2]
        curv = f1 - f + dec * t
        tq = 0.5 * dec * t * t / curv if curv > 0.0 else 0.5 * t
        t = min(0.5 * t, max(0.1 * t, tq))
    return t, 0.0, False


@njit(cache=True)
def minimise_kernel(
    xi0, xi_hat, M, w, dx, dy, mx, my, dt, eps, k, tau, r0, floor, a, b, constrained, tol, itmax
):
    """Damped Newton on `objective_kernel`, optionally on the plane a . xi = b (KKT).

    The objective's Hessian is positive definite (the mass matrix plus convex terms), so the
    Newton step is two 3x3 LDL^T solves: y = H^-1 g, z = H^-1 a, and on the plane
    step = -(y - z (a . y) / (a . z)). The backtracking line search (Armijo, 1/4) takes the
    minimiser of the quadratic through f, its slope and the rejected trial, within [1/10,
    1/2] of the rejected step: near the norms' kinks a Newton step overshoots by orders of
    magnitude, which halving pays for one pass over the samples per factor 2. A trial is
    evaluated with its gradient and Hessian: accepted (nearly always), that pass is the next
    iteration's, so an iteration costs one pass over the samples, not a pass and a value pass.
    Returns the minimiser and the plane's multiplier (an impulse, N s)."""
    xi = xi0.copy()
    if constrained:
        den = 0.0
        ax = 0.0
        for i in range(3):
            den += a[i] * a[i] / M[i]
            ax += a[i] * xi[i]
        for i in range(3):
            xi[i] += a[i] / M[i] * (b - ax) / den
    g = np.zeros(3)
    H = np.zeros((3, 3))
    g1 = np.zeros(3)  # the trial's: an accepted trial's pass is the next iteration's
    H1 = np.zeros((3, 3))
    y = np.zeros(3)
    z = np.zeros(3)
    step = np.zeros(3)
    trial = np.zeros(3)
    f = _objective_into(xi, xi_hat, M, w, dx, dy, mx, my, dt, eps, k, tau, r0, floor, g, H)
    for _ in range(itmax):
        solve_spd3(H, g, y)
        if constrained:
            solve_spd3(H, a, z)
            ratio = (a[0] * y[0] + a[1] * y[1] + a[2] * y[2]) / (
                a[0] * z[0] + a[1] * z[1] + a[2] * z[2]
            )
            for i in range(3):
                step[i] = -(y[i] - z[i] * ratio)
        else:
            for i in range(3):
                step[i] = -y[i]
        dec = -(g[0] * step[0] + g[1] * step[1] + g[2] * step[2])
        if dec < tol:
            break
        t = 1.0
        if k > 0.0:
            # the pusher's friction |tau . xi - r0| has its kink where the contact sticks;
            # beyond the smoothing its curvature vanishes, so a step that crosses the kink
            # overshoots it by orders of magnitude: try landing on the kink first
            r = tau[0] * xi[0] + tau[1] * xi[1] + tau[2] * xi[2] - r0
            dr = tau[0] * step[0] + tau[1] * step[1] + tau[2] * step[2]
            if abs(r) > eps and r * (r + dr) < 0.0:
                t = -r / dr
        t, f1, accepted = _line_search(
            xi, step, t, f, dec, trial, xi_hat, M, w, dx, dy, mx, my, dt, eps, k, tau, r0, floor,
            g1, H1,
        )  # fmt: skip
        for i in range(3):
            xi[i] = xi[i] + t * step[i]
        if accepted:  # the trial's pass is the new point's (the same twist)
            f = f1
            g, g1 = g1, g
            H, H1 = H1, H
        else:
            f = _objective_into(xi, xi_hat, M, w, dx, dy, mx, my, dt, eps, k, tau, r0, floor, g, H)
    lam = 0.0
    if constrained:  # g is the objective's gradient at xi
        lam = (g[0] * a[0] + g[1] * a[1] + g[2] * a[2]) / (a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    return xi, lam


def footprint_samples(outline_m: np.ndarray, n_target: int) -> tuple[np.ndarray, np.ndarray]:
    """Area samples of the footprint: the cells of a regular grid clipped to the polygon, each
    sample at its clipped cell's centroid with the clipped area.

    The spacing h = sqrt(area / n_target); the grid is anchored at the polygon's centroid so
    that symmetric shapes get symmetric samples. Clipping makes the samples' area, first and
    second moments those of the polygon to O(h^2) and lets the boundary cells' samples reach
    close to the edges, where the pressure of an object about to tip concentrates.
    """
    poly = shapely.Polygon(outline_m)
    h = math.sqrt(poly.area / max(n_target, 1))
    lo = np.floor(outline_m.min(axis=0) / h) - 1
    hi = np.ceil(outline_m.max(axis=0) / h) + 1
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
    x0, y0 = gx.ravel() * h, gy.ravel() * h
    cells = shapely.box(x0, y0, x0 + h, y0 + h)
    hit = shapely.intersects(poly, cells)
    clipped = shapely.intersection(poly, cells[hit])
    area = shapely.area(clipped)
    keep = area > 1e-6 * h * h
    cent = shapely.get_coordinates(shapely.centroid(clipped[keep]))
    return cent, area[keep]


@functools.lru_cache(maxsize=64)
def _cached_samples(outline: tuple, n_target: int) -> tuple[np.ndarray, np.ndarray]:
    return footprint_samples(np.array(outline, dtype=float), n_target)


def outline_key(outline_m: np.ndarray) -> tuple:
    """An outline as the hashable key of the per-outline caches below (its vertices' floats)."""
    return tuple(tuple(float(v) for v in row) for row in np.asarray(outline_m, dtype=float))


def samples_of(
    outline_m: np.ndarray, n_target: int, key: tuple | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """`footprint_samples`, kept per outline: an episode rebuilds its scene for every push
    (re-centring), and the polygon clipping was most of a planar build. `key`: the outline's
    `outline_key`, when the caller has it already. Copies: the caller owns them."""
    pts, area = _cached_samples(outline_key(outline_m) if key is None else key, int(n_target))
    return pts.copy(), area.copy()


def hulls_of(
    outline_m: np.ndarray, n_target: int, com_m: np.ndarray, key: tuple | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The half planes (from the CoM) of the samples' convex hull and of the outline's (the
    support polygon), kept per outline and CoM as `samples_of` keeps the samples: the
    re-centring builds of an episode ask for the same ones. `key` as for `samples_of`.
    Copies: the caller owns them."""
    com = (float(com_m[0]), float(com_m[1]))
    key = outline_key(outline_m) if key is None else key
    hulls = _cached_hulls(key, int(n_target), com)
    return tuple(a.copy() for a in hulls)  # type: ignore[return-value]


@functools.lru_cache(maxsize=64)
def _cached_hulls(outline: tuple, n_target: int, com: tuple) -> tuple[np.ndarray, ...]:
    pts, _ = _cached_samples(outline, n_target)
    c = np.array(com, dtype=float)
    sample_n, sample_o = half_planes(
        np.asarray(shapely.MultiPoint(pts).convex_hull.exterior.coords)[:-1] - c
    )
    hull = np.asarray(shapely.Polygon(np.array(outline, dtype=float)).convex_hull.exterior.coords)
    hull_n, hull_o = half_planes(hull[:-1] - c)
    return sample_n, sample_o, hull_n, hull_o


class FrictionGeometry(NamedTuple):
    """What the compiled kernels know of one object on its floor (read-only, SI units).

    Offsets and the hulls are from the CoM in the object frame; `wm` is the samples' area
    moment matrix of the Winkler solve inside the kern."""

    M: np.ndarray  # (m, m, I_zz)
    mu_x: float
    mu_y: float
    m: float
    h_com: float
    z_push: float
    dx: np.ndarray  # sample offsets, object frame
    dy: np.ndarray
    r: np.ndarray  # their distances from the CoM
    area: np.ndarray
    W: float  # weight (N)
    wm: np.ndarray
    hull_n: np.ndarray  # support polygon: inside is n . c <= o
    hull_o: np.ndarray
    sample_hull_n: np.ndarray
    sample_hull_o: np.ndarray
    eps: float  # FrictionSettings, see there
    tol: float
    itmax: int
    rest_snap: float


# Friction state vector `fs` (float64): the pressure centre (object frame, from the CoM), the
# flag set once a required centre left the hull (`TIPPED`; planar's pitch, not this flag, says
# whether the object tips), the holding force and torque at the current pressure, the yaw the
# world-axis sample offsets were last computed for (NaN: never), the last tensionless
# pressure's three coefficients (`pressure_kernel`'s warm start; NaN: none).
COP_X, COP_Y, TIPPED, F_HOLD, TAU_HOLD, YAW_CACHED, WARM_A, WARM_BX, WARM_BY = range(9)
FS_SIZE = 9


@sample_loop
def offsets_kernel(geo, fs, yaw, dxw, dyw):
    """The samples' offsets from the CoM in world axes, into (dxw, dyw); recomputed only when
    the yaw changed (an object at rest keeps them)."""
    if yaw != fs[YAW_CACHED]:
        c, s = math.cos(yaw), math.sin(yaw)
        for k in range(geo.dx.shape[0]):
            dxw[k] = c * geo.dx[k] - s * geo.dy[k]
            dyw[k] = s * geo.dx[k] + c * geo.dy[k]
        fs[YAW_CACHED] = yaw


@njit(cache=True)
def _set_holding(geo, fs, tot, mom):
    """Friction force and torque the floor can surely supply at a pressure whose normal
    forces sum to `tot` and their moments |d_k| N_k to `mom`."""
    mu_min = min(geo.mu_x, geo.mu_y)
    fs[F_HOLD] = max(mu_min * tot, 1e-300)
    fs[TAU_HOLD] = max(mu_min * mom, 1e-300)


@sample_loop
def _update_holding(geo, fs, normal):
    """`_set_holding` of the pressure `normal`."""
    tot = 0.0
    mom = 0.0
    for k in range(normal.shape[0]):
        tot += normal[k]
        mom += normal[k] * geo.r[k]
    _set_holding(geo, fs, tot, mom)


@njit(cache=True)
def set_cop_kernel(geo, fs, normal, cx, cy):
    """Pressure (into `normal`) for a centre of pressure c (object frame, from the CoM);
    fs[TIPPED] once c leaves the convex hull of the footprint (then the pressure is recomputed
    at every nonzero c; whether the object tips is planar's pitch, backends/planar_sim.py).
    (Between the samples' hull and the footprint's the pressure is as close to the edge as the
    samples reach.)"""
    for i in range(geo.hull_o.shape[0]):
        if geo.hull_n[i, 0] * cx + geo.hull_n[i, 1] * cy - geo.hull_o[i] > 0.0:
            fs[TIPPED] = 1.0
    cx, cy = inside_hull(geo.sample_hull_n, geo.sample_hull_o, cx, cy)
    # a 2 um move of the pressure centre changes nothing that matters: keep the pressure
    moved = math.hypot(cx - fs[COP_X], cy - fs[COP_Y]) > 2e-6
    nonzero = cx != 0.0 or cy != 0.0
    released = not nonzero and (fs[COP_X] != 0.0 or fs[COP_Y] != 0.0)  # the weight alone
    if moved or released or (fs[TIPPED] != 0.0 and nonzero):
        tot, mom = pressure_kernel(
            geo.dx, geo.dy, geo.area, geo.r, geo.W, geo.wm, cx, cy, fs[WARM_A : WARM_BY + 1],
            normal,
        )  # fmt: skip
        fs[COP_X], fs[COP_Y] = cx, cy
        _set_holding(geo, fs, tot, mom)


@njit(cache=True)
def free_solve_kernel(geo, normal, xi_hat, dxw, dyw, dt):
    """End-of-step twist under the floor's friction alone; exactly zero when the friction
    can hold the object (compared on the exact, unsmoothed objective)."""
    zero = np.zeros(3)
    if xi_hat[0] == 0.0 and xi_hat[1] == 0.0 and xi_hat[2] == 0.0:
        return zero
    mx, my = geo.mu_x, geo.mu_y
    sol, _ = minimise_kernel(
        xi_hat, xi_hat, geo.M, normal, dxw, dyw, mx, my, dt, geo.eps, 0.0, zero, 0.0, True,
        zero, 0.0, False, geo.tol, geo.itmax,
    )  # fmt: skip
    snap = geo.rest_snap
    if abs(sol[0]) < snap and abs(sol[1]) < snap and abs(sol[2]) < 1e-4:
        f0 = value_kernel(zero, xi_hat, geo.M, normal, dxw, dyw, mx, my, dt, 0.0, 0.0, zero,
                          0.0, True)  # fmt: skip
        f1 = value_kernel(sol, xi_hat, geo.M, normal, dxw, dyw, mx, my, dt, 0.0, 0.0, zero,
                          0.0, True)  # fmt: skip
        if f0 <= f1:
            return zero
    return sol


@njit(cache=True)
def impulse_kernel(geo, fs, normal, dxw, dyw, xi_hat, yaw, dt, pushed):
    """`FootprintFriction.impulse`, compiled: the friction impulse, the pressure updated."""
    M = geo.M
    need_x, need_y, need_w = M[0] * xi_hat[0] / dt, M[1] * xi_hat[1] / dt, M[2] * xi_hat[2] / dt
    imp = np.empty(3)
    if (abs(need_x) + abs(need_y)) / fs[F_HOLD] + abs(need_w) / fs[TAU_HOLD] < 0.9:
        # inside the limit surface (its octahedron of pure-force and pure-torque vertices):
        # static friction holds the object, no solve needed
        for i in range(3):
            imp[i] = -M[i] * xi_hat[i]
    else:
        offsets_kernel(geo, fs, yaw, dxw, dyw)
        sol = free_solve_kernel(geo, normal, xi_hat, dxw, dyw, dt)
        for i in range(3):
            imp[i] = M[i] * (sol[i] - xi_hat[i])
    z = geo.z_push if pushed else geo.h_com
    den = dt * geo.m * GRAVITY_M_S2
    cwx, cwy = -z * imp[0] / den, -z * imp[1] / den
    c, s = math.cos(yaw), math.sin(yaw)
    set_cop_kernel(geo, fs, normal, c * cwx + s * cwy, -s * cwx + c * cwy)
    return imp


@njit(cache=True)
def impulse_of_twist_kernel(geo, fs, normal, dxw, dyw, vx, vy, wz, yaw, dt, pushed):
    """`impulse_kernel` of the twist (vx, vy, wz), its impulse as three floats: an engine
    stepped from Python (pybullet) then builds and unpacks no array per step."""
    xi_hat = np.empty(3)
    xi_hat[0], xi_hat[1], xi_hat[2] = vx, vy, wz
    imp = impulse_kernel(geo, fs, normal, dxw, dyw, xi_hat, yaw, dt, pushed)
    return imp[0], imp[1], imp[2]


# `FootprintFriction.impulse_of_twist` is called from Python every engine step (pybullet)
_impulse_of_twist_call = DirectCall(impulse_of_twist_kernel)


class FootprintFriction:
    """The floor's friction on one object: area samples, Winkler pressure, the implicit solve.

    Frames: samples and the centre of pressure (`cop`, an offset from the CoM) live in the
    object frame; twists xi = (v_x, v_y, omega) of the CoM and impulses in the world frame.
    The state (`fs`, `normal`, the world-axis offsets) lives in arrays that the compiled
    kernels update in place, so that a backend can run whole steps without Python.
    """

    def __init__(
        self,
        obj: ObjectSpec,
        mu_x: float,
        mu_y: float,
        pusher: PusherSpec,
        settings: FrictionSettings | None = None,
    ) -> None:
        self.set = settings or FrictionSettings()
        self.m = obj.mass_kg
        self.M = np.array([obj.mass_kg, obj.mass_kg, obj.izz_kg_m2])
        self.mu = np.array([mu_x, mu_y], dtype=float)
        self.com = np.asarray(obj.com_m, dtype=float)
        outline = np.asarray(obj.outline_m, dtype=float)
        self.h_com = obj.height_m / 2.0
        self.z_push = pusher_contact_height_m(pusher, obj.height_m)
        key = outline_key(outline)  # the per-outline caches' key, made once
        pts, area = samples_of(outline, self.set.samples, key)
        self.d_obj = pts - self.com  # sample offsets from the CoM, object frame
        self.pressure = WinklerPressure(self.d_obj, area, self.m * GRAVITY_M_S2)
        # the samples' hull and the support polygon (the outline's hull), from the CoM
        self.sample_hull_n, self.sample_hull_o, self.hull_n, self.hull_o = hulls_of(
            outline, self.set.samples, self.com, key
        )
        if float(np.min(self.sample_hull_o)) < COP_INSIDE_M:
            # no pressure on the samples holds up a CoM beyond them (on or past the outline's
            # edge); `set_cop_kernel` would shrink the pressure centre towards it for ever
            raise ValueError(
                f"{obj.name}: the CoM ({self.com[0]:.4f}, {self.com[1]:.4f}) m is not inside "
                "the footprint's support: nothing holds the object up"
            )
        s = self.set
        c = np.ascontiguousarray
        self.geo = FrictionGeometry(
            M=self.M, mu_x=float(mu_x), mu_y=float(mu_y), m=float(self.m),
            h_com=float(self.h_com), z_push=float(self.z_push),
            dx=c(self.d_obj[:, 0]), dy=c(self.d_obj[:, 1]),
            r=np.hypot(self.d_obj[:, 0], self.d_obj[:, 1]), area=c(area, dtype=float),
            W=float(self.pressure.W), wm=c(self.pressure._m), hull_n=c(self.hull_n),
            hull_o=c(self.hull_o), sample_hull_n=c(self.sample_hull_n),
            sample_hull_o=c(self.sample_hull_o), eps=float(s.smoothing_m_s),
            tol=float(s.newton_tol), itmax=int(s.max_newton), rest_snap=float(s.rest_snap_m_s),
        )  # fmt: skip
        # a list: every step's input (xi_hat x, y, z, yaw, pushed) is appended to it, by
        # `impulse` or by a backend's compiled loop (bench/step_cost.py replays them)
        self.inputs: list[tuple[float, float, float, float, bool]] | None = None
        self.fs = np.zeros(FS_SIZE)
        self.fs[YAW_CACHED] = np.nan
        self.fs[WARM_A : WARM_BY + 1] = np.nan
        self.normal = self.pressure.forces(np.zeros(2))
        n = self.normal.shape[0]
        self.dxw, self.dyw = np.zeros(n), np.zeros(n)  # offsets in world axes (offsets_kernel)
        _update_holding(self.geo, self.fs, self.normal)
        self._fresh = (self.fs.copy(), self.normal.copy())

    def reset(self) -> None:
        """Back to the state it was made with (the object at rest, nothing cached), in place:
        the same object on the same floor again costs no new samples or pressure."""
        fs, normal = self._fresh
        self.fs[:] = fs
        self.normal[:] = normal
        self.dxw[:] = 0.0
        self.dyw[:] = 0.0

    @property
    def cop(self) -> np.ndarray:
        """Centre of pressure, object frame, from the CoM (a view of the state)."""
        return self.fs[COP_X : COP_Y + 1]

    def impulse(self, xi_hat: np.ndarray, yaw: float, dt: float, pushed: bool) -> np.ndarray:
        """The floor's friction impulse (N s, and N m s about z) over one step of an engine,
        from the twist `xi_hat` the object would have without it; the pressure centre then
        follows for the next step: c = -z F_f / (m g), with z the pusher's contact height
        while the pusher holds the object against the friction (it then balances F_f), the
        CoM's height while the object slides free (inertia balances F_f)."""
        vx, vy, wz = np.asarray(xi_hat, dtype=np.float64).tolist()
        return np.array(self.impulse_of_twist(vx, vy, wz, float(yaw), float(dt), bool(pushed)))

    def impulse_of_twist(
        self, vx: float, vy: float, wz: float, yaw: float, dt: float, pushed: bool
    ) -> tuple[float, float, float]:
        """`impulse` of the twist (vx, vy, wz) given as floats, as a tuple: the per-step call
        of a backend stepped from Python, which then builds and unpacks no array per step
        (`impulse_kernel`'s bits, as MuJoCo's compiled loop computes them)."""
        if self.inputs is not None:
            self.inputs.append((vx, vy, wz, yaw, pushed))
        return _impulse_of_twist_call(
            self.geo, self.fs, self.normal, self.dxw, self.dyw, vx, vy, wz, yaw, dt, pushed
        )
