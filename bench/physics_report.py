"""Print the measured values behind the physics contract (tests/test_physics.py) for a backend.

Uses only the public Simulator interface, so it works for every backend:

    .venv/bin/python bench/physics_report.py --backend pybullet
    .venv/bin/python bench/physics_report.py --backend mujoco

Tables: sliding deceleration per floor axis (vs mu*g), rotation of a push through the CoM,
rotation of pushes 1.5 cm either side of the CoM, pusher tracking lag, and wall time of the
main operations. The scenes are the ones the contract tests use.
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from comexp.experiment.simulator import PushOutcome, Simulator, contact_push, make_simulator  # noqa: E402
from comexp.method.geometry import box_object  # noqa: E402
from comexp.method.scene import GRAVITY_M_S2, FloorSpec, Pose2D, SceneSpec  # noqa: E402

PUSH_LENGTH_M = 0.03
FLOORS = {
    "iso0.1": (0.1, 0.1),
    "iso1": (1.0, 1.0),
    "aniso_x0.1": (0.1, 1.0),
    "aniso_x1": (1.0, 0.1),
}
SPEEDS_M_S = (0.4, 0.04)


def _box(com=(0.0, 0.0), mu_pusher=0.5):
    return box_object(0.08, 0.05, 0.03, com_m=com, mu_pusher=mu_pusher)


def sliding_deceleration(sim: Simulator, mu_x: float, mu_y: float, axis: int) -> dict:
    """Slide along a world axis and fit the velocity decay (same method as the contract test)."""
    sim.build(SceneSpec(FloorSpec(mu_x, mu_y), _box()))
    sim.step(0.05)
    mu = (mu_x, mu_y)[axis]
    v0 = 0.6 if mu >= 1.0 else 0.3
    lin = [0.0, 0.0, 0.0]
    lin[axis] = v0
    sim.set_object_velocity(tuple(lin), (0.0, 0.0, 0.0))
    dt, t, ts, vs = 0.002, 0.0, [], []
    for _ in range(2000):
        sim.step(dt)
        t += dt
        v = sim.object_state().linear_velocity_m_s[axis]
        if v < 0.2 * v0:
            break
        ts.append(t)
        vs.append(v)
    ts_a, vs_a = np.array(ts), np.array(vs)
    keep = ts_a > 0.01
    decel = -float(np.polyfit(ts_a[keep], vs_a[keep], 1)[0])
    st = sim.object_state()
    return {
        "decel": decel,
        "expected": mu * GRAVITY_M_S2,
        "veer_mm": 1e3 * abs(st.position_m[1 - axis]),
        "yaw_deg": math.degrees(st.yaw_rad),
        "tilt_deg": st.tilt_deg,
    }


def push_left_face(sim: Simulator, scene: SceneSpec, y_contact: float, speed: float):
    """Push the box's -x face at world height y along +x (as the contract tests do)."""
    half_len = max(p[0] for p in scene.obj.outline_m)
    contact = (scene.initial_pose.x_m - half_len, scene.initial_pose.y_m + y_contact)
    cmd = contact_push(contact, (1.0, 0.0), PUSH_LENGTH_M, speed, scene.pusher.radius_m)
    return sim.push(cmd)


YAWS_DEG = (0, 30, 45, 90, -160)


def yaw_rotations(sim: Simulator, mu_floor: float, offset_m: float, speed: float) -> list[float]:
    """Rotation of the same object-frame push (along object +y, `offset_m` right of the CoM)
    started at several world yaws; on an isotropic floor they should all be equal."""
    com = (0.015, 0.008)
    obj = _box(com=com, mu_pusher=0.5)
    rots = []
    for yaw_deg in YAWS_DEG:
        pose = Pose2D(0.0, 0.0, math.radians(yaw_deg))
        scene = SceneSpec(FloorSpec(mu_floor, mu_floor), obj, initial_pose=pose)
        sim.build(scene)
        contact = pose.to_world(np.array([com[0] + offset_m, -0.025]))
        d = pose.to_world(np.array([0.0, 1.0]))
        cmd = contact_push(contact, d, PUSH_LENGTH_M, speed, scene.pusher.radius_m)
        rots.append(sim.push(cmd).rotation_deg)
    return rots


