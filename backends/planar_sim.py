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
  If c leaves the footprint's convex hull the object tips, and the push reports it.
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
- **The camera** is the exact ray-cast of the prism (`comexp.perception.render_prism_depth`).

Vectorised NumPy over the area samples; a handful of 3-variable Newton iterations per step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from comexp.backends.floor_friction import FootprintFriction, FrictionSettings
from comexp.perception import render_prism_depth
from comexp.scene import (
    GRAVITY_M_S2,
    DepthImage,
    ObjectSpec,
    ObjectState,
    SceneSpec,
    SimSettings,
)
from comexp.simulator import Simulator

_PARK_XY_M = (0.0, 0.5)  # outside the floor and the camera's view


@dataclass
class _Contact:
    """Pusher-object contact of one step, world frame: normal n points into the object."""

    n: np.ndarray
    point_rel: np.ndarray  # contact point minus the CoM
    gap_m: float  # signed, positive when apart


@njit(cache=True)
def _closest_on_polygon(q: np.ndarray, poly: np.ndarray) -> tuple[np.ndarray, float, bool]:
    """Closest boundary point of a polygon to q, its distance, and whether q is inside."""
    n = poly.shape[0]
    best = np.inf
    bx = by = 0.0
    inside = False
    for i in range(n):
        ax, ay = poly[i, 0], poly[i, 1]
        cx, cy = poly[(i + 1) % n, 0], poly[(i + 1) % n, 1]
        ex, ey = cx - ax, cy - ay
        t = ((q[0] - ax) * ex + (q[1] - ay) * ey) / (ex * ex + ey * ey)
        t = min(1.0, max(0.0, t))
        px, py = ax + t * ex, ay + t * ey
        d = math.hypot(px - q[0], py - q[1])
        if d < best:
            best, bx, by = d, px, py
        if (ay > q[1]) != (cy > q[1]) and q[0] < ax + (q[1] - ay) * ex / ey:
            inside = not inside  # (the edge crosses q's row, so ey != 0 here)
    return np.array([bx, by]), best, inside


