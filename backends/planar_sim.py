"""The planar reference backend: a rigid extruded polygon on a rigid, flat floor, in x, y, yaw.

This is the physics model of the design brief, implemented directly (docs/physics.md, "The
model"), so that the 3-D engines can be checked against it:

- **Floor friction** is Coulomb, integrated over the footprint: the footprint is sampled on a
  regular grid of cells (`FrictionSettings.samples` of them), each carrying the normal force of
  its area. Anisotropic floors follow the elliptic maximum-dissipation law: the friction force
  of a sample with slip u lies in the ellipse |(f_x / mu_x, f_y / mu_y)| <= N and dissipates the
  most, f = -N A^2 u / |A u| with A = diag(mu_x, mu_y) along the floor's axes.
- **Normal pressure** is that of a uniform elastic (Winkler) foundation under a rigid plate:
  linear over the footprint, tensionless (clipped at zero), its centre placed by moment balance
  about the horizontal axes through the CoM: c - G = ((z_p - h_G) F_p - h_G F_f) / (m g), with
  F_p the pusher's force at its contact height z_p and F_f the floor's friction at the floor.
- **Pitch about a support edge** (tipping): when c would leave the footprint's convex hull
  across an edge, the floor can no longer balance the moment and the object pitches about
  that edge: I_e theta'' = m g (c_n - o cos theta + h_G sin theta), with c_n the required
  centre's reach along the edge's outward normal, o the edge's distance from the CoM and I_e
  the moment of inertia about the edge; on the leaning face the pusher's force is normal to
  it, at the pusher's height. An impact does not pitch the object: the pusher's
  line contact spans the CoM's height, so its impulse can pass through it, and a plastic
  impact takes the least kinetic energy it can. The pitch lands back (plastically) at 0 or
  tips the object over once the CoM passes above the edge (theta >= atan(o / h_G)); the
  object's tilt is the pitch, and the protocol's one rule (`tip_limit_deg`) says `tipped`, as
  for the engines. The pitch is a small-angle sub-model: the slide and spin go on as on the
  flat footprint with the pressure at the edge (docs/physics.md, "Tipping").
- **Stiction** without creep or chatter: each step solves for the end-of-step velocity
  implicitly (backward Euler on the friction, a convex minimisation of kinetic energy change
  plus the step's frictional dissipation); an object whose friction can hold it is exactly at
  rest, not creeping.
- **The pusher** is a kinematic disc following the command; its contact is plastic (no
  restitution) with Coulomb friction mu_p, as a velocity-level constraint that also catches a
  contact that would begin inside the step (so the moment of impact within a step is resolved,
  not rounded to a step). An impact is resolved first, without floor friction (an impulse is
  instantaneous; the floor's friction over it is negligible), then the step's friction and the
  sustained push are solved together; the pressure follows the sustained forces only.
- **The camera** is the exact ray-cast of the prism (`comexp.method.rendering.render_prism_depth`).

Where the pusher and the object move slowly (quasi-static pushing, the end of a slide) one
step covers five of the protocol's (`SlowSteps`; its accuracy in docs/physics.md).

One compiled call (Numba) runs many steps: contact, impact, the friction solves with the
pusher constraint, the pressure fixed point, integration and the penetration projection, on
preallocated state arrays; a handful of 3-variable Newton iterations per step.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from comexp.backends import floor_friction
from comexp.backends.floor_friction import (
    COP_X,
    COP_Y,
    FootprintFriction,
    free_solve_kernel,
    minimise_kernel,
    offsets_kernel,
    set_cop_kernel,
)
from comexp.backends.numba_kernels import DirectCall, stamp_with_sources
from comexp.backends.physics_settings import PLANAR, FrictionSettings, SlowSteps
from comexp.method.frames import DepthImage
from comexp.method.rendering import render_prism_depth, render_prism_window_depth
from comexp.sim import clear_steps as clear_steps_module
from comexp.sim import stop_rule as stop_rule_module
from comexp.sim.clear_steps import clear_steps, closest_on_polygon
from comexp.sim.protocol import ChunkStop, RunsChunks, SkipsStillSteps
from comexp.sim.scene import GRAVITY_M_S2, ObjectSpec, ObjectState, SceneSpec, SimSettings
from comexp.sim.simulator import Simulator
from comexp.sim.stop_rule import chunk_stops

_PARK_XY_M = (0.0, 0.5)  # outside the floor and the camera's view


class PlanarGeometry(NamedTuple):
    """What the compiled step knows of the object beyond its floor friction (SI units)."""

    outline: np.ndarray  # object frame
    com: np.ndarray  # object frame
    r_bound: float  # reach of the outline from the CoM
    radius: float  # the pusher's
    poly: np.ndarray  # scratch: the outline in world coordinates
    edge_n: np.ndarray  # the support hull's edges (object frame): outward unit normals
    edge_o: np.ndarray  # and distances from the CoM
    edge_inertia: np.ndarray  # moment of inertia about each edge (kg m^2)
    edge_over: np.ndarray  # the pitch at which the CoM is above the edge (rad)


# Model state vector `ms` (float64): CoM position, yaw, CoM twist (v_x, v_y, omega), the
# pusher's normal impulse of the last sustained solve (the next step's first guess), the
# pusher's normal impulse of the last step (N s), the pitch about a support edge (rad, >= 0),
# its rate (rad/s), that edge's index (meaningful while pitched), 1 once tipped over, and the
# largest pitch of the current `_run` call.
G_X, G_Y, YAW, XI_X, XI_Y, XI_W, LAM_PREV, IMPULSE, PITCH, PITCH_W, PITCH_EDGE, OVER, PITCH_MAX = (
    range(13)
)
MS_SIZE = 13
TRACE_COLS = 9  # per step: CoM x, y, yaw, twist (3), tilt (rad), its rate's world x, y
TIPPED_OVER_RAD = math.pi / 2  # the tilt an object that tipped over reports: on its side


@njit(cache=True)
def _contact(pg, ms, qx, qy):
    """Pusher-object contact at pusher centre q, world frame: (found, normal pointing into
    the object, contact point minus the CoM, signed gap positive when apart)."""
    c, s = math.cos(ms[YAW]), math.sin(ms[YAW])
    com, out, poly = pg.com, pg.outline, pg.poly
    ox = ms[G_X] - (c * com[0] - s * com[1])
    oy = ms[G_Y] - (s * com[0] + c * com[1])
    for i in range(out.shape[0]):
        poly[i, 0] = out[i, 0] * c - out[i, 1] * s + ox
        poly[i, 1] = out[i, 0] * s + out[i, 1] * c + oy
    px, py, dist, inside = closest_on_polygon(qx, qy, poly)
    if dist < 1e-12:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    if inside:
        nx, ny, gap = (qx - px) / dist, (qy - py) / dist, -dist - pg.radius
    else:
        nx, ny, gap = (px - qx) / dist, (py - qy) / dist, dist - pg.radius
    return True, nx, ny, px - ms[G_X], py - ms[G_Y], gap


@njit(cache=True)
def _plane_solve(geo, normal, floor, xi_hat, dxw, dyw, dt, a, b, tau, r0, mu_p, lam0):
    """The solve with the pusher's contact plane a . xi = b as a constraint, with a fixed
    point on the normal impulse (from `lam0`) that scales the tangential friction (tau, r0).
    It starts from the twist the object brings into the step (projected on the plane), not
    from the free solve's: on a sustained push that is next to the answer, while the free
    solve's twist has the pusher's tangential friction far off its kink, where Newton's steps
    overshoot. Returns (xi, normal impulse, tangential impulse)."""
    M, mx, my, eps, tol, itmax = geo.M, geo.mu_x, geo.mu_y, geo.eps, geo.tol, geo.itmax
    lam = max(lam0, 0.0)
    xi = xi_hat.copy()  # the step's start: on a sustained push, near its own solution
    for _ in range(8):  # fixed point on the normal impulse of the tangential friction
        k = lam * mu_p if mu_p > 0 and lam > 0 else 0.0
        xi, lam_new = minimise_kernel(xi, xi_hat, M, normal, dxw, dyw, mx, my, dt, eps, k,
                                      tau, r0, floor, a, b, True, tol, itmax)  # fmt: skip
        lam_new = max(lam_new, 0.0)
        if abs(lam_new - lam) <= 1e-9 + 1e-6 * lam_new:
            lam = lam_new
            break
        lam = lam_new
    t_imp = 0.0
    if mu_p > 0 and lam > 0:
        r = tau[0] * xi[0] + tau[1] * xi[1] + tau[2] * xi[2] - r0
        t_imp = -lam * mu_p * r / math.sqrt(r * r + eps * eps)
    return xi, lam, t_imp


@njit(cache=True)
def _solve_with_pusher(geo, normal, floor, xi_hat, dxw, dyw, dt, con, vqx, vqy, mu_p, lam0):
    """The step's solve with the pusher's unilateral plastic contact and its friction: the
    free solve; if it would leave the pusher inside, the solve on the contact plane
    (`_plane_solve`). On a sustained push the free solve is the costly one (its object stops
    against the floor's friction at the norms' kink, where Newton takes up to `max_newton`
    iterations) and its answer is known: when the last step pushed (`lam0` > 0) the plane's
    solve comes first, and the free solve is skipped when the plane's multiplier without the
    pusher's friction is positive: the free objective's minimum over the half space a . xi
    >= b is then on the plane, so its free minimiser is outside (convexity), as the free
    solve would have found. Otherwise (a push ending, or a push held by the pusher's
    friction alone) the free solve decides, as always.
    Returns (xi, normal impulse, tangential impulse)."""
    nx, ny, rx, ry, gap = con
    a = np.array([nx, ny, rx * ny - ry * nx])
    b = (vqx * nx + vqy * ny) - max(gap, 0.0) / dt
    tx, ty = -ny, nx
    tau = np.array([tx, ty, rx * ty - ry * tx])
    r0 = vqx * tx + vqy * ty
    pushed = lam0 > 0.0
    xi, lam, t_imp = xi_hat, 0.0, 0.0
    if pushed:
        xi, lam, t_imp = _plane_solve(geo, normal, floor, xi_hat, dxw, dyw, dt, a, b, tau, r0,
                                      mu_p, lam0)  # fmt: skip
        if lam > 0.0:
            _, lam_frictionless = minimise_kernel(
                xi, xi_hat, geo.M, normal, dxw, dyw, geo.mu_x, geo.mu_y, dt, geo.eps, 0.0, tau,
                r0, floor, a, b, True, geo.tol, geo.itmax,
            )  # fmt: skip
            if lam_frictionless > 1e-9:
                return xi, lam, t_imp
    xi_free, _ = minimise_kernel(xi_hat, xi_hat, geo.M, normal, dxw, dyw, geo.mu_x, geo.mu_y,
                                 dt, geo.eps, 0.0, tau, 0.0, floor, a, b, False, geo.tol,
                                 geo.itmax)  # fmt: skip
    if a[0] * xi_free[0] + a[1] * xi_free[1] + a[2] * xi_free[2] >= b:
        return xi_free, 0.0, 0.0
    if pushed:
        return xi, lam, t_imp
    return _plane_solve(geo, normal, floor, xi_hat, dxw, dyw, dt, a, b, tau, r0, mu_p, lam0)


@njit(cache=True)
def _pitch_step(geo, pg, ms, cx, cy, fpx, fpy, rx, ry, dt):
    """Advance the pitch about a support edge by one step (semi-implicit Euler), given the
    centre of pressure c (object frame, from the CoM) that the step's forces require: the
    floor supplies m g times c's reach inside the hull, and what lies beyond the edge pitches
    the object. A flat object starts pitching about the edge c leaves the hull by most.

    c counts the pusher's force F_p (object frame; its contact point r from the CoM) at the
    height z_p. On a face leaning by theta the force is normal to the face and still at the
    pusher's height, so its moment about the edge is F_pn (z_p - D sin theta) / cos theta,
    D the contact's distance behind the edge: the difference is added here."""
    theta, w = ms[PITCH], ms[PITCH_W]
    if theta == 0.0 and w == 0.0:
        worst, edge = 0.0, -1
        for i in range(pg.edge_o.shape[0]):
            v = pg.edge_n[i, 0] * cx + pg.edge_n[i, 1] * cy - pg.edge_o[i]
            if v > worst:
                worst, edge = v, i
        if edge < 0:
            return
        ms[PITCH_EDGE] = edge
    e = int(ms[PITCH_EDGE])
    ex, ey = pg.edge_n[e, 0], pg.edge_n[e, 1]
    cn = ex * cx + ey * cy
    arm = cn - pg.edge_o[e] * math.cos(theta) + geo.h_com * math.sin(theta)
    f_n = ex * fpx + ey * fpy
    if f_n != 0.0 and theta != 0.0:
        lean = pg.edge_o[e] - (ex * rx + ey * ry)  # D
        z = geo.z_push
        arm += f_n / (geo.m * GRAVITY_M_S2) * ((z - lean * math.sin(theta)) / math.cos(theta) - z)
    w += geo.m * GRAVITY_M_S2 * arm / pg.edge_inertia[e] * dt
    theta += w * dt
    if theta <= 0.0:  # lands back flat: a plastic landing
        theta = w = 0.0
    if theta >= pg.edge_over[e]:  # the CoM is above the edge: it falls over
        ms[OVER] = 1.0
    ms[PITCH], ms[PITCH_W] = theta, w


