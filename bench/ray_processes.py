"""Which processes Ray starts for comexp, and their memory (PSS), idle, after start-up.

    .venv/bin/python bench/ray_processes.py                          # a local job's Ray
    .venv/bin/python bench/ray_processes.py --address HOST:PORT      # comexp's join node
    .venv/bin/python bench/ray_processes.py --address HOST:PORT --plain
        # the same zero-CPU node with `ray start`'s defaults (log monitor, 30 % RAM store)

Local: `ensure_ray(None, 2)` as a job starts it; Ray's processes are the driver's
descendants. Join: `ensure_ray(HOST:PORT)` (workers/session.py `JoinNode`), or with --plain a
bare `ray start --address=HOST:PORT --num-cpus=0 --block`; its processes are that session's.
PSS (from /proc/PID/smaps_rollup) shares out pages that processes have in common, so the
column sums to the real footprint; the figure is the mean of 3 samples 1 s apart, taken
`--settle-s` after start-up.
"""

from __future__ import annotations

import argparse
import collections
import os
import subprocess
import sys
import tempfile
import time

from memory import descendants, memory_kb, proc_name

os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")


def session_pids(sid: int) -> list[int]:
    out = []
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat") as f:
                stat = f.read()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[3]) == sid:  # state ppid pgrp session
            out.append(int(name))
    return out


def sample(pids_fn, n: int = 3) -> dict[str, list[int]]:
    """name -> PSS (kB) per process of that name, averaged over `n` samples."""
    acc: dict[int, list[int]] = collections.defaultdict(list)
    names: dict[int, str] = {}
    for i in range(n):
        for pid in pids_fn():
            m = memory_kb(pid)
            if m is None or m["pss"] == 0:
                continue
            acc[pid].append(m["pss"])
            names[pid] = proc_name(pid)
        if i < n - 1:
            time.sleep(1)
    out: dict[str, list[int]] = collections.defaultdict(list)
    for pid, v in acc.items():
        out[names[pid]].append(sum(v) // len(v))
    return out


def report(title: str, by_name: dict[str, list[int]]) -> None:
    print(title)
    total = 0
    for name, kbs in sorted(by_name.items(), key=lambda kv: -sum(kv[1])):
        total += sum(kbs)
        each = ", ".join(f"{k / 1024:.0f}" for k in kbs)
        print(f"  {name:28s} x{len(kbs)}  PSS {each} MB")
    print(f"  {'total':28s}      PSS {total / 1024:.0f} MB")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--address", help="HOST:PORT of a running Ray head (join mode)")
    ap.add_argument("--plain", action="store_true", help="bare `ray start --num-cpus=0`")
    ap.add_argument("--settle-s", type=float, default=8.0)
    args = ap.parse_args(argv)

    from comexp.workers import session

    if args.address is None:
        session.ensure_ray(None, 2)
        time.sleep(args.settle_s)
        me = os.getpid()
        by_name = sample(lambda: [p for p in descendants(me) if p != me])
        report("a local job's Ray (ensure_ray(None, 2)), idle", by_name)
        session.shutdown_ray()
        return
    if not args.plain:
        session.ensure_ray(args.address)
        node = session._join_node
        assert node is not None
        time.sleep(args.settle_s)
        by_name = sample(lambda: session_pids(node.proc.pid))
        report(f"comexp's join node ({' '.join(node.proc.args[3:])})", by_name)
        session.shutdown_ray()
        return
    temp_dir = tempfile.mkdtemp(prefix="comexp-join-", dir=tempfile.gettempdir())
    cmd = [sys.executable, "-m", "ray.scripts.scripts", "start", f"--address={args.address}"]
    cmd += ["--num-cpus=0", f"--temp-dir={temp_dir}", "--disable-usage-stats", "--block"]
    p = subprocess.Popen(
        cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
    )
    try:
        time.sleep(args.settle_s)
        by_name = sample(lambda: session_pids(p.pid))
        report(f"plain `ray start {' '.join(cmd[4:])}`", by_name)
    finally:
        session.JoinNode(p, temp_dir).stop()


if __name__ == "__main__":
    main()
