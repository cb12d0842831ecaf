"""`comexp-ray`: a local Ray kept running between jobs, on request.

    comexp-ray start [--cpus N]   # a Ray for the next jobs on this machine (default 2 CPUs)
    comexp-ray status             # is one running, where, for which comexp
    comexp-ray stop               # end it, and every worker it holds

While it runs, every `comexp` job and `comexp.run` call with a local Ray (`ray.address` null)
uses it instead of starting a Ray of its own, and leaves its workers running in it, warm, for
the next job of the same backend and physics: a small job then takes about a second instead of
several (docs/performance.md, "The fixed cost of a job"). Nothing else keeps running after a
command; `ray.address=local` gives a job a Ray of its own all the same.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

from comexp.workers import kept


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="comexp-ray", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    start = sub.add_parser("start", help="start a Ray that the next jobs use")
    start.add_argument("--cpus", type=int, default=2, help="CPUs it offers (workers, 2)")
    sub.add_parser("status", help="say whether one runs")
    sub.add_parser("stop", help="end it and its workers")
    args = ap.parse_args(argv)
    if args.command == "start":
        if args.cpus < 1:
            return _error(f"--cpus must be >= 1, got {args.cpus}")
        try:
            ray = kept.start(args.cpus)
        except RuntimeError as e:
            return _error(str(e))
        print(
            f"a Ray for comexp jobs runs at {ray.address} with {ray.cpus} CPUs (pid {ray.pid}, "
            f"temp dir {ray.temp_dir}); it keeps running, and the jobs' workers in it, "
            "until `comexp-ray stop`"
        )
        return 0
    if args.command == "status":
        ray, why = kept.load()
        if ray is None:
            print(why or "no kept Ray: each job starts a Ray of its own")
            return 0 if why is None else 1
        print(f"a kept Ray runs at {ray.address} with {ray.cpus} CPUs (pid {ray.pid}, since "
              f"{ray.started}); `comexp-ray stop` ends it")  # fmt: skip
        return 0
    ray = kept.stop()
    print("no kept Ray was running" if ray is None else f"stopped the kept Ray (pid {ray.pid})")
    return 0


def _error(message: str) -> int:
    print(f"comexp-ray: error: {message}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    sys.exit(main())