@njit(cache=True)
def _sustained_solve(
    geo, fs, normal, dxw, dyw, dt, active, con, vqx, vqy, mu_p, lam0, xi_hat, c, s
):
    """The step's floor friction and sustained push, with the pressure fixed by the sustained
    forces: solved, the pressure updated from its forces, solved once more when the centre of
    pressure moved. Returns the twist, the pusher's normal impulse, and (object frame) the
    centre of pressure the forces require and the pusher's force."""
    nx, ny = con[0], con[1]
    sol = xi_hat
    lam2 = 0.0
    cox = coy = fpx = fpy = 0.0
    den = geo.m * GRAVITY_M_S2
    arm = geo.z_push - geo.h_com
    for it in range(2):
        if active:
            sol, lam2, t2 = _solve_with_pusher(
                geo, normal, True, xi_hat, dxw, dyw, dt, con, vqx, vqy, mu_p, lam0
            )
        else:
            sol = free_solve_kernel(geo, normal, xi_hat, dxw, dyw, dt)
            lam2 = t2 = 0.0
        # forces of this step (N): floor friction from the momentum balance
        ix, iy = geo.M[0] * (sol[0] - xi_hat[0]), geo.M[1] * (sol[1] - xi_hat[1])
        pix = piy = 0.0
        if active and lam2 > 0:
            pix, piy = lam2 * nx + t2 * -ny, lam2 * ny + t2 * nx
        ffx, ffy = (ix - pix) / dt, (iy - piy) / dt
        fpx, fpy = pix / dt, piy / dt
        cwx = (arm * fpx - geo.h_com * ffx) / den
        cwy = (arm * fpy - geo.h_com * ffy) / den
        cox, coy = c * cwx + s * cwy, -s * cwx + c * cwy
        moved = math.hypot(cox - fs[COP_X], coy - fs[COP_Y])
        set_cop_kernel(geo, fs, normal, cox, coy)
        if moved < 1e-4 or it == 1:
            break
    return sol, lam2, cox, coy, c * fpx + s * fpy, -s * fpx + c * fpy


