"""Planar backend: time per push, and the same pushes against an older version of the model.

    .venv/bin/python bench/planar_speed.py [--repeat 3]
    git show HEAD~1:backends/planar_sim.py > /tmp/old/planar_sim.py
    git show HEAD~1:backends/floor_friction.py > /tmp/old/floor_friction.py
    .venv/bin/python bench/planar_speed.py --baseline /tmp/old

The pushes: 3 objects (rect_8x5, l_shape, triangle_right_11x7, CoM off-centre) x floors
mu 0.1, 1 and anisotropic (0.1, 1) x lever arms 0, 5 mm, 1 cm x 4 and 40 cm/s, a 3 cm
push into the object's -x side (mu_pusher 0.5). With `--baseline DIR` (the two modules of
another version) every push runs with both, interleaved on the same machine state: the
wall-time ratio and the largest differences in rotation (deg) and final pose are printed.
The other version is loaded beside this one under names of its own, nothing swapped in;
it must speak today's simulator interface (`comexp.sim`): an older checkout as a whole is
bench/compare_checkouts.py's to compare.

`--self-noise` instead runs each push twice on one version (the baseline if given), the
second time with the object's start moved by 1e-15 m: the model's own sensitivity to
rounding (its solver tolerances and stick/slip decisions), the floor under which two
versions that round differently cannot agree.

`--resolutions` instead runs every push at the default resolution (400 footprint samples,
1 ms steps, slow steps of 5) and at others (slow steps off, fewer samples, longer steps):
per resolution the CPU time against the default's and the largest rotation change at 40 and
at 4 cm/s: what the model's cheaper settings would buy and cost (docs/performance.md,
"planar").

`--passes` instead times one pass over the footprint's samples (rect_8x5's 416, an
anisotropic floor, a sliding and turning twist): the Newton pass (value, gradient, Hessian:
`_objective_into`) and the line search's (value alone: `value_kernel`), 20,000 passes in a
compiled loop (2,000 with `--pushes`, the smoke run), in us per pass (docs/performance.md,
"What a step costs"); with `--baseline DIR` the same passes of DIR's floor_friction.py too,
in the same run.

`--convergence` instead prints docs/physics.md's convergence table: the rotation (deg) of an
8 x 5 x 1.5 cm box pushed 1 cm beside its CoM (pusher mu 0.5, 3 cm at 40 and 4 cm/s, floor
mu 0.1 and 1) at the default resolution, with slow steps off, 100 and 1600 samples, 0.5 and
0.25 ms steps, and 0.25 ms with slow steps off (the case of
`tests/test_planar.py::test_rotation_converges_in_the_grid_and_the_timestep`).

`--pushes N` runs N of the 54 pushes, spread over the list (tests/test_bench.py's smoke run).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from common import load_module

from comexp.backends.physics_settings import FrictionSettings, SlowSteps
from comexp.backends.planar_sim import PlanarSimulator
from comexp.experiment.objects import com_point, load_objects
from comexp.sim.bodies import box_object
from comexp.sim.contact import contact_push
from comexp.sim.protocol import push
from comexp.sim.scene import FloorSpec, SceneSpec, SimSettings

OBJECTS = ("rect_8x5", "l_shape", "triangle_right_11x7")
FLOORS = ((0.1, 0.1), (1.0, 1.0), (0.1, 1.0))
LEVERS_M = (0.0, 0.005, 0.01)
SPEEDS_M_S = (0.04, 0.4)


def cases() -> list[tuple[str, SceneSpec, object]]:
    out = []
    for name in OBJECTS:
        od = load_objects([name])[name]
        spec = od.model(com_point(od, 0), izz_scale=1.0, mu_pusher=0.5)
        outline = np.asarray(spec.outline_m)
        for mu in FLOORS:
            for lever in LEVERS_M:
                for speed in SPEEDS_M_S:
                    scene = SceneSpec(FloorSpec(*mu), spec)
                    y = spec.com_m[1] + lever
                    cmd = contact_push((outline[:, 0].min(), y), (1.0, 0.0), 0.03, speed, 0.005)
                    label = f"{name} mu={mu} lever={lever * 1e3:.0f}mm v={speed * 100:.0f}cm/s"
                    out.append((label, scene, cmd))
    return out


def load_baseline(directory: Path) -> type:
    """PlanarSimulator of the version in `directory` (its floor_friction.py beside it),
    loaded beside the package's modules under names of its own (`common.load_module`): its
    planar_sim.py, copied as _planar_sim_baseline.py, imports that floor_friction.py."""
    ff_name = "planar_baseline_floor_friction"
    load_module(ff_name, directory / "floor_friction.py")
    src = (directory / "planar_sim.py").read_text()
    src = src.replace(
        "from comexp.backends import floor_friction\n", f"import {ff_name} as floor_friction\n"
    )
    path = directory / "_planar_sim_baseline.py"
    path.write_text(src.replace("comexp.backends.floor_friction", ff_name))
    return load_module("planar_baseline_sim", path).PlanarSimulator


def run(sim_cls: type, scene: SceneSpec, cmd) -> tuple[float, object]:
    sim = sim_cls()
    sim.build(scene)
    t0 = time.perf_counter()
    out = push(sim, cmd)
    return time.perf_counter() - t0, out


def self_noise(sim_cls: type, all_cases) -> None:
    worst, worst_label = 0.0, ""
    for label, scene, cmd in all_cases:
        nudged = replace(scene, initial_pose=replace(scene.initial_pose, x_m=1e-15))
        a, b = run(sim_cls, scene, cmd)[1], run(sim_cls, nudged, cmd)[1]
        d = abs(a.rotation_deg - b.rotation_deg)
        print(f"{label:48s} rot {a.rotation_deg:+9.4f} deg  nudged d_rot {d:.1e}")
        if d > worst:
            worst, worst_label = d, label
    print(f"max |d rotation| under a 1e-15 m nudge: {worst:.2e} deg ({worst_label})")


# (footprint samples, step in ms, slow steps) against the default (400, 1, 5)
RESOLUTIONS = (
    (400, 1.0, 5),
    (400, 1.0, 1),
    (200, 1.0, 5),
    (100, 1.0, 5),
    (400, 2.0, 5),
    (100, 2.0, 5),
)


CONVERGENCE_COLUMNS = (
    ("default (400 samples, 1 ms, slow steps)", {}),
    ("slow steps off", {"slow_steps": SlowSteps(steps=1)}),
    ("100 samples", {"planar": replace(FrictionSettings(), samples=100)}),
    ("1600 samples", {"planar": replace(FrictionSettings(), samples=1600)}),
    ("0.5 ms", {"settings": replace(SimSettings(), timestep_s=0.0005)}),
    ("0.25 ms", {"settings": replace(SimSettings(), timestep_s=0.00025)}),
    (
        "0.25 ms, slow steps off",
        {"settings": replace(SimSettings(), timestep_s=0.00025), "slow_steps": SlowSteps(steps=1)},
    ),
)


def convergence() -> None:
    """docs/physics.md's convergence table, as Markdown."""
    box = box_object(0.08, 0.05, 0.015, mu_pusher=0.5)
    print("| floor mu | cm/s | " + " | ".join(c for c, _ in CONVERGENCE_COLUMNS) + " |")
    print("|---|---|" + "---|" * len(CONVERGENCE_COLUMNS))
    for mu in (0.1, 1.0):
        for speed in (0.4, 0.04):
            cmd = contact_push((-0.04, 0.01), (1.0, 0.0), 0.03, speed, 0.005)
            rots = []
            for _, kw in CONVERGENCE_COLUMNS:
                sim = PlanarSimulator(**kw)
                sim.build(SceneSpec(FloorSpec(mu, mu), box))
                rots.append(f"{push(sim, cmd).rotation_deg:.3f}")
            print(f"| {mu:.1f} | {speed * 100:g} | " + " | ".join(rots) + " |")


