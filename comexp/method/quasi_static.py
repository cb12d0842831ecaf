"""The quasi-static pushing model the `fit` estimator reads slow pushes with: a limit surface
(Lynch, Maekawa and Tanie 1992) built from the footprint, the floor's anisotropy and a candidate
CoM, and the pusher's point contact with Coulomb friction (stick or slide, Mason's motion cone).

Why this model: in a slow push the object's inertia plays no part, so its motion at every
instant is fixed by where the pusher touches, how the floor's friction resists a twist, and
the pusher's friction cone; the CoM enters through the floor's pressure, centred under it. The
friction's scale (mu g m) and Izz cancel: only the CoM, the floor's anisotropy (the ratio of its
two friction coefficients and the angle of its axes) and the pusher's friction are left, the
hypotheses this module evaluates side by side. Each tracked interval of a push is predicted on
its own, from the observed pose at its middle (the contact's geometry is then the same for every
hypothesis), so no prediction error accumulates along a push.

The limit surface is the ellipsoid (f_x / a)^2 + (f_y / b)^2 + (m / c)^2 = 1 in the floor's axes,
a = mu_1, b = mu_2 (normal force 1), c = the largest friction moment about the CoM,
sum_i w_i |A (z x r_i)| with the pressure w linear, tensionless and centred under the CoM (the
referee's Winkler pressure, `comexp.method.pressure`, without the move the forces' heights give
it). A twist is the ellipsoid's normal at the pusher's wrench: V = B J^T f, B = diag(1/a^2,
1/b^2, 1/c^2). With contact velocity J V = M f (M = J B J^T), the pusher sticks when
f = M^-1 v_p lies in its cone, else slides with f on the cone's edge and the contact's normal
velocity matched. `tests/quasi_static_reference.py` solves the same push without the ellipsoid
(docs/method.md, "What the ellipsoid leaves out").

The same model integrated along a whole push (`rollout_losses`, `roll_out`): the pusher's disc
driven along its path in steps, the object moved at each step with the twist for the contact
where the disc meets the outline; the moment c tabulated over the floor's axis per candidate
(`moment_table`), the contact searched near the last full search's while that provably
suffices. `FitEstimator` reads a push's
rest pose this way too.

Frames: the estimator's (metres, y up, CCW positive; docs/method.md), floor angles in the world.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from comexp.method.frames import Pose2D
from comexp.method.pressure import centred_pressure


@dataclass(frozen=True)
class ContactStep:
    """One tracked interval of a push with the pusher driving against the object: the contact
    point and the inward normal at the interval's middle, the pusher's velocity (m/s), all in
    the object frame; the object frame's world yaw then (the floor's axes turn against it),
    how long the pusher drove within the interval, and the observed motion: the frame origin's
    displacement (object frame at the middle) and the turn."""

    contact: np.ndarray
    normal: np.ndarray
    push_velocity: np.ndarray
    yaw_rad: float
    drive_s: float
    d_origin: np.ndarray
    d_yaw: float


def _closest_on_outline(q: np.ndarray, outline: np.ndarray) -> tuple[np.ndarray, float, bool]:
    """The outline's point closest to q, its distance, and whether q is inside the outline."""
    x, y, dist, _, inside = _closest_full(q[0], q[1], outline, np.empty(len(outline)))
    return np.array([x, y]), dist, inside


@njit(cache=True)
def _edge_point(qx, qy, outline, i):
    """The point of edge i (vertex i to i + 1) closest to q, and its distance."""
    n = outline.shape[0]
    j = i + 1 if i + 1 < n else 0
    ax, ay = outline[i, 0], outline[i, 1]
    ex, ey = outline[j, 0] - ax, outline[j, 1] - ay
    t = ((qx - ax) * ex + (qy - ay) * ey) / max(ex * ex + ey * ey, 1e-30)
    t = min(1.0, max(0.0, t))
    px, py = ax + t * ex, ay + t * ey
    return px, py, math.hypot(px - qx, py - qy)


@njit(cache=True)
def _inside(qx, qy, outline):
    """Whether (qx, qy) is inside the outline (even-odd rule, a ray to +x)."""
    n = outline.shape[0]
    inside = False
    for i in range(n):
        ay, cy = outline[i, 1], outline[(i + 1) % n, 1]
        if (ay > qy) != (cy > qy):
            ax, cx = outline[i, 0], outline[(i + 1) % n, 0]
            if qx < ax + (qy - ay) * (cx - ax) / (cy - ay):
                inside = not inside
    return inside