@njit(cache=True)
def _step(geo, fs, normal, dxw, dyw, pg, ms, q0x, q0y, q1x, q1y, dt, mu_p):
    """Advance one step; the pusher moves from q0 to q1 (world, its centre) within it."""
    vqx, vqy = (q1x - q0x) / dt, (q1y - q0y) / dt
    reach = math.sqrt(vqx * vqx + vqy * vqy) * dt + abs(ms[XI_W]) * pg.r_bound * dt
    reach += math.sqrt(ms[XI_X] ** 2 + ms[XI_Y] ** 2) * dt + 1e-5
    far = math.hypot(q0x - ms[G_X], q0y - ms[G_Y]) > pg.r_bound + pg.radius + reach
    if far and ms[XI_X] == 0.0 and ms[XI_Y] == 0.0 and ms[XI_W] == 0.0:
        if fs[COP_X] != 0.0 or fs[COP_Y] != 0.0:  # no force acts: the weight's pressure alone
            set_cop_kernel(geo, fs, normal, 0.0, 0.0)
        if ms[PITCH] != 0.0 or ms[PITCH_W] != 0.0:
            _pitch_step(geo, pg, ms, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, dt)  # the weight alone acts
        return  # at rest, pusher away: friction holds it exactly (no creep)
    active = False
    con = (0.0, 0.0, 0.0, 0.0, 0.0)
    if not far:
        found, nx, ny, rx, ry, gap = _contact(pg, ms, q0x, q0y)
        con = (nx, ny, rx, ry, gap)
        active = found and gap < reach
    nx, ny, rx, ry, gap = con
    yaw = ms[YAW]
    c, s = math.cos(yaw), math.sin(yaw)
    offsets_kernel(geo, fs, yaw, dxw, dyw)
    xi = ms[XI_X : XI_W + 1].copy()
    ms[IMPULSE] = 0.0
    if active:
        # would the pusher penetrate within the step at the current velocities?
        vcx, vcy = xi[0] - xi[2] * ry, xi[1] + xi[2] * rx
        if (vcx - vqx) * nx + (vcy - vqy) * ny < -max(gap, 0.0) / dt:
            # 1) impact: plastic, frictionless floor (instantaneous)
            xi, lam1, t1 = _solve_with_pusher(
                geo, normal, False, xi, dxw, dyw, dt, con, vqx, vqy, mu_p, 0.0
            )
            ms[IMPULSE] += lam1
    # 2) the step's floor friction (and the sustained push), with the pressure fixed by the
    #    sustained forces
    sol, lam2, cox, coy, fpx, fpy = _sustained_solve(
        geo, fs, normal, dxw, dyw, dt, active, con, vqx, vqy, mu_p, ms[LAM_PREV], xi, c, s
    )
    rx_o, ry_o = c * rx + s * ry, -s * rx + c * ry
    _pitch_step(geo, pg, ms, cox, coy, fpx, fpy, rx_o, ry_o, dt)
    ms[IMPULSE] += lam2
    ms[LAM_PREV] = lam2
    ms[XI_X], ms[XI_Y], ms[XI_W] = sol[0], sol[1], sol[2]
    ms[G_X] += sol[0] * dt
    ms[G_Y] += sol[1] * dt
    ms[YAW] += sol[2] * dt
    # plastic contact: a penetration left by the linearised constraint is removed by moving
    # the object (position only, no velocity: no energy is injected)
    if active:
        found, nx, ny, rx, ry, gap = _contact(pg, ms, q1x, q1y)
        if found and gap < 0.0:
            ms[G_X] += nx * -gap
            ms[G_Y] += ny * -gap


