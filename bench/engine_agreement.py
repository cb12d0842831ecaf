"""Cross-engine agreement: the study's own first pushes on pybullet and MuJoCo vs planar.

    .venv/bin/python bench/engine_agreement.py [--pushes 400] [--engines pybullet mujoco]
        [--floor-friction model|native]
    .venv/bin/python bench/engine_agreement.py --tipping [--d-cm 1.3 1.1 1.0 0.9 0.7 0.5 0.3]
    .venv/bin/python bench/engine_agreement.py --steps-ms 1 0.5 0.25 [--pushes 160] [--json NAME]

Pushes are drawn from the grid of both floors and both speeds (`common.job_specs`, a strided
slice holding every object and condition): for each episode, the scene is built as
`run_episode` builds it (object, CoM, Izz, frictions, start yaw), the contact is the
estimator's first choice (Algorithm 1, `make_estimator` as the episode makes it) on the planar
backend's first image, and that same world-frame push (start, direction, travel, speed) runs
on every backend (`comexp.sim.protocol.push`). Printed per
engine: the median |rotation / planar rotation - 1| over pushes where planar turns more than
1 deg, the share of those with the same sign, the largest disagreements, and the cost per push.
Targets (issue "pybullet and MuJoCo pass the physics contract"): median <= 10%, same sign
>= 99%, over >= 400 pushes.

`--tipping` instead replays the tipping band of docs/physics.md ("Tipping"): a 3 x 3 x 2 cm
block on mu 1, its CoM d behind the leading edge, pushed 3 cm through it at 40 and 4 cm/s on
every backend, with the protocol's tip rule lifted to 89 deg and 1 s of rest after the push,
to see whether it falls over or lands back: per case the outcome and the largest tilt.

`--steps-ms` instead measures the engines' splitting error on slow pushes: the engines apply
the floor's friction as an impulse solved for the step from its starting twist, apart from
the pusher's contact (docs/physics.md, "Known limitations"), where the referee solves both
together. The first pushes of the anisotropic 4 cm/s job (Algorithm 1's, as above) run on
every engine at each step length (`SimSettings.timestep_s`) against planar's at 1 ms (its own
step-converged answer, docs/physics.md): per engine, step and pusher friction, the median
|rotation / planar's - 1| and the median signed ratio - 1 over the pushes planar turns by
more than 1 deg. `--json NAME` writes the table as docs/data/NAME.json.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from dataclasses import replace

from common import job_specs, strided, write_table

from comexp.episode.task import build_scene
from comexp.experiment.config import make_simulator
from comexp.method.estimators import make_estimator
from comexp.method.observation import perceive_first
from comexp.sim.bodies import box_object
from comexp.sim.contact import contact_push
from comexp.sim.protocol import push
from comexp.sim.scene import FloorSpec, SceneSpec, SimSettings


def first_push(planar, spec):
    """Algorithm 1's first push for an episode, from the planar backend's first image."""
    scene = build_scene(spec)
    planar.build(scene)
    perc, _ = perceive_first(planar.render_depth(), spec.estimator.contact_spacing_px)
    est = make_estimator(
        perc.region_m,
        perc.contacts_m,
        perc.contact_normals,
        perc.pixel_m,
        spec.estimator,
        outline_m=perc.outline_m,
        pusher_radius_m=scene.pusher.radius_m,
    )
    choice = est.next_push()
    if choice is None:
        return scene, None
    P, N = choice
    f = perc.frame_pose
    cmd = contact_push(
        f.to_world(P),
        N,  # the estimator frame has yaw 0 in the world at the first image
        spec.push_length_cm / 100.0,
        spec.speed_cm_s / 100.0,
        scene.pusher.radius_m,
    )
    return scene, cmd


def tipping_outcome(backend: str, d_m: float, speed_m_s: float) -> str:
    """The block's fate: `tips over` or `stays up`, with the largest tilt (deg)."""
    sim = make_simulator(backend, replace(SimSettings(), tip_limit_deg=89.0))
    try:
        sim.build(SceneSpec(FloorSpec(1.0, 1.0), box_object(0.03, 0.03, 0.02, (0.015 - d_m, 0))))
        out = push(sim, contact_push((-0.015, 0.0), (1.0, 0.0), 0.03, speed_m_s, 0.005))
        for _ in range(200):
            sim.step(0.005)
        over = sim.object_state().tilt_deg > 45.0 or out.status.value == "tipped"
        return "tips over" if over else f"stays up, {out.max_tilt_deg:.2f}"
    finally:
        sim.close()


def tipping(d_cm: list[float], engines: list[str]) -> None:
    backends = ["planar", *engines]
    print("tipping band: 3 x 3 x 2 cm block, mu 1, pushed 3 cm through its CoM")
    print()
    print("| d (cm) | cm/s | " + " | ".join(backends) + " |")
    print("|---|---|" + "---|" * len(backends))
    for speed in (0.4, 0.04):
        for d in d_cm:
            cells = [tipping_outcome(b, d / 100.0, speed) for b in backends]
            print(f"| {d:.2f} | {100 * speed:.0f} | " + " | ".join(cells) + " |", flush=True)


