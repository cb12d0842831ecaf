"""Tracking during the push: which camera rate unwraps every rotation, and what it costs.

    .venv/bin/python bench/tracking.py --backend planar --speed 40 --mu 0.1 --episodes 48
    .venv/bin/python bench/tracking.py --backend planar --speed 4 --mu 1 --episodes 24 \\
        --fps 0,5,10 --oracle

A strided slice of the job's own grid (`bench/episode_profile.job_specs`: every object, both
pusher frictions, both Izz scales) on one floor `mu`; every episode is run once per camera
rate in `--fps` (vision) and once with `rotation_source=oracle` (`--oracle`), the variants of
one episode back to back so that the machine's load hits them alike. Watching never changes
the physics (frames hang on the protocol's checks), so the variants differ only in what was
measured and in what the estimator then chose.

Per rate: pushes, the share of pushes turning > 1 deg whose measured rotation has the true
sign, the number of "aliased" pushes (measured off the true rotation by > 10 deg: a wrong
symmetric basin), the worst |measured - true| rotation, frames per push, the mean CoM error,
and the episode's CPU time (`time.process_time`, so that other load on a shared machine does
not count) relative to rate 0 (median of per-episode ratios, and the ratio of the totals).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from dataclasses import replace

sys.path.insert(0, os.path.dirname(__file__))

from episode_profile import job_specs  # noqa: E402

from comexp.experiment.episode import EpisodeResult, run_episode  # noqa: E402
from comexp.experiment.simulator import make_simulator  # noqa: E402

ALIAS_DEG = 10.0


def summarise(label: str, results: list[EpisodeResult], walls: list[float], base: list[float]):
    ok = [r for r in results if r.status == "ok"]
    pushes = [p for r in results for p in r.pushes]
    turning = [p for p in pushes if abs(p.rotation_true_deg) > 1.0]
    right = sum((p.rotation_deg > 0) == (p.rotation_true_deg > 0) for p in turning)
    errs = [abs(p.rotation_deg - p.rotation_true_deg) for p in pushes]
    aliased = sum(e > ALIAS_DEG for e in errs)
    frames = sum(p.n_frames for p in pushes) / max(1, len(pushes))
    mean_err = statistics.fmean(r.error_cm for r in ok) if ok else float("nan")
    ratio = statistics.median(w / b for w, b in zip(walls, base, strict=True))
    total = sum(walls) / sum(base)
    big = max((abs(p.rotation_true_deg) for p in pushes), default=0.0)
    print(
        f"| {label:>7} | {len(ok):>3}/{len(results):<3} | {len(pushes):>6} | "
        f"{100.0 * right / max(1, len(turning)):6.2f}% of {len(turning):<4} | {aliased:>7} | "
        f"{max(errs, default=0.0):8.2f} | {big:7.1f} | {frames:6.1f} | {mean_err:8.3f} | "
        f"{ratio:5.3f} / {total:5.3f} |"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="planar")
    ap.add_argument("--speed", type=float, default=40.0)
    ap.add_argument("--mu", type=float, default=0.1, help="the floor's friction (iso)")
    ap.add_argument("--episodes", type=int, default=48)
    ap.add_argument("--fps", default="0,10,15,30", help="camera rates (vision), 0 first")
    ap.add_argument("--oracle", action="store_true", help="also rotation_source=oracle")
    args = ap.parse_args()
    rates = [float(f) for f in args.fps.split(",")]
    if rates[0] != 0.0:
        raise SystemExit("--fps must start with 0 (the baseline of the cost ratio)")
    specs = job_specs(args.backend, "iso", args.speed, [f"floor.mu=[{args.mu:g}]"])
    stride = max(1, len(specs) // args.episodes)
    specs = specs[::stride][: args.episodes]
    opts = {} if args.backend == "planar" else {"floor_friction": "model"}
    sim = make_simulator(args.backend, **opts)
    run_episode(specs[0], sim)  # warm-up (JIT, renderer)
    variants: list[tuple[str, dict]] = [(f"{f:g} fps", {"camera_fps": f}) for f in rates]
    if args.oracle:
        variants.append(("oracle", {}))
    results: dict[str, list[EpisodeResult]] = {v: [] for v, _ in variants}
    walls: dict[str, list[float]] = {v: [] for v, _ in variants}
    t0 = time.perf_counter()
    for spec in specs:
        for label, change in variants:
            s = replace(spec, **change)
            if label == "oracle":
                s = replace(s, estimator=replace(s.estimator, rotation_source="oracle"))
            t = time.process_time()  # CPU time: the machine's other load does not count
            results[label].append(run_episode(s, sim))
            walls[label].append(time.process_time() - t)
    print(
        f"{args.backend}, iso floor mu {args.mu:g}, {args.speed:g} cm/s, {len(specs)} episodes "
        f"(every {stride}th of the job's grid), {time.perf_counter() - t0:.0f} s"
    )
    print(
        "|    rate |  ok     | pushes | sign right (>1 deg) | aliased | max|err| | max|rot|"
        " | fr/push | CoM err  | cost (median / total) |"
    )
    print("|" + "---|" * 10)
    base = walls[variants[0][0]]
    for label, _ in variants:
        summarise(label, results[label], walls[label], base)


if __name__ == "__main__":
    main()