@njit(cache=True)
def _slow(pg, ms, qx, qy, targets, i, k, dt, v):
    """Whether targets[i : i + k] may be one step (`SlowSteps`): the object flat and its
    fastest point, and the pusher in each of those steps, no faster than v."""
    if ms[PITCH] != 0.0 or ms[PITCH_W] != 0.0 or ms[OVER] != 0.0:
        return False
    if math.hypot(ms[XI_X], ms[XI_Y]) + abs(ms[XI_W]) * pg.r_bound > v:
        return False
    for j in range(i, i + k):
        if math.hypot(targets[j, 0] - qx, targets[j, 1] - qy) > v * dt:
            return False
        qx, qy = targets[j, 0], targets[j, 1]
    return True


@njit(cache=True)
def _run(geo, fs, normal, dxw, dyw, pg, ms, q_start, targets, dt, mu_p, trace, group, v_slow):
    """Steps to each of `targets` in turn from the pusher at `q_start`, `group` of them as
    one step where the motion is slow (`_slow`); whether the pusher pushed in any of them, and
    how many steps were taken. `trace` (n x TRACE_COLS, or 0 rows: none) gets each one's state."""
    touched = False
    qx, qy = q_start[0], q_start[1]
    ms[PITCH_MAX] = TIPPED_OVER_RAD if ms[OVER] != 0.0 else ms[PITCH]
    n, i, taken = targets.shape[0], 0, 0
    while i < n:
        k = 1
        if group > 1 and i + group <= n and _slow(pg, ms, qx, qy, targets, i, group, dt, v_slow):
            k = group
        j = i + k - 1
        _step(geo, fs, normal, dxw, dyw, pg, ms, qx, qy, targets[j, 0], targets[j, 1], k * dt, mu_p)
        qx, qy = targets[j, 0], targets[j, 1]
        touched = touched or ms[IMPULSE] > 0.0
        if trace.shape[0] > 0:
            for c in range(6):
                trace[taken, c] = ms[c]
            trace[taken, 6] = TIPPED_OVER_RAD if ms[OVER] != 0.0 else ms[PITCH]
            wx, wy = _pitch_rate_world(pg, ms)
            trace[taken, 7], trace[taken, 8] = wx, wy
        ms[PITCH_MAX] = max(ms[PITCH_MAX], TIPPED_OVER_RAD if ms[OVER] != 0.0 else ms[PITCH])
        i += k
        taken += 1
    return touched, taken


