"""Episodes per second on one worker, and where an episode's time goes.

    .venv/bin/python bench/episode_profile.py --backend pybullet [--episodes 40] [--speed 40]
    .venv/bin/python bench/episode_profile.py --backend mujoco --speed 4 --dump /tmp/mj.json

In-process, one simulator, real episodes: the specs are the job's own grid (`comexp.experiment.grid`
over the built-in objects, through the Hydra config like `comexp` itself), a strided slice
of it that holds every object and every condition (`strided`). Time is split by wrapping
the functions that `run_episode` calls (sim.push, sim.build, sim.render_depth, perception,
estimator) with timers from outside: the hot path carries no instrumentation. "rest" is
what no wrapper saw (the episode's own bookkeeping, true poses for evaluation, frames).

A warm-up pass first runs one episode per object untimed (the engine's one-off costs per
object: MuJoCo builds one GL renderer per object geometry, kept for the rest of the job), so
the figures are the steady state a worker reaches in a 1,600-episode job; the warm-up's own
time per episode is printed too.

The floor below which an episode cannot go: the engine's raw steps per second on a built
pushing scene (`sim.step`, object at rest, pusher parked), and the steps per second reached
inside pushes (`PushOutcome.steps` over push wall time, which includes the backend's
per-step Python: pusher command, state checks).

`--dump PATH` writes every episode's result (estimate, error, per-push rotations and
decisions) as JSON, to check that an optimisation leaves results unchanged.

`--baseline DIR` compares the episode path against other versions of `perception.py` and
`estimator.py` found in DIR (e.g. `git show 706e37b:comexp/perception.py > DIR/perception.py`):
every episode is run with both, interleaved on the same simulator (builds are full resets,
so runs are bit-identical); the episode, perception and estimator time ratios and any
difference in results are printed.
"""

from __future__ import annotations

import argparse
import collections
import functools
import hashlib
import json
import math
import os
import re
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import TYPE_CHECKING, Any

from comexp.experiment.task import EpisodeResult, EpisodeSpec

if TYPE_CHECKING:
    from comexp.experiment.simulator import Simulator

# The episode loop (Numba, OpenCV, the engines) is imported by the functions that run
# episodes, not here: bench/memory.py imports `job_specs` as `comexp`'s driver does, lightly.

PHASES = ("physics (sim.push)", "scene build", "render", "perception", "estimator")


def _job(backend: str, floor: str, speed: float, overrides: Sequence[str]) -> Any:
    """The job `comexp` would prepare (Hydra config, validation, objects). The database
    setting points at a temp dir so nothing is probed or created under results/. Prepared
    once per process and job: `job_specs` and `job_backend_options` of one job share it."""
    return _prepared_job(backend, floor, float(speed), tuple(overrides))


@functools.lru_cache(maxsize=8)
def _prepared_job(backend: str, floor: str, speed: float, overrides: tuple[str, ...]) -> Any:
    from hydra import compose, initialize_config_module

    from comexp.experiment.config import prepare_job

    db = os.path.join(tempfile.gettempdir(), "comexp-bench-unused.db")
    args = [f"backend={backend}", f"floor={floor}", f"speed={speed:g}", f"db={db}", *overrides]
    with initialize_config_module("comexp.conf", version_base="1.3"):
        cfg = compose("config", overrides=args, return_hydra_config=True)
    return prepare_job(cfg)


def job_specs(
    backend: str, floor: str = "iso", speed: float = 40.0, overrides: Sequence[str] = ()
) -> list[EpisodeSpec]:
    """All episodes of one job, expanded exactly as `comexp` does (grid order)."""
    from comexp.experiment.grid import expand_grid

    job = _job(backend, floor, speed, overrides)
    return expand_grid(job.cfg, job.objects, estimator=job.estimator)


def job_backend_options(
    backend: str, floor: str = "iso", speed: float = 40.0, overrides: Sequence[str] = ()
) -> dict[str, Any]:
    """The backend options `comexp` hands its workers for this job (`EpisodePool`'s
    `backend_options`): without them a worker runs another physics than the episodes name,
    and refuses every one (`physics_mismatch`)."""
    from comexp.experiment.config import simulator_options

    return simulator_options(_job(backend, floor, speed, overrides).cfg)


