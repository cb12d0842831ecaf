"""CPU time per episode of `paper`, `magnitude` and `motion` on the same episodes, in one
process (each episode run with each method in turn, after one warm-up episode), and the part
spent in the estimator (`next_push`, `observe`, `observe_path`). docs/method.md quotes it.

    .venv/bin/python bench/motion_cost.py --backend planar --floor aniso --episodes 16
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from episode_profile import job_backend_options, job_specs  # noqa: E402

from comexp.experiment import episode as ep  # noqa: E402
from comexp.experiment.simulator import make_simulator  # noqa: E402

METHODS = ("paper", "magnitude", "motion")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="planar")
    ap.add_argument("--floor", default="aniso")
    ap.add_argument("--speed", type=float, default=40.0)
    ap.add_argument("--episodes", type=int, default=16)
    args = ap.parse_args()
    specs = job_specs(args.backend, args.floor, args.speed, ["grid.coms_per_object=1"])
    specs = specs[:: max(1, len(specs) // args.episodes)][: args.episodes]
    sim = make_simulator(args.backend, **job_backend_options(args.backend, args.floor, args.speed))
    make = ep.make_estimator
    spent = [0.0]

    def timed(*a, **k):
        est = make(*a, **k)
        for name in ("next_push", "observe", "observe_path"):
            f = getattr(est, name, None)
            if f is None:
                continue

            def wrap(*aa, _f=f, **kk):
                t = time.process_time()
                try:
                    return _f(*aa, **kk)
                finally:
                    spent[0] += time.process_time() - t

            setattr(est, name, wrap)
        return est

    ep.make_estimator = timed
    total = dict.fromkeys(METHODS, 0.0)
    in_est = dict.fromkeys(METHODS, 0.0)
    ep.run_episode(specs[0], sim)  # compile and warm up
    for spec in specs:
        for m in METHODS:
            s = replace(spec, estimator=replace(spec.estimator, method=m))
            spent[0] = 0.0
            t = time.process_time()
            ep.run_episode(s, sim)
            total[m] += time.process_time() - t
            in_est[m] += spent[0]
    n = len(specs)
    for m in METHODS:
        print(
            f"{m:10s} CPU s/episode {total[m] / n:.3f}  estimator {in_est[m] / n:.3f}  "
            f"ratio to paper {total[m] / total['paper']:.2f}"
        )


if __name__ == "__main__":
    main()