@njit(cache=True)
def _run_chunks(
    geo, fs, normal, dxw, dyw, pg, ms, q_start, targets, chunk, dt, mu_p, trace, group, v_slow,
    stop, rest_after, out,
):  # fmt: skip
    """`_run` over each whole chunk of `targets` in turn (the protocol's `advance` calls,
    one compiled call), stopping after the first chunk whose state `_stops` names (the rest
    rule after those `rest_after` marks); per chunk run, `out` gets whether it pushed, its
    largest pitch (rad) and the yaw. Returns how many chunks ran."""
    n = targets.shape[0] // chunk
    for c in range(n):
        q = q_start if c == 0 else targets[c * chunk - 1]
        seg = targets[c * chunk : (c + 1) * chunk]
        touched, _ = _run(geo, fs, normal, dxw, dyw, pg, ms, q, seg, dt, mu_p, trace, group, v_slow)
        out[c, 0] = 1.0 if touched else 0.0
        out[c, 1] = ms[PITCH_MAX]
        out[c, 2] = ms[YAW]
        if _stops(pg, ms, stop, rest_after[c]):
            return c + 1
    return n


@njit(cache=True)
def _stops(pg, ms, stop, rest):
    """`ChunkStop`'s rule (`stop_rule.chunk_stops`, `stop` its `rule`) on the model state:
    healthy is finite and flat on the floor; the object frame's origin and its |v_x| + |v_y|,
    and the spin."""
    healthy = True
    for i in range(XI_W + 1):
        if not math.isfinite(ms[i]):
            healthy = False
    if ms[PITCH] != 0.0 or ms[PITCH_W] != 0.0 or ms[OVER] != 0.0:
        healthy = False
    c, s = math.cos(ms[YAW]), math.sin(ms[YAW])
    r0 = c * pg.com[0] - s * pg.com[1]  # origin -> CoM
    r1 = s * pg.com[0] + c * pg.com[1]
    w = ms[XI_W]
    v = abs(ms[XI_X] + w * r1) + abs(ms[XI_Y] - w * r0)
    return chunk_stops(healthy, ms[G_X] - r0, ms[G_Y] - r1, rest, v, w, stop)


@njit(cache=True)
def _pitch_rate_world(pg, ms):
    """The pitch rate as an angular velocity (world x, y): about the edge, z x n."""
    if ms[PITCH_W] == 0.0 or ms[OVER] != 0.0:
        return 0.0, 0.0
    e = int(ms[PITCH_EDGE])
    c, s = math.cos(ms[YAW]), math.sin(ms[YAW])
    nx = c * pg.edge_n[e, 0] - s * pg.edge_n[e, 1]
    ny = s * pg.edge_n[e, 0] + c * pg.edge_n[e, 1]
    return -ny * ms[PITCH_W], nx * ms[PITCH_W]


# the steps above compile the friction kernels into their own machine code
stamp_with_sources(globals(), floor_friction, clear_steps_module, stop_rule_module)
_run_call = DirectCall(_run)  # every chunk of the protocol's steps, from Python
_run_chunks_call = DirectCall(_run_chunks)  # chunks of them (`advance_chunks`)