def strided(specs: Sequence[EpisodeSpec], n: int) -> list[EpisodeSpec]:
    """n episodes spread over the whole grid: a fixed, reproducible slice, in grid order.

    The grid is object-major with the 8 conditions (Izz x floor mu x pusher mu) innermost,
    so a plain stride of 1600 / n (a multiple of 8 for n = 200, 40) would pick one condition
    only. The step is the first integer >= len / n that is coprime with len (indices taken
    modulo len stay distinct); for len = 1600 it is odd and not a multiple of 5, so
    consecutive picks also cycle through all 8 conditions."""
    total = len(specs)
    n = min(n, total)
    step = max(1, math.ceil(total / n))
    while math.gcd(step, total) != 1:
        step += 1
    return [specs[i] for i in sorted((k * step) % total for k in range(n))]


class PhaseTimer:
    """Accumulates wall time per phase from wrapped callables (patched in from outside)."""

    def __init__(self) -> None:
        self.seconds: collections.Counter[str] = collections.Counter()
        self.calls: collections.Counter[str] = collections.Counter()
        self.push_steps = 0
        self.push_sim_s = 0.0
        self.enabled = True

    def wrap(self, phase: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(fn)
        def timed(*args: Any, **kwargs: Any) -> Any:
            if not self.enabled:
                return fn(*args, **kwargs)
            t0 = time.perf_counter()
            try:
                out = fn(*args, **kwargs)
            finally:
                self.seconds[phase] += time.perf_counter() - t0
                self.calls[phase] += 1
            if phase == PHASES[0]:  # a PushOutcome
                self.push_steps += out.steps
                self.push_sim_s += out.sim_time_s
            return out

        return timed

    def reset(self) -> None:
        self.seconds.clear()
        self.calls.clear()
        self.push_steps = 0
        self.push_sim_s = 0.0


@contextmanager
def instrumented(sim: Simulator, timer: PhaseTimer) -> Iterator[None]:
    """Patch timers around everything `run_episode` calls; restore on exit.

    The wrapped functions do not call one another (images are rendered before perception
    sees them), so the phases are disjoint and add up to at most the episode's wall time.
    """
    from comexp.experiment import episode as episode_mod
    from comexp.method.estimator import ComEstimator
    from comexp.method.perception import PoseTracker

    patches: list[tuple[Any, str, Any]] = [
        (sim, "push", PHASES[0]),
        (sim, "build", PHASES[1]),
        (episode_mod, "build_scene", PHASES[1]),
        (sim, "render_depth", PHASES[2]),
        (episode_mod, "perceive_first", PHASES[3]),
        (episode_mod, "observe", PHASES[3]),
        (PoseTracker, "__init__", PHASES[3]),
        (PoseTracker, "fit", PHASES[3]),
        (ComEstimator, "__init__", PHASES[4]),
        (ComEstimator, "next_push", PHASES[4]),
        (ComEstimator, "observe", PHASES[4]),
    ]
    saved = []
    for owner, attr, phase in patches:
        had_own = attr in vars(owner)  # instance attribute vs class attribute
        orig = getattr(owner, attr)
        saved.append((owner, attr, vars(owner).get(attr), had_own))
        setattr(owner, attr, timer.wrap(phase, orig))
    try:
        yield
    finally:
        for owner, attr, orig, had_own in reversed(saved):
            if had_own:
                setattr(owner, attr, orig)
            else:
                delattr(owner, attr)


@contextmanager
def engine_stdout_silenced(enabled: bool = True) -> Iterator[None]:
    """Send file descriptor 1 to /dev/null: pybullet's C++ prints a URDF warning per build
    straight to the fd, bypassing sys.stdout, which would bury the figures."""
    if not enabled:
        yield
        return
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        sys.stdout.flush()
        _libc_fflush()  # C stdio buffers still hold engine text meant for /dev/null
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def _libc_fflush() -> None:
    import ctypes

    with suppress(OSError, AttributeError):
        ctypes.CDLL(None).fflush(None)


def source_digest(backend: str) -> str:
    """Short hash of the backend's source file: the backends change under active work, so
    every figure is tied to the exact engine code it measured."""
    import importlib

    from comexp.experiment.simulator import BACKENDS

    mod = importlib.import_module(BACKENDS[backend].split(":")[0])
    with open(mod.__file__ or "", "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()[:12]


def raw_steps_per_s(sim: Simulator, spec: EpisodeSpec, seconds: float = 1.0) -> float:
    """`sim.step` on the episode's built scene (object resting, pusher parked): the engine's
    speed with the backend's stepping loop but no push logic. Best of three."""
    from comexp.experiment import episode as episode_mod

    sim.build(episode_mod.build_scene(spec))
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


def use_one_cpu() -> None:
    """This process's thread pools as a pool worker's (`comexp.workers.actor.use_one_cpu`):
    the figures are one worker's, and OpenCV's spinning threads would add to its CPU."""
    from comexp.workers.actor import use_one_cpu as worker_threads

    worker_threads()


def warm_up(specs: Sequence[EpisodeSpec], sim: Any) -> int:
    """Run the first episode of each object once, untimed (the engine's one-offs per object:
    compilation, scene caches); returns how many ran."""
    from comexp.experiment.episode import run_episode

    first: dict[str, EpisodeSpec] = {}
    for s in specs:
        first.setdefault(s.object, s)
    for s in first.values():
        run_episode(s, sim)
    return len(first)


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
    from comexp.experiment.episode import run_episode
    from comexp.experiment.simulator import make_simulator

    opts = job_backend_options(backend, floor, speed, overrides)
    sim = make_simulator(backend, **opts)
    out_digest = source_digest(backend)
    timer = PhaseTimer()
    out: dict[str, Any] = {
        "backend": backend,
        "options": opts,
        "episodes": len(specs),
        "speed": speed,
        "source": out_digest,
    }
    try:
        t0 = time.perf_counter()
        n_warm = warm_up(specs, sim)
        out["warmup_s_per_ep"] = (time.perf_counter() - t0) / n_warm

        results: list[EpisodeResult] = []
        walls: list[float] = []
        with instrumented(sim, timer):
            t_all = time.perf_counter()
            cpu0 = time.process_time()
            for s in specs:
                t0 = time.perf_counter()
                results.append(run_episode(s, sim))
                walls.append(time.perf_counter() - t0)
            elapsed = time.perf_counter() - t_all
            out["cpu_ms_per_ep"] = (time.process_time() - cpu0) * 1e3 / len(specs)
        out["steps_per_s_raw"] = raw_steps_per_s(sim, specs[0], raw_s)
    finally:
        sim.close()

    total = sum(walls)
    out.update(
        elapsed_s=elapsed,
        eps_per_s=len(specs) / elapsed,
        mean_ms=1e3 * total / len(walls),
        median_ms=1e3 * statistics.median(walls),
        max_ms=1e3 * max(walls),
        ok_mean_ms=1e3
        * statistics.fmean(
            [w for w, r in zip(walls, results, strict=True) if r.status == "ok"] or [0]
        ),
        status=collections.Counter(r.failure or r.status for r in results),
        phases={p: timer.seconds[p] / total for p in PHASES},
        calls={p: timer.calls[p] / len(specs) for p in PHASES},
        phase_ms={p: 1e3 * timer.seconds[p] / len(specs) for p in PHASES},
        steps_per_ep=timer.push_steps / len(specs),
        steps_per_s_push=timer.push_steps / max(timer.seconds[PHASES[0]], 1e-12),
    )
    out["phases"]["rest"] = 1.0 - sum(out["phases"].values())
    out["phase_ms"]["rest"] = out["mean_ms"] - sum(out["phase_ms"].values())
    out["floor_ms"] = 1e3 * out["steps_per_ep"] / out["steps_per_s_raw"]
    if dump:
        with open(dump, "w") as f:
            json.dump([result_record(r) for r in results], f, indent=0)
    return out


def report(o: dict[str, Any]) -> None:
    print(
        f"== {o['backend']} {o.get('options') or ''} (source {o['source']}), "
        f"speed {o['speed']:g} cm/s: "
        f"{o['episodes']} episodes, one worker"
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
    print(f"{'phase':<20}{'share':>7}{'ms/ep':>9}{'calls/ep':>10}")
    for p, share in o["phases"].items():
        calls = o["calls"].get(p)
        c = f"{calls:10.1f}" if calls is not None else ""
        print(f"{p:<20}{100 * share:6.1f}%{o['phase_ms'][p]:9.1f}{c}")
    print(f"engine steps/ep     {o['steps_per_ep']:.0f}")
    print(f"steps/s raw         {o['steps_per_s_raw']:,.0f}  (sim.step, built pushing scene)")
    print(f"steps/s in pushes   {o['steps_per_s_push']:,.0f}  (PushOutcome.steps / push wall)")
    print(
        f"physics floor       {o['floor_ms']:.1f} ms/ep at the raw rate "
        f"({100 * o['floor_ms'] / o['mean_ms']:.0f}% of the mean episode)"
    )


def _load_module(name: str, path: str) -> Any:
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # dataclasses look their module up while the class is created
    spec.loader.exec_module(mod)
    return mod


def compare_baseline(backend: str, n: int, speed: float, floor: str, baseline: str) -> list[str]:
    """Same episodes with the baseline modules and the current ones, interleaved (ABBA)."""
    from comexp.experiment import episode as episode_mod
    from comexp.experiment.episode import run_episode
    from comexp.experiment.simulator import make_simulator

    names = ("perceive_first", "observe", "PoseTracker", "PerceptionError", "ComEstimator")
    current = {k: getattr(episode_mod, k) for k in names}
    base = dict(current)
    perc_path = os.path.join(baseline, "perception.py")
    est_path = os.path.join(baseline, "estimator.py")
    if os.path.exists(perc_path):
        m = _load_module("baseline_perception", perc_path)
        base.update({k: getattr(m, k) for k in names[:4]})
    if os.path.exists(est_path):
        base["ComEstimator"] = _load_module("baseline_estimator", est_path).ComEstimator
    specs = strided(job_specs(backend, floor, speed), n)
    sim = make_simulator(backend)
    spent = {"baseline": 0.0, "current": 0.0}
    differ = []
    # per-variant phase timers: module functions are wrapped in the swapped-in dicts, class
    # methods on each variant's own class (a class shared by both variants is not timed)
    timers = {"baseline": PhaseTimer(), "current": PhaseTimer()}
    variants = {"baseline": dict(base), "current": dict(current)}
    for lab, fns in variants.items():
        for fn in ("perceive_first", "observe"):
            fns[fn] = timers[lab].wrap(PHASES[3], fns[fn])
    patched: list[tuple[type, str, Any]] = []
    for lab, fns in variants.items():
        for key, attrs, phase in (
            ("PoseTracker", ("__init__", "fit"), PHASES[3]),
            ("ComEstimator", ("__init__", "next_push", "observe"), PHASES[4]),
        ):
            cls = fns[key]
            if base[key] is current[key]:
                continue
            for attr in attrs:
                patched.append((cls, attr, vars(cls)[attr]))
                setattr(cls, attr, timers[lab].wrap(phase, vars(cls)[attr]))
    try:
        # warm-up, one episode per object: a first episode pays one-offs (MuJoCo's renderer
        # for that geometry) that would otherwise bias whichever variant runs it
        for s in {s.object: s for s in specs}.values():
            run_episode(s, sim)
        for t in timers.values():
            t.reset()
        for i, s in enumerate(specs):
            rec = {}
            for lab in ("baseline", "current") if i % 2 == 0 else ("current", "baseline"):
                for k, v in variants[lab].items():
                    setattr(episode_mod, k, v)
                t0 = time.perf_counter()
                r = run_episode(s, sim)
                spent[lab] += time.perf_counter() - t0
                rec[lab] = result_record(r)
            if rec["baseline"] != rec["current"]:
                differ.append(f"{s.object}/{s.com_index}")
    finally:
        for k, v in current.items():
            setattr(episode_mod, k, v)
        for cls, attr, fn in patched:
            setattr(cls, attr, fn)
        sim.close()
    b, c = (1e3 * spent[k] / len(specs) for k in ("baseline", "current"))
    phases = []
    for ph in PHASES[3:]:
        tb, tc = (timers[k].seconds[ph] for k in ("baseline", "current"))
        if tb > 0 and tc > 0:
            phases.append(
                f"{ph} ms/episode: baseline {1e3 * tb / len(specs):.1f}, "
                f"current {1e3 * tc / len(specs):.1f}, ratio {tc / tb:.2f}"
            )
    return [
        f"== {backend} (source {source_digest(backend)}), speed {speed:g}: {len(specs)} "
        f"episodes, baseline {baseline} vs current, interleaved; "
        f"load {os.getloadavg()[0]:.2f}",
        f"ms/episode: baseline {b:.0f}, current {c:.0f}, ratio {c / b:.3f}",
        *phases,
        f"episodes whose results differ: {len(differ)} {' '.join(differ[:10])}",
    ]


def cprofile_lines(
    backend: str, n: int, speed: float, floor: str, overrides: Sequence[str], top: int
) -> list[str]:
    """The same strided episodes under cProfile with the CPU clock (after one warm-up episode
    per object): the functions taking the largest share of the episodes' CPU, by cumulative and
    by own time. Where an episode's time goes at function level (docs/performance.md)."""
    import cProfile
    import pstats

    from comexp.experiment.episode import run_episode
    from comexp.experiment.simulator import make_simulator

    specs = strided(job_specs(backend, floor, speed, overrides), n)
    sim = make_simulator(backend, **job_backend_options(backend, floor, speed, overrides))
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
    root = Path(__file__).resolve().parents[1]

    def name(key: tuple) -> str:
        path, line, func = key
        compiled = re.fullmatch(r"<built-in method (comexp\.[\w.]+)>", func)
        if path == "~" and compiled:  # a kernel called at its entry point (DirectCall)
            return f"{compiled.group(1)} (compiled)"
        try:
            path = str(Path(path).resolve().relative_to(root))
        except ValueError:
            path = Path(path).name
        return f"{path}:{line}({func})"

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
                f"{st[1] / len(specs):8.1f}  {name(key)}"
            )
    return lines


def still_jumps_ab(backend: str, n: int, speed: float, floor: str) -> list[str]:
    """CPU per episode with the engine's still steps jumped against every step stepped
    (`still_jumps` None), the same episodes in one process, alternating which goes
    first: the host's drift between passes cancels. Then what the jumps change: how many
    episode errors agree, the largest difference of a push's true turn between the two (the
    same push: same contact and direction), and the largest tilt a jump started from."""
    from comexp.experiment.episode import run_episode
    from comexp.experiment.registry import make_simulator

    sim = make_simulator(backend, **job_backend_options(backend, floor, speed))
    jumps_on = sim.still_jumps
    if jumps_on is None:
        return [f"{backend} steps every still step: nothing to compare"]
    specs = strided(job_specs(backend, floor, speed), n)
    cpu = {True: 0.0, False: 0.0}
    runs: dict[bool, list] = {True: [], False: []}
    start_tilts: list[float] = []
    advance_still = sim._advance_still

    def recorded(targets):  # the tilt each jump starts from (one state read a jump)
        start_tilts.append(sim.object_state().tilt_deg)
        return advance_still(targets)

    sim._advance_still = recorded
    try:
        run_episode(specs[0], sim)  # warm-up
        for k, spec in enumerate(specs):
            for jumps in (True, False) if k % 2 else (False, True):
                sim.still_jumps = jumps_on if jumps else None
                t0 = time.process_time()
                r = run_episode(spec, sim)
                cpu[jumps] += time.process_time() - t0
                runs[jumps].append(r)
    finally:
        sim.close()
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
        f"== still steps: {backend} {floor} {speed:g} cm/s, {len(specs)} episodes, one process",
        f"CPU ms/episode  jumped {1e3 * cpu[True] / len(specs):.1f}, stepped "
        f"{1e3 * cpu[False] / len(specs):.1f}: stepped / jumped {cpu[False] / cpu[True]:.3f}",
        f"episode errors identical in {same} of {len(specs)}",
        f"the same push's true turn, jumped - stepped: max {max(turn, default=0.0):.4f} deg, "
        f"median {statistics.median(turn) if turn else 0.0:.5f} deg, "
        f"{sum(t > 0.1 for t in turn)} over 0.1 deg, of {len(turn)} pushes",
        f"tilt where a jump starts: max {max(start_tilts, default=0.0):.4f} deg over "
        f"{len(start_tilts)} jumps",
    ]


def main(argv: Sequence[str] | None = None) -> int:
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
    ap.add_argument("--baseline", help="dir with perception.py/estimator.py to compare against")
    ap.add_argument(
        "--cprofile", type=int, metavar="TOP", help="cProfile the episodes: the TOP functions"
    )
    ap.add_argument(
        "--still-jumps",
        action="store_true",
        help="engines: CPU with the still steps jumped against stepped, alternating",
    )
    a = ap.parse_args(argv)
    use_one_cpu()
    if a.still_jumps:
        with engine_stdout_silenced(not a.engine_output):
            lines = still_jumps_ab(a.backend, a.episodes, a.speed, a.floor)
        print("\n".join(lines))
        return 0
    if a.baseline:
        with engine_stdout_silenced(not a.engine_output):
            lines = compare_baseline(a.backend, a.episodes, a.speed, a.floor, a.baseline)
        print("\n".join(lines))
        return 0
    with engine_stdout_silenced(not a.engine_output):
        overrides = [f"backend.floor_friction={a.floor_friction}"] if a.floor_friction else []
        overrides += [f"camera.renderer={a.renderer}"] if a.renderer else []
        if a.cprofile:
            lines = cprofile_lines(a.backend, a.episodes, a.speed, a.floor, overrides, a.cprofile)
        else:
            o = profile(a.backend, a.episodes, a.speed, a.floor, a.dump, a.raw_seconds, overrides)
    if a.cprofile:
        print("\n".join(lines))
    else:
        report(o)
    return 0


if __name__ == "__main__":
    sys.exit(main())
