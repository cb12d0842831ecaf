"""How far the identity slice's results move under a rounding-level change: the episodes of a
`bench/identity_check.py` measurement re-run in this process, compared with its stored rows.

    .venv/bin/python bench/rounding_noise.py before.json                      # as is
    .venv/bin/python bench/rounding_noise.py before.json --numpy-icp          # numpy ICP
    .venv/bin/python bench/rounding_noise.py before.json --numpy-icp --nudge  # + 1 ulp

`--numpy-icp` runs the tracking frames through `PoseTracker._icp` (numpy, lstsq), as before the
ICP kernel; `--nudge` moves every push's start point by one ulp in x (~1e-18 m), a change no
result should depend on. Printed: episodes whose status, failure, push choices or decisions
differ, and the largest |difference| of the rotations (deg) and of the CoM estimate and error
(cm). With the code of the measurement and neither option the re-run is exact (0 everywhere).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from comexp.experiment.episode import EpisodeSpec, EstimatorSettings, run_episode
from comexp.experiment.simulator import make_simulator
from comexp.method.perception import PoseTracker


def spec_of(row: dict) -> EpisodeSpec:
    """The `EpisodeSpec` of a stored episode row (its `spec` column)."""
    sp = json.loads(row["spec"])
    est = sp["estimator"]
    sp["estimator"] = EstimatorSettings(**{**est, "w": tuple(est["w"])})
    sp["outline_cm"] = tuple(tuple(p) for p in sp["outline_cm"])
    sp["com_cm"] = tuple(sp["com_cm"])
    return EpisodeSpec(**sp)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("measurement", type=Path, help="a bench/identity_check.py --out file")
    ap.add_argument("--numpy-icp", action="store_true", help="tracking frames by _icp")
    ap.add_argument("--nudge", action="store_true", help="every push's start x + 1 ulp")
    args = ap.parse_args()
    rows = json.loads(args.measurement.read_text())["rows"]
    if args.numpy_icp:

        def numpy_icp(self, q, yaw0, t0, max_iter, tol_rad, tol_m):
            return self._icp(q, yaw0, t0, max_iter=max_iter, tol_rad=tol_rad, tol_m=tol_m)

        PoseTracker._icp_fast = numpy_icp
    backends = {r["backend"] for r in rows.values()}
    if len(backends) != 1:
        print(f"error: one backend per measurement, found {sorted(backends)}", file=sys.stderr)
        return 2
    sim = make_simulator(backends.pop())
    if args.nudge:
        push = sim.push

        def nudged(cmd, **kw):
            x, y = cmd.start_xy_m
            return push(replace(cmd, start_xy_m=(float(np.nextafter(x, np.inf)), y)), **kw)

        sim.push = nudged
    worst = dict.fromkeys(
        ("rotation_deg", "rotation_true_deg", "est_com_x_cm", "est_com_y_cm", "error_cm"), 0.0
    )
    other = 0
    for _key, row in sorted(rows.items()):
        r = run_episode(spec_of(row), sim)
        mine = [(p.contact_x_cm, p.contact_y_cm, p.dir_x, p.dir_y, p.decision) for p in r.pushes]
        theirs = [
            (p["contact_x_cm"], p["contact_y_cm"], p["dir_x"], p["dir_y"], p["decision"])
            for p in row["pushes"]
        ]
        if (r.status, r.failure, mine) != (row["status"], row["failure"], theirs):
            other += 1
            continue
        for p, q in zip(r.pushes, row["pushes"], strict=True):
            for col in ("rotation_deg", "rotation_true_deg"):
                worst[col] = max(worst[col], abs(getattr(p, col) - q[col]))
        if r.est_com_cm is not None:
            worst["est_com_x_cm"] = max(
                worst["est_com_x_cm"], abs(r.est_com_cm[0] - row["est_com_x_cm"])
            )
            worst["est_com_y_cm"] = max(
                worst["est_com_y_cm"], abs(r.est_com_cm[1] - row["est_com_y_cm"])
            )
            worst["error_cm"] = max(worst["error_cm"], abs(r.error_cm - row["error_cm"]))
    opts = " ".join(o for o, on in (("--numpy-icp", args.numpy_icp), ("--nudge", args.nudge)) if on)
    print(
        f"{len(rows)} episodes ({opts or 'as is'}): {other} differ in status, failure, push "
        "choice or decision; max |difference| "
        + ", ".join(f"{c} {d:.3g}" for c, d in worst.items())
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
