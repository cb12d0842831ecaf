"""Results identical across a refactoring: the episode keys of a job's grid and the stored rows
of a small slice that really runs (through the `comexp` command, Ray and the database).

    .venv/bin/python bench/identity_check.py --out before.json        # on the old commit
    .venv/bin/python bench/identity_check.py --compare before.json    # on the new one

`keys`: every `episode_key` of the default job (floor=iso speed=40 backend=pybullet, 1,600
episodes) over the expanded grid, computed without running anything. `rows`: a 40-episode
planar slice (2 objects x 5 CoMs x 2 floors x 2 pusher frictions, Izz x1) run by the `comexp`
command into a fresh SQLite file, every episode and push column except what differs from run
to run (ids, timestamps, wall time, the worker's pid, the sweep id). Exit 1 when anything differs.

    .venv/bin/python bench/identity_check.py --compare before.json --float-tol 1e-6

"The same up to rounding": float columns may differ by at most `--float-tol` (their units:
cm, deg, s, unit vectors); the largest |difference| per float column is printed. Any other
column (a decision, a failure, a count, a string) must be equal. `--now after.json` compares
with a measurement written before instead of running one.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import json
import os
import sqlite3
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

SLICE = [
    "backend=planar",
    "grid.objects=[rect_8x5,l_shape]",
    "grid.coms_per_object=5",
    "grid.izz_scales=[1]",
    "workers=2",
]
# columns that differ between two runs of the same episodes
VOLATILE_EPISODE = {"id", "sweep_id", "wall_s", "created_at", "worker"}
VOLATILE_PUSH = {"id", "episode_id"}


def default_job_keys(overrides: list[str]) -> list[str]:
    """The episode keys of one job's grid, in grid order (nothing runs)."""
    from hydra import compose, initialize_config_module

    # the layout by concern first, then the flat one before it (b32f6b0)
    for config, grid, identity in (
        ("comexp.experiment.config", "comexp.experiment.grid", "comexp.results.identity"),
        ("comexp.experiment.config", "comexp.experiment.grid", "comexp.results.store"),
        ("comexp.config", "comexp.grid", "comexp.db"),
    ):
        try:
            prepare_job = importlib.import_module(config).prepare_job
            expand_grid = importlib.import_module(grid).expand_grid
            episode_key = importlib.import_module(identity).episode_key
            break
        except ImportError:
            continue
    else:
        raise SystemExit("cannot find comexp's config, grid and episode identity modules")

    with initialize_config_module("comexp.conf", version_base="1.3"):
        cfg = compose("config", overrides=overrides, return_hydra_config=True)
    job = prepare_job(cfg)
    return [episode_key(s) for s in expand_grid(job.cfg, job.objects, estimator=job.estimator)]


def slice_rows(workdir: Path) -> dict[str, Any]:
    """Run the slice with the `comexp` command; the stored rows keyed by episode_key."""
    db = workdir / "slice.db"
    cmd = [
        sys.executable,
        "-c",
        "import sys; from importlib.metadata import entry_points;"
        "sys.argv[0] = 'comexp';"
        "(ep,) = [e for e in entry_points(group='console_scripts') if e.name == 'comexp'];"
        "ep.load()()",
        *SLICE,
        f"db={db}",
        f"hydra.run.dir={workdir / 'run'}",
    ]
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    res = subprocess.run(cmd, cwd=workdir, capture_output=True, text=True, env=env)
    if res.returncode != 0:
        raise SystemExit(f"comexp failed ({res.returncode}):\n{res.stderr[-3000:]}")
    con = sqlite3.connect(db)
    con.row_factory = sqlite3.Row
    episodes: dict[str, Any] = {}
    for r in con.execute("SELECT * FROM episodes ORDER BY id"):
        d = {k: r[k] for k in r.keys() if k not in VOLATILE_EPISODE}  # noqa: SIM118 - a Row
        pushes = con.execute("SELECT * FROM pushes WHERE episode_id = ? ORDER BY k", (r["id"],))
        d["pushes"] = [
            {k: p[k] for k in p.keys() if k not in VOLATILE_PUSH}  # noqa: SIM118 - a Row
            for p in pushes.fetchall()
        ]
        episodes[r["episode_key"]] = d
    con.close()
    return episodes


