"""The floor's Coulomb friction over a prism's footprint: the model every backend shares.

- The footprint is sampled by the cells of a regular grid clipped to the polygon; each sample
  carries the normal force of its area.
- The normal pressure is that of a rigid plate on a uniform elastic (Winkler) foundation:
  linear, tensionless (clipped at zero), its centre of pressure placed by moment balance.
- Anisotropic floors follow the elliptic maximum-dissipation law: the friction force of a
  sample with slip u lies in the ellipse |(f_x / mu_x, f_y / mu_y)| <= N and dissipates the
  most, f = -N A^2 u / |A u|, A = diag(mu_x, mu_y) along the floor's axes.
- A step's friction is solved at the velocity level, implicitly (backward Euler): the
  end-of-step twist minimises the kinetic-energy change plus the step's frictional
  dissipation, a convex problem in 3 variables (damped Newton, Numba-compiled kernels). An
  object the friction can hold is exactly at rest: no creep, no chatter.

`backend=planar` solves this together with its pusher contact (backends/planar_sim.py); the
engines, with `floor_friction=model`, apply `FootprintFriction.impulse` as an external force
each step, their own object-floor friction off (docs/physics.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely
from numba import njit

from comexp.scene import GRAVITY_M_S2, ObjectSpec, PusherSpec
from comexp.simulator import pusher_contact_height_m

ZERO3 = np.zeros(3)
EMPTY = np.zeros(0)


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
    f = 0.0
    for i in range(3):
        dv = xi[i] - xi_hat[i]
        f += 0.5 * M[i] * dv * dv
        g[i] = M[i] * dv
        H[i, i] = M[i]
    e2 = eps * eps
    if floor:
        for j in range(w.shape[0]):
            gx = mx * (xi[0] - xi[2] * dy[j])
            gy = my * (xi[1] + xi[2] * dx[j])
            s = math.sqrt(gx * gx + gy * gy + e2)
            f += dt * w[j] * s
            ws = dt * w[j] / s
            ax = ws * gx * mx
            ay = ws * gy * my
            g[0] += ax
            g[1] += ay
            g[2] += ay * dx[j] - ax * dy[j]
            s2 = s * s
            exx = ws * (gy * gy + e2) / s2
            eyy = ws * (gx * gx + e2) / s2
            exy = -ws * gx * gy / s2
            b2x = -mx * dy[j]
            b2y = my * dx[j]
            H[0, 0] += mx * mx * exx
            H[1, 1] += my * my * eyy
            H[0, 1] += mx * my * exy
            H[0, 2] += mx * (exx * b2x + exy * b2y)
            H[1, 2] += my * (exy * b2x + eyy * b2y)
            H[2, 2] += b2x * b2x * exx + 2.0 * b2x * b2y * exy + b2y * b2y * eyy
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
    return f, g, H


@njit(cache=True)
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
def minimise_kernel(
    xi0, xi_hat, M, w, dx, dy, mx, my, dt, eps, k, tau, r0, floor, a, b, constrained, tol, itmax
):
    """Damped Newton on `objective_kernel`, optionally on the plane a . xi = b (KKT).

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
    K = np.zeros((4, 4))
    rhs = np.zeros(4)
    for _ in range(itmax):
        f, g, H = objective_kernel(xi, xi_hat, M, w, dx, dy, mx, my, dt, eps, k, tau, r0, floor)
        if constrained:
            K[:3, :3] = H
            for i in range(3):
                K[i, 3] = a[i]
                K[3, i] = a[i]
                rhs[i] = -g[i]
            K[3, 3] = 0.0
            rhs[3] = 0.0
            step = np.linalg.solve(K, rhs)[:3]
        else:
            step = np.linalg.solve(H, -g)
        dec = -(g[0] * step[0] + g[1] * step[1] + g[2] * step[2])
        if dec < tol:
            break
        t = 1.0
        while t > 1e-12:
            f1 = value_kernel(
                xi + t * step, xi_hat, M, w, dx, dy, mx, my, dt, eps, k, tau, r0, floor
            )
            if f1 <= f - 0.25 * t * dec:
                break
            t *= 0.5
        xi = xi + t * step
    lam = 0.0
    if constrained:
        g = objective_kernel(xi, xi_hat, M, w, dx, dy, mx, my, dt, eps, k, tau, r0, floor)[1]
        lam = (g[0] * a[0] + g[1] * a[1] + g[2] * a[2]) / (a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    return xi, lam


@dataclass(frozen=True)
class FrictionSettings:
    """Numerical settings of the footprint friction (their convergence is tested)."""

    samples: int = 400  # target number of footprint area samples (grid cells)
    smoothing_m_s: float = 1e-7  # |u| is smoothed below this slip inside the Newton solve only
    newton_tol: float = 1e-13  # Newton decrement (J) at which a step's solve has converged
    max_newton: int = 60
    rest_snap_m_s: float = 1e-6  # a solved velocity this small, and no better than 0, is 0


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


@njit(cache=True)
def _winkler_kernel(dx, dy, a, W, cx, cy, coef):
    """Tensionless linear pressure: minimise the convex, C1, piecewise-quadratic
    Phi(alpha, beta) = sum a_k max(0, alpha + beta . d_k)^2 / 2 - W (alpha + beta . c), whose
    stationarity is the force and moment balance sum p_k a_k (1, d_k) = W (1, c) with
    p_k = max(0, alpha + beta . d_k). Damped Newton from `coef` (updated in place)."""
    n = dx.shape[0]
    for _ in range(100):
        g = np.zeros(3)
        H = np.zeros((3, 3))
        phi = 0.0
        for k in range(n):
            p = coef[0] + coef[1] * dx[k] + coef[2] * dy[k]
            if p > 0.0:
                ak = a[k]
                phi += 0.5 * ak * p * p
                g[0] += ak * p
                g[1] += ak * p * dx[k]
                g[2] += ak * p * dy[k]
                H[0, 0] += ak
                H[0, 1] += ak * dx[k]
                H[0, 2] += ak * dy[k]
                H[1, 1] += ak * dx[k] * dx[k]
                H[1, 2] += ak * dx[k] * dy[k]
                H[2, 2] += ak * dy[k] * dy[k]
        phi -= W * (coef[0] + coef[1] * cx + coef[2] * cy)
        g[0] -= W
        g[1] -= W * cx
        g[2] -= W * cy
        if abs(g[0]) <= 1e-12 * W and abs(g[1]) + abs(g[2]) <= 1e-15 * W:
            break
        H[1, 0] = H[0, 1]
        H[2, 0] = H[0, 2]
        H[2, 1] = H[1, 2]
        for i in range(3):
            H[i, i] += 1e-18
        step = -np.linalg.solve(H, g)
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
    out = np.empty(n)
    for k in range(n):
        p = coef[0] + coef[1] * dx[k] + coef[2] * dy[k]
        out[k] = a[k] * p if p > 0.0 else 0.0
    return out


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
        rhs = self.W * np.array([1.0, c[0], c[1]])
        coef = np.linalg.solve(self._m, rhs)
        p = coef[0] + self.d @ coef[1:]
        if p.min() >= 0.0:
            return p * self.a
        return _winkler_kernel(self._dx, self._dy, self.a, self.W, float(c[0]), float(c[1]), coef)


def half_planes(hull: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Outward unit normals n and offsets o of a convex polygon: inside is n . x <= o."""
    if shapely.Polygon(hull).exterior.is_ccw is False:
        hull = hull[::-1]
    e = np.roll(hull, -1, axis=0) - hull
    n = np.stack([e[:, 1], -e[:, 0]], axis=1) / np.hypot(e[:, 0], e[:, 1])[:, None]
    return n, np.einsum("ij,ij->i", n, hull)


class FootprintFriction:
    """The floor's friction on one object: area samples, Winkler pressure, the implicit solve.

    Frames: samples and the centre of pressure (`cop`, an offset from the CoM) live in the
    object frame; twists xi = (v_x, v_y, omega) of the CoM and impulses in the world frame.
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
        pts, area = footprint_samples(outline, self.set.samples)
        self.d_obj = pts - self.com  # sample offsets from the CoM, object frame
        self.pressure = WinklerPressure(self.d_obj, area, self.m * GRAVITY_M_S2)
        self.sample_hull_n, self.sample_hull_o = half_planes(
            np.asarray(shapely.MultiPoint(pts).convex_hull.exterior.coords)[:-1] - self.com
        )
        hull = np.asarray(shapely.Polygon(outline).convex_hull.exterior.coords)[:-1]
        self.hull_n, self.hull_o = half_planes(hull - self.com)  # support polygon, from CoM
        self.cop = np.zeros(2)
        self.normal = self.pressure.forces(self.cop)
        self.tipped = False
        self._yaw_cached: float | None = None
        self._offsets = (EMPTY, EMPTY)
        self._update_holding()

    def _update_holding(self) -> None:
        """Friction force and torque the floor can surely supply at the current pressure."""
        mu_min = float(self.mu.min())
        self._f_hold = max(mu_min * float(self.normal.sum()), 1e-300)
        r = np.hypot(self.d_obj[:, 0], self.d_obj[:, 1])
        self._tau_hold = max(mu_min * float(self.normal @ r), 1e-300)

    def offsets_world(self, yaw: float) -> tuple[np.ndarray, np.ndarray]:
        """The samples' offsets from the CoM in world axes (x and y arrays)."""
        if yaw != self._yaw_cached:
            c, s = math.cos(yaw), math.sin(yaw)
            dx = c * self.d_obj[:, 0] - s * self.d_obj[:, 1]
            dy = s * self.d_obj[:, 0] + c * self.d_obj[:, 1]
            self._offsets, self._yaw_cached = (dx, dy), yaw
        return self._offsets

    def set_cop(self, c_obj: np.ndarray) -> None:
        """Pressure for a centre of pressure c (object frame, from the CoM); `tipped` when c
        leaves the convex hull of the footprint. (Between the samples' hull and the
        footprint's the pressure is as close to the edge as the samples reach.)"""
        if float((self.hull_n @ c_obj - self.hull_o).max()) > 0.0:
            self.tipped = True
        k = 1.0
        while k > 0 and float((self.sample_hull_n @ (k * c_obj) - self.sample_hull_o).max()) > (
            -1e-5
        ):
            k *= 0.95
        c_obj = k * c_obj
        # a 2 um move of the pressure centre changes nothing that matters: keep the pressure
        moved = float(np.hypot(*(c_obj - self.cop))) > 2e-6
        released = not c_obj.any() and self.cop.any()  # back to the weight alone, exactly
        if moved or released or (self.tipped and c_obj.any()):
            self.normal = self.pressure.forces(c_obj)
            self.cop = c_obj
            self._update_holding()

    def objective(self, xi, xi_hat, w, dx, dy, dt, fr=None, eps=None) -> float:
        """Value of a step's convex objective (`objective_kernel`); `eps` overrides the
        smoothing (0: the exact objective). `w` None: no floor term (an impact)."""
        k, tau, r0 = fr if fr is not None else (0.0, ZERO3, 0.0)
        eps = self.set.smoothing_m_s if eps is None else eps
        wv = w if w is not None else EMPTY
        return value_kernel(
            xi, xi_hat, self.M, wv, dx, dy, self.mu[0], self.mu[1], dt, eps, k, tau, r0,
            w is not None,
        )  # fmt: skip

    def minimise(self, xi0, xi_hat, w, dx, dy, dt, fr=None, a=None, b=0.0):
        """Damped Newton on the objective, optionally on the plane a . xi = b; returns (xi,
        the plane's multiplier in N s)."""
        k, tau, r0 = fr if fr is not None else (0.0, ZERO3, 0.0)
        wv = w if w is not None else EMPTY
        av = a if a is not None else ZERO3
        return minimise_kernel(
            np.asarray(xi0, dtype=np.float64), np.asarray(xi_hat, dtype=np.float64), self.M,
            wv, dx, dy, self.mu[0], self.mu[1], dt, self.set.smoothing_m_s, k, tau, r0,
            w is not None, av, b, a is not None, self.set.newton_tol, self.set.max_newton,
        )  # fmt: skip

    def free_solve(self, xi_hat: np.ndarray, dx, dy, dt: float) -> np.ndarray:
        """End-of-step twist under the floor's friction alone; exactly zero when the friction
        can hold the object (compared on the exact, unsmoothed objective)."""
        if not xi_hat.any():
            return np.zeros(3)
        w = self.normal
        sol, _ = self.minimise(xi_hat, xi_hat, w, dx, dy, dt)
        if np.all(np.abs(sol[:2]) < self.set.rest_snap_m_s) and abs(sol[2]) < 1e-4:
            zero = np.zeros(3)
            if self.objective(zero, xi_hat, w, dx, dy, dt, None, 0.0) <= self.objective(
                sol, xi_hat, w, dx, dy, dt, None, 0.0
            ):
                return zero
        return sol

    def impulse(self, xi_hat: np.ndarray, yaw: float, dt: float, pushed: bool) -> np.ndarray:
        """The floor's friction impulse (N s, and N m s about z) over one step of an engine,
        from the twist `xi_hat` the object would have without it; the pressure centre then
        follows for the next step: c = -z F_f / (m g), with z the pusher's contact height
        while the pusher holds the object against the friction (it then balances F_f), the
        CoM's height while the object slides free (inertia balances F_f)."""
        xi_hat = np.asarray(xi_hat, dtype=float)
        need = self.M * xi_hat / dt  # the force and torque that would stop it within the step
        if (abs(need[0]) + abs(need[1])) / self._f_hold + abs(need[2]) / self._tau_hold < 0.9:
            # inside the limit surface (its octahedron of pure-force and pure-torque vertices):
            # static friction holds the object, no solve needed
            imp = -self.M * xi_hat
        else:
            dx, dy = self.offsets_world(yaw)
            sol = self.free_solve(xi_hat, dx, dy, dt)
            imp = self.M * (sol - xi_hat)
        z = self.z_push if pushed else self.h_com
        c_w = -z * imp[:2] / (dt * self.m * GRAVITY_M_S2)
        c, s = math.cos(yaw), math.sin(yaw)
        self.set_cop(np.array([c * c_w[0] + s * c_w[1], -s * c_w[0] + c * c_w[1]]))
        return imp
