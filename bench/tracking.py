"""Tracking during the push: which camera rate unwraps every rotation, and what it costs.

    .venv/bin/python bench/tracking.py --backend planar --speed 40 --mu 0.1 --episodes 48
    .venv/bin/python bench/tracking.py --backend planar --speed 4 --mu 1 --episodes 24 \\
        --fps 0,5,10 --oracle

A strided slice of the job's own grid (`bench/episode_profile.job_specs`: every object, both
pusher frictions, both Izz scales) on one floor `mu`; every episode is run once per camera
rate in `--fps` (vision), once per rate > 0 with full-image tracking frames (`--full-frames`:
the cost before the engines' window renders) and once with `rotation_source=oracle`
(`--oracle`), the variants of one episode back to back so that the machine's load hits them
alike. Watching never changes
the physics (frames hang on the protocol's checks), so the variants differ only in what was
measured and in what the estimator then chose.

Per rate: pushes, the share of pushes turning > 1 deg whose measured rotation has the true
sign, the number of "aliased" pushes (measured off the true rotation by > 10 deg: a wrong
symmetric basin), the worst |measured - true| rotation, frames per push, the mean CoM error,
and the episode's CPU time (`time.process_time`, so that other load on a shared machine does
not count) relative to rate 0 (median of per-episode ratios, and the ratio of the totals);
then per variant the tracking renders' mean CPU time and size; with `--full-frames` how far
the measured rotations of window and full frames are apart; with `--compare-frames` a
pixel-level comparison of window and full frames over every frame of a further run; per
variant the tracking's own CPU time per frame (`mask_pusher`, `observe_boundary`,
`PoseTracker.track`). `--baseline FILE` adds every rate once more with another version
of comexp/method/perception.py (the episode's perception and tracking, and planar's ray cast
for every image), in the same run (its cost relative to its own 0 fps), and compares the
results episode by episode:

    git show a74eeeb:comexp/method/perception.py > /tmp/perception_old.py
    .venv/bin/python bench/tracking.py --backend pybullet --episodes 16 --fps 0,30 \\
        --baseline /tmp/perception_old.py
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))

from episode_profile import _load_module, job_specs  # noqa: E402

import comexp.experiment.episode as episode_module  # noqa: E402
from comexp.experiment.episode import EpisodeResult, build_scene, run_episode  # noqa: E402
from comexp.experiment.simulator import make_simulator  # noqa: E402
from comexp.method import perception  # noqa: E402
from comexp.method.perception import MIN_HEIGHT_M, mask_pusher  # noqa: E402
from comexp.method.scene import DepthImage  # noqa: E402

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


def _timed(render: Callable[[], DepthImage], log: list[tuple[float, int]]):
    """`render`, logging each call's CPU time and pixel count."""

    def timed() -> DepthImage:
        t = time.process_time()
        img = render()
        log.append((time.process_time() - t, img.depth_m.size))
        return img

    return timed


# what a baseline perception module replaces in the episode (`--baseline`)
SWAPPED = (
    "perceive_first",
    "observe",
    "PoseTracker",
    "PerceptionError",
    "mask_pusher",
    "observe_boundary",
)


class FrameClock:
    """CPU time of the tracking pieces of every frame (the episode's `on_frame`): the
    variant's mask_pusher + observe_boundary + PoseTracker.track, logged into `log`; and
    each tracked frame's turn beyond the tracker's prediction (|fitted - predicted yaw|,
    deg) into `surprise`: what a frame must stay below (half a symmetry angle)."""

    def __init__(self) -> None:
        self.log: list[float] = []
        self.surprise: list[float] = []
        self.worst: list[tuple[float, str, float, float]] = []  # deg, episode, t_s, gap_s
        self.context = ""
        self._acc = 0.0

    def surprised(self, track: Callable) -> Callable:
        def g(tracker, view, t_s, *a, **k):
            yaw0 = tracker.predicted_yaw(t_s)
            h = tracker._history
            gap_s = t_s - h[-1][0] if h else t_s
            f = track(tracker, view, t_s, *a, **k)
            deg = abs(math.degrees(f.pose.yaw_rad - yaw0))
            self.surprise.append(deg)
            self.worst.append((deg, self.context, t_s, gap_s))
            self.worst = sorted(self.worst, reverse=True)[:3]
            return f

        return g

    def timed(self, f: Callable, closes: bool) -> Callable:
        def g(*a, **k):
            t = time.process_time()
            try:
                return f(*a, **k)
            finally:
                self._acc += time.process_time() - t
                if closes:  # track ends a frame
                    self.log.append(self._acc)
                    self._acc = 0.0

        return g

    def wrap(self, fns: dict) -> dict:
        """The episode's names `fns`, their frame pieces timed (`track` on the class)."""
        out = dict(fns)
        out["mask_pusher"] = self.timed(fns["mask_pusher"], False)
        out["observe_boundary"] = self.timed(fns["observe_boundary"], False)
        cls = fns["PoseTracker"]
        cls.track = self.timed(self.surprised(cls.track), True)
        return out


