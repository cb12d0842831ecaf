"""Episodes per second on one worker, and where an episode's time goes.

    .venv/bin/python bench/episode_profile.py --backend pybullet [--episodes 40] [--speed 40]
    .venv/bin/python bench/episode_profile.py --backend mujoco --speed 4 --dump /tmp/mj.json
    .venv/bin/python bench/episode_profile.py --backend planar --cprofile 30
    .venv/bin/python bench/episode_profile.py --backend pybullet --still-jumps

In-process, one simulator, real episodes: the specs are the job's own grid (`comexp.experiment.grid`
over the built-in objects, through the Hydra config like `comexp` itself), a strided slice
of it that holds every object and every condition (`common.strided`), on the job's own
simulator (`common.job_simulator`). Time is split by the episode loop's own phase timer
(`run_episode(..., timer=PhaseTimer())`, `comexp.episode.timing`): build (the scene, the
first image and its perception), choose (Algorithm 1), push (the protocol, its tracking
frames included; of it the tracking and the frames' renders), measure (re-centring, the
image at rest, its pose), estimate (Algorithm 2); "rest" is what no phase holds (the
estimator's construction, scoring, the loop's bookkeeping). The engine's own calls in them
(`build`, `render_depth`, `render_tracking_depth`) are timed by a subclass of the backend's
class (`TimedEngine`), and the pushes' steps counted by the push handed to `run_episode`:
nothing of the package is patched, and the hot path carries no instrumentation of ours
beyond the loop's phase contexts.

A warm-up pass first runs one episode per object untimed (the engine's one-off costs per
object: MuJoCo builds one GL renderer per object geometry, kept for the rest of the job), so
the figures are the steady state a worker reaches in a 1,600-episode job; the warm-up's own
time per episode is printed too.

The floor below which an episode cannot go: the engine's raw steps per second on a built
pushing scene (`sim.step`, object at rest, pusher parked), and the steps per second reached
inside pushes (`PushOutcome.steps` over the pushes' wall time, which includes the
protocol's per-step Python: pusher command, state checks; and the tracking frames).

`--dump PATH` writes every episode's result (estimate, error, per-push rotations and
decisions) as JSON, to check that an optimisation leaves results unchanged. To compare the
episodes against another version of the code (perception, estimator, a backend), run
bench/compare_checkouts.py: each checkout in its own process and venv, nothing swapped in.

`--estimators paper,fit` times the same episodes with each estimator (`estimator.method`),
alternating per episode in one process, after a warm-up pass of each: the cost of an estimator
as a ratio to the first one's episodes, and their mean errors; `--json` writes the table as
docs/data/NAME.json for the docs (`bench/docs_tables.py render`).

`--cprofile TOP` profiles the same episodes (CPU clock): the TOP functions by cumulative and
by own time. `--still-jumps` runs an engine's episodes with its still steps jumped and with
every step stepped (a subclass with `still_jumps = None`), alternating, in one process.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import re
import statistics
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from common import (
    bench_simulator,
    engine_stdout_silenced,
    job_simulator,
    job_specs,
    source_digest,
    strided,
    use_one_cpu,
    warm_up,
    write_table,
)

from comexp.episode.task import EpisodeResult, EpisodeSpec
from comexp.episode.timing import NO_TIMER, PhaseTimer, Timer

# The report's rows: the loop's phases (`comexp.episode.timing`), those nested in a phase
# indented under it; "physics" is the pushes less their tracking frames (renders, tracking).
ROWS = (
    ("build", "build (scene, 1st image)"),
    ("choose", "choose (Algorithm 1)"),
    ("push", "push (the protocol)"),
    ("physics", "  physics (push - frames)"),
    ("sim.render_tracking_depth", "  frames rendered"),
    ("track", "  tracking"),
    ("measure", "measure (image at rest)"),
    ("estimate", "estimate (Algorithm 2)"),
    ("rest", "rest"),
)
TOP_LEVEL = ("build", "choose", "push", "measure", "estimate")
# the engine's calls outside the pushes, in the phases build and measure (re-centring)
ENGINE_CALLS = ("sim.build", "sim.render_depth")


class TimedEngine:
    """The engine's calls an episode makes, each timed as a phase of `timer` (NO_TIMER:
    untimed); a mixin before the backend's class (`common.bench_simulator`)."""

    timer: Timer = NO_TIMER

    def build(self, scene: Any) -> None:
        with self.timer.phase("sim.build"):
            super().build(scene)

    def render_depth(self) -> Any:
        with self.timer.phase("sim.render_depth"):
            return super().render_depth()

    def render_tracking_depth(self) -> Any:
        with self.timer.phase("sim.render_tracking_depth"):
            return super().render_tracking_depth()


