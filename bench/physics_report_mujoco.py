"""MuJoCo physics measurements behind docs/physics_mujoco.md (set-ups of tests/test_physics.py).

Usage: .venv/bin/python bench/physics_report_mujoco.py [naive|default] ["{'field': value, ...}"]
The optional dict overrides fields of MujocoContactSettings (parameter studies).

       .venv/bin/python bench/physics_report_mujoco.py objects   # the 20 built-in objects
       .venv/bin/python bench/physics_report_mujoco.py speed     # steps/s, wall time per push
       .venv/bin/python bench/physics_report_mujoco.py phase ["{...}"]  # impact-phase spread
"""

from __future__ import annotations

import ast
import math
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace

import mujoco
import numpy as np

from comexp.backends.mujoco_sim import DEFAULT_CONTACT, NAIVE_CONTACT, MujocoSimulator
from comexp.experiment.objects import builtin_objects, com_points, load_builtin, to_object_spec
from comexp.experiment.simulator import contact_push
from comexp.method.geometry import box_object, signed_area
from comexp.method.scene import GRAVITY_M_S2, FloorSpec, Pose2D, SceneSpec


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


THROUGH_COM_SETUPS = (  # (CoM in the object frame, object yaw): contract, mirrored, rotated
    ((0.015, 0.01), 0.0),
    ((0.015, -0.01), 0.0),
    ((0.015, 0.01), 0.7),
    ((-0.015, -0.01), 2.0),
)


def push_through_com(sim: MujocoSimulator, mu: float, speed: float, com, yaw: float):
    """Push the box's -x face (object frame) along its normal at the CoM's y, box at `yaw`."""
    obj = box_object(0.08, 0.05, 0.03, com_m=com, mu_pusher=1.0)
    sc = SceneSpec(FloorSpec(mu, mu), obj, initial_pose=Pose2D(0.0, 0.0, yaw))
    sim.build(sc)
    contact = sc.initial_pose.to_world(np.array([-0.04, com[1]]))
    normal = (math.cos(yaw), math.sin(yaw))
    return sim.push(contact_push(contact, normal, 0.03, speed, sc.pusher.radius_m))


def stop_distance_mm(sim: MujocoSimulator, mu: float, v0: float) -> float:
    """Distance (mm) a box slides from v0 along x before it stops."""
    sim.build(SceneSpec(FloorSpec(mu, mu), box_object(0.08, 0.05, 0.03, mu_pusher=0.5)))
    x0 = sim.object_state().position_m[0]
    sim.set_object_velocity((v0, 0.0, 0.0), (0.0, 0.0, 0.0))
    for _ in range(200):
        sim.step(0.01)
        v = sim.object_state().linear_velocity_m_s
        if math.hypot(v[0], v[1]) < 1e-5:
            break
    return 1e3 * (sim.object_state().position_m[0] - x0)