@njit(cache=True)
def _inside_all(points, outline, out):
    """`_inside` for every point (out: bool, one per point)."""
    for k in range(points.shape[0]):
        out[k] = _inside(points[k, 0], points[k, 1], outline)


@njit(cache=True)
def _closest_full(qx, qy, outline, dist):
    """The outline's point closest to q over every edge: (x, y, distance, edge, inside); each
    edge's distance is left in `dist` (at least as long as the outline)."""
    best, bx, by, bi = 1e30, 0.0, 0.0, 0
    for i in range(outline.shape[0]):
        px, py, d = _edge_point(qx, qy, outline, i)
        dist[i] = d
        if d < best:
            best, bx, by, bi = d, px, py, i
    return bx, by, best, bi, _inside(qx, qy, outline)


def _between(a: Pose2D, b: Pose2D) -> Pose2D:
    """The pose halfway between a and b (yaw along the shorter way)."""
    d = (b.yaw_rad - a.yaw_rad + math.pi) % (2 * math.pi) - math.pi
    return Pose2D((a.x_m + b.x_m) / 2, (a.y_m + b.y_m) / 2, a.yaw_rad + d / 2)


@dataclass(frozen=True, eq=False)
class PusherDrive:
    """One push as the camera and the command saw it: poses are world poses of the object frame
    (the pose before the push first, then one per tracked frame at `t_s`); the pusher moves
    along `direction` (object frame at the push's start) at `speed_m_s`, its disc of
    `pusher_radius_m` touching `contact_m` at `t_contact_s`, until `t_end_s`."""

    pose_before: Pose2D
    t_s: tuple[float, ...]
    poses: tuple[Pose2D, ...]
    contact_m: np.ndarray
    direction: np.ndarray
    t_contact_s: float
    t_end_s: float
    speed_m_s: float
    outline_m: np.ndarray
    pusher_radius_m: float

    def _intervals(self, radius_m: float, t_contact_s: float):
        """(k, lo, hi, middle pose, the disc's centre in the object frame then, the push's
        world direction) for every interval between consecutive poses in which the pusher
        drove past the contact, for a disc of `radius_m` touching at `t_contact_s`."""
        N = np.asarray(self.direction, dtype=float)
        N = N / np.linalg.norm(N)
        b = self.pose_before
        start = b.to_world(np.asarray(self.contact_m, dtype=float) - radius_m * N)
        c0, s0 = math.cos(b.yaw_rad), math.sin(b.yaw_rad)
        n_world = np.array([c0 * N[0] - s0 * N[1], s0 * N[0] + c0 * N[1]])
        times = (0.0, *self.t_s)
        track = (b, *self.poses)
        for k in range(len(track) - 1):
            lo, hi = max(times[k], t_contact_s), min(times[k + 1], self.t_end_s)
            if hi <= lo:
                continue
            mid = _between(track[k], track[k + 1])
            t_mid = 0.5 * (lo + hi)
            q = mid.to_object(start + n_world * self.speed_m_s * (t_mid - t_contact_s))
            yield k, lo, hi, mid, q, n_world

    def gaps_m(self, window_m: float) -> list[float]:
        """How far the pusher's disc stayed from the outline while it drove the object: the
        signed gap (negative: overlap) at the middle of each interval, those within `window_m`
        either way. A pusher that touches early or late (its calibration, its compliance, an
        engine's contact margin, a bias of the perceived outline) shows as their median, the
        same push after push."""
        r = self.pusher_radius_m
        gaps = []
        for *_, q, _ in self._intervals(r, self.t_contact_s):
            _, dist, inside = _closest_on_outline(q, self.outline_m)
            gap = (-dist if inside else dist) - r
            if abs(gap) <= window_m:
                gaps.append(gap)
        return gaps

    def steps(self, max_gap_m: float, offset_m: float = 0.0) -> list[ContactStep]:
        """The intervals in which the pusher drove with its disc within `max_gap_m` of the
        outline. `offset_m` (the median of `gaps_m`): the disc acts as if that much larger,
        touching that much earlier."""
        radius = self.pusher_radius_m + offset_m
        t_touch = self.t_contact_s - (offset_m / self.speed_m_s if self.speed_m_s > 0 else 0.0)
        yaw_prev = self.pose_before.yaw_rad
        unwrapped = [yaw_prev]
        for p in self.poses:
            yaw_prev += (p.yaw_rad - yaw_prev + math.pi) % (2 * math.pi) - math.pi
            unwrapped.append(yaw_prev)
        track = (self.pose_before, *self.poses)
        steps: list[ContactStep] = []
        for k, lo, hi, mid, q, n_world in self._intervals(radius, t_touch):
            p, dist, inside = _closest_on_outline(q, self.outline_m)
            if inside or dist - radius > max_gap_m or dist < 1e-9:
                continue
            normal = (p - q) / dist
            c, s = math.cos(mid.yaw_rad), math.sin(mid.yaw_rad)
            v_world = n_world * self.speed_m_s
            v = np.array([c * v_world[0] + s * v_world[1], -s * v_world[0] + c * v_world[1]])
            if v @ normal <= 0:
                continue
            dxy = np.array([track[k + 1].x_m - track[k].x_m, track[k + 1].y_m - track[k].y_m])
            d_origin = np.array([c * dxy[0] + s * dxy[1], -s * dxy[0] + c * dxy[1]])
            steps.append(
                ContactStep(
                    p, normal, v, mid.yaw_rad, hi - lo, d_origin, unwrapped[k + 1] - unwrapped[k]
                )
            )
        return steps


