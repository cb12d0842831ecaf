"""The same episodes on 1 and 2 workers through the real pool, measured in one run.

    .venv/bin/python bench/scaling.py                       # pybullet, 200 episodes, 1 and 2
    .venv/bin/python bench/scaling.py --backend mujoco --episodes 100 --workers 1 2
    .venv/bin/python bench/scaling.py --backend mujoco --episodes 400 --rounds 3

The episodes are a fixed slice of the iso / 40 cm/s job (every 8th of its 1,600, so every
object and condition is in it), run by `workers/pool.py` on a local Ray exactly as `comexp`
runs them, the driver writing a throwaway SQLite database in a temp dir as results arrive.

Per worker count: elapsed time of the run, speed-up over the first count, busy fraction
(sum of the episodes' own wall_s / (workers x elapsed): the share of the workers' time spent
inside episodes), and where the rest goes, from CPU time read in /proc for every process of
the driver's tree: the workers (episodes + Ray's task handling), the driver (result handling,
database writes, timed separately too) and Ray's own processes (gcs_server, raylet, agents),
which compete with the workers for the same two cores. One-off costs are timed apart: Ray's
start, the pool's start (actors + one simulator each), and the job set-up the CLI does
(Hydra compose + validation + grid expansion of the 1,600 episodes + the resume query).

Ratios measured within one run are the figures to quote: the machine is shared. On a host
whose speed drifts within a minute (a worker's CPU per episode moving by up to 20% between two
runs of the same code), one 1-then-2 sequence decides little: `--rounds N` alternates the worker
counts N times, gives each round's speed-up over its own first count and their median.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass

os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

from common import (
    CLK_TCK,
    cpu_seconds,
    descendants,
    job_simulator,
    job_specs,
    proc_name,
    source_digest,
    strided,
)

from comexp.episode.task import EpisodeResult, EpisodeSpec
from comexp.results.identity import episode_key
from comexp.results.store import ResultsDB


@dataclass
class Run:
    workers: int
    pool_start_s: float
    elapsed_s: float
    episode_wall_s: float  # sum of EpisodeResult.wall_s
    db_write_s: float
    cpu_workers_s: float
    cpu_driver_s: float
    cpu_ray_s: float
    cpu_machine_s: float  # busy CPU seconds of the whole machine (all users) during the run
    failed: int
    failures: dict[str, int]  # failure reason -> episodes
    errors: dict[str, float]  # episode key -> error_cm (None for failed), to compare runs
    load: float

    @property
    def busy(self) -> float:
        return self.episode_wall_s / (self.workers * self.elapsed_s)


def _tree_cpu(root: int) -> dict[int, float]:
    out = {}
    for pid in descendants(root):
        c = cpu_seconds(pid)
        if c is not None:
            out[pid] = c
    return out


def machine_cpu_s() -> tuple[float, float]:
    """(busy, total) CPU seconds of the whole machine since boot, from /proc/stat: with the
    tree's own CPU time this tells how much the other users of the machine took."""
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    idle = v[3] + v[4]  # idle + iowait
    total = sum(v[:8])  # guest time is already inside user
    return (total - idle) / CLK_TCK, total / CLK_TCK


def _delta(before: dict[int, float], after: dict[int, float], pids: set[int]) -> float:
    return sum(after.get(p, before.get(p, 0.0)) - before.get(p, 0.0) for p in pids)


def run_once(
    backend: str, specs: Sequence[EpisodeSpec], workers: int, tmp: str, tag: str = ""
) -> Run:
    """One pool of `workers` actors runs `specs` into a fresh database (`tag`: of the round)."""
    import ray

    from comexp.workers.driver import run_and_store
    from comexp.workers.pool import EpisodePool

    db = ResultsDB(os.path.join(tmp, f"scaling_{workers}{tag}.db"))
    results: list[EpisodeResult] = []
    db_time = 0.0
    try:
        sweep = db.start_sweep(command_line=f"bench/scaling.py workers={workers}")

        def store(rs: list[EpisodeResult]) -> int:
            nonlocal db_time
            results.extend(rs)
            t0 = time.perf_counter()
            n = db.add_results(sweep, rs)
            db_time += time.perf_counter() - t0
            return n

        pool = EpisodePool(job_simulator(backend), workers)  # the job's physics
        t0 = time.perf_counter()
        pool.start()
        pool_start = time.perf_counter() - t0
        try:
            wpids = {
                ray.get(s.actor.ready.remote())["pid"]
                for s in pool._slots  # noqa: SLF001 - bench: which processes are ours
            }
            me = os.getpid()
            cpu0 = _tree_cpu(me)
            ru0 = resource.getrusage(resource.RUSAGE_SELF)
            m0 = machine_cpu_s()[0]
            stats = run_and_store(pool, specs, store)
            m1 = machine_cpu_s()[0]
            ru1 = resource.getrusage(resource.RUSAGE_SELF)
            cpu1 = _tree_cpu(me)
        finally:
            pool.close()
    finally:
        db.close()
    others = (set(cpu0) | set(cpu1)) - wpids - {me}
    return Run(
        workers=workers,
        pool_start_s=pool_start,
        elapsed_s=stats.wall_s,
        episode_wall_s=sum(r.wall_s for r in results),
        db_write_s=db_time,
        cpu_workers_s=_delta(cpu0, cpu1, wpids),
        cpu_driver_s=(ru1.ru_utime + ru1.ru_stime) - (ru0.ru_utime + ru0.ru_stime),
        cpu_ray_s=_delta(cpu0, cpu1, others),
        cpu_machine_s=m1 - m0,
        failed=stats.failed,
        failures=dict(stats.failures),
        errors={episode_key(r.spec): r.error_cm for r in results},
        load=os.getloadavg()[0],
    )