class CountedPush:
    """The push protocol as `run_episode` calls it (its `push`), counting the pushes' steps
    (`PushOutcome.steps`, still ones an engine jumps included) and simulated time."""

    def __init__(self) -> None:
        self.steps = 0
        self.sim_s = 0.0

    def __call__(self, sim: Any, cmd: Any, **kwargs: Any) -> Any:
        from comexp.sim.protocol import push

        out = push(sim, cmd, **kwargs)
        self.steps += out.steps
        self.sim_s += out.sim_time_s
        return out


def raw_steps_per_s(sim: Any, spec: EpisodeSpec, seconds: float = 1.0) -> float:
    """`sim.step` on the episode's built scene (object resting, pusher parked): the engine's
    speed with the backend's stepping loop but no push logic. Best of three."""
    from comexp.episode.task import build_scene

    sim.build(build_scene(spec))
    n = round(seconds / sim.settings.timestep_s)
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        sim.step(seconds)
        best = min(best, time.perf_counter() - t0)
    return n / best


def result_record(r: EpisodeResult) -> dict[str, Any]:
    """What must not change when the episode path is optimised."""
    s = r.spec
    return {
        "object": s.object,
        "com_index": s.com_index,
        "izz": s.izz_scale,
        "mu_floor": [s.mu_floor_x, s.mu_floor_y],
        "mu_pusher": s.mu_pusher,
        "status": r.status,
        "failure": r.failure,
        "detail": r.detail[:300],
        "est_com_cm": r.est_com_cm,
        "error_cm": r.error_cm,
        "pushes": [
            [
                p.contact_x_cm,
                p.contact_y_cm,
                p.rotation_deg,
                p.decision,
                p.region_px,
                p.rotation_true_deg,
            ]  # fmt: skip
            for p in r.pushes
        ],
    }


def timed_episodes(
    specs: Sequence[EpisodeSpec], sim: Any, timer: PhaseTimer, pushes: CountedPush
) -> tuple[list[EpisodeResult], list[float], float]:
    """The episodes with the loop's phases and the engine's calls timed: their results, wall
    times, and CPU ms per episode."""
    from comexp.episode.loop import run_episode

    results: list[EpisodeResult] = []
    walls: list[float] = []
    sim.timer = timer
    cpu0 = time.process_time()
    try:
        for s in specs:
            t0 = time.perf_counter()
            results.append(run_episode(s, sim, push=pushes, timer=timer))
            walls.append(time.perf_counter() - t0)
    finally:
        sim.timer = NO_TIMER
    return results, walls, (time.process_time() - cpu0) * 1e3 / len(specs)


def phase_split(timer: PhaseTimer, n: int, total_s: float) -> dict[str, dict[str, float]]:
    """Per row of `ROWS` and per engine call of `ENGINE_CALLS`: its share of the episodes'
    wall time, ms and calls per episode."""
    wall, calls = collections.Counter(timer.wall_s), collections.Counter(timer.calls)
    wall["physics"] = wall["push"] - wall["sim.render_tracking_depth"] - wall["track"]
    calls["physics"] = calls["push"]
    wall["rest"] = total_s - sum(wall[p] for p in TOP_LEVEL)
    keys = [key for key, _ in ROWS] + list(ENGINE_CALLS)
    return {
        k: {"share": wall[k] / total_s, "ms": 1e3 * wall[k] / n, "calls": calls[k] / n}
        for k in keys
    }


