"""Mean CoM error of the method, per backend x rotation source x speed, on the iso floor, over
objects x CoMs; optionally the same for the alternative readings of the paper's ambiguities.
Also reports how well vision measures each push's rotation on real renders.

    .venv/bin/python bench/method_table.py                  # main table
    .venv/bin/python bench/method_table.py --readings \\
        --backends mujoco --sources oracle                                 # ambiguity readings
    .venv/bin/python bench/method_table.py --pose-synthetic   # vision yaw error, exact renders
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import defaultdict

import numpy as np

from comexp.experiment.episode import EpisodeSpec, EstimatorSettings, run_episode
from comexp.experiment.objects import com_points, load_objects
from comexp.experiment.simulator import make_simulator

READINGS: dict[str, dict] = {
    "default": {},
    "d=distance_px": {"d_metric": "distance_px"},
    "d signed": {"d_signed": True},
    "cos signed": {"cos_signed": True},
    "band signed": {"band_signed": True},
    "all literal": {"d_signed": True, "cos_signed": True, "band_signed": True},
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backends", nargs="+", default=["pybullet", "mujoco"])
    ap.add_argument("--sources", nargs="+", default=["vision", "oracle"])
    ap.add_argument("--speeds", nargs="+", type=float, default=[40.0, 4.0])
    ap.add_argument("--coms", type=int, default=2, help="CoMs per object")
    ap.add_argument("--objects", nargs="*", default=None, help="default: all built-in")
    ap.add_argument("--mu-floor", type=float, default=1.0)
    ap.add_argument("--mu-pusher", type=float, default=0.5)
    ap.add_argument("--izz", type=float, default=1.0)
    ap.add_argument("--readings", action="store_true", help="compare the ambiguity readings")
    ap.add_argument(
        "--pose-synthetic", action="store_true", help="yaw error of vision on exact renders"
    )
    args = ap.parse_args(argv)
    if args.pose_synthetic:
        return pose_synthetic()

    objs = load_objects().values()
    if args.objects:
        objs = [o for o in objs if o.name in args.objects]
    readings = READINGS if args.readings else {"default": {}}
    print(
        f"# {len(objs)} objects x {args.coms} CoMs, iso floor mu {args.mu_floor}, "
        f"pusher mu {args.mu_pusher}, Izz x{args.izz}"
    )
    rows = []
    per_object: dict[tuple, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for backend in args.backends:
        sim = make_simulator(backend)
        for source in args.sources:
            for speed in args.speeds:
                for rname, kw in readings.items():
                    settings = EstimatorSettings(rotation_source=source, **kw)
                    errs, rot_err, fails, walls = [], [], defaultdict(int), []
                    for obj in objs:
                        for k, com in enumerate(com_points(obj, args.coms)):
                            spec = EpisodeSpec.for_object(
                                obj,
                                k,
                                com,
                                backend=backend,
                                floor="iso",
                                mu_floor_x=args.mu_floor,
                                mu_floor_y=args.mu_floor,
                                mu_pusher=args.mu_pusher,
                                speed_cm_s=speed,
                                izz_scale=args.izz,
                                seed=k,
                                estimator=settings,
                            )
                            r = run_episode(spec, sim)
                            walls.append(r.wall_s)
                            if r.status != "ok":
                                fails[r.failure] += 1
                                continue
                            errs.append(r.error_cm)
                            per_object[(backend, source, speed, rname)][obj.name].append(r.error_cm)
                            rot_err += [abs(p.rotation_deg - p.rotation_true_deg) for p in r.pushes]
                    e = np.array(errs) if errs else np.array([np.nan])
                    re_ = np.array(rot_err) if rot_err else np.array([np.nan])
                    rows.append(
                        (
                            backend,
                            source,
                            speed,
                            rname,
                            len(errs),
                            dict(fails),
                            float(np.mean(e)),
                            float(np.median(e)),
                            float(np.mean(e < 1.0)),
                            float(np.median(re_)),
                            float(np.percentile(re_, 95)),
                            float(np.mean(walls)),
                        )
                    )
                    print(_row_markdown(rows[-1]), flush=True)
        sim.close()
    print()
    print(
        "| backend | rotation | speed cm/s | reading | ok | failed | mean err cm | median | "
        "share < 1 cm | rot err p50 deg | rot err p95 deg | wall s/ep |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        print(_row_markdown(row))
    if not args.readings:
        print("\n# per-object mean error (cm)")
        for key, by_obj in per_object.items():
            print(
                " ".join(map(str, key)),
                " ".join(f"{n}={np.mean(v):.2f}" for n, v in sorted(by_obj.items())),
            )
    return 0


def pose_synthetic(n_images: int = 20) -> int:
    """Vision's yaw error on exact ray-cast images: random moves of up to 10 cm and 0.5 rad."""
    from comexp.method.perception import PoseTracker, observe, perceive_first, render_prism_depth
    from comexp.method.scene import CameraSpec, Pose2D

    cam = CameraSpec().model()
    shapes = {
        "box 8x5": [(-0.04, -0.025), (0.04, -0.025), (0.04, 0.025), (-0.04, 0.025)],
        "triangle": [(-0.04, -0.03), (0.05, -0.02), (-0.01, 0.05)],
        "L 10x8": [(0, 0), (0.1, 0), (0.1, 0.03), (0.03, 0.03), (0.03, 0.08), (0, 0.08)],
    }
    print("| shape | median deg | 95th pct deg | max deg | max position error mm |")
    print("|---|---|---|---|---|")
    for name, poly in shapes.items():
        poly = np.asarray(poly) - np.mean(poly, axis=0)
        pose0 = Pose2D(0.05, -0.03, 0.3)
        perc, obs = perceive_first(render_prism_depth(cam, poly, 0.03, pose0))
        f_obj = pose0.to_object(np.array([perc.frame_pose.x_m, perc.frame_pose.y_m]))
        tracker = PoseTracker(perc, obs)
        rng = np.random.default_rng(0)
        errs, pos = [], []
        for _ in range(n_images):
            dx, dy, dth = rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), rng.uniform(-0.5, 0.5)
            pose = Pose2D(pose0.x_m + dx, pose0.y_m + dy, pose0.yaw_rad + dth)
            tracker.last = perc.frame_pose
            fit = tracker.fit(observe(render_prism_depth(cam, poly, 0.03, pose)))
            errs.append(abs(np.degrees(fit.pose.yaw_rad - dth)))
            pos.append(np.hypot(*(pose.to_world(f_obj) - [fit.pose.x_m, fit.pose.y_m])))
        e = np.array(errs)
        print(
            f"| {name} | {np.median(e):.3f} | {np.percentile(e, 95):.3f} | {e.max():.3f} | "
            f"{1000 * max(pos):.2f} |"
        )
    return 0


def _row_markdown(row: tuple) -> str:
    b, s, sp, rn, n, fails, mean, med, share, r50, r95, wall = row
    f = ", ".join(f"{k}:{v}" for k, v in fails.items()) or "0"
    return (
        f"| {b} | {s} | {sp:g} | {rn} | {n} | {f} | {mean:.3f} | {med:.3f} | {share:.2f} | "
        f"{r50:.3f} | {r95:.3f} | {wall:.2f} |"
    )


if __name__ == "__main__":
    t0 = time.perf_counter()
    rc = main()
    print(f"# total {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    sys.exit(rc)
