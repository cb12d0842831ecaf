"""How often the turn seen at each tracked frame of a push has the sign of the true lever arm
(P - G) x N, against the net turn's: the evidence behind `estimator.method=motion`
(docs/method.md). Runs a job's episodes in this process with the `magnitude` estimator
(no floor model: it chooses the pushes), collects every push's path, and prints, per floor
condition and pusher friction, the share of pushes whose turn (beyond a threshold) has the
lever arm's sign, for the net turn and for frames 0-3 after the impact.

    .venv/bin/python bench/motion_signs.py --backend planar --floor aniso --episodes 160
"""

from __future__ import annotations

import argparse
import math
import sys
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from episode_profile import job_backend_options, job_specs  # noqa: E402

from comexp.experiment import episode as ep  # noqa: E402
from comexp.experiment.simulator import make_simulator  # noqa: E402
from comexp.method.estimator import ComEstimator  # noqa: E402


class _Logger(ComEstimator):
    last: _Logger | None = None

    def __init__(self, *a, **k):
        a = list(a)
        a[4] = replace(a[4], method="magnitude", mag_floor_model=False)
        super().__init__(*a, **k)
        self.paths: list = []
        _Logger.last = self

    def observe_path(self, path):
        self.paths.append(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="planar")
    ap.add_argument("--floor", default="aniso")
    ap.add_argument("--speed", type=float, default=40.0)
    ap.add_argument("--episodes", type=int, default=160)
    args = ap.parse_args()
    specs = job_specs(args.backend, args.floor, args.speed, ["grid.coms_per_object=1"])
    specs = specs[:: max(1, len(specs) // args.episodes)][: args.episodes]
    sim = make_simulator(args.backend, **job_backend_options(args.backend, args.floor, args.speed))
    ep.make_estimator = lambda *a, **k: _Logger(*a, **k)
    rows = []
    for spec in specs:
        res = ep.run_episode(spec, sim)
        if res.status != "ok" or _Logger.last is None:
            continue
        G = np.array(spec.com_cm) / 100
        for rec, path in zip(res.pushes, _Logger.last.paths, strict=False):
            r = np.array([rec.contact_x_cm, rec.contact_y_cm]) / 100 - G
            lev = r[0] * rec.dir_y - r[1] * rec.dir_x
            rel = path.relative()
            frames = [
                math.degrees(y)
                for t, y in zip(rel[1:-1, 0], rel[1:-1, 3], strict=True)
                if t - path.t_contact_s >= 0.003
            ]
            key = (spec.mu_floor_x, spec.mu_floor_y, spec.mu_pusher)
            rows.append((key, lev, rec.rotation_deg, frames))
    print(f"{len(rows)} pushes of {len(specs)} episodes")
    for name, pick, thr in [("net", lambda r: r[2], 1.0)] + [
        (f"frame {i}", (lambda r, i=i: r[3][i] if len(r[3]) > i else None), t)
        for i in range(4)
        for t in (0.3, 1.0)
    ]:
        agree: dict = defaultdict(lambda: [0, 0])
        for r in rows:
            v = pick(r)
            if v is None or abs(v) <= thr or abs(r[1]) < 1e-4:
                continue
            for k in (r[0], "all"):
                agree[k][0] += int(np.sign(v) == np.sign(r[1]))
                agree[k][1] += 1
        cells = ", ".join(
            f"{k}: {a / b:.3f} of {b}" for k, (a, b) in sorted(agree.items(), key=str)
        )
        print(f"{name} (|turn| > {thr} deg): {cells}")


if __name__ == "__main__":
    main()