def profile(
    backend: str,
    n: int,
    speed: float,
    floor: str,
    dump: str | None,
    raw_s: float,
    overrides: Sequence[str] = (),
) -> dict[str, Any]:
    specs = strided(job_specs(backend, floor, speed, overrides), n)
    simulator = job_simulator(backend, floor, speed, overrides)
    sim = bench_simulator(simulator, TimedEngine)
    timer, pushes = PhaseTimer(), CountedPush()
    out: dict[str, Any] = {
        "backend": backend,
        "options": dict(simulator.options),
        "episodes": len(specs),
        "speed": speed,
        "source": source_digest(backend),
    }
    try:
        t0 = time.perf_counter()
        n_warm = warm_up(specs, sim)
        out["warmup_s_per_ep"] = (time.perf_counter() - t0) / n_warm
        t0 = time.perf_counter()
        results, walls, out["cpu_ms_per_ep"] = timed_episodes(specs, sim, timer, pushes)
        elapsed = time.perf_counter() - t0
        out["steps_per_s_raw"] = raw_steps_per_s(sim, specs[0], raw_s)
    finally:
        sim.close()
    total = sum(walls)
    split = phase_split(timer, len(specs), total)
    ok_walls = [w for w, r in zip(walls, results, strict=True) if r.status == "ok"]
    out.update(
        elapsed_s=elapsed,
        eps_per_s=len(specs) / elapsed,
        mean_ms=1e3 * total / len(walls),
        median_ms=1e3 * statistics.median(walls),
        max_ms=1e3 * max(walls),
        ok_mean_ms=1e3 * statistics.fmean(ok_walls or [0]),
        status=collections.Counter(r.failure or r.status for r in results),
        split=split,
        steps_per_ep=pushes.steps / len(specs),
        steps_per_s_push=pushes.steps / max(timer.wall_s["push"], 1e-12),
    )
    out["floor_ms"] = 1e3 * out["steps_per_ep"] / out["steps_per_s_raw"]
    if dump:
        with open(dump, "w") as f:
            json.dump([result_record(r) for r in results], f, indent=0)
    return out


def report(o: dict[str, Any]) -> None:
    print(
        f"== {o['backend']} {o.get('options') or ''} (source {o['source']}), "
        f"speed {o['speed']:g} cm/s: {o['episodes']} episodes, one worker"
    )
    print(f"load: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} (1, 5 min)")
    print(f"episodes/s          {o['eps_per_s']:.2f}  (elapsed {o['elapsed_s']:.1f} s)")
    print(f"CPU ms/episode      {o['cpu_ms_per_ep']:.0f}  (this process; robust to other load)")
    print(
        f"per episode ms      mean {o['mean_ms']:.0f}  median {o['median_ms']:.0f}  "
        f"max {o['max_ms']:.0f}  (warm-up, 1st of each object: {1e3 * o['warmup_s_per_ep']:.0f})"
    )
    print(
        f"status              {dict(o['status'])}  (mean of the ok ones {o['ok_mean_ms']:.0f} ms)"
    )
    split = o["split"]
    print(f"{'phase':<28}{'share':>7}{'ms/ep':>9}{'calls/ep':>10}")
    for key, label in ROWS:
        row = split[key]
        calls = f"{row['calls']:10.1f}" if key != "rest" else ""
        print(f"{label:<28}{100 * row['share']:6.1f}%{row['ms']:9.1f}{calls}")
    calls = ", ".join(
        f"{k} {split[k]['ms']:.1f} ms ({split[k]['calls']:.1f} calls)" for k in ENGINE_CALLS
    )
    print(f"engine calls/ep     {calls}  (in build and measure)")
    print(f"engine steps/ep     {o['steps_per_ep']:.0f}")
    print(f"steps/s raw         {o['steps_per_s_raw']:,.0f}  (sim.step, built pushing scene)")
    print(f"steps/s in pushes   {o['steps_per_s_push']:,.0f}  (PushOutcome.steps / push wall)")
    print(
        f"physics floor       {o['floor_ms']:.1f} ms/ep at the raw rate "
        f"({100 * o['floor_ms'] / o['mean_ms']:.0f}% of the mean episode)"
    )


def cprofile_lines(
    backend: str, n: int, speed: float, floor: str, overrides: Sequence[str], top: int
) -> list[str]:
    """The same strided episodes under cProfile with the CPU clock (after one warm-up episode
    per object): the functions taking the largest share of the episodes' CPU, by cumulative and
    by own time. Where an episode's time goes at function level (docs/performance.md)."""
    import cProfile
    import pstats

    from comexp.episode.loop import run_episode

    specs = strided(job_specs(backend, floor, speed, overrides), n)
    sim = job_simulator(backend, floor, speed, overrides).make()
    try:
        warm_up(specs, sim)
        prof = cProfile.Profile(time.process_time)
        cpu0 = time.process_time()
        prof.enable()
        for s in specs:
            run_episode(s, sim)
        prof.disable()
        cpu_s = time.process_time() - cpu0
    finally:
        sim.close()
    stats = pstats.Stats(prof).stats  # {(file, line, name): (cc, nc, own, cum, callers)}
    lines = [
        f"== cProfile: {backend} {floor} {speed:g} cm/s, {len(specs)} episodes, "
        f"CPU {1e3 * cpu_s / len(specs):.0f} ms/episode (with the profiler's overhead)"
    ]
    for title, col in (("cumulative", 3), ("own", 2)):
        lines.append(f"top {top} by {title} CPU: share, ms/episode, calls/episode, function")
        rows = sorted(stats.items(), key=lambda kv: -kv[1][col])[:top]
        for key, st in rows:
            lines.append(
                f"  {100 * st[col] / cpu_s:5.1f}%  {1e3 * st[col] / len(specs):7.1f}  "
                f"{st[1] / len(specs):8.1f}  {_function_name(key)}"
            )
    return lines