def footprint_samples(outline_m: np.ndarray, n: int = 64) -> np.ndarray:
    """About `n` points on a regular grid inside the outline (even-odd rule): where the floor
    presses."""
    outline = np.asarray(outline_m, dtype=float)
    lo, hi = outline.min(0), outline.max(0)
    area = abs(
        0.5
        * np.sum(
            outline[:, 0] * np.roll(outline[:, 1], -1) - np.roll(outline[:, 0], -1) * outline[:, 1]
        )
    )
    h = math.sqrt(area / n)
    while True:
        xs = np.arange(lo[0] + h / 2, hi[0], h)
        ys = np.arange(lo[1] + h / 2, hi[1], h)
        grid = np.array([(x, y) for y in ys for x in xs])
        keep = np.zeros(len(grid), dtype=np.bool_)
        _inside_all(grid, outline, keep)
        pts = grid[keep]
        if len(pts) >= n // 2 or h < 1e-4:
            return pts
        h *= 0.8


def pressure_weights(samples: np.ndarray, G: np.ndarray) -> np.ndarray:
    """(nG, ns) normal forces of the footprint samples, summing to 1 per candidate: the
    referee's pressure with its centre under G (a rigid plate on a uniform elastic foundation,
    linear and tensionless: `comexp.method.pressure.centred_pressure`)."""
    return centred_pressure(samples, G)


@njit(cache=True)
def _moment(samples, weights, gx, gy, ratio, ca, sa):
    """The limit surface's c about (gx, gy): the largest friction moment, for a floor with
    friction 1 along the axis (cos, sin) = (ca, sa) and `ratio` across it (object frame)."""
    c = 0.0
    for i in range(samples.shape[0]):
        rx = samples[i, 0] - gx
        ry = samples[i, 1] - gy
        r_par = rx * ca + ry * sa
        r_perp = -rx * sa + ry * ca
        c += weights[i] * math.sqrt(r_perp * r_perp + ratio * ratio * r_par * r_par)
    return c


@njit(cache=True)
def _twist(bxx, byy, bxy, ic2, rx, ry, mu, nx, ny, vx, vy):
    """The pusher's force (fx, fy) at arm r from the pressure centre, scaled so that the contact
    moves with the pusher (sticking) or along its normal with it (sliding on the cone's edge),
    and the twist it drives: (v_x, v_y, omega) of the pressure centre."""
    mxx = bxx + ic2 * ry * ry
    myy = byy + ic2 * rx * rx
    mxy = bxy - ic2 * rx * ry
    det = mxx * myy - mxy * mxy
    fx = (myy * vx - mxy * vy) / det
    fy = (mxx * vy - mxy * vx) / det
    tx, ty = -ny, nx
    fn = fx * nx + fy * ny
    ft = fx * tx + fy * ty
    if not (fn > 0.0 and abs(ft) <= mu * fn):  # slides: the force on the cone's edge
        sigma = 1.0 if ft >= 0.0 else -1.0
        gx = nx + sigma * mu * tx
        gy = ny + sigma * mu * ty
        lam = (vx * nx + vy * ny) / ((mxx * gx + mxy * gy) * nx + (mxy * gx + myy * gy) * ny)
        fx, fy = lam * gx, lam * gy
    return fx, fy, bxx * fx + bxy * fy, bxy * fx + byy * fy, (rx * fy - ry * fx) * ic2