def use(fns: dict, render: Callable) -> None:
    """Make the episode (and planar's images: the name it imported) use these versions."""
    for k, v in fns.items():
        setattr(episode_module, k, v)
    planar_sim = sys.modules.get("comexp.backends.planar_sim")
    if planar_sim is not None:
        planar_sim.render_prism_depth = render


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="planar")
    ap.add_argument("--speed", type=float, default=40.0)
    ap.add_argument("--mu", type=float, default=0.1, help="the floor's friction (iso)")
    ap.add_argument("--episodes", type=int, default=48)
    ap.add_argument("--fps", default="0,10,15,30", help="camera rates (vision), 0 first")
    ap.add_argument("--oracle", action="store_true", help="also rotation_source=oracle")
    ap.add_argument(
        "--track-gaps",
        default="",
        metavar="S,...",
        help="also every rate > 0 with these estimator.track_gap values (default step)",
    )
    ap.add_argument(
        "--track-steps",
        default="",
        metavar="DEG,...",
        help="also every rate > 0 with these estimator.track_step values (0 = every camera "
        "frame), compared episode by episode with the default",
    )
    ap.add_argument(
        "--full-frames",
        action="store_true",
        help="also every rate > 0 with full-image tracking frames (render_depth), as before "
        "the engines' window renders",
    )
    ap.add_argument(
        "--compare-frames",
        action="store_true",
        help="then run every episode once more at the last rate, rendering each tracking frame "
        "as window and as full image, and compare their pixels",
    )
    ap.add_argument(
        "--baseline",
        metavar="FILE",
        help="also every rate with this version of comexp/method/perception.py (e.g. git "
        "show a74eeeb:comexp/method/perception.py > /tmp/perception_old.py), in the same run",
    )
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
    if args.full_frames:
        variants += [(f"{f:g} full", {"camera_fps": f}) for f in rates if f > 0]
    steps = [float(x) for x in args.track_steps.split(",") if x.strip()]
    for step in steps:
        variants += [(f"{f:g} st{step:g}", {"camera_fps": f}) for f in rates if f > 0]
    for gap in [float(x) for x in args.track_gaps.split(",") if x.strip()]:
        variants += [(f"{f:g} gap{gap:g}", {"camera_fps": f}) for f in rates if f > 0]
    clock = FrameClock()
    current = clock.wrap({k: getattr(episode_module, k) for k in SWAPPED})
    render_now = perception.render_prism_depth
    if args.baseline:
        if not os.path.isfile(args.baseline):
            raise SystemExit(f"--baseline: no such file: {args.baseline}")
        old = _load_module("baseline_perception", args.baseline)
        baseline = clock.wrap({k: getattr(old, k) for k in SWAPPED})
        # every rate, 0 too: a baseline's cost is relative to its own 0 fps episode
        variants += [(f"{f:g} base", {"camera_fps": f}) for f in rates]
    if args.oracle:
        variants.append(("oracle", {}))
    frame_cpu: dict[str, list[float]] = {v: [] for v, _ in variants}
    surprise: dict[str, list[float]] = {v: [] for v, _ in variants}
    worst: dict[str, list[tuple[float, str, float, float]]] = {v: [] for v, _ in variants}
    results: dict[str, list[EpisodeResult]] = {v: [] for v, _ in variants}
    walls: dict[str, list[float]] = {v: [] for v, _ in variants}
    window = sim.render_tracking_depth
    renders: dict[str, list[tuple[float, int]]] = {v: [] for v, _ in variants}
    t0 = time.perf_counter()
    for spec in specs:
        # untimed: MuJoCo creates a new object geometry's renderer (~70 ms) on its first
        # render, which would otherwise be charged to whichever variant runs first
        sim.build(build_scene(spec))
        sim.render_depth()
        for label, change in variants:
            s = replace(spec, **change)
            if label == "oracle":
                s = replace(s, estimator=replace(s.estimator, rotation_source="oracle"))
            if " st" in label:
                step = float(label.split(" st")[1])
                s = replace(s, estimator=replace(s.estimator, track_step_deg=step))
            if " gap" in label:
                gap = float(label.split(" gap")[1])
                s = replace(s, estimator=replace(s.estimator, track_gap_s=gap))
            # "full": tracking frames through the full image (the hook's default)
            render = sim.render_depth if label.endswith("full") else window
            sim.render_tracking_depth = _timed(render, renders[label])
            clock.log = frame_cpu[label]
            clock.surprise = surprise[label]
            clock.worst = worst[label]
            clock.context = f"{s.object} com {s.com_index} mu_p {s.mu_pusher:g} Izz {s.izz_scale:g}"
            if label.endswith("base"):
                use(baseline, old.render_prism_depth)
            t = time.process_time()  # CPU time: the machine's other load does not count
            results[label].append(run_episode(s, sim))
            worst[label] = clock.worst
            walls[label].append(time.process_time() - t)
            use(current, render_now)
    print(
        f"{args.backend}, iso floor mu {args.mu:g}, {args.speed:g} cm/s, {len(specs)} episodes "
        f"(every {stride}th of the job's grid), {time.perf_counter() - t0:.0f} s"
    )
    print(
        "|    rate |  ok     | pushes | sign right (>1 deg) | aliased | max|err| | max|rot|"
        " | fr/push | CoM err  | cost (median / total) |"
    )
    print("|" + "---|" * 10)
    for label, _ in variants:
        base = walls["0 base" if label.endswith("base") else variants[0][0]]
        summarise(label, results[label], walls[label], base)
    for label, _ in variants:
        if renders[label]:
            ms = 1e3 * statistics.fmean(t for t, _ in renders[label])
            px = statistics.fmean(n for _, n in renders[label])
            print(
                f"{label}: {len(renders[label])} tracking renders, {ms:.2f} ms CPU, "
                f"{px:.0f} px each"
            )
    for label, _ in variants:
        if frame_cpu[label]:
            ms = 1e3 * statistics.fmean(frame_cpu[label])
            print(
                f"{label}: tracking (mask_pusher + observe_boundary + track) {ms:.3f} ms CPU "
                f"per frame, {len(frame_cpu[label])} frames"
            )
    for label, _ in variants:
        if surprise[label]:
            q = np.quantile(surprise[label], [0.5, 0.99, 1.0])
            print(
                f"{label}: turn beyond the prediction per tracked frame, median / 99% / max "
                f"{q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f} deg; largest: "
                + "; ".join(
                    f"{d:.2f} deg ({c}, t {t:.3f} s, gap {g:.3f} s)" for d, c, t, g in worst[label]
                )
            )
    for label, _ in variants:
        if label.endswith("base"):
            compare_baseline(label, results[label.replace("base", "fps")], results[label])
        if " st" in label or " gap" in label:
            rate = label.split(" ")[0]
            compare_baseline(label, results[rate + " fps"], results[label])
    for label, _ in variants:
        if label.endswith("full"):
            compare_results(label, results[label.replace("full", "fps")], results[label])
    if args.compare_frames:
        compare_frames(sim, [replace(s, camera_fps=rates[-1]) for s in specs], window)