def diagonal_slide(sim: Simulator, mu_x: float, mu_y: float, angle_deg: float) -> np.ndarray:
    """Mean acceleration (m/s^2, world) over 10-20 ms of a free slide at `angle_deg`."""
    sim.build(SceneSpec(FloorSpec(mu_x, mu_y), _box()))
    sim.step(0.05)
    a = math.radians(angle_deg)
    sim.set_object_velocity((0.3 * math.cos(a), 0.3 * math.sin(a), 0.0), (0.0, 0.0, 0.0))
    sim.step(0.01)
    va = np.array(sim.object_state().linear_velocity_m_s[:2])
    sim.step(0.01)
    vb = np.array(sim.object_state().linear_velocity_m_s[:2])
    return (vb - va) / 0.01


def objects_at_rest(sim: Simulator) -> list[tuple[str, ...]]:
    """Tilt and residual motion of every built-in object left at rest for 0.5 s."""
    from comexp.experiment.episode import EpisodeSpec, build_scene
    from comexp.experiment.objects import builtin_objects, com_points

    rows = []
    for obj in builtin_objects():
        for k, com in enumerate(com_points(obj, 2)):
            spec = EpisodeSpec.for_object(
                obj,
                k,
                com,
                backend=sim.name,
                floor="iso",
                mu_floor_x=1.0,
                mu_floor_y=1.0,
                mu_pusher=0.5,
                speed_cm_s=4.0,
                izz_scale=1.0,
                seed=k,
            )
            scene = build_scene(spec)
            sim.build(scene)
            c = scene.obj.height_m / 2.0
            tilt = planar = spin = full = 0.0
            for _ in range(250):
                sim.step(0.002)
                st = sim.object_state()
                v, w = st.linear_velocity_m_s, st.angular_velocity_rad_s
                # object-frame origin is on the floor; the point under the CoM moves like it
                tilt = max(tilt, st.tilt_deg)
                planar = max(planar, math.hypot(v[0], v[1]))
                spin = max(spin, abs(w[2]))
                full = max(full, math.hypot(*v) + c * math.hypot(w[0], w[1]))
            rows.append(
                (
                    obj.name,
                    str(k),
                    f"{tilt:.3f}",
                    f"{1e3 * planar:.3f}",
                    f"{spin:.4f}",
                    f"{1e3 * full:.2f}",
                )
            )
    return rows