@njit(cache=True)
def _floor_b(ratio, axis_rad):
    """The floor's B_f = R diag(1, 1 / ratio^2) R^T (object frame): (b_xx, b_yy, b_xy)."""
    ca, sa = math.cos(axis_rad), math.sin(axis_rad)
    inv2 = 1.0 / (ratio * ratio)
    return ca * ca + inv2 * sa * sa, sa * sa + inv2 * ca * ca, ca * sa * (1.0 - inv2)


@njit(cache=True)
def _predict_b(c, gx, gy, bxx, byy, bxy, mu, px, py, nx, ny, vx, vy):
    """`_predict` for a floor given by its `_floor_b`."""
    fx, fy, wx, wy, om = _twist(bxx, byy, bxy, 1.0 / (c * c), px - gx, py - gy, mu, nx, ny, vx, vy)
    # the twist is about G: the origin moves with v_G + omega z x (O - G)
    return wx + om * gy, wy - om * gx, om


@njit(cache=True)
def _predict(c, gx, gy, ratio, axis_rad, mu, px, py, nx, ny, vx, vy):
    """Origin displacement rate and turn rate (per second of driving) for one hypothesis: CoM
    (gx, gy) with limit-surface moment c, floor (ratio, axis_rad: object frame), pusher
    friction mu."""
    bxx, byy, bxy = _floor_b(ratio, axis_rad)
    return _predict_b(c, gx, gy, bxx, byy, bxy, mu, px, py, nx, ny, vx, vy)


@njit(cache=True)
def add_step_loglik(G, samples, weights, ratios, axes, mus, gains, active, step, noise, out):
    """Adds one step's log-likelihood to out (nG, nfloor, nmu, ngain) for the active floors.
    step = (px, py, nx, ny, vx, vy, yaw, drive_s, dOx, dOy, dyaw); noise = (sigma_move_m,
    sigma_turn_rad, rel_model)."""
    px, py, nx, ny, vx, vy, yaw, tau, ox, oy, oth = step
    sd, st, rel = noise
    for g in range(G.shape[0]):
        for j in range(ratios.shape[0]):
            if not active[j]:
                continue
            axis = axes[j] - yaw
            c = _moment(
                samples, weights[g], G[g, 0], G[g, 1], ratios[j], math.cos(axis), math.sin(axis)
            )
            bxx, byy, bxy = _floor_b(ratios[j], axis)  # once for every pusher friction
            for m in range(mus.shape[0]):
                ux, uy, om = _predict_b(
                    c, G[g, 0], G[g, 1], bxx, byy, bxy, mus[m], px, py, nx, ny, vx, vy
                )
                for k in range(gains.shape[0]):
                    # the turn's gain: an object slow to spin up (large Izz on a slippery
                    # floor) turns less than the inertia-free model says
                    q = gains[k] * om * tau
                    dx = ux * tau + (gains[k] - 1.0) * om * tau * G[g, 1]
                    dy = uy * tau - (gains[k] - 1.0) * om * tau * G[g, 0]
                    ex, ey, et = dx - ox, dy - oy, q - oth
                    vd = sd * sd + rel * rel * (dx * dx + dy * dy)
                    vt = st * st + rel * rel * q * q
                    out[g, j, m, k] += (
                        -0.5 * (ex * ex + ey * ey) / vd
                        - math.log(vd)
                        - 0.5 * et * et / vt
                        - 0.5 * math.log(vt)
                    )


@njit(cache=True)
def _predict_all(G, samples, weights, ratio, axis, mu, step, d, turn):
    """`predict_step`'s loop over the candidates, compiled (a push choice calls it for every
    candidate push)."""
    px, py, nx, ny, vx, vy, _, tau = step[:8]
    ca, sa = math.cos(axis), math.sin(axis)
    for g in range(G.shape[0]):
        c = _moment(samples, weights[g], G[g, 0], G[g, 1], ratio, ca, sa)
        ux, uy, om = _predict(c, G[g, 0], G[g, 1], ratio, axis, mu, px, py, nx, ny, vx, vy)
        d[g, 0] = ux * tau
        d[g, 1] = uy * tau
        turn[g] = om * tau


