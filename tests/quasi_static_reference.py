"""A reference solution of quasi-static pushing for the tests: no limit-surface approximation.

The floor's friction is summed sample by sample over the footprint (the elliptic law of
docs/physics.md, f = -N A^2 u / |A u|), the pressure is the referee's (`comexp.method.pressure`)
with its centre moved by the pusher's force at its height (moment balance: c - G = z_p F / (m g)
once the floor's friction balances the push), and the object's twist is the one the pusher's
point contact allows: sticking, the twist that moves the contact with the pusher and
dissipates least; sliding, the one whose friction wrench is a force on the cone's edge at the
contact (least dissipation with that force's power fixed). Slow and plain: numpy Newton
iterations, for checking the referee and the `fit` model against it, not for estimating.

Units and frames: metres, seconds, the object frame; normal forces sum to 1 (friction 1 along
the floor's first axis, `ratio` across it).
"""

from __future__ import annotations

import math

import numpy as np

from comexp.method.pressure import centred_pressure


def _friction_matrix(ratio: float, axis_rad: float) -> np.ndarray:
    c, s = math.cos(axis_rad), math.sin(axis_rad)
    R = np.array([[c, -s], [s, c]])
    return R @ np.diag([1.0, ratio]) @ R.T


def _sample_velocities(samples, p, v_c, omega):
    """Velocities of the samples for the contact point p moving at v_c and the turn rate."""
    d = samples - p
    return v_c[None, :] + omega * np.stack([-d[:, 1], d[:, 0]], axis=1)


def _dissipation(samples, w, A, p, v_c, omega, eps):
    u = _sample_velocities(samples, p, v_c, omega) @ A.T
    return float(w @ np.sqrt((u * u).sum(1) + eps * eps))


def _minimise(samples, w, A, p, base, dirs, eps):
    """Least dissipation over v = base + x . dirs (dirs: (k, 3) twists (v_c, omega) at p):
    damped Newton on the convex dissipation. Returns the twist (v_c, omega)."""
    x = np.zeros(len(dirs))
    d = samples - p
    perp = np.stack([-d[:, 1], d[:, 0]], axis=1)
    for _ in range(100):
        t = base + x @ dirs
        u = (t[None, :2] + t[2] * perp) @ A.T
        n = np.sqrt((u * u).sum(1) + eps * eps)
        # each direction's sample velocities (through A)
        du = np.stack([(k[None, :2] + k[2] * perp) @ A.T for k in dirs])  # (k, ns, 2)
        proj = (du * u[None]).sum(2) / n[None]  # (k, ns)
        g = (proj * w[None]).sum(1)
        H = np.einsum("aic,bic,i->ab", du, du, w / n) - np.einsum("ai,bi,i->ab", proj, proj, w / n)
        step = np.linalg.solve(H + 1e-15 * np.eye(len(x)), g)
        f0 = _dissipation(samples, w, A, p, t[:2], t[2], eps)
        s = 1.0
        while s > 1e-12:
            t1 = base + (x - s * step) @ dirs
            if _dissipation(samples, w, A, p, t1[:2], t1[2], eps) <= f0 - 1e-4 * s * (g @ step):
                break
            s *= 0.5
        x = x - s * step
        if s * np.abs(step).max() < 1e-13:
            break
    return base + x @ dirs


def pusher_force(samples, w, A, p, v_c, omega) -> np.ndarray:
    """The force the pusher must apply (normal forces summing to 1): minus the floor's."""
    u = _sample_velocities(samples, p, v_c, omega) @ A.T
    n = np.sqrt((u * u).sum(1)) + 1e-300
    return (w[:, None] * (u @ A) / n[:, None]).sum(0)


def twist(samples, w, ratio, axis_rad, mu_p, p, normal, v_pusher):
    """The contact point's velocity and the turn rate for pressure `w`, the pusher's disc at
    contact `p` (inward `normal`) moving at `v_pusher`, pusher friction `mu_p`."""
    A = _friction_matrix(ratio, axis_rad)
    p, normal, v_pusher = (np.asarray(a, dtype=float) for a in (p, normal, v_pusher))
    eps = 1e-9 * float(np.hypot(*v_pusher))
    stick = _minimise(samples, w, A, p, np.array([*v_pusher, 0.0]), np.array([[0, 0, 1.0]]), eps)
    f = pusher_force(samples, w, A, p, stick[:2], stick[2])
    tangent = np.array([-normal[1], normal[0]])
    fn, ft = f @ normal, f @ tangent
    if fn > 0 and abs(ft) <= mu_p * fn:
        return stick[:2], stick[2]
    for sigma in (np.sign(ft) or 1.0, -(np.sign(ft) or 1.0)):
        g = normal + sigma * mu_p * tangent
        across = np.array([-g[1], g[0]]) / np.hypot(*g)
        base = np.array([*(g / (g @ g)), 0.0])
        sol = _minimise(samples, w, A, p, base, np.array([[*across, 0.0], [0, 0, 1.0]]), eps)
        scale = (v_pusher @ normal) / (sol[:2] @ normal)
        v_c, omega = scale * sol[:2], scale * sol[2]
        if scale > 0 and sigma * ((v_c - v_pusher) @ tangent) <= 1e-12:
            return v_c, omega
    return stick[:2], stick[2]


def turn_rate(samples, com, ratio, axis_rad, mu_p, p, normal, v_pusher, lift_m=0.0, mu_floor=1.0):
    """The turn rate with the pressure centred under `com`, moved by `lift_m` (the pusher's
    contact height) times the pusher's force over the weight (friction `mu_floor` along the
    floor's first axis): a fixed point, the force depending on the pressure it moves."""
    com = np.asarray(com, dtype=float)
    centre = com
    for _ in range(8):
        w = centred_pressure(samples, centre[None])[0]
        v_c, omega = twist(samples, w, ratio, axis_rad, mu_p, p, normal, v_pusher)
        if lift_m == 0.0:
            break
        A = _friction_matrix(ratio, axis_rad)
        moved = com + lift_m * mu_floor * pusher_force(samples, w, A, np.asarray(p), v_c, omega)
        if np.hypot(*(moved - centre)) < 1e-7:
            break
        centre = moved
    return omega
