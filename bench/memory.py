"""Peak resident memory of the driver, the workers and Ray's own processes during a job.

    .venv/bin/python bench/memory.py                                 # iso/40, 1,600 episodes
    .venv/bin/python bench/memory.py --episodes 200 --backend mujoco # a quick run

Runs the job through the real pool (`workers/pool.py`, a local Ray, a throwaway SQLite
database in a temp dir: the driver writes it as `comexp` does) and samples every process of
the driver's tree from /proc (psutil is not a dependency): VmRSS and, because Ray's processes
share pages (libraries, the object store), PSS from smaps_rollup, whose sum over processes is
the real footprint. VmHWM (the kernel's own peak RSS per process, between samples too) is read
at the end. Worker RSS right after start-up vs at the end shows growth over a long job.

The /proc readings (`descendants`, `memory_kb`, `proc_name`) are bench/common.py's, shared
with bench/scaling.py.
"""

from __future__ import annotations

import argparse
import collections
import os
import resource
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

from common import descendants, job_simulator, job_specs, memory_kb, proc_name, strided


@dataclass
class ProcPeak:
    name: str
    rss: int = 0
    pss: int = 0
    hwm: int = 0
    first_rss: int = 0
    last_rss: int = 0


@dataclass
class TreeSampler:
    """Samples the memory of every process under `root` in a background thread."""

    root: int
    interval_s: float = 1.0
    procs: dict[int, ProcPeak] = field(default_factory=dict)
    peak_total_pss: int = 0
    peak_total_rss: int = 0
    samples: int = 0

    def __post_init__(self) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="mem-sampler", daemon=True)

    def start(self) -> TreeSampler:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()
        self.sample()  # a last one, and the kernel's peaks (VmHWM) of the survivors

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            self.sample()

    def sample(self) -> None:
        tot_pss = tot_rss = 0
        for pid in descendants(self.root):
            m = memory_kb(pid)
            if m is None:
                continue
            p = self.procs.get(pid)
            if p is None:
                p = self.procs[pid] = ProcPeak(proc_name(pid), first_rss=m["rss"])
            elif p.name.startswith("ray::IDLE") or p.name == "default_worker.py":
                p.name = proc_name(pid)  # an idle worker that became an actor
            p.rss, p.pss, p.hwm = max(p.rss, m["rss"]), max(p.pss, m["pss"]), max(p.hwm, m["hwm"])
            p.last_rss = m["rss"]
            tot_pss += m["pss"]
            tot_rss += m["rss"]
        self.peak_total_pss = max(self.peak_total_pss, tot_pss)
        self.peak_total_rss = max(self.peak_total_rss, tot_rss)
        self.samples += 1


def _mb(kb: int) -> str:
    return f"{kb / 1024:7.0f}"


# --- the job -----------------------------------------------------------------------------------


def run_job(
    backend: str, floor: str, speed: float, n: int | None, workers: int, interval_s: float
) -> dict[str, Any]:
    from comexp.results.store import ResultsDB
    from comexp.workers.driver import run_and_store
    from comexp.workers.kernel_cache import warm_kernel_cache
    from comexp.workers.pool import EpisodePool
    from comexp.workers.session import ensure_ray

    specs = job_specs(backend, floor, speed)
    if n is not None and n < len(specs):
        specs = strided(specs, n)
    sampler = TreeSampler(os.getpid(), interval_s).start()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="comexp-bench-mem-") as tmp:
        db = ResultsDB(os.path.join(tmp, "mem.db"))
        try:
            sweep = db.start_sweep(command_line="bench/memory.py")
            simulator = job_simulator(backend, floor, speed)  # the job's physics
            # as `comexp` does: the kernels in a child while Ray starts
            warm_kernel_cache(simulator, specs[0], meanwhile=lambda: ensure_ray(None, workers))
            pool = EpisodePool(simulator, workers)
            with pool:
                worker_pids = [
                    ray_get(s.actor.ready.remote())["pid"]
                    for s in pool._slots  # noqa: SLF001 - bench: which processes are ours
                ]
                sampler.sample()
                start_rss = {pid: (memory_kb(pid) or {"rss": 0})["rss"] for pid in worker_pids}
                stats = run_and_store(pool, specs, lambda rs: db.add_results(sweep, rs))
                sampler.sample()
                end_rss = {pid: (memory_kb(pid) or {"rss": 0})["rss"] for pid in worker_pids}
        finally:
            db.close()
            sampler.stop()
    return {
        "backend": backend,
        "episodes": len(specs),
        "workers": workers,
        "elapsed_s": time.perf_counter() - t0,
        "stats": stats,
        "sampler": sampler,
        "worker_pids": worker_pids,
        "start_rss": start_rss,
        "end_rss": end_rss,
        "driver_maxrss_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
    }


def ray_get(ref: Any) -> Any:
    import ray

    return ray.get(ref)


def report(o: dict[str, Any]) -> None:
    s: TreeSampler = o["sampler"]
    st = o["stats"]
    print(
        f"== memory: {o['backend']} {o['episodes']} episodes on {o['workers']} workers, "
        f"{o['elapsed_s']:.0f} s, {st.failed} failed, {s.samples} samples"
    )
    if st.failures:
        print(f"failures: {', '.join(f'{k} {v}' for k, v in st.failures.most_common())}")
    print(f"load: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} (1, 5 min)")
    print(f"{'process':<34}{'pid':>8}{'peak RSS':>10}{'VmHWM':>8}{'peak PSS':>10}  MB")
    me = os.getpid()
    rows = sorted(s.procs.items(), key=lambda kv: (kv[0] != me, kv[0] not in o["worker_pids"]))
    groups: collections.Counter[str] = collections.Counter()
    for pid, p in rows:
        if p.hwm < 20 * 1024 and pid != me and pid not in o["worker_pids"]:
            groups["small (<20 MB each)"] += p.pss
            continue
        role = "driver" if pid == me else ("worker" if pid in o["worker_pids"] else "ray")
        print(f"{role + ' ' + p.name:<34.34}{pid:>8}{_mb(p.rss)}  {_mb(p.hwm)}{_mb(p.pss)}")
        groups[role] += p.pss
    for g, v in groups.items():
        if g.startswith("small"):
            print(f"{g:<42}{'':>18}{_mb(v)}")
    print(
        f"peak total over the tree: PSS {s.peak_total_pss / 1024:.0f} MB "
        f"(RSS sum {s.peak_total_rss / 1024:.0f} MB, double-counts shared pages)"
    )
    print(f"driver ru_maxrss {o['driver_maxrss_kb'] / 1024:.0f} MB")
    for pid in o["worker_pids"]:
        a, b = o["start_rss"].get(pid, 0), o["end_rss"].get(pid, 0)
        print(f"worker {pid}: RSS after start {a / 1024:.0f} MB, at the end {b / 1024:.0f} MB")


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--backend", choices=("pybullet", "mujoco"), default="pybullet")
    ap.add_argument("--floor", choices=("iso", "aniso"), default="iso")
    ap.add_argument("--speed", type=float, default=40.0)
    ap.add_argument("--episodes", type=int, help="a strided slice of the job (default: all)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--interval", type=float, default=1.0, help="sampling period, s")
    a = ap.parse_args(argv)
    report(run_job(a.backend, a.floor, a.speed, a.episodes, a.workers, a.interval))
    return 0


if __name__ == "__main__":
    sys.exit(main())