class PlanarModel:
    """State and time steps of the planar rigid-body model (SI units, world frame).

    The state lives in arrays (`ms`, and the friction's `fr.fs`, `fr.normal`) that the
    compiled step updates in place; the attributes below are views of it."""

    def __init__(
        self, obj: ObjectSpec, mu_x: float, mu_y: float, settings: FrictionSettings, pusher
    ) -> None:
        self.obj = obj
        self.set = settings
        self.fr = FootprintFriction(obj, mu_x, mu_y, pusher, settings)
        self.m = obj.mass_kg
        self.M = self.fr.M
        self.com = self.fr.com
        self.com_xy = (float(self.com[0]), float(self.com[1]))
        self.outline = np.asarray(obj.outline_m, dtype=float)
        self.h_com = self.fr.h_com
        self.z_push = self.fr.z_push
        self.r_bound = float(np.max(np.hypot(*(self.outline - self.com).T)))  # reach from CoM
        self.radius = pusher.radius_m
        edge_n, edge_o = self.fr.hull_n, self.fr.hull_o  # the support hull, from the CoM
        # about each edge: the inertia about the CoM's parallel axis (products of inertia
        # neglected, as in the model) moved to the edge, o^2 + h_G^2 away
        tx, ty = -edge_n[:, 1], edge_n[:, 0]
        i_axis = obj.ixx_kg_m2 * tx**2 + obj.iyy_kg_m2 * ty**2
        self.geo = PlanarGeometry(
            outline=np.ascontiguousarray(self.outline), com=np.ascontiguousarray(self.com),
            r_bound=self.r_bound, radius=float(self.radius), poly=np.zeros_like(self.outline),
            edge_n=np.ascontiguousarray(edge_n, dtype=float),
            edge_o=np.ascontiguousarray(edge_o, dtype=float),
            edge_inertia=np.ascontiguousarray(i_axis + self.m * (edge_o**2 + self.h_com**2)),
            edge_over=np.ascontiguousarray(np.arctan2(edge_o, self.h_com)),
        )  # fmt: skip
        self.ms = np.zeros(MS_SIZE)

    @property
    def g(self) -> np.ndarray:
        return self.ms[G_X : G_Y + 1]

    @property
    def yaw(self) -> float:
        return float(self.ms[YAW])

    @property
    def xi(self) -> np.ndarray:
        return self.ms[XI_X : XI_W + 1]

    @xi.setter
    def xi(self, value) -> None:
        self.ms[XI_X : XI_W + 1] = value

    @property
    def tilt_rad(self) -> float:
        """The pitch about a support edge; on its side once tipped over."""
        return TIPPED_OVER_RAD if self.ms[OVER] != 0.0 else float(self.ms[PITCH])

    @property
    def flat(self) -> bool:
        """On the floor and not pitching (the pitch and its rate exactly 0)."""
        return self.ms[PITCH] == 0.0 and self.ms[PITCH_W] == 0.0 and self.ms[OVER] == 0.0

    def tilt_axis_rate(self) -> tuple[float, float]:
        """The pitch rate as a world angular velocity's x, y."""
        return _pitch_rate_world(self.geo, self.ms)

    def tilt_direction(self) -> np.ndarray:
        """The object-frame outward normal of the edge the object pitches about."""
        return self.geo.edge_n[int(self.ms[PITCH_EDGE])]

    # --- frames ------------------------------------------------------------------------
    def rot(self) -> np.ndarray:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, -s], [s, c]])

    def reset(self) -> None:
        """The state of a new model (at rest, flat, the friction's as made), in place."""
        self.ms[:] = 0.0
        self.geo.poly[:] = 0.0
        self.fr.reset()

    def set_pose(self, x: float, y: float, yaw: float) -> None:
        """Object frame origin at (x, y), yaw; at rest."""
        self.ms[YAW] = yaw
        self.ms[G_X : G_Y + 1] = np.array([x, y]) + self.rot() @ self.com
        self.xi = np.zeros(3)

    def origin(self) -> np.ndarray:
        return self.g - self.rot() @ self.com

    def run(
        self,
        q0: np.ndarray,
        targets: np.ndarray,
        dt: float,
        mu_p: float,
        trace: np.ndarray,
        slow: SlowSteps | None = None,
    ) -> tuple[bool, int]:
        """Steps from the pusher at q0 to each target in turn (`_run`): whether it pushed, and
        how many steps the model took (fewer than targets where `slow` grouped them)."""
        fr, slow = self.fr, slow or SlowSteps(steps=1)
        return _run_call(
            fr.geo, fr.fs, fr.normal, fr.dxw, fr.dyw, self.geo, self.ms,
            np.ascontiguousarray(q0, dtype=np.float64),
            np.ascontiguousarray(targets, dtype=np.float64),
            float(dt), float(mu_p), trace, int(slow.steps), float(slow.speed_m_s),
        )  # fmt: skip

    def run_chunks(
        self,
        q0: np.ndarray,
        targets: np.ndarray,
        chunk: int,
        dt: float,
        mu_p: float,
        stop: np.ndarray,
        rest_after: np.ndarray,
        out: np.ndarray,
        slow: SlowSteps,
    ) -> int:
        """`run` over each whole chunk of `targets`, stopping where `stop` and `rest_after`
        say (`_run_chunks`); how many chunks ran, their records in `out`."""
        fr = self.fr
        return _run_chunks_call(
            fr.geo, fr.fs, fr.normal, fr.dxw, fr.dyw, self.geo, self.ms,
            np.ascontiguousarray(q0, dtype=np.float64),
            np.ascontiguousarray(targets, dtype=np.float64),
            int(chunk), float(dt), float(mu_p), _NO_TRACE, int(slow.steps),
            float(slow.speed_m_s), stop, rest_after, out,
        )  # fmt: skip

    def step(self, q0: np.ndarray, q1: np.ndarray, dt: float, mu_p: float) -> None:
        """Advance one step; the pusher moves from q0 to q1 (world, its centre) within it."""
        self.run(q0, np.asarray(q1, dtype=np.float64)[None, :], dt, mu_p, _NO_TRACE)