def compare_results(label: str, win: list[EpisodeResult], full: list[EpisodeResult]) -> None:
    """Window vs full-image tracking frames, episode by episode: over the pushes both chose
    alike (same contact and direction), the largest difference in measured rotation; and how
    many episodes chose a different push somewhere (a measured rotation moved a decision)."""
    worst, diverged = 0.0, 0
    for a, b in zip(win, full, strict=True):
        for p, q in zip(a.pushes, b.pushes, strict=False):
            if (p.contact_x_cm, p.contact_y_cm, p.dir_x, p.dir_y) != (
                q.contact_x_cm,
                q.contact_y_cm,
                q.dir_x,
                q.dir_y,
            ):
                diverged += 1
                break
            worst = max(worst, abs(p.rotation_deg - q.rotation_deg))
    print(
        f"{label} vs window: max |rotation difference| {worst:.2e} deg over the pushes chosen "
        f"alike; {diverged} of {len(win)} episodes chose a different push"
    )


def compare_baseline(label: str, new: list[EpisodeResult], ref: list[EpisodeResult]) -> None:
    """Current vs baseline perception, episode by episode: episodes whose status, failure, push
    choices or decisions differ (any is a bug), and the largest |difference| of the measured
    and true rotations and of the CoM error over the rest."""
    other = 0
    rot = rot_true = err = 0.0
    for a, b in zip(new, ref, strict=True):
        pa = [(p.contact_x_cm, p.contact_y_cm, p.dir_x, p.dir_y, p.decision) for p in a.pushes]
        pb = [(p.contact_x_cm, p.contact_y_cm, p.dir_x, p.dir_y, p.decision) for p in b.pushes]
        if (a.status, a.failure, pa) != (b.status, b.failure, pb):
            other += 1
            continue
        for p, q in zip(a.pushes, b.pushes, strict=True):
            rot = max(rot, abs(p.rotation_deg - q.rotation_deg))
            rot_true = max(rot_true, abs(p.rotation_true_deg - q.rotation_true_deg))
        if a.error_cm is not None and b.error_cm is not None:
            err = max(err, abs(a.error_cm - b.error_cm))
    print(
        f"{label} vs current: {other} of {len(new)} episodes differ in status, failure, push "
        f"choice or decision; over the others max |difference| rotation {rot:.2e} deg, true "
        f"rotation {rot_true:.2e} deg, CoM error {err:.2e} cm"
    )