def resolutions(all_cases) -> None:
    """CPU time and rotation change of each resolution against the default's."""
    print(
        "| samples | step (ms) | slow steps | CPU vs default | max abs(d rot) 40 cm/s | 4 cm/s "
        "| median |"
    )
    print("|---|---|---|---|---|---|---|")
    base = None
    for samples, step_ms, slow in RESOLUTIONS:
        sim = PlanarSimulator(
            SimSettings(timestep_s=step_ms / 1e3),
            replace(FrictionSettings(), samples=samples),
            SlowSteps(steps=slow),
        )
        rots, cpu = [], 0.0
        for _, scene, cmd in all_cases:
            sim.build(scene)
            t0 = time.process_time()
            rots.append(push(sim, cmd).rotation_deg)
            cpu += time.process_time() - t0
        rots = np.array(rots)
        base = base or (rots, cpu)
        d = np.abs(rots - base[0])
        fast = np.array(["v=40" in label for label, _, _ in all_cases])
        worst = [f"{d[m].max():.3f}" if m.any() else "-" for m in (fast, ~fast)]
        print(
            f"| {samples} | {step_ms:g} | {slow} | x{base[1] / cpu:.2f} | {worst[0]} | "
            f"{worst[1]} | {np.median(d):.4f} |"
        )


def passes(n_loop: int = 20000, baseline: Path | None = None) -> None:
    """CPU time of one pass over the footprint's samples, Newton's and the line search's,
    of this version's kernels and, given `baseline`, of that directory's."""
    from comexp.backends import floor_friction

    versions = [("", floor_friction)]
    if baseline is not None:
        load_baseline(baseline)
        versions.append(("baseline ", sys.modules["planar_baseline_floor_friction"]))
    for label, ff in versions:
        _passes_of(ff, n_loop, label)


