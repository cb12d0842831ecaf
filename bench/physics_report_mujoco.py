"""MuJoCo physics measurements behind docs/physics_mujoco.md (set-ups of tests/test_physics.py).

Usage: .venv/bin/python bench/physics_report_mujoco.py [naive|default] ["{'field': value, ...}"]
The optional dict overrides fields of MujocoContactSettings (parameter studies).
"""

from __future__ import annotations

import ast
import sys
from dataclasses import replace

import numpy as np
from comexp.backends.mujoco_sim import DEFAULT_CONTACT, NAIVE_CONTACT, MujocoSimulator

from comexp.geometry import box_object
from comexp.scene import GRAVITY_M_S2, FloorSpec, SceneSpec
from comexp.simulator import contact_push


def slide(sim: MujocoSimulator, mu_xy: tuple[float, float], axis: int) -> tuple[float, float]:
    """Deceleration / (mu g) while clearly sliding (v > 0.2 v0), and the max height (mm)."""
    sim.build(SceneSpec(FloorSpec(*mu_xy), box_object(0.08, 0.05, 0.03, mu_pusher=0.5)))
    sim.step(0.05)
    mu = mu_xy[axis]
    v0 = 0.6 if mu >= 1 else 0.3
    lin = [0.0, 0.0, 0.0]
    lin[axis] = v0
    sim.set_object_velocity(tuple(lin), (0.0, 0.0, 0.0))
    ts, vs, zs = [], [], []
    for k in range(2000):
        sim.step(0.002)
        st = sim.object_state()
        zs.append(st.position_m[2])
        if st.linear_velocity_m_s[axis] < 0.2 * v0:
            break
        ts.append((k + 1) * 0.002)
        vs.append(st.linear_velocity_m_s[axis])
    t, v = np.array(ts), np.array(vs)
    keep = t > 0.01
    dec = -np.polyfit(t[keep], v[keep], 1)[0] if keep.sum() > 2 else float("nan")
    return dec / (mu * GRAVITY_M_S2), max(zs) * 1e3


def push(sim: MujocoSimulator, mu: float, speed: float, com, y_contact: float, mu_p: float):
    sc = SceneSpec(FloorSpec(mu, mu), box_object(0.08, 0.05, 0.03, com_m=com, mu_pusher=mu_p))
    sim.build(sc)
    out = sim.push(contact_push((-0.04, y_contact), (1.0, 0.0), 0.03, speed, sc.pusher.radius_m))
    return out


def main() -> None:
    base = NAIVE_CONTACT if len(sys.argv) > 1 and sys.argv[1] == "naive" else DEFAULT_CONTACT
    kw = ast.literal_eval(sys.argv[2]) if len(sys.argv) > 2 else {}
    sim = MujocoSimulator(contact=replace(base, **kw))
    print("| floor (mu_x, mu_y) | axis | decel / (mu g) | max z (mm) |")
    print("|---|---|---|---|")
    for mu_xy in [(0.1, 0.1), (1.0, 1.0), (0.1, 1.0), (1.0, 0.1)]:
        for axis in (0, 1):
            r, z = slide(sim, mu_xy, axis)
            print(f"| {mu_xy} | {'xy'[axis]} | {r:.3f} | {z:.3f} |")
    print("\n| push | floor mu | speed (m/s) | rotation (deg) | max tilt (deg) | status |")
    print("|---|---|---|---|---|---|")
    com = (0.015, 0.01)
    for mu in (0.1, 1.0):
        for speed in (0.4, 0.04):
            o = push(sim, mu, speed, com, com[1], 1.0)
            print(
                f"| through CoM | {mu} | {speed} | {o.rotation_deg:+.3f} | "
                f"{o.max_tilt_deg:.2f} | {o.status.value} |"
            )
    for mu in (0.1, 1.0):
        for speed in (0.4, 0.04):
            for off in (0.015, -0.015):
                o = push(sim, mu, speed, (0.0, 0.0), off, 0.5)
                print(
                    f"| offset {off:+.3f} m | {mu} | {speed} | {o.rotation_deg:+.3f} | "
                    f"{o.max_tilt_deg:.2f} | {o.status.value} |"
                )
    sim.close()


if __name__ == "__main__":
    main()
