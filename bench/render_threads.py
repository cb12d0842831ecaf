"""MuJoCo's depth renders with Mesa's llvmpipe threads on and off (`LP_NUM_THREADS`).

    .venv/bin/python bench/render_threads.py --rounds 4 --repeat 20

Without a GPU, MuJoCo's EGL context is Mesa's software rasteriser, which by default hands
each render to one thread per core. backends/mujoco_sim.py sets `LP_NUM_THREADS=0`
(rasterise in the calling thread) unless the environment says otherwise. Each round runs
one child process per setting, alternately (so that the machine's load hits them alike):
the child places every built-in object at 5 seeded poses and renders each pose's tracking
window and full image `--repeat` times, timing CPU (`time.process_time`, every thread of
the process) and wall time per render. Printed: per setting the median over rounds of the
CPU and wall ms per window and per full render, the ratio to the threaded default, and
whether every pixel equals the default's.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

SETTINGS = {"mesa default (threads)": None, "LP_NUM_THREADS=0": "0"}


def child(out: str, repeat: int) -> None:
    """Render and time; write the timings (json) and the first render of each pose (npz)."""
    from dataclasses import replace

    import shapely

    from comexp.experiment.episode import EpisodeSpec, build_scene
    from comexp.experiment.objects import load_objects
    from comexp.experiment.simulator import make_simulator
    from comexp.method.scene import Pose2D

    objs = load_objects()
    sim = make_simulator("mujoco", floor_friction="model")
    rng = np.random.default_rng(0)
    images: dict[str, np.ndarray] = {}
    cpu = {"window": 0.0, "full": 0.0}
    wall = {"window": 0.0, "full": 0.0}
    n = 0
    for name in sorted(objs):
        c = shapely.Polygon(objs[name].outline_cm).representative_point()
        spec = EpisodeSpec.for_object(
            objs[name],
            0,
            (c.x, c.y),
            backend="mujoco",
            floor="iso",
            mu_floor_x=0.1,
            mu_floor_y=0.1,
            mu_pusher=0.1,
            speed_cm_s=40.0,
            izz_scale=1.0,
        )
        for k in range(5):
            pose = Pose2D(*(float(v) for v in rng.uniform([-0.1, -0.1, -3.0], [0.1, 0.1, 3.0])))
            sim.build(replace(build_scene(spec), initial_pose=pose))
            images[f"{name}{k}w"] = sim.render_tracking_depth().depth_m  # untimed: warm
            images[f"{name}{k}f"] = sim.render_depth().depth_m
            for kind, render in (("window", sim.render_tracking_depth), ("full", sim.render_depth)):
                t, w = time.process_time(), time.perf_counter()
                for _ in range(repeat):
                    render()
                cpu[kind] += time.process_time() - t
                wall[kind] += time.perf_counter() - w
            n += repeat
    np.savez(out + ".npz", **images)
    with open(out + ".json", "w") as f:
        json.dump({k: {"cpu": 1e3 * cpu[k] / n, "wall": 1e3 * wall[k] / n} for k in cpu}, f)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=20, help="renders per pose and kind")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.child, args.repeat)
        return
    tmp = tempfile.mkdtemp(prefix="render_threads_")
    times: dict[str, list[dict]] = {s: [] for s in SETTINGS}
    for r in range(args.rounds):
        for label, value in SETTINGS.items():
            env = dict(os.environ)
            env.pop("LP_NUM_THREADS", None)
            # the backend's own default is 0: the default setting must be asked for by name
            env["LP_NUM_THREADS"] = value if value is not None else str(os.cpu_count() or 1)
            out = os.path.join(tmp, f"{r}_{value}")
            cmd = [sys.executable, __file__, "--child", out, "--repeat", str(args.repeat)]
            subprocess.run(cmd, env=env, check=True, stderr=subprocess.DEVNULL)
            with open(out + ".json") as f:
                times[label].append(json.load(f))
    ref = next(iter(SETTINGS))
    base = np.load(os.path.join(tmp, f"0_{SETTINGS[ref]}.npz"))
    print(f"{args.rounds} rounds, {os.cpu_count()} cores, 20 objects x 5 poses x {args.repeat}")
    print("| setting | window CPU ms | wall ms | full CPU ms | wall ms | CPU vs default | pixels |")
    print("|---|---|---|---|---|---|---|")
    med = {
        s: {k: {m: statistics.median(t[k][m] for t in ts) for m in ("cpu", "wall")} for k in ts[0]}
        for s, ts in times.items()
    }
    for label, value in SETTINGS.items():
        m = med[label]
        same = all(
            np.array_equal(base[k], np.load(os.path.join(tmp, f"{r}_{value}.npz"))[k])
            for r in range(args.rounds)
            for k in base.files
        )
        ratio = m["window"]["cpu"] / med[ref]["window"]["cpu"]
        print(
            f"| {label} | {m['window']['cpu']:.3f} | {m['window']['wall']:.3f} | "
            f"{m['full']['cpu']:.3f} | {m['full']['wall']:.3f} | {ratio:.2f} (window), "
            f"{m['full']['cpu'] / med[ref]['full']['cpu']:.2f} (full) | "
            f"{'identical' if same else 'DIFFER'} |"
        )


if __name__ == "__main__":
    main()