def _passes_of(ff, n_loop: int, label: str) -> None:
    from numba import njit

    from comexp.sim.scene import PusherSpec

    od = load_objects(["rect_8x5"])["rect_8x5"]
    spec = od.model(com_point(od, 0), izz_scale=1.0, mu_pusher=0.5)
    fr = ff.FootprintFriction(spec, 0.1, 1.0, PusherSpec())
    grad_pass, value_pass = ff._objective_into, ff.value_kernel

    @njit
    def loop_grad(n, xi, xi_hat, M, w, dx, dy, tau, g, H):  # noqa: N803 - the kernel's names
        acc = 0.0
        for _ in range(n):
            xi[0] += 1e-12  # a new point each pass: nothing hoisted out of the loop
            acc += grad_pass(xi, xi_hat, M, w, dx, dy, 0.1, 1.0, 1e-3, 1e-7, 0.0, tau, 0.0,
                             True, g, H)  # fmt: skip
        return acc

    @njit
    def loop_value(n, xi, xi_hat, M, w, dx, dy, tau):  # noqa: N803
        acc = 0.0
        for _ in range(n):
            xi[0] += 1e-12
            acc += value_pass(xi, xi_hat, M, w, dx, dy, 0.1, 1.0, 1e-3, 1e-7, 0.0, tau, 0.0, True)
        return acc

    xi = np.array([0.1, 0.02, 0.5])
    args = (xi, xi * 1.01, fr.M, fr.normal, fr.dxw, fr.dyw, np.zeros(3))
    ff.offsets_kernel(fr.geo, fr.fs, 0.3, fr.dxw, fr.dyw)
    g, H = np.zeros(3), np.zeros((3, 3))
    for name, run_loop, extra in (("Newton", loop_grad, (g, H)), ("line search", loop_value, ())):
        run_loop(10, *args, *extra)  # compile
        t0 = time.process_time()
        run_loop(n_loop, *args, *extra)
        us = (time.process_time() - t0) / n_loop * 1e6
        print(f"{label}{name} pass over {len(fr.normal)} samples: {us:.2f} us")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", type=Path, help="an older planar_sim.py + floor_friction.py")
    ap.add_argument("--repeat", type=int, default=1, help="timed runs per push (best kept)")
    ap.add_argument("--self-noise", action="store_true", help="one version vs itself, nudged")
    ap.add_argument("--pushes", type=int, help="only this many of the pushes, spread out")
    ap.add_argument("--resolutions", action="store_true", help="coarser settings vs default")
    ap.add_argument("--passes", action="store_true", help="CPU of one pass over the samples")
    ap.add_argument("--convergence", action="store_true", help="docs/physics.md's table")
    args = ap.parse_args()
    if args.convergence:
        convergence()
        return
    if args.passes:
        passes(2000 if args.pushes else 20000, args.baseline)
        return
    old_cls = load_baseline(args.baseline) if args.baseline else None
    all_cases = cases()
    if args.pushes:
        all_cases = all_cases[:: -(-len(all_cases) // args.pushes)][: args.pushes]
    if args.self_noise:
        self_noise(old_cls or PlanarSimulator, all_cases)
        return
    if args.resolutions:
        for _, scene, cmd in all_cases[:2]:  # warm-up: compile / load the kernels
            run(PlanarSimulator, scene, cmd)
        resolutions(all_cases)
        return
    for _, scene, cmd in all_cases[:2]:  # warm-up: compile / load the kernels
        run(PlanarSimulator, scene, cmd)
        if old_cls:
            run(old_cls, scene, cmd)
    t_new = t_old = 0.0
    d_rot = d_pos = 0.0
    worst = ""
    for label, scene, cmd in all_cases:
        tn, out = min((run(PlanarSimulator, scene, cmd) for _ in range(args.repeat)),
                      key=lambda r: r[0])  # fmt: skip
        t_new += tn
        line = f"{label:48s} {out.status.value:8s} rot {out.rotation_deg:+9.4f} deg"
        line += f"  {tn * 1e3:7.1f} ms"
        if old_cls:
            to, ref = min((run(old_cls, scene, cmd) for _ in range(args.repeat)),
                          key=lambda r: r[0])  # fmt: skip
            t_old += to
            dr = abs(out.rotation_deg - ref.rotation_deg)
            a, b = out.pose_after, ref.pose_after
            dp = max(abs(a.x_m - b.x_m), abs(a.y_m - b.y_m))
            same = out.status == ref.status and out.steps == ref.steps
            line += f"  old {to * 1e3:7.1f} ms  x{to / tn:5.1f}  d_rot {dr:.1e} d_pos {dp:.1e}"
            line += "" if same else f"  DIFFERS: {ref.status.value} {ref.steps} steps"
            if dr > d_rot:
                d_rot, worst = dr, label
            d_pos = max(d_pos, dp)
        print(line)
    n = len(all_cases)
    print(f"{n} pushes: {t_new / n * 1e3:.1f} ms per push (new)")
    if old_cls:
        print(f"old {t_old / n * 1e3:.1f} ms per push; speed-up x{t_old / t_new:.1f}")
        print(f"max |d rotation| {d_rot:.2e} deg ({worst}); max |d position| {d_pos:.2e} m")


if __name__ == "__main__":
    main()