_NO_TRACE = np.zeros((0, TRACE_COLS))
# clearance beyond a step's length for `steps_still` (m): 10x the step's own contact reach
_STILL_MARGIN_M = 1e-4


_FLAT = (0.0, (1.0, 0.0), (0.0, 0.0))  # `_model_tilt` of an object flat on the floor


def _object_state(com: tuple[float, float], g, yaw: float, xi, tilt=_FLAT):
    """The interface's state of the object frame from the model's CoM state (floats, read
    once per state: the protocol asks for it after every chunk of steps). `tilt` is the
    pitch (rad), the object-frame direction it tilts toward (the edge's outward normal) and
    its rate as a world angular velocity's x, y; roll and pitch (ZYX) tilt the body's z axis
    by that angle toward that direction."""
    c, s = math.cos(yaw), math.sin(yaw)
    cx, cy = com
    r0, r1 = c * cx - s * cy, s * cx + c * cy  # origin -> CoM
    g0, g1 = float(g[0]), float(g[1])
    v0, v1, w = float(xi[0]), float(xi[1]), float(xi[2])
    theta, (nx, ny), (wx, wy) = tilt
    if theta == 0.0:  # what the two lines below give for no tilt
        roll, pitch = -0.0, 0.0
    else:
        roll = math.asin(max(-1.0, min(1.0, -math.sin(theta) * ny)))
        pitch = math.atan2(math.sin(theta) * nx, math.cos(theta))
    return ObjectState(
        position_m=(g0 - r0, g1 - r1, 0.0),
        roll_rad=roll,
        pitch_rad=pitch,
        yaw_rad=math.atan2(s, c),
        linear_velocity_m_s=(v0 - w * -r1, v1 - w * r0, 0.0),
        angular_velocity_rad_s=(float(wx), float(wy), w),
    )


def _model_tilt(m: PlanarModel) -> tuple:
    """`_object_state`'s tilt of the model's current state."""
    if m.flat:
        return _FLAT
    return (m.tilt_rad, tuple(m.tilt_direction()), m.tilt_axis_rate())


def _same_physics(a: SceneSpec, b: SceneSpec) -> bool:
    """Scenes whose models are the same but for the pose: object, floor and pusher."""
    return (
        (a.obj is b.obj or a.obj == b.obj)
        and a.floor.mu_x == b.floor.mu_x
        and a.floor.mu_y == b.floor.mu_y
        and a.pusher == b.pusher
    )