class PlanarModel:
    """State and one time step of the planar rigid-body model (SI units, world frame)."""

    def __init__(
        self, obj: ObjectSpec, mu_x: float, mu_y: float, settings: FrictionSettings, pusher
    ) -> None:
        self.obj = obj
        self.set = settings
        self.fr = FootprintFriction(obj, mu_x, mu_y, pusher, settings)
        self.m = obj.mass_kg
        self.M = self.fr.M
        self.com = self.fr.com
        self.outline = np.asarray(obj.outline_m, dtype=float)
        self.h_com = self.fr.h_com
        self.z_push = self.fr.z_push
        self.r_bound = float(np.max(np.hypot(*(self.outline - self.com).T)))  # reach from CoM
        self.radius = pusher.radius_m
        # state: CoM position, yaw, CoM velocity, yaw rate
        self.g = np.zeros(2)
        self.yaw = 0.0
        self.xi = np.zeros(3)
        self._impact_tipped = False
        self.contact_impulse = 0.0  # pusher normal impulse of the last step (N s)
        self._lam_prev = 0.0

    @property
    def tipped(self) -> bool:
        return self.fr.tipped or self._impact_tipped

    # --- frames ------------------------------------------------------------------------
    def rot(self) -> np.ndarray:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, -s], [s, c]])

    def set_pose(self, x: float, y: float, yaw: float) -> None:
        """Object frame origin at (x, y), yaw; at rest."""
        self.yaw = yaw
        self.g = np.array([x, y]) + self.rot() @ self.com
        self.xi = np.zeros(3)

    def origin(self) -> np.ndarray:
        return self.g - self.rot() @ self.com

    def _contact(self, q: np.ndarray) -> _Contact | None:
        R = self.rot()
        poly = self.outline @ R.T + self.origin()
        p, dist, inside = _closest_on_polygon(q, poly)
        if dist < 1e-12:
            return None
        n = (p - q) / dist if not inside else (q - p) / dist
        gap = (-dist if inside else dist) - self.radius
        return _Contact(n=n, point_rel=p - self.g, gap_m=gap)

    def _solve_with_pusher(self, xi_hat, w, dx, dy, dt, con, v_q, mu_p, lam_guess):
        """The step's solve with the pusher's unilateral plastic contact and its friction."""
        a = np.array(
            [con.n[0], con.n[1], con.point_rel[0] * con.n[1] - con.point_rel[1] * con.n[0]]
        )
        b = float(v_q @ con.n) - max(con.gap_m, 0.0) / dt
        t_dir = np.array([-con.n[1], con.n[0]])
        tau = np.array(
            [t_dir[0], t_dir[1], con.point_rel[0] * t_dir[1] - con.point_rel[1] * t_dir[0]]
        )
        r0 = float(v_q @ t_dir)
        xi, _ = self.fr.minimise(xi_hat, xi_hat, w, dx, dy, dt, None)
        if float(a @ xi) >= b:
            return xi, 0.0, 0.0
        lam = max(lam_guess, 0.0)
        for _ in range(8):  # fixed point on the normal impulse of the tangential friction
            fr = (lam * mu_p, tau, r0) if mu_p > 0 and lam > 0 else None
            xi, lam_new = self.fr.minimise(xi, xi_hat, w, dx, dy, dt, fr, a=a, b=b)
            lam_new = max(lam_new, 0.0)
            if abs(lam_new - lam) <= 1e-9 + 1e-6 * lam_new:
                lam = lam_new
                break
            lam = lam_new
        t_imp = 0.0
        if mu_p > 0 and lam > 0:
            r = float(tau @ xi) - r0
            eps = self.set.smoothing_m_s
            t_imp = -lam * mu_p * r / math.sqrt(r * r + eps * eps)
        return xi, lam, t_imp

    @staticmethod
    def _approaching(xi: np.ndarray, con: _Contact, v_q: np.ndarray, dt: float) -> bool:
        """Would the pusher penetrate within the step at the current velocities?"""
        r = con.point_rel
        v_c = np.array([xi[0] - xi[2] * r[1], xi[1] + xi[2] * r[0]])
        return float((v_c - v_q) @ con.n) < -max(con.gap_m, 0.0) / dt

    def step(self, q0: np.ndarray, q1: np.ndarray, dt: float, mu_p: float) -> None:
        """Advance one step; the pusher moves from q0 to q1 (world, its centre) within it."""
        v_q = (q1 - q0) / dt
        reach = float(np.linalg.norm(v_q)) * dt + abs(self.xi[2]) * self.r_bound * dt
        reach += float(np.linalg.norm(self.xi[:2])) * dt + 1e-5
        far = float(np.hypot(*(q0 - self.g))) > self.r_bound + self.radius + reach
        if far and not self.xi.any():
            if self.fr.cop.any():  # no force acts: the pressure is the weight's alone
                self.fr.set_cop(np.zeros(2))
            return  # at rest, pusher away: friction holds it exactly (no creep)
        con = None if far else self._contact(q0)
        active = con is not None and con.gap_m < reach
        R = self.rot()
        dx, dy = self.fr.offsets_world(self.yaw)
        xi = self.xi
        self.contact_impulse = 0.0
        if active and self._approaching(xi, con, v_q, dt):
            # 1) impact: plastic, frictionless floor (instantaneous)
            xi, lam1, t1 = self._solve_with_pusher(xi, None, dx, dy, dt, con, v_q, mu_p, 0.0)
            if lam1 > 0:
                self._impact_tip_check(lam1, t1, con, R)
            self.contact_impulse += lam1
        # 2) the step's floor friction (and the sustained push), with the pressure fixed by the
        #    sustained forces: solved, the pressure updated from its forces, solved once more
        #    when the centre of pressure moved
        xi_hat = xi
        for it in range(2):
            w = self.fr.normal
            if active:
                sol, lam2, t2 = self._solve_with_pusher(
                    xi_hat, w, dx, dy, dt, con, v_q, mu_p, self._lam_prev
                )
            else:
                sol = self.fr.free_solve(xi_hat, dx, dy, dt)
                lam2 = t2 = 0.0
            # forces of this step (N): floor friction from the momentum balance
            imp = self.M * (sol - xi_hat)  # floor + pusher impulses
            push_imp = np.zeros(2)
            if active and lam2 > 0:
                push_imp = lam2 * con.n + t2 * np.array([-con.n[1], con.n[0]])
            F_f = (imp[:2] - push_imp) / dt
            F_p = push_imp / dt
            c_w = ((self.z_push - self.h_com) * F_p - self.h_com * F_f) / (self.m * GRAVITY_M_S2)
            c_obj = R.T @ c_w
            moved = float(np.linalg.norm(c_obj - self.fr.cop))
            self.fr.set_cop(c_obj)
            if moved < 1e-4 or it == 1:
                break
        self.contact_impulse += lam2
        self._lam_prev = lam2
        self.xi = sol
        self.g = self.g + sol[:2] * dt
        self.yaw = self.yaw + sol[2] * dt
        # plastic contact: a penetration left by the linearised constraint is removed by
        # moving the object (position only, no velocity: no energy is injected)
        con_after = self._contact(q1) if active else None
        if con_after is not None and con_after.gap_m < 0.0:
            self.g = self.g + con_after.n * (-con_after.gap_m)

    def _impact_tip_check(self, lam: float, t_imp: float, con: _Contact, R: np.ndarray) -> None:
        """An impact's impulsive moment about the horizontal axes tips the object when the
        kinetic energy it gives a rotation about the support edge beats the potential barrier
        of lifting the CoM over that edge."""
        P = lam * con.n + t_imp * np.array([-con.n[1], con.n[0]])
        arm = self.z_push - self.h_com
        if abs(arm) < 1e-12 or float(np.hypot(*P)) == 0.0:
            return
        d_dir = R.T @ (P / np.hypot(*P)) * math.copysign(1.0, arm)
        dist = float(np.min(self.fr.hull_o / np.maximum(self.fr.hull_n @ d_dir, 1e-9)))
        i_edge = self.obj.ixx_kg_m2 + self.m * (dist**2 + self.h_com**2)
        L = abs(arm) * float(np.hypot(*P))
        energy = L * L / (2.0 * i_edge)
        barrier = self.m * GRAVITY_M_S2 * (math.hypot(dist, self.h_com) - self.h_com)
        if energy > barrier:
            self._impact_tipped = True