def predict_step(
    G: np.ndarray,
    samples: np.ndarray,
    weights: np.ndarray,
    ratio: float,
    axis_rad: float,
    mu_p: float,
    step: ContactStep,
) -> tuple[np.ndarray, np.ndarray]:
    """The model's motion over `step` for candidate CoMs G (nG, 2) with pressure `weights`
    (nG, ns) on the footprint `samples`: the frame origin's displacement (nG, 2) and the turn
    (nG,), for a floor with friction 1 along the axis at `axis_rad` (world) and `ratio` across
    it and pusher friction `mu_p`."""
    d = np.empty((len(G), 2))
    turn = np.empty(len(G))
    _predict_all(
        np.ascontiguousarray(G, dtype=float),
        samples,
        weights,
        ratio,
        axis_rad - step.yaw_rad,
        mu_p,
        step_array(step),
        d,
        turn,
    )
    return d, turn


def step_array(step: ContactStep) -> np.ndarray:
    """`add_step_loglik`'s packing of a step."""
    return np.array(
        [
            *step.contact,
            *step.normal,
            *step.push_velocity,
            step.yaw_rad,
            step.drive_s,
            *step.d_origin,
            step.d_yaw,
        ]
    )


# ----------------------------------------------------------------------------------------------
# the same model integrated along a push (`FitEstimator`'s rollout reading)


@dataclass(frozen=True, eq=False)
class RolloutPush:
    """One slow push as the rollout replays it, world frame: the object frame's pose before it
    (x, y, yaw), the pusher disc's centre when it touches and its world direction and speed,
    how long it drives after touching, the disc's radius (the measured offset included), and
    what the camera saw: the poses (x, y, unwrapped yaw) at `t_s` after the touch while it
    drove, and where the object came to rest."""

    pose0: np.ndarray  # (3,)
    start_m: np.ndarray  # (2,)
    direction: np.ndarray  # (2,) unit, world
    speed_m_s: float
    duration_s: float
    radius_m: float
    t_s: np.ndarray  # (nf,)
    poses: np.ndarray  # (nf, 3)
    end: np.ndarray  # (3,)

    def packed(self) -> np.ndarray:
        """The compiled rollout's `push` argument."""
        return np.array(
            [
                *self.pose0,
                *self.start_m,
                *self.direction,
                self.speed_m_s,
                self.duration_s,
                self.radius_m,
            ]
        )


def rollout_push(drive: PusherDrive, end: Pose2D, offset_m: float = 0.0) -> RolloutPush | None:
    """`drive` as the rollout replays it, its disc `offset_m` larger and touching that much
    earlier (as `PusherDrive.steps`), ending at rest at `end`; None for a push without
    driving time."""
    radius = drive.pusher_radius_m + offset_m
    t_touch = drive.t_contact_s - (offset_m / drive.speed_m_s if drive.speed_m_s > 0 else 0.0)
    duration = drive.t_end_s - t_touch
    if not duration > 0 or not drive.speed_m_s > 0:
        return None
    N = np.asarray(drive.direction, dtype=float)
    N = N / np.linalg.norm(N)
    b = drive.pose_before
    c, s = math.cos(b.yaw_rad), math.sin(b.yaw_rad)
    yaw = b.yaw_rad
    t, poses = [], []
    for ti, p in zip(drive.t_s, drive.poses, strict=True):
        yaw += math.remainder(p.yaw_rad - yaw, math.tau)
        if t_touch < ti <= drive.t_end_s:
            t.append(ti - t_touch)
            poses.append((p.x_m, p.y_m, yaw))
    end_yaw = yaw + math.remainder(end.yaw_rad - yaw, math.tau)
    return RolloutPush(
        np.array([b.x_m, b.y_m, b.yaw_rad]),
        b.to_world(np.asarray(drive.contact_m, dtype=float) - radius * N),
        np.array([c * N[0] - s * N[1], s * N[0] + c * N[1]]),
        float(drive.speed_m_s),
        float(duration),
        float(radius),
        np.array(t, dtype=float),
        np.array(poses, dtype=float).reshape(-1, 3),
        np.array([end.x_m, end.y_m, end_yaw]),
    )