def compare_frames(sim, specs: list, window: Callable[[], DepthImage]) -> None:
    """Every tracking frame rendered both ways (window and full image) in the same state:
    how far the window's pixels are from the full image's window, whether the object mask
    (the tracker's threshold) differs, and how many pixels of the full image above the floor
    lie outside the window once the pusher is masked (object pixels the window would miss, or
    pusher pixels the mask leaves)."""
    diffs: list[float] = []
    flips = outside = 0

    def both() -> DepthImage:
        nonlocal flips, outside
        w, f = window(), sim.render_depth()
        fc, wc = f.camera, w.camera
        u0, v0 = round(fc.cx_px - wc.cx_px), round(fc.cy_px - wc.cy_px)
        h, wd = w.depth_m.shape
        part = f.depth_m[v0 : v0 + h, u0 : u0 + wd]
        diffs.append(float(np.max(np.abs(w.depth_m - part))))
        level = fc.position_m[2] - MIN_HEIGHT_M
        flips += bool(np.any((w.depth_m < level) != (part < level)))
        xy = sim._pusher_xy()
        masked = mask_pusher(f, (float(xy[0]), float(xy[1])), sim._pusher_radius_m()).depth_m
        above = masked < level
        outside += int(above.sum() - above[v0 : v0 + h, u0 : u0 + wd].sum())
        return w

    sim.render_tracking_depth = both
    for spec in specs:
        run_episode(spec, sim)
    print(
        f"frames compared: {len(diffs)}; |window - full| depth max {max(diffs, default=0):.2e} m, "
        f"median of frame maxima {statistics.median(diffs) if diffs else 0:.2e} m; frames whose "
        f"object mask differs: {flips}; pixels above the floor outside the window, pusher masked: "
        f"{outside}"
    )


if __name__ == "__main__":
    main()