class PlanarSimulator(Simulator):
    """`backend=planar`: the reference model behind the shared simulator interface."""

    name = "planar"

    def __init__(
        self, settings: SimSettings | None = None, planar: FrictionSettings | None = None
    ) -> None:
        super().__init__(settings)
        self.planar = planar or FrictionSettings()
        self._model: PlanarModel | None = None
        self._scene: SceneSpec | None = None
        self._q = np.array(_PARK_XY_M, dtype=float)
        self._camera = None

    def build(self, scene: SceneSpec) -> None:
        self._scene = scene
        fl = scene.floor
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
        m = self._require()
        o = m.origin()
        r = m.rot() @ m.com  # origin -> CoM
        v = m.xi[:2] - m.xi[2] * np.array([-r[1], r[0]])
        tilt = math.radians(90.0) if m.tipped else 0.0
        return ObjectState(
            position_m=(float(o[0]), float(o[1]), 0.0),
            roll_rad=tilt,
            pitch_rad=0.0,
            yaw_rad=float(math.atan2(math.sin(m.yaw), math.cos(m.yaw))),
            linear_velocity_m_s=(float(v[0]), float(v[1]), 0.0),
            angular_velocity_rad_s=(0.0, 0.0, float(m.xi[2])),
        )

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

    # --- protocol primitives ---------------------------------------------------------------
    def _place_pusher(self, xy) -> None:
        self._q = np.asarray(xy, dtype=float).copy()

    def _pusher_xy(self) -> np.ndarray:
        return self._q.copy()

    def _advance(self, targets: np.ndarray) -> tuple[bool, float]:
        m = self._require()
        dt = self.settings.timestep_s
        mu_p = self._scene.obj.mu_pusher
        touched = False
        for q1 in targets:
            m.step(self._q, q1, dt, mu_p)
            self._q = np.asarray(q1, dtype=float).copy()
            touched = touched or m.contact_impulse > 0.0
            if self.trace is not None:
                self.trace.append(self.object_state())
        return touched, 90.0 if m.tipped else 0.0

    def close(self) -> None:
        self._model = None


# The model's revision: bump when a change changes results (it is part of episode identity).
PHYSICS_VERSION = "planar-1"
ENGINE_DISTRIBUTION = "numba"  # the kernels are compiled by it: its version is part of the physics
PHYSICS_SETTINGS = FrictionSettings()

__all__ = ["PlanarModel", "PlanarSimulator"]
