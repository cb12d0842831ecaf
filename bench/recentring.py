"""How often 5-push episodes leave the view on the mu 0.1 floor at 40 cm/s, with and without
the episode protocol's re-centring (EpisodeSpec.recenter_beyond_cm).

    .venv/bin/python bench/recentring.py [--backend pybullet|mujoco] [--coms 2]
"""

from __future__ import annotations

import argparse
import collections
import dataclasses

import numpy as np

from comexp.experiment.episode import EpisodeSpec, run_episode
from comexp.experiment.objects import com_points, load_objects
from comexp.experiment.simulator import make_simulator


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", choices=["pybullet", "mujoco"], default="pybullet")
    ap.add_argument("--coms", type=int, default=2)
    args = ap.parse_args()
    sim = make_simulator(args.backend)
    print("| recenter_beyond_cm | ok | failures | re-centred episodes | mean error cm |")
    print("|---|---|---|---|---|")
    for recenter in (0.0, 10.0):
        outcomes: collections.Counter[str] = collections.Counter()
        errors, recentred = [], 0
        for obj in load_objects().values():
            for k, com in enumerate(com_points(obj, args.coms)):
                spec = EpisodeSpec.for_object(
                    obj,
                    k,
                    com,
                    backend=args.backend,
                    floor="iso",
                    mu_floor_x=0.1,
                    mu_floor_y=0.1,
                    mu_pusher=1.0,
                    speed_cm_s=40.0,
                    izz_scale=1.0,
                    seed=k,
                )
                r = run_episode(dataclasses.replace(spec, recenter_beyond_cm=recenter), sim)
                outcomes[r.failure or "ok"] += 1
                recentred += "re-centred" in r.detail
                if r.error_cm is not None:
                    errors.append(r.error_cm)
        fails = ", ".join(f"{k}: {v}" for k, v in sorted(outcomes.items()) if k != "ok") or "0"
        print(
            f"| {recenter:g} | {outcomes['ok']} | {fails} | {recentred} | {np.mean(errors):.3f} |"
        )
    sim.close()


if __name__ == "__main__":
    main()