class PlanarSimulator(SkipsStillSteps, RunsChunks, Simulator):
    """`backend=planar`: the reference model behind the shared simulator interface."""

    name = "planar"
    # the protocol's chunk of 10 steps (`Simulator.check_every_steps`): two slow steps

    def __init__(
        self,
        settings: SimSettings | None = None,
        planar: FrictionSettings | None = None,
        slow_steps: SlowSteps | None = None,
    ) -> None:
        super().__init__(settings)
        self.planar = planar or FrictionSettings()
        self.slow_steps = slow_steps or SlowSteps()
        self._model: PlanarModel | None = None
        self._scene: SceneSpec | None = None
        self._q = np.array(_PARK_XY_M, dtype=float)
        self._camera = None
        # `object_state`'s last answer, the model it is of and that model's state array
        self._state_of: PlanarModel | None = None
        self._state_key = b""
        self._state: ObjectState | None = None

    def build(self, scene: SceneSpec) -> None:
        """A new model, or the last one reset when only the pose changed (an episode re-centres
        its object ~2 times at 40 cm/s; a model costs ~0.3 ms to make)."""
        last, self._scene = self._scene, scene
        fl = scene.floor
        if self._model is not None and last is not None and _same_physics(last, scene):
            self._model.reset()
        else:
            self._model = PlanarModel(scene.obj, fl.mu_x, fl.mu_y, self.planar, scene.pusher)
        p = scene.initial_pose
        self._model.set_pose(p.x_m, p.y_m, p.yaw_rad)
        self._q = np.array(_PARK_XY_M, dtype=float)
        self._camera = scene.camera.model()

    def _require(self) -> PlanarModel:
        if self._model is None:
            raise RuntimeError("build() a scene first")
        return self._model

    # --- state -----------------------------------------------------------------------------
    def object_state(self) -> ObjectState:
        """The state of the model's state array, made once per distinct array: the protocol
        and the camera ask again for the state between steps (the frame after a check, a
        still object's every check)."""
        m = self._require()
        key = m.ms.tobytes()
        if self._state_of is m and self._state_key == key:
            return self._state
        state = m.ms[: XI_W + 1].tolist()  # CoM x, y, yaw, twist
        st = _object_state(m.com_xy, state[:2], state[2], state[3:], _model_tilt(m))
        self._state_of, self._state_key, self._state = m, key, st
        return st

    def set_object_velocity(self, linear_m_s, angular_rad_s) -> None:
        m = self._require()
        w = float(angular_rad_s[2])
        r = m.rot() @ m.com
        v_com = np.asarray(linear_m_s[:2], dtype=float) + w * np.array([-r[1], r[0]])
        m.xi = np.array([v_com[0], v_com[1], w])

    def render_depth(self) -> DepthImage:
        m = self._require()
        pose = self.object_state().pose
        return render_prism_depth(self._camera, m.outline, m.obj.height_m, pose)

    def render_tracking_depth(self) -> DepthImage:
        """Only the window the prism can cover (`render_prism_window_depth`)."""
        m = self._require()
        pose = self.object_state().pose
        return render_prism_window_depth(self._camera, m.outline, m.obj.height_m, pose)

    # --- protocol primitives ---------------------------------------------------------------
    def place_pusher(self, xy) -> None:
        self._q = np.asarray(xy, dtype=float).copy()

    def pusher_xy(self) -> np.ndarray:
        return self._q.copy()

    def steps_still(self, targets: np.ndarray) -> int:
        """The leading steps in which the pusher surely stays clear of an object that is
        exactly at rest: friction then holds it exactly (no creep), so nothing moves. A step
        is clear when the pusher's end position is farther from the outline than the step is
        long (by `_STILL_MARGIN_M`): every point of its straight path is then outside."""
        m = self._require()
        if not m.flat or m.ms[XI_X] != 0.0 or m.ms[XI_Y] != 0.0 or m.ms[XI_W] != 0.0:
            return 0
        poly = self.object_state().pose.to_world(m.outline)
        pts = np.ascontiguousarray(targets, dtype=np.float64).reshape(-1, 2)
        q0x, q0y = float(self._q[0]), float(self._q[1])
        return clear_steps(q0x, q0y, pts, poly, float(m.radius), _STILL_MARGIN_M)

    def advance(self, targets: np.ndarray) -> tuple[bool, float]:
        m = self._require()
        dt = self.settings.timestep_s
        mu_p = self._scene.obj.mu_pusher
        targets = np.ascontiguousarray(targets, dtype=np.float64).reshape(-1, 2)
        rows = _NO_TRACE if self.trace is None else np.zeros((len(targets), TRACE_COLS))
        touched, taken = m.run(self._q, targets, dt, mu_p, rows, self.slow_steps)
        for r in rows[:taken]:
            n = tuple(m.tilt_direction()) if r[6] != 0.0 else (1.0, 0.0)
            tilt = (float(r[6]), n, (float(r[7]), float(r[8])))
            self.trace.append(_object_state(m.com_xy, r[0:2], float(r[2]), r[3:6], tilt))
        if len(targets):
            self._q = targets[-1].copy()
        return touched, math.degrees(m.ms[PITCH_MAX])

    def advance_chunks(
        self, targets: np.ndarray, chunk: int, stop: ChunkStop
    ) -> list[tuple[bool, float, float]]:
        """`advance` chunk after chunk in one compiled call (`PlanarModel.run_chunks`). The
        pusher is kinematic (on its target after every step) and the model reports no
        failures of its own. A traced run (`trace`) goes one chunk at a time."""
        if self.trace is not None:
            touched, tilt = self.advance(targets[:chunk])
            return [(touched, tilt, self.object_state().pose.yaw_rad)]
        m = self._require()
        targets = np.ascontiguousarray(targets, dtype=np.float64).reshape(-1, 2)
        n = len(targets) // chunk
        out = np.empty((n, 3))
        rule = stop.rule()
        mu_p = self._scene.obj.mu_pusher
        dt = self.settings.timestep_s
        rest = np.ascontiguousarray(stop.rest_after[:n], dtype=np.bool_)
        done = m.run_chunks(self._q, targets, chunk, dt, mu_p, rule, rest, out, self.slow_steps)
        self._q = targets[done * chunk - 1].copy()
        # the yaw as `object_state` reads it (`_object_state`)
        return [
            (bool(t), math.degrees(p), math.atan2(math.sin(y), math.cos(y)))
            for t, p, y in out[:done].tolist()
        ]

    def close(self) -> None:
        self._model = None


# The model's revision and settings live in backends/physics_settings.py (PLANAR): bump the
# revision there when a change here changes results.
PHYSICS_VERSION, ENGINE_DISTRIBUTION, PHYSICS_SETTINGS = PLANAR

__all__ = ["PlanarModel", "PlanarSimulator"]