def objects(sim: MujocoSimulator) -> None:
    """Every built-in object at its first study CoM, yawed 0.4 rad: rest after build, rendered
    area, stopping distance of a 0.5 m/s slide (mu 1 and 0.1) and a through-CoM push."""
    print(
        "| object | parts | supports | tilt deg | z mm | area ratio | stop/ideal mu1 | "
        "stop/ideal mu0.1 | through-CoM rot deg (4 / 40 cm/s, mu 1) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for obj in builtin_objects():
        name = obj if isinstance(obj, str) else obj.name
        o = load_builtin(name)
        com = com_points(o, 1)[0]
        spec = to_object_spec(o, com, 1.0, 1.0)
        pose = Pose2D(0.03, -0.02, 0.4)
        sim.build(SceneSpec(FloorSpec(1.0, 1.0), spec, initial_pose=pose))
        st = sim.object_state()
        img = sim.render_depth()
        cam = img.camera
        mask = img.depth_m < cam.position_m[2] - 0.5 * spec.height_m
        area = mask.sum() * cam.pixel_size_m(cam.position_m[2] - spec.height_m) ** 2
        ratio = area / abs(signed_area(spec.outline_m))
        stops = []
        for mu in (1.0, 0.1):
            sim.build(SceneSpec(FloorSpec(mu, mu), spec, initial_pose=pose))
            x0 = sim.object_state().position_m[0]
            sim.set_object_velocity((0.5, 0.0, 0.0), (0.0, 0.0, 0.0))
            sim.step(0.2 / mu)
            stops.append((sim.object_state().position_m[0] - x0) / (0.25 / (2 * mu * GRAVITY_M_S2)))
        rots = []
        line = _normal_through_com(spec.outline_m, spec.com_m)
        for v in (0.04, 0.4) if line else ():
            contact, normal = line
            sim.build(SceneSpec(FloorSpec(1.0, 1.0), spec))
            out = sim.push(contact_push(contact, normal, 0.03, v, 0.005))
            rots.append(f"{out.rotation_deg:+.3f}" if out.ok else out.status.value)
        n_sup = sum(
            1 for g in range(sim.model.ngeom) if (sim.model.geom(g).name or "").startswith("sup")
        )
        print(
            f"| {name} | {len(spec.convex_parts_m)} | {n_sup} | {st.tilt_deg:.3f} | "
            f"{1e3 * st.position_m[2]:+.3f} | {ratio:.3f} | {stops[0]:.3f} | {stops[1]:.3f} | "
            f"{' / '.join(rots) or 'no edge normal through the CoM'} |"
        )


def _normal_through_com(outline, com) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """The longest edge whose inward normal through the CoM meets it (contact, normal)."""
    p = np.asarray(outline, dtype=float)
    c = np.asarray(com, dtype=float)
    best = None
    for i in range(len(p)):
        a, b = p[i], p[(i + 1) % len(p)]
        e = b - a
        length = float(np.hypot(*e))
        t = float((c - a) @ e) / length
        if not 0.005 <= t <= length - 0.005:
            continue
        foot = a + e / length * t
        n = np.array([-e[1], e[0]]) / length  # CCW outline: left normal points inward
        if best is None or length > best[0]:
            best = (length, foot, n)
    if best is None:
        return None
    _, foot, n = best
    return (float(foot[0]), float(foot[1])), (float(n[0]), float(n[1]))


def speed_report(sim: MujocoSimulator) -> None:
    """Wall time and steps/s of the contract's through-CoM pushes (best of 3 after warm-up)."""
    sc = SceneSpec(
        FloorSpec(1.0, 1.0), box_object(0.08, 0.05, 0.03, com_m=(0.015, 0.01), mu_pusher=1.0)
    )
    print("| push | steps | wall ms | steps/s | contacts at rest |")
    print("|---|---|---|---|---|")
    for v in (0.04, 0.4):
        best = math.inf
        for _ in range(4):
            sim.build(sc)
            t0 = time.perf_counter()
            out = sim.push(contact_push((-0.04, 0.01), (1.0, 0.0), 0.03, v, 0.005))
            best = min(best, time.perf_counter() - t0)
        sim.build(sc)
        print(
            f"| {100 * v:g} cm/s, mu 1 | {out.steps} | {1e3 * best:.1f} | {out.steps / best:.0f} "
            f"| {sim.data.ncon} |"
        )
    t0 = time.perf_counter()
    for _ in range(50):
        sim.build(sc)
    print(f"\nbuild (same scene) {1e3 * (time.perf_counter() - t0) / 50:.2f} ms")


@contextmanager
def _per_step_probe(sim: MujocoSimulator, rec: dict[str, float]) -> Iterator[None]:
    """Runs `mujoco.mj_step` one step at a time and records, over the push, the object's
    highest lift above its rest height (mm), the longest time without any floor force (ms,
    a ballistic hop) and the largest total floor normal force (N). Measurement only: the
    chunked stepping of the backend is reproduced step by step (bit-identical physics)."""
    orig = mujoco.mj_step
    m = sim.model
    floor = m.geom("floor").id
    rec.update(z_mm=0.0, air_ms=0.0, floor_n=0.0)
    air = [0.0]
    f6 = np.zeros(6)

    def step(m_: mujoco.MjModel, d_: mujoco.MjData, n: int = 1) -> None:
        for _ in range(n):
            orig(m_, d_)
            fz = 0.0
            for i in range(d_.ncon):
                c = d_.contact[i]
                if floor in (c.geom1, c.geom2) and c.efc_address >= 0:
                    mujoco.mj_contactForce(m_, d_, i, f6)
                    fz += f6[0]
            air[0] = air[0] + m_.opt.timestep if fz == 0.0 else 0.0
            rec["air_ms"] = max(rec["air_ms"], 1e3 * air[0])
            rec["floor_n"] = max(rec["floor_n"], fz)
            rec["z_mm"] = max(rec["z_mm"], 1e3 * float(d_.qpos[sim._obj_qadr + 2]))

    mujoco.mj_step = step
    try:
        yield
    finally:
        mujoco.mj_step = orig


def phase_report(sim: MujocoSimulator) -> None:
    """The push of the contract's yaw-invariance test (box 8x5x3 cm, CoM (1.5, 0.8) cm, pusher
    mu 0.5, 1 cm right of the CoM line, 40 cm/s, floor mu 1) at yaw 0, with the approach gap
    shifted by a fraction of one step of pusher travel (0.4 mm): the object's physics is the
    same up to where between two steps the pusher first touches. A spread here is a spread
    the yaw test sees whenever float rounding moves first contact by one step."""
    com = (0.015, 0.008)
    obj = box_object(0.08, 0.05, 0.03, com_m=com, mu_pusher=0.5)
    step_m = 0.4 * sim.settings.timestep_s
    print(
        "| start yaw deg | gap phase (steps) | rotation deg | max tilt deg | max lift mm "
        "| longest hop ms | peak floor normal N |"
    )
    print("|---|---|---|---|---|---|---|")
    rots: dict[str, list[float]] = {"phase": [], "yaw": []}
    cases = [(0.0, f) for f in (-0.01, 0.0, 0.01, 0.1, 0.25, 0.5, 0.75, 0.9)]
    cases += [(y, 0.0) for y in (30.0, 45.0, 90.0, -160.0)]
    for yaw_deg, frac in cases:
        pose = Pose2D(0.0, 0.0, math.radians(yaw_deg))
        sc = SceneSpec(FloorSpec(1.0, 1.0), obj, initial_pose=pose)
        sim.build(sc)
        contact = pose.to_world(np.array([com[0] + 0.01, -0.025]))
        direction = pose.to_world(np.array([0.0, 1.0])) - np.array([pose.x_m, pose.y_m])
        gap = 0.01 + frac * step_m
        cmd = contact_push(contact, direction, 0.03, 0.4, sc.pusher.radius_m, gap)
        rec: dict[str, float] = {}
        with _per_step_probe(sim, rec):
            o = sim.push(cmd)
        (rots["phase"] if yaw_deg == 0.0 else rots["yaw"]).append(o.rotation_deg)
        print(
            f"| {yaw_deg:g} | {frac:+.2f} | {o.rotation_deg:+.3f} | {o.max_tilt_deg:.2f} | "
            f"{rec['z_mm']:.3f} | {rec['air_ms']:.0f} | {rec['floor_n']:.1f} |"
        )
    ph, yw = np.array(rots["phase"]), np.array(rots["yaw"] + [rots["phase"][1]])
    print(
        f"\nspread over phase {ph.max() - ph.min():.2f} deg, over the 5 contract yaws "
        f"{yw.max() - yw.min():.2f} deg (bound 1.5)"
    )


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "phase":
        kw = ast.literal_eval(sys.argv[2]) if len(sys.argv) > 2 else {}
        sim = MujocoSimulator(contact=replace(DEFAULT_CONTACT, **kw))
        phase_report(sim)
        sim.close()
        return
    if len(sys.argv) > 1 and sys.argv[1] in ("objects", "speed"):
        sim = MujocoSimulator()
        (objects if sys.argv[1] == "objects" else speed_report)(sim)
        sim.close()
        return
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
    print(
        "\n| through CoM, pusher mu 1 | "
        + " | ".join(
            f"CoM {c[0] * 100:+.1f},{c[1] * 100:+.1f} cm yaw {y}" for c, y in THROUGH_COM_SETUPS
        )
        + " |"
    )
    print("|---" * (len(THROUGH_COM_SETUPS) + 1) + "|")
    for mu in (1.0, 0.1):
        for speed in (0.04, 0.4):
            cells = []
            for c, y in THROUGH_COM_SETUPS:
                o = push_through_com(sim, mu, speed, c, y)
                cells.append(
                    f"{o.rotation_deg:+.3f} (tilt {o.max_tilt_deg:.1f})" if o.ok else o.status.value
                )
            print(f"| floor mu {mu}, {100 * speed:g} cm/s | " + " | ".join(cells) + " |")
    print("\n| slide stop | floor mu | v0 (m/s) | stop (mm) | v0^2/(2 mu g) (mm) |")
    print("|---|---|---|---|---|")
    for mu in (1.0, 0.1):
        for v0 in (0.04, 0.4):
            ideal = 1e3 * v0 * v0 / (2 * mu * GRAVITY_M_S2)
            print(f"| | {mu} | {v0} | {stop_distance_mm(sim, mu, v0):.3f} | {ideal:.3f} |")
    print("\n| push | floor mu | speed (m/s) | rotation (deg) | max tilt (deg) | status |")
    print("|---|---|---|---|---|---|")
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