def _function_name(key: tuple) -> str:
    """cProfile's (file, line, function) as `path:line(function)`, the path from the
    repository's root; a compiled kernel called at its entry point (`DirectCall`) by name."""
    path, line, func = key
    compiled = re.fullmatch(r"<built-in method (comexp\.[\w.]+)>", func)
    if path == "~" and compiled:
        return f"{compiled.group(1)} (compiled)"
    try:
        path = str(Path(path).resolve().relative_to(Path(__file__).resolve().parents[1]))
    except ValueError:
        path = Path(path).name
    return f"{path}:{line}({func})"


class StillStepped:
    """Every still step stepped (`JumpsStillSteps.still_jumps` None): the jumps' baseline."""

    still_jumps = None


class JumpTilts:
    """The tilt each jump starts from (one state read per jump), in `tilts`."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.tilts: list[float] = []
        super().__init__(*args, **kwargs)

    def advance_still(self, targets: Any) -> bool:
        self.tilts.append(self.object_state().tilt_deg)
        return super().advance_still(targets)


def still_jumps_ab(backend: str, n: int, speed: float, floor: str) -> list[str]:
    """CPU per episode with the engine's still steps jumped against every step stepped
    (`still_jumps` None), the same episodes in one process on two simulators of the job's
    backend, alternating which goes first: the host's drift between passes cancels. Then what
    the jumps change: how many episode errors agree, the largest difference of a push's true
    turn between the two (the same push: same contact and direction), and the largest tilt a
    jump started from."""
    from comexp.episode.loop import run_episode

    simulator = job_simulator(backend, floor, speed)
    if getattr(simulator.simulator_class(), "still_jumps", None) is None:
        return [f"{backend} steps every still step: nothing to compare"]
    sims = {
        True: bench_simulator(simulator, JumpTilts),
        False: bench_simulator(simulator, StillStepped),
    }
    specs = strided(job_specs(backend, floor, speed), n)
    cpu = {True: 0.0, False: 0.0}
    runs: dict[bool, list[EpisodeResult]] = {True: [], False: []}
    try:
        for sim in sims.values():
            run_episode(specs[0], sim)  # warm-up
        sims[True].tilts.clear()
        for k, spec in enumerate(specs):
            for jumps in (True, False) if k % 2 else (False, True):
                t0 = time.process_time()
                runs[jumps].append(run_episode(spec, sims[jumps]))
                cpu[jumps] += time.process_time() - t0
    finally:
        for sim in sims.values():
            sim.close()
    return _still_jumps_lines(backend, floor, speed, cpu, runs, sims[True].tilts)


def _still_jumps_lines(
    backend: str, floor: str, speed: float, cpu: dict, runs: dict, start_tilts: list[float]
) -> list[str]:
    n = len(runs[True])
    pairs = list(zip(runs[True], runs[False], strict=True))
    same = sum(a.error_cm == b.error_cm for a, b in pairs)
    turn = [
        abs(p.rotation_true_deg - q.rotation_true_deg)
        for a, b in pairs
        for p, q in zip(a.pushes, b.pushes, strict=False)
        if (p.contact_x_cm, p.contact_y_cm, p.dir_x, p.dir_y)
        == (q.contact_x_cm, q.contact_y_cm, q.dir_x, q.dir_y)
    ]
    return [
        f"== still steps: {backend} {floor} {speed:g} cm/s, {n} episodes, one process",
        f"CPU ms/episode  jumped {1e3 * cpu[True] / n:.1f}, stepped "
        f"{1e3 * cpu[False] / n:.1f}: stepped / jumped {cpu[False] / cpu[True]:.3f}",
        f"episode errors identical in {same} of {n}",
        f"the same push's true turn, jumped - stepped: max {max(turn, default=0.0):.4f} deg, "
        f"median {statistics.median(turn) if turn else 0.0:.5f} deg, "
        f"{sum(t > 0.1 for t in turn)} over 0.1 deg, of {len(turn)} pushes",
        f"tilt where a jump starts: max {max(start_tilts, default=0.0):.4f} deg over "
        f"{len(start_tilts)} jumps",
    ]


def estimator_costs(
    backend: str, n: int, speed: float, floor: str, methods: Sequence[str]
) -> tuple[list[str], list[list[Any]]]:
    """The same strided episodes with each estimator, alternating per episode: per method the
    mean and median wall ms per episode, the ratio of its mean to the first method's, and its
    mean error (cm) over the episodes every method finished."""
    from dataclasses import replace

    from comexp.episode.loop import run_episode

    specs = strided(job_specs(backend, floor, speed), n)
    sim = bench_simulator(job_simulator(backend, floor, speed))
    walls: dict[str, list[float]] = {m: [] for m in methods}
    errors: dict[str, list[float | None]] = {m: [] for m in methods}
    try:
        for m in methods:  # compile and warm each estimator's code (Numba, caches)
            run_episode(replace(specs[0], estimator=replace(specs[0].estimator, method=m)), sim)
        for spec in specs:
            for m in methods:
                s = replace(spec, estimator=replace(spec.estimator, method=m))
                t0 = time.perf_counter()
                r = run_episode(s, sim)
                walls[m].append(time.perf_counter() - t0)
                errors[m].append(r.error_cm if r.status == "ok" else None)
    finally:
        sim.close()
    both = [i for i in range(len(specs)) if all(errors[m][i] is not None for m in methods)]
    base = statistics.fmean(walls[methods[0]])
    rows = [
        [
            f"{backend}, {floor}, {speed:g} cm/s",
            m,
            len(specs),
            1e3 * statistics.fmean(walls[m]),
            1e3 * statistics.median(walls[m]),
            statistics.fmean(walls[m]) / base,
            statistics.fmean(errors[m][i] for i in both) if both else None,
        ]
        for m in methods
    ]
    columns = [
        "condition",
        "estimator",
        "episodes",
        "mean ms",
        "median ms",
        "cost ratio",
        "error cm",
    ]
    return columns, rows


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--backend", choices=("planar", "pybullet", "mujoco"), default="pybullet")
    ap.add_argument(
        "--floor-friction",
        choices=("model", "native"),
        help="engines: backend.floor_friction (default: the config's, model)",
    )
    ap.add_argument(
        "--renderer",
        choices=("raycast", "engine"),
        help="engines: camera.renderer (default: the config's, raycast)",
    )
    ap.add_argument("--episodes", type=int, default=40)
    ap.add_argument("--speed", type=float, default=40.0, help="cm/s (40 dynamic, 4 quasi-static)")
    ap.add_argument("--floor", choices=("iso", "aniso"), default="iso")
    ap.add_argument("--raw-seconds", type=float, default=1.0, help="sim time for the raw rate")
    ap.add_argument("--dump", help="write per-episode results as JSON")
    ap.add_argument("--engine-output", action="store_true", help="keep the engine's own prints")
    ap.add_argument(
        "--cprofile", type=int, metavar="TOP", help="cProfile the episodes: the TOP functions"
    )
    ap.add_argument(
        "--estimators",
        help="comma-separated methods: the same episodes with each, alternating (cost ratios)",
    )
    ap.add_argument("--json", metavar="NAME", help="--estimators: write docs/data/NAME.json")
    ap.add_argument(
        "--still-jumps",
        action="store_true",
        help="engines: CPU with the still steps jumped against stepped, alternating",
    )
    return ap.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    a = parse_args(argv)
    use_one_cpu()
    overrides = [f"backend.floor_friction={a.floor_friction}"] if a.floor_friction else []
    overrides += [f"camera.renderer={a.renderer}"] if a.renderer else []
    if a.estimators:
        methods = [m.strip() for m in a.estimators.split(",") if m.strip()]
        with engine_stdout_silenced(not a.engine_output):
            columns, rows = estimator_costs(a.backend, a.episodes, a.speed, a.floor, methods)
        print(" | ".join(columns))
        for row in rows:
            print(" | ".join(f"{v:.3f}" if isinstance(v, float) else str(v) for v in row))
        if a.json:
            cmd = "python bench/episode_profile.py " + " ".join(argv or sys.argv[1:])
            print(write_table(a.json, columns, rows, cmd))
        return 0
    with engine_stdout_silenced(not a.engine_output):
        if a.still_jumps:
            lines = still_jumps_ab(a.backend, a.episodes, a.speed, a.floor)
        elif a.cprofile:
            lines = cprofile_lines(a.backend, a.episodes, a.speed, a.floor, overrides, a.cprofile)
        else:
            o = profile(a.backend, a.episodes, a.speed, a.floor, a.dump, a.raw_seconds, overrides)
    if a.still_jumps or a.cprofile:
        print("\n".join(lines))
    else:
        report(o)
    return 0


if __name__ == "__main__":
    sys.exit(main())