def _moved_cm(out: PushOutcome) -> float:
    a, b = out.pose_before, out.pose_after
    return 100.0 * math.hypot(b.x_m - a.x_m, b.y_m - a.y_m)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", choices=["pybullet", "mujoco"], default="pybullet")
    args = ap.parse_args()
    sim = make_simulator(args.backend)
    dt_ms = 1e3 * sim.settings.timestep_s
    print(f"# physics report: backend={args.backend}, timestep={dt_ms:g} ms\n")

    print("## Sliding deceleration (box 8x5x3 cm, 0.2 kg; bound: within 5% of mu*g)\n")
    print("| floor (mu_x, mu_y) | axis | decel m/s^2 | mu*g m/s^2 | ratio | veer mm | yaw deg |")
    print("|---|---|---|---|---|---|---|")
    for name, (mx, my) in FLOORS.items():
        for axis in (0, 1):
            r = sliding_deceleration(sim, mx, my, axis)
            print(
                f"| {name} ({mx}, {my}) | {'xy'[axis]} | {r['decel']:.4f} | {r['expected']:.4f}"
                f" | {r['decel'] / r['expected']:.4f} | {r['veer_mm']:.3f} | {r['yaw_deg']:.3f} |"
            )

    print("\n## Push through the CoM (CoM (1.5, 1.0) cm, pusher mu 1; bound: |rot| < 0.5 deg)\n")
    print("| floor mu | speed cm/s | rotation deg | moved cm | max tilt deg | lag mm | status |")
    print("|---|---|---|---|---|---|---|")
    com = (0.015, 0.01)
    for mu in (0.1, 1.0):
        for speed in SPEEDS_M_S:
            scene = SceneSpec(FloorSpec(mu, mu), _box(com=com, mu_pusher=1.0))
            sim.build(scene)
            out = push_left_face(sim, scene, com[1], speed)
            print(
                f"| {mu} | {100 * speed:g} | {out.rotation_deg:+.4f} | {_moved_cm(out):.2f}"
                f" | {out.max_tilt_deg:.3f} | {1e3 * out.max_pusher_lag_m:.4f} | {out.status} |"
            )

    print("\n## Offset pushes (CoM at centroid, pusher mu 0.5, contact 1.5 cm off the CoM line)")
    print(
        "Expected sign: offset +1.5 cm -> CW (negative), -1.5 cm -> CCW (positive), |rot| > 1 deg"
    )
    print("and, at floor mu 1, |rot| at 40 cm/s > |rot| at 4 cm/s.\n")
    print("| floor mu | offset cm | rot @40 cm/s deg | rot @4 cm/s deg | moved @40 / @4 cm |")
    print("|---|---|---|---|---|")
    for mu in (0.1, 1.0):
        for offset in (0.015, -0.015):
            row = []
            for speed in SPEEDS_M_S:
                scene = SceneSpec(FloorSpec(mu, mu), _box())
                sim.build(scene)
                row.append(push_left_face(sim, scene, offset, speed))
            print(
                f"| {mu} | {100 * offset:+.1f} | {row[0].rotation_deg:+.3f} | "
                f"{row[1].rotation_deg:+.3f} | {_moved_cm(row[0]):.2f} / {_moved_cm(row[1]):.2f} |"
            )

    print("\n## Yaw invariance (iso floor; same object-frame push at yaw " + str(YAWS_DEG) + ")")
    print("Box CoM (1.5, 0.8) cm, push along object +y, pusher mu 0.5; rotations in deg.\n")
    print("| floor mu | offset mm | speed cm/s | rotations deg | spread deg |")
    print("|---|---|---|---|---|")
    for mu in (1.0, 0.1):
        for offset in (0.002, 0.01):
            for speed in SPEEDS_M_S:
                r = yaw_rotations(sim, mu, offset, speed)
                print(
                    f"| {mu} | {1e3 * offset:g} | {100 * speed:g} | "
                    f"{' '.join(f'{x:+.2f}' for x in r)} | {max(r) - min(r):.2f} |"
                )

    print("\n## Diagonal slides: acceleration over 10-20 ms (m/s^2), slide at 0.3 m/s\n")
    print("Models for a unit slip direction s: elliptic max-dissipation")
    print("-g (mu_x^2 s_x, mu_y^2 s_y)")
    print("/ |(mu_x s_x, mu_y s_y)|; per-component -g (mu_x s_x, mu_y s_y).\n")
    print("| floor (mu_x, mu_y) | slide deg | measured | elliptic max-diss | per-component |")
    print("|---|---|---|---|---|")
    for mx, my in ((1.0, 1.0), (0.1, 1.0), (1.0, 0.1)):
        for ang in (0, 30, 45, 60):
            acc = diagonal_slide(sim, mx, my, ang)
            sx, sy = math.cos(math.radians(ang)), math.sin(math.radians(ang))
            n = math.hypot(mx * sx, my * sy)
            ell = (-GRAVITY_M_S2 * mx * mx * sx / n, -GRAVITY_M_S2 * my * my * sy / n)
            comp = (-GRAVITY_M_S2 * mx * sx, -GRAVITY_M_S2 * my * sy)
            print(
                f"| ({mx}, {my}) | {ang} | ({acc[0]:+.3f}, {acc[1]:+.3f}) | "
                f"({ell[0]:+.3f}, {ell[1]:+.3f}) | ({comp[0]:+.3f}, {comp[1]:+.3f}) |"
            )

    print("\n## Built-in objects at rest (2 CoMs each, iso floor mu 1, 0.5 s after build)\n")
    print("Planar: horizontal speed of the object-frame origin (on the floor); 3D: its full")
    print("speed + (h/2)|w_xy|, which includes the rocking of many-sided footprints.\n")
    print("| object | com | max tilt deg | max planar mm/s | max yaw rate rad/s | max 3D mm/s |")
    print("|---|---|---|---|---|---|")
    for row in objects_at_rest(sim):
        print("| " + " | ".join(row) + " |")

    print("\n## Wall time (this machine)\n")
    scene = SceneSpec(FloorSpec(0.5, 0.5), _box(com=(0.01, -0.005)))
    n = 50
    t0 = time.perf_counter()
    for _ in range(n):
        sim.build(scene)
    t_build = (time.perf_counter() - t0) / n
    t0 = time.perf_counter()
    for _ in range(10):
        sim.render_depth()
    t_render = (time.perf_counter() - t0) / 10
    pushes = []
    for speed in SPEEDS_M_S:
        sim.build(scene)
        t0 = time.perf_counter()
        out = push_left_face(sim, scene, 0.012, speed)
        pushes.append((speed, time.perf_counter() - t0, out))
    print("| operation | wall ms |")
    print("|---|---|")
    print(f"| build (mean of {n}) | {1e3 * t_build:.2f} |")
    print(f"| render_depth 224x224 (mean of 10) | {1e3 * t_render:.2f} |")
    for speed, wall, out in pushes:
        print(
            f"| push @{100 * speed:g} cm/s ({out.steps} steps, {out.sim_time_s:.2f} s sim) "
            f"| {1e3 * wall:.1f} |"
        )
    sim.close()


if __name__ == "__main__":
    main()