MOMENT_ANGLES = 36  # the limit surface's moment tabulated over the floor's axis, per pi


@njit(cache=True)
def moment_table(samples, weights, G, ratios, n_angles):
    """(nG, nratio, n_angles + 1): `_moment` about each candidate for a floor of each ratio
    whose axis lies at k pi / n_angles in the object frame (the last column repeats the first:
    the moment has period pi)."""
    out = np.empty((G.shape[0], ratios.shape[0], n_angles + 1))
    for g in range(G.shape[0]):
        for r in range(ratios.shape[0]):
            for k in range(n_angles):
                a = math.pi * k / n_angles
                out[g, r, k] = _moment(
                    samples, weights[g], G[g, 0], G[g, 1], ratios[r], math.cos(a), math.sin(a)
                )
            out[g, r, n_angles] = out[g, r, 0]
    return out


NEAR_EDGES = 4  # the edges either side of the anchor's closest one searched first (4 of 5,
# 8 and 16: the cheapest, bench/episode_profile.py)


@njit(cache=True)
def _closest_near(qx, qy, outline, anchor, scratch):
    """The full search's answer (`_closest_full`) from only the edges near the last full
    search's closest one while that is provably enough: anchor = (x, y, edge, d_out, d) of the
    last full search at (x, y), which found the outline d away (outside it) and the nearest
    edge outside the window d_out away. An edge outside the window is then at least d_out -
    |q - anchor| from q; while the window's best is no farther, it is the outline's, and while
    q is less than d from the anchor it is still outside. Else (or with edge < 0: the anchor
    was inside) a full search re-anchors (its distances kept in `scratch`, at least as long as
    the outline). Returns (x, y, distance, inside); `anchor` is updated in place."""
    n = outline.shape[0]
    e0 = int(anchor[2])
    if e0 >= 0:
        best, bx, by = 1e30, 0.0, 0.0
        for o in range(-NEAR_EDGES, NEAR_EDGES + 1):
            px, py, d = _edge_point(qx, qy, outline, (e0 + o) % n)
            if d < best:
                best, bx, by = d, px, py
        moved = math.hypot(qx - anchor[0], qy - anchor[1])
        if best <= anchor[3] - moved and moved < anchor[4]:
            return bx, by, best, False
    bx, by, best, bi, inside = _closest_full(qx, qy, outline, scratch)
    d_out = 1e30
    for o in range(NEAR_EDGES + 1, n - NEAR_EDGES):
        d_out = min(d_out, scratch[(bi + o) % n])
    anchor[0], anchor[1], anchor[3], anchor[4] = qx, qy, d_out, best
    anchor[2] = -1.0 if inside else float(bi)  # inside: search in full until outside again
    return bx, by, best, inside


@njit(cache=True)
def _rollout(outline, table_row, gx, gy, ratio, axis_w, mu, push, step_m, t_s, out):
    """Drives the model through one push for one hypothesis; writes the poses at `t_s` (after
    the touch; sorted) to out[:-1] and the final pose to out[-1]. push = (x0, y0, yaw0, sx,
    sy, dx, dy, speed, duration, radius). The pusher advances `step_m` per step; where its
    disc at the step's end overlaps the outline the object moves with the model's twist for
    the pusher's velocity, its normal part the one that clears the overlap within the step
    (so that no drift accumulates)."""
    x, y, th, sx, sy, dx, dy, speed, duration, radius = push
    n_angles = table_row.shape[0] - 1
    nsteps = max(1, int(math.ceil(duration * speed / step_m)))
    h = duration / nsteps
    fi = 0
    anchor = np.array([0.0, 0.0, -1.0, 0.0, 0.0])  # `_closest_near`'s
    scratch = np.empty(outline.shape[0])
    for k in range(nsteps):
        while fi < t_s.shape[0] and t_s[fi] < (k + 0.5) * h:  # the nearest step boundary
            out[fi, 0], out[fi, 1], out[fi, 2] = x, y, th
            fi += 1
        t = (k + 1) * h  # where the pusher is at the step's end: the object must be clear
        c, s = math.cos(th), math.sin(th)
        wx, wy = sx + dx * speed * t - x, sy + dy * speed * t - y
        qx, qy = c * wx + s * wy, -s * wx + c * wy
        px, py, dist, inside = _closest_near(qx, qy, outline, anchor, scratch)
        if inside or dist < 1e-9 or dist >= radius:
            continue
        nx, ny = (px - qx) / dist, (py - qy) / dist
        vx = (c * dx + s * dy) * speed
        vy = (-s * dx + c * dy) * speed
        if vx * nx + vy * ny <= 0:
            continue
        push_in = (radius - dist) / h - (vx * nx + vy * ny)  # the overlap left after the step
        vx += nx * push_in
        vy += ny * push_in
        axis = axis_w - th
        u = (axis / math.pi) % 1.0 * n_angles
        i = min(int(u), n_angles - 1)
        f = u - i
        cm = table_row[i] * (1.0 - f) + table_row[i + 1] * f
        ux, uy, om = _predict(cm, gx, gy, ratio, axis, mu, px, py, nx, ny, vx, vy)
        x += (c * ux - s * uy) * h
        y += (s * ux + c * uy) * h
        th += om * h
    while fi < t_s.shape[0]:
        out[fi, 0], out[fi, 1], out[fi, 2] = x, y, th
        fi += 1
    out[-1, 0], out[-1, 1], out[-1, 2] = x, y, th


