"""How often a push turns the object against the sign of its lever arm about the true CoM,
measured against the push line and against the force line of `floor_force_direction` with
several shares of the friction angle: the evidence behind `estimator.mag_floor_model`.

Reads a results database (no simulation); a push counts when it turned more than 1 deg. The
object's world yaw at each push is the seed's initial yaw plus the true rotations before it
(re-centring keeps the yaw).

    .venv/bin/python bench/force_lines.py --db results/comexp.db [--shares 0,0.5] [--by-pusher]
"""

from __future__ import annotations

import argparse
import math
import sqlite3
from collections import defaultdict

import numpy as np

from comexp.experiment.episode import initial_yaw_rad
from comexp.method.estimator import cross2, floor_force_direction


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--db", required=True, help="SQLite results file")
    ap.add_argument("--shares", default="0,0.25,0.3,0.5,0.6,1")
    ap.add_argument("--by-pusher", action="store_true", help="one row per pusher friction too")
    args = ap.parse_args()
    shares = [float(s) for s in args.shares.split(",")]
    con = sqlite3.connect(f"file:{args.db}?mode=ro", uri=True)
    eps = {
        r[0]: r[1:]
        for r in con.execute(
            "select id, seed, floor, mu_floor_x, mu_floor_y, mu_pusher, true_com_x_cm,"
            " true_com_y_cm from episodes where status = 'ok'"
        )
    }
    pushes = defaultdict(list)
    for r in con.execute(
        "select episode_id, contact_x_cm, contact_y_cm, dir_x, dir_y, rotation_deg,"
        " rotation_true_deg from pushes order by episode_id, k"
    ):
        pushes[r[0]].append(r[1:])
    counted: dict[tuple[str, float], list[int]] = defaultdict(lambda: [0, 0])
    for eid, (seed, floor, mux, muy, mup, gx, gy) in eps.items():
        yaw = initial_yaw_rad(seed)
        for cx, cy, dx, dy, rot, rot_true in pushes[eid]:
            if abs(rot) > 1.0:
                for share in shares:
                    line = floor_force_direction((dx, dy), yaw, mux, muy, mup, share=share)
                    lever = float(cross2(np.array([cx - gx, cy - gy]), line))
                    label = f"{floor}, pusher mu {mup:g}" if args.by_pusher else floor
                    c = counted[(label, share)]
                    c[0] += 1
                    c[1] += int(math.copysign(1.0, lever) != math.copysign(1.0, rot))
            yaw += math.radians(rot_true)
    print("| floor | share of the friction angle | pushes turning > 1 deg | wrong sign |")
    print("|---|---|---|---|")
    for (floor, share), (n, bad) in sorted(counted.items()):
        print(f"| {floor} | {share:g} | {n} | {bad} ({100.0 * bad / max(n, 1):.1f}%) |")


if __name__ == "__main__":
    main()