def step_convergence(
    engines: list[str], steps_ms: list[float], pushes: int
) -> tuple[list[str], list[list[object]]]:
    """The slow anisotropic job's first pushes on each engine at each step against planar's
    (module docstring): the table's columns and rows."""
    specs = strided(job_specs("planar", "aniso", 4.0), pushes)
    planar = make_simulator("planar")
    sims = {
        (e, dt): make_simulator(e, replace(SimSettings(), timestep_s=dt / 1000.0))
        for e in engines
        for dt in steps_ms
    }
    ratios: dict[tuple[str, float, float], list[float]] = {}
    for spec in specs:
        scene, cmd = first_push(planar, spec)
        if cmd is None:
            continue
        planar.build(scene)
        ref = push(planar, cmd)
        if not (ref.ok and abs(ref.rotation_deg) > 1.0):
            continue
        for (e, dt), sim in sims.items():
            sim.build(scene)
            out = push(sim, cmd)
            if out.ok:
                key = (e, dt, spec.mu_pusher)
                ratios.setdefault(key, []).append(out.rotation_deg / ref.rotation_deg - 1.0)
    for sim in (planar, *sims.values()):
        sim.close()
    columns = ["engine", "step (ms)", "pusher friction", "pushes",
               "median abs(ratio - 1)", "median ratio - 1"]  # fmt: skip
    rows: list[list[object]] = [
        [e, dt, mu, len(v), statistics.median(map(abs, v)), statistics.median(v)]
        for (e, dt, mu), v in sorted(ratios.items())
    ]
    return columns, rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pushes", type=int, default=400)
    ap.add_argument("--engines", nargs="+", default=["pybullet", "mujoco"])
    ap.add_argument("--floor-friction", default="model", choices=["model", "native"])
    ap.add_argument("--tipping", action="store_true", help="the tipping band instead")
    ap.add_argument("--d-cm", nargs="+", type=float, default=[1.3, 1.1, 1.0, 0.9, 0.7, 0.5, 0.3])
    ap.add_argument(
        "--steps-ms", nargs="+", type=float, help="the engines' splitting error at these steps"
    )
    ap.add_argument("--json", metavar="NAME", help="--steps-ms: write docs/data/NAME.json")
    args = ap.parse_args()
    if args.tipping:
        tipping(args.d_cm, args.engines)
        return
    if args.steps_ms:
        columns, rows = step_convergence(args.engines, args.steps_ms, args.pushes)
        print(" | ".join(columns))
        for row in rows:
            print(" | ".join(f"{v:.3f}" if isinstance(v, float) else str(v) for v in row))
        if args.json:
            command = "python bench/engine_agreement.py " + " ".join(sys.argv[1:])
            print(write_table(args.json, columns, rows, command))
        return
    per_job = math.ceil(args.pushes / 4)
    specs = []
    for floor in ("iso", "aniso"):
        for speed in (40.0, 4.0):
            specs += strided(job_specs("planar", floor, speed), per_job)
    planar = make_simulator("planar")
    engines = {e: make_simulator(e, floor_friction=args.floor_friction) for e in args.engines}
    rows = []
    cost = {e: 0.0 for e in ["planar", *args.engines]}
    for spec in specs:
        scene, cmd = first_push(planar, spec)
        if cmd is None:
            continue
        row = {"spec": spec}
        for name, sim in [("planar", planar), *engines.items()]:
            sim.build(scene)
            t0 = time.perf_counter()
            out = push(sim, cmd)
            cost[name] += time.perf_counter() - t0
            row[name] = out.rotation_deg if out.ok else float("nan")
            row[name + "_status"] = out.status.value
        rows.append(row)
    n = len(rows)
    print(
        f"engine agreement: {n} first pushes of the grid (both floors, both speeds), "
        f"engine floor friction = {args.floor_friction}"
    )
    print()
    print(
        "| engine | pushes turning > 1 deg | median abs(ratio - 1) | same sign | "
        "worst ratios | s per push (planar) |"
    )
    print("|---|---|---|---|---|---|")
    for e in args.engines:
        turning = [r for r in rows if abs(r["planar"]) > 1.0 and math.isfinite(r[e])]
        dev = [abs(r[e] / r["planar"] - 1.0) for r in turning]
        same = sum(1 for r in turning if r[e] * r["planar"] > 0)
        worst = sorted(turning, key=lambda r: -abs(r[e] / r["planar"] - 1.0))[:3]
        worst_txt = ", ".join(f"{r['spec'].object} {r[e]:.1f}/{r['planar']:.1f}" for r in worst)
        failed = sum(1 for r in rows if r[e + "_status"] != "ok")
        print(
            f"| {e} | {len(turning)} ({failed} pushes failed) | "
            f"{100 * statistics.median(dev):.1f}% | {100 * same / max(len(turning), 1):.1f}% | "
            f"{worst_txt} | {cost[e] / n:.3f} ({cost['planar'] / n:.3f}) |"
        )


if __name__ == "__main__":
    main()