@njit(cache=True)
def _pose_term(p, q, pose0, sd, st, rel):
    """-2 log-likelihood (without constants) of observing q where the model puts p, both
    reached from pose0: vision's noise plus the model's error relative to the motion."""
    ex, ey, et = p[0] - q[0], p[1] - q[1], p[2] - q[2]
    mx, my, mt = p[0] - pose0[0], p[1] - pose0[1], p[2] - pose0[2]
    vd = sd * sd + rel * rel * (mx * mx + my * my)
    vt = st * st + rel * rel * mt * mt
    return (ex * ex + ey * ey) / vd + et * et / vt


@njit(cache=True)
def rollout_losses(
    outline,
    G,
    table,
    hyp_ratio,
    hyp_axis,
    hyp_mu,
    ratio_index,
    g_idx,
    h_idx,
    push,
    t_s,
    observed,
    end,
    noise,
    path_weight,
    step_m,
    out,
):
    """out[i] = the push's loss (-2 log-likelihood) for candidate G[g_idx[i]] under hypothesis
    h_idx[i] (floor ratio and world axis, pusher friction; its ratio's column of `table`):
    the rolled-out rest pose against `end`, plus `path_weight` times the mean over the
    tracked poses `observed` (at `t_s`). noise = (sigma_move_m, sigma_turn_rad, rel_model)."""
    sd, st, rel = noise[0], noise[1], noise[2]
    nf = t_s.shape[0]
    poses = np.empty((nf + 1, 3))
    pose0 = push[:3]
    for i in range(g_idx.shape[0]):
        g, h = g_idx[i], h_idx[i]
        _rollout(
            outline,
            table[g, ratio_index[h]],
            G[g, 0],
            G[g, 1],
            hyp_ratio[h],
            hyp_axis[h],
            hyp_mu[h],
            push,
            step_m,
            t_s,
            poses,
        )
        loss = _pose_term(poses[nf], end, pose0, sd, st, rel)
        if nf > 0 and path_weight > 0:
            acc = 0.0
            for f in range(nf):
                acc += _pose_term(poses[f], observed[f], pose0, sd, st, rel)
            loss += path_weight * acc / nf
        out[i] = loss


def roll_out(
    push: RolloutPush,
    outline_m: np.ndarray,
    samples: np.ndarray,
    G: np.ndarray,
    ratio: float,
    axis_rad: float,
    mu_p: float,
    step_m: float = 0.001,
) -> np.ndarray:
    """The model's poses (x, y, yaw; world) through `push` for a CoM G (object frame) on the
    floor (`ratio` across the low-friction axis at world angle `axis_rad`) with pusher
    friction `mu_p`: one row per tracked time `push.t_s`, then the pose at the push's end."""
    G = np.atleast_2d(np.asarray(G, dtype=float))
    outline = np.ascontiguousarray(outline_m, dtype=float)
    table = moment_table(
        samples, pressure_weights(samples, G), G, np.array([float(ratio)]), MOMENT_ANGLES
    )
    out = np.empty((len(push.t_s) + 1, 3))
    _rollout(
        outline,
        table[0, 0],
        G[0, 0],
        G[0, 1],
        ratio,
        axis_rad,
        mu_p,
        push.packed(),
        step_m,
        push.t_s,
        out,
    )
    return out