def setup_costs(backend: str, tmp: str, cpus: int = 2) -> dict[str, float]:
    """What `comexp` does before the first episode: Hydra + validation + grid, the resume
    query against an empty database, the kernels compiled (or loaded) in a child process
    while Ray starts."""
    from comexp.workers.kernel_cache import warm_kernel_cache
    from comexp.workers.session import ensure_ray

    t0 = time.perf_counter()
    specs = job_specs(backend)
    t_grid = time.perf_counter() - t0
    db = ResultsDB(os.path.join(tmp, "setup.db"))
    try:
        t0 = time.perf_counter()
        db.stored_keys(episode_key(s) for s in specs)
        t_resume = time.perf_counter() - t0
    finally:
        db.close()
    t_ray: list[float] = []

    def start_ray() -> None:
        t = time.perf_counter()
        ensure_ray(None, cpus)
        t_ray.append(time.perf_counter() - t)

    t0 = time.perf_counter()  # as `comexp` does: the kernels in a child while Ray starts
    warm_kernel_cache(job_simulator(backend), specs[0], meanwhile=start_ray)
    t_both = time.perf_counter() - t0
    return {
        "hydra_grid_s": t_grid,
        "resume_query_s": t_resume,
        "kernels_and_ray_s": t_both,
        "ray_start_s": t_ray[0],
    }


def report(backend: str, n: int, setup: dict[str, float], runs: list[Run], rounds: int = 1) -> None:
    """`runs`: `rounds` rounds of the same worker counts, one after the other; each run's
    speed-up is over its own round's first."""
    per_round = len(runs) // rounds
    base = runs[0]
    print(f"== scaling: {backend} (source {source_digest(backend)}), {n} episodes (iso/40 slice)")
    print(
        f"one-off: Hydra+validation+grid (1,600) {setup['hydra_grid_s']:.2f} s, "
        f"resume query {setup['resume_query_s']:.2f} s, kernels beside Ray's start "
        f"{setup['kernels_and_ray_s']:.2f} s (Ray's start {setup['ray_start_s']:.2f} s)"
    )
    hdr = (
        f"{'workers':>7}{'load':>6}{'pool start':>11}{'elapsed':>9}{'ep/s':>7}{'speed-up':>9}"
        f"{'busy':>7}{'ep ms':>7}{'cpu ms':>7}{'db write':>9}{'cpu wrk':>8}{'driver':>8}"
        f"{'ray':>6}{'others':>8}"
    )
    print(hdr)
    for i, r in enumerate(runs):
        first = runs[i // per_round * per_round]
        cap = r.workers * r.elapsed_s  # worker-seconds available
        ours = r.cpu_workers_s + r.cpu_driver_s + r.cpu_ray_s
        others = max(r.cpu_machine_s - ours, 0.0)  # other users of the machine, in cores
        print(
            f"{r.workers:>7}{r.load:>6.2f}{r.pool_start_s:>10.1f}s{r.elapsed_s:>8.1f}s"
            f"{n / r.elapsed_s:>7.2f}{first.elapsed_s / r.elapsed_s:>9.2f}"
            f"{100 * r.busy:>6.1f}%{1e3 * r.episode_wall_s / n:>7.0f}"
            f"{1e3 * r.cpu_workers_s / n:>7.0f}"
            f"{100 * r.db_write_s / r.elapsed_s:>8.1f}%"
            f"{100 * r.cpu_workers_s / cap:>7.0f}%{100 * r.cpu_driver_s / cap:>7.1f}%"
            f"{100 * r.cpu_ray_s / cap:>5.1f}%{others / r.elapsed_s:>6.2f}cpu"
        )
    print(
        "  busy = sum(episode wall_s) / (workers x elapsed); ep ms = mean episode wall_s;\n"
        "  cpu ms = worker CPU time per episode (ep ms above it = waiting for a core);\n"
        "  db write = driver time in db.add_results / elapsed; cpu wrk/driver/ray = CPU time of\n"
        "  the workers / driver / Ray's processes over (workers x elapsed); others = CPU cores\n"
        f"  used by everything else on the machine ({os.cpu_count()} cores) during the run"
    )
    if rounds > 1:
        for k in range(1, per_round):
            starts = range(0, len(runs), per_round)
            ups = [runs[j].elapsed_s / runs[j + k].elapsed_s for j in starts]
            print(
                f"speed-up of {runs[k].workers} workers over {base.workers}, per round: "
                f"{', '.join(f'{u:.2f}' for u in ups)} (median {statistics.median(ups):.2f})"
            )
    for r in runs[1:]:
        if r.workers == base.workers:
            continue
        same = r.errors == base.errors
        print(f"results of {r.workers} workers identical to {base.workers}: {same}")
    print(f"failed episodes: {', '.join(f'{r.workers}w {r.failed} {r.failures}' for r in runs)}")
    names = sorted({proc_name(p) for p in descendants(os.getpid())})
    print(f"processes in the tree: {', '.join(names)}")


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--backend", choices=("pybullet", "mujoco"), default="pybullet")
    ap.add_argument("--episodes", type=int, default=200)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument(
        "--rounds", type=int, default=1, help="alternate the worker counts this many times"
    )
    a = ap.parse_args(argv)
    specs = strided(job_specs(a.backend), a.episodes)
    with tempfile.TemporaryDirectory(prefix="comexp-bench-scaling-") as tmp:
        setup = setup_costs(a.backend, tmp, max(2, *a.workers))
        runs = [
            run_once(a.backend, specs, w, tmp, f"_r{k}")
            for k in range(max(1, a.rounds))
            for w in a.workers
        ]
    report(a.backend, len(specs), setup, runs, max(1, a.rounds))
    return 0


if __name__ == "__main__":
    sys.exit(main())
