"""Tracking during the push: which camera rate unwraps every rotation, and what it costs.

    .venv/bin/python bench/tracking.py --backend planar --speed 40 --mu 0.1 --episodes 48
    .venv/bin/python bench/tracking.py --backend planar --speed 4 --mu 1 --episodes 24 \\
        --fps 0,5,10 --oracle

A strided slice of the job's own grid (`common.job_specs`: every object, both pusher
frictions, both Izz scales) on one floor `mu`; every episode is run once per camera rate in
`--fps` (vision), once per rate > 0 with full-image tracking frames (`--full-frames`: the
cost before the engines' window renders) and once with `rotation_source=oracle`
(`--oracle`), the variants of one episode back to back so that the machine's load hits them
alike. Watching never changes the physics (frames hang on the protocol's checks), so the
variants differ only in what was measured and in what the estimator then chose.

Per rate: pushes, the share of pushes turning > 1 deg whose measured rotation has the true
sign, the number of "aliased" pushes (measured off the true rotation by > 10 deg: a wrong
symmetric basin), the worst |measured - true| rotation, frames per push, the mean CoM error,
and the episode's CPU time (`time.process_time`, so that other load on a shared machine does
not count) relative to rate 0 (median of per-episode ratios, and the ratio of the totals);
then per variant the tracking renders' mean CPU time and size; with `--full-frames` how far
the measured rotations of window and full frames are apart; with `--compare-frames` a
pixel-level comparison of window and full frames over every frame of a further run; per
variant the tracking's own CPU time per frame (the episode loop's `track` phase:
`mask_pusher`, `observe_boundary`, `PoseTracker.track`) and each tracked frame's turn beyond
the tracker's prediction.

Measured as a client: the frames through a subclass of the backend's class
(`TrackingFrames`), the tracking's time through the loop's phase timer (`run_episode`'s
`timer`) and the turns beyond the prediction through the push handed to `run_episode`
(`FrameWatch.push`, which sees the tracker the protocol's `on_still` belongs to). To compare
another version of perception or tracking, run bench/compare_checkouts.py against a checkout
of it (each checkout in its own process and venv): nothing is swapped in here.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from common import bench_simulator, job_specs

from comexp.episode.loop import run_episode
from comexp.episode.task import EpisodeResult, EpisodeSpec, build_scene
from comexp.method.frames import DepthImage
from comexp.method.observation import MIN_HEIGHT_M, mask_pusher
from comexp.sim.protocol import Frame, push

ALIAS_DEG = 10.0


# --- what is measured, as a client -------------------------------------------------------------


class FrameComparison:
    """Every tracking frame rendered both ways (window and full image) in the same state:
    how far the window's pixels are from the full image's window, whether the object mask
    (the tracker's threshold) differs, and how many pixels of the full image above the floor
    lie outside the window once the pusher is masked (object pixels the window would miss, or
    pusher pixels the mask leaves)."""

    def __init__(self) -> None:
        self.diffs: list[float] = []
        self.flips = 0
        self.outside = 0

    def add(self, sim: Any, w: DepthImage) -> None:
        f = sim.render_depth()
        fc, wc = f.camera, w.camera
        u0, v0 = round(fc.cx_px - wc.cx_px), round(fc.cy_px - wc.cy_px)
        h, wd = w.depth_m.shape
        part = f.depth_m[v0 : v0 + h, u0 : u0 + wd]
        self.diffs.append(float(np.max(np.abs(w.depth_m - part))))
        level = fc.position_m[2] - MIN_HEIGHT_M
        self.flips += bool(np.any((w.depth_m < level) != (part < level)))
        xy = sim.pusher_xy()
        masked = mask_pusher(f, (float(xy[0]), float(xy[1])), sim.pusher_radius_m()).depth_m
        above = masked < level
        self.outside += int(above.sum() - above[v0 : v0 + h, u0 : u0 + wd].sum())


class TrackingFrames:
    """The tracking frames a variant renders (a mixin before the backend's class): the
    engine's window (its own `render_tracking_depth`) or, `full_frames`, the full image
    (`render_depth`, as before the engines' window renders); each render's CPU time and
    pixels logged into `render_log` (a list, or None), each window compared with the full
    image by `comparison` (or None)."""

    full_frames = False
    render_log: list[tuple[float, int]] | None = None
    comparison: FrameComparison | None = None

    def render_tracking_depth(self) -> DepthImage:
        t = time.process_time()
        full = self.full_frames
        img = self.render_depth() if full else super().render_tracking_depth()
        if self.render_log is not None:
            self.render_log.append((time.process_time() - t, img.depth_m.size))
        if self.comparison is not None:
            self.comparison.add(self, img)
        return img


class FrameWatch:
    """One variant's tracking, frame by frame: the CPU time of each frame's tracking (the
    loop's "track" phase, as the episode's `timer`) and, through the push handed to the loop
    (`push`), each tracked frame's turn beyond the tracker's prediction (|fitted - predicted
    yaw|, deg: what a frame must stay below, half a symmetry angle), with the 3 largest."""

    def __init__(self) -> None:
        self.cpu: list[float] = []
        self.surprise: list[float] = []
        self.worst: list[tuple[float, str, float, float]] = []  # deg, episode, t_s, gap_s
        self.context = ""

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        if name != "track":
            yield
            return
        t = time.process_time()
        try:
            yield
        finally:
            self.cpu.append(time.process_time() - t)

    def push(self, sim: Any, cmd: Any, **kwargs: Any) -> Any:
        """The protocol's push; a watched push's frames seen before and after the tracker
        takes them (the tracker is the one whose `hold` the loop hands over as `on_still`)."""
        tracker = getattr(kwargs.get("on_still"), "__self__", None)
        on_frame = kwargs.get("on_frame")
        if tracker is not None and on_frame is not None:
            kwargs["on_frame"] = self._watched(on_frame, tracker)
        return push(sim, cmd, **kwargs)

    def _watched(self, on_frame: Callable[[Frame], None], tracker: Any) -> Callable:
        def watched(f: Frame) -> None:
            history = tracker._history  # (t_s, yaw) of the push's frames so far
            n, yaw0 = len(history), tracker.predicted_yaw(f.t_s)
            gap_s = f.t_s - history[-1][0] if history else f.t_s
            on_frame(f)
            if len(tracker._history) > n:  # tracked (a frame showing no object is not used)
                deg = abs(math.degrees(tracker.last.yaw_rad - yaw0))
                self.surprise.append(deg)
                self.worst = sorted([*self.worst, (deg, self.context, f.t_s, gap_s)], reverse=True)[
                    :3
                ]

        return watched


@dataclass
class Variant:
    """One way of running every episode, and what its runs measured."""

    label: str
    change: dict[str, Any]
    results: list[EpisodeResult] = field(default_factory=list)
    cpu_s: list[float] = field(default_factory=list)
    renders: list[tuple[float, int]] = field(default_factory=list)
    watch: FrameWatch = field(default_factory=FrameWatch)

    def spec(self, spec: EpisodeSpec) -> EpisodeSpec:
        s = replace(spec, **self.change)
        if self.label == "oracle":
            s = replace(s, estimator=replace(s.estimator, rotation_source="oracle"))
        if " st" in self.label:
            step = float(self.label.split(" st")[1])
            s = replace(s, estimator=replace(s.estimator, track_step_deg=step))
        if " gap" in self.label:
            gap = float(self.label.split(" gap")[1])
            s = replace(s, estimator=replace(s.estimator, track_gap_s=gap))
        return s


# --- the runs -------------------------------------------------------------------------------


def make_variants(args: argparse.Namespace, rates: list[float]) -> list[Variant]:
    variants = [Variant(f"{f:g} fps", {"camera_fps": f}) for f in rates]
    if args.full_frames:
        variants += [Variant(f"{f:g} full", {"camera_fps": f}) for f in rates if f > 0]
    for step in [float(x) for x in args.track_steps.split(",") if x.strip()]:
        variants += [Variant(f"{f:g} st{step:g}", {"camera_fps": f}) for f in rates if f > 0]
    for gap in [float(x) for x in args.track_gaps.split(",") if x.strip()]:
        variants += [Variant(f"{f:g} gap{gap:g}", {"camera_fps": f}) for f in rates if f > 0]
    if args.oracle:
        variants.append(Variant("oracle", {}))
    return variants


def run_variants(sim: Any, specs: list[EpisodeSpec], variants: list[Variant]) -> None:
    """Every episode once per variant, back to back."""
    for spec in specs:
        # untimed: MuJoCo creates a new object geometry's renderer (~70 ms) on its first
        # render, which would otherwise be charged to whichever variant runs first
        sim.build(build_scene(spec))
        sim.render_depth()
        for v in variants:
            s = v.spec(spec)
            sim.full_frames = v.label.endswith("full")  # "full": through the full image
            sim.render_log = v.renders
            v.watch.context = (
                f"{s.object} com {s.com_index} mu_p {s.mu_pusher:g} Izz {s.izz_scale:g}"
            )
            t = time.process_time()  # CPU time: the machine's other load does not count
            v.results.append(run_episode(s, sim, push=v.watch.push, timer=v.watch))
            v.cpu_s.append(time.process_time() - t)
    sim.full_frames, sim.render_log = False, None


def compare_frames(sim: Any, specs: list[EpisodeSpec]) -> None:
    """Every episode once more, each tracking frame rendered as window and as full image and
    compared (`FrameComparison`)."""
    sim.comparison = c = FrameComparison()
    try:
        for spec in specs:
            run_episode(spec, sim)
    finally:
        sim.comparison = None
    print(
        f"frames compared: {len(c.diffs)}; |window - full| depth max "
        f"{max(c.diffs, default=0):.2e} m, median of frame maxima "
        f"{statistics.median(c.diffs) if c.diffs else 0:.2e} m; frames whose object mask "
        f"differs: {c.flips}; pixels above the floor outside the window, pusher masked: "
        f"{c.outside}"
    )


# --- the report -----------------------------------------------------------------------------


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


def report(variants: list[Variant]) -> None:
    print(
        "|    rate |  ok     | pushes | sign right (>1 deg) | aliased | max|err| | max|rot|"
        " | fr/push | CoM err  | cost (median / total) |"
    )
    print("|" + "---|" * 10)
    for v in variants:
        summarise(v.label, v.results, v.cpu_s, variants[0].cpu_s)
    for v in variants:
        if v.renders:
            ms = 1e3 * statistics.fmean(t for t, _ in v.renders)
            px = statistics.fmean(n for _, n in v.renders)
            print(
                f"{v.label}: {len(v.renders)} tracking renders, {ms:.2f} ms CPU, {px:.0f} px each"
            )
    for v in variants:
        if v.watch.cpu:
            ms = 1e3 * statistics.fmean(v.watch.cpu)
            print(
                f"{v.label}: tracking (mask_pusher + observe_boundary + track) {ms:.3f} ms CPU "
                f"per frame, {len(v.watch.cpu)} frames"
            )
    for v in variants:
        if v.watch.surprise:
            q = np.quantile(v.watch.surprise, [0.5, 0.99, 1.0])
            worst = "; ".join(
                f"{d:.2f} deg ({c}, t {t:.3f} s, gap {g:.3f} s)" for d, c, t, g in v.watch.worst
            )
            print(
                f"{v.label}: turn beyond the prediction per tracked frame, median / 99% / max "
                f"{q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f} deg; largest: {worst}"
            )
    by_label = {v.label: v for v in variants}
    for v in variants:
        rate = v.label.split(" ")[0]
        if " st" in v.label or " gap" in v.label:
            compare_variant(v.label, by_label[rate + " fps"].results, v.results)
        if v.label.endswith("full"):
            compare_results(v.label, by_label[rate + " fps"].results, v.results)


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


def compare_variant(label: str, ref: list[EpisodeResult], new: list[EpisodeResult]) -> None:
    """A tracking rule's variant vs the default, episode by episode: episodes whose status,
    failure, push choices or decisions differ, and the largest |difference| of the measured
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
        f"{label} vs default: {other} of {len(new)} episodes differ in status, failure, push "
        f"choice or decision; over the others max |difference| rotation {rot:.2e} deg, true "
        f"rotation {rot_true:.2e} deg, CoM error {err:.2e} cm"
    )


def parse_args() -> argparse.Namespace:
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
    return ap.parse_args()


def main() -> None:
    args = parse_args()
    rates = [float(f) for f in args.fps.split(",")]
    if rates[0] != 0.0:
        raise SystemExit("--fps must start with 0 (the baseline of the cost ratio)")
    specs = job_specs(args.backend, "iso", args.speed, [f"floor.mu=[{args.mu:g}]"])
    stride = max(1, len(specs) // args.episodes)
    specs = specs[::stride][: args.episodes]
    opts = {} if args.backend == "planar" else {"floor_friction": "model"}
    sim = bench_simulator(args.backend, TrackingFrames, **opts)
    try:
        run_episode(specs[0], sim)  # warm-up (JIT, renderer)
        variants = make_variants(args, rates)
        t0 = time.perf_counter()
        run_variants(sim, specs, variants)
        print(
            f"{args.backend}, iso floor mu {args.mu:g}, {args.speed:g} cm/s, {len(specs)} "
            f"episodes (every {stride}th of the job's grid), {time.perf_counter() - t0:.0f} s"
        )
        report(variants)
        if args.compare_frames:
            compare_frames(sim, [replace(s, camera_fps=rates[-1]) for s in specs])
    finally:
        sim.close()


if __name__ == "__main__":
    main()