def measure() -> dict[str, Any]:
    keys = default_job_keys([])
    with tempfile.TemporaryDirectory(prefix="comexp-identity-") as tmp:
        rows = slice_rows(Path(tmp))
    return {
        "keys": {
            "n": len(keys),
            "distinct": len(set(keys)),
            "sha256": hashlib.sha256("\n".join(keys).encode()).hexdigest(),
            "list": keys,
        },
        "rows": rows,
    }


def compare(
    old: dict[str, Any],
    new: dict[str, Any],
    float_tol: float | None = None,
    worst: dict[str, float] | None = None,
) -> list[str]:
    """What differs; with `float_tol`, float columns count only beyond it (their largest
    |difference| collected into `worst`)."""
    worst = {} if worst is None else worst
    diffs = []
    if old["keys"]["list"] != new["keys"]["list"]:
        a, b = set(old["keys"]["list"]), set(new["keys"]["list"])
        diffs.append(
            f"default job keys differ: {len(a - b)} only before, {len(b - a)} only after"
            f" (order equal: {old['keys']['list'] == new['keys']['list']})"
        )
    ro, rn = old["rows"], new["rows"]
    if set(ro) != set(rn):
        diffs.append(f"slice episodes differ: {len(set(ro) ^ set(rn))} keys in one run only")
    for key in sorted(set(ro) & set(rn)):
        if ro[key] == rn[key]:
            continue
        if float_tol is None:
            cols = sorted(c for c in ro[key] if ro[key].get(c) != rn[key].get(c))
            diffs.append(f"episode {key[:12]}: {', '.join(cols)} differ")
            continue
        hard = _float_differences(ro[key], rn[key], worst, "")
        bad = hard + sorted(c for c, d in worst.items() if d > float_tol)
        if bad:
            diffs.append(f"episode {key[:12]}: {', '.join(sorted(set(bad)))} differ")
    return diffs


def _float_differences(a: dict, b: dict, worst: dict[str, float], prefix: str) -> list[str]:
    """Record the largest |a - b| of every float column in `worst` (pushes as "pushes.col");
    return the columns that differ otherwise (not floats, or a different number of pushes)."""
    hard = []
    for col in sorted(set(a) | set(b)):
        x, y = a.get(col), b.get(col)
        name = prefix + col
        if col == "pushes" and isinstance(x, list) and isinstance(y, list):
            if len(x) != len(y):
                hard.append("pushes (number)")
            for p, q in zip(x, y, strict=False):
                hard += _float_differences(p, q, worst, "pushes.")
        elif isinstance(x, float) and isinstance(y, float):
            worst[name] = max(worst.get(name, 0.0), abs(x - y))
        elif x != y:
            hard.append(name)
    return hard


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--out", type=Path, help="write the measurement (JSON)")
    g.add_argument("--compare", type=Path, help="compare with a measurement written before")
    p.add_argument("--float-tol", type=float, help="float columns may differ by this much")
    p.add_argument("--now", type=Path, help="with --compare: this measurement, not a new run")
    args = p.parse_args()
    if args.now and not args.compare:
        p.error("--now needs --compare")
    now = json.loads(args.now.read_text()) if args.now else measure()
    n_pushes = sum(len(r["pushes"]) for r in now["rows"].values())
    print(
        f"default job: {now['keys']['n']} episode keys ({now['keys']['distinct']} distinct), "
        f"sha256 {now['keys']['sha256'][:16]}; slice: {len(now['rows'])} episodes, "
        f"{n_pushes} pushes stored"
    )
    if args.out:
        args.out.write_text(json.dumps(now, indent=1, sort_keys=True))
        print(f"written: {args.out}")
        return 0
    worst: dict[str, float] = {}
    diffs = compare(json.loads(args.compare.read_text()), now, args.float_tol, worst)
    if args.float_tol is not None:
        for col, d in sorted(worst.items()):
            print(f"  max |difference| {col}: {d:.3g}")
    for d in diffs:
        print(d)
    same = "identical" if args.float_tol is None else f"identical up to {args.float_tol:g}"
    print(same if not diffs else f"{len(diffs)} difference(s)")
    return 1 if diffs else 0


if __name__ == "__main__":
    sys.exit(main())
