"""The notebook path and re-running one episode: `comexp.load_results`, `comexp.replay` and
`comexp-db show`, on a real one-episode pybullet job (a few seconds, most of it Ray start)."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from test_cli import comexp_in_process
from test_db import make_result

import comexp as package
from comexp.cli.query import main as dbcli
from comexp.method.estimator import EstimatorSettings
from comexp.results.identity import canonical_json, episode_key, spec_from_json
from comexp.results.plots import reconstruct_regions
from comexp.results.reports import condition_tables
from comexp.results.store import ResultsDB

README = Path(__file__).resolve().parents[1] / "README.md"
TINY = [
    "grid.objects=[square_7]",
    "grid.coms_per_object=1",
    "grid.izz_scales=[1]",
    "pusher.mu=[1.0]",
    "floor.mu=[0.1]",
    "workers=1",
]


@pytest.fixture(scope="module")
def job_db(tmp_path_factory: pytest.TempPathFactory, local_ray) -> Path:
    """The job through the command's own `main()`, in this process, on the module's Ray
    (the installed script runs real jobs in test_notebook_run.py and test_postgres.py)."""
    work = tmp_path_factory.mktemp("job")
    r = comexp_in_process(work, *TINY, "db=job.db")
    assert r.returncode == 0, r.stderr
    return work / "job.db"


def test_replay_equals_the_stored_episode(job_db: Path) -> None:
    with ResultsDB(job_db, readonly=True) as db:
        (row,) = db.episodes()
        stored_pushes = db.pushes(row["id"])
        result = package.replay(db, row["id"])
    assert row["seed"] != 0  # the grid's per-(object, CoM) seed, not for_object's default
    assert result.spec.seed == row["seed"] and episode_key(result.spec) == row["episode_key"]
    assert (result.status, result.failure) == (row["status"], row["failure"])
    assert result.error_cm == row["error_cm"]
    assert result.est_com_cm == (row["est_com_x_cm"], row["est_com_y_cm"])
    assert result.n_pushes == row["n_pushes"] == len(stored_pushes) > 0
    for mine, theirs in zip(result.pushes, stored_pushes, strict=True):
        for f in dataclasses.fields(mine):
            stored = theirs[f.name]
            if f.name == "region_cm":  # stored as JSON
                stored = tuple(tuple(v) for v in json.loads(stored))
            assert getattr(mine, f.name) == stored, f.name
    # by path too, and a missing id is one clear error
    assert package.replay(job_db, row["id"]).error_cm == row["error_cm"]
    with pytest.raises(ValueError, match=r"no episode with id 99 \(stored ids 1..1\)"):
        package.replay(job_db, 99)


def test_replay_runs_a_native_episode_with_native_friction(tmp_path: Path) -> None:
    """`backend.floor_friction` is in the physics identity only as a hash: replay must find
    it, or a `native` episode re-runs with the model's friction (the bug this catches)."""
    from comexp.backends.physics_settings import physics_identity
    from comexp.episode.loop import run_episode
    from comexp.episode.task import EpisodeSpec
    from comexp.experiment.config import make_simulator
    from comexp.experiment.objects import load_objects

    obj = load_objects()["square_7"]
    spec = EpisodeSpec.for_object(
        obj,
        0,
        (0.8, -0.5),
        backend="pybullet",
        floor="iso",
        mu_floor_x=0.1,
        mu_floor_y=0.1,
        mu_pusher=1.0,
        speed_cm_s=40.0,
        izz_scale=1.0,
        camera_fps=0.0,
        estimator=EstimatorSettings(n_push=2),
        physics=physics_identity(
            "pybullet",
            "comexp.backends.pybullet_sim.PybulletSimulator",
            options={"floor_friction": "native", "renderer": "raycast"},
        ),
    )
    with make_simulator("pybullet", floor_friction="native") as sim:
        native = run_episode(spec, sim)
    with make_simulator("pybullet") as sim:
        model = run_episode(spec, sim)
    assert native.status == model.status == "ok"
    # the two frictions turn the object differently: the test can tell them apart
    assert [p.rotation_true_deg for p in native.pushes] != [
        p.rotation_true_deg for p in model.pushes
    ]
    with ResultsDB(tmp_path / "n.db") as db:
        db.add_results(None, [native])
        (row,) = db.episodes()
        again = package.replay(db, row["id"])
    assert [p.rotation_true_deg for p in again.pushes] == [
        p.rotation_true_deg for p in native.pushes
    ]
    assert again.est_com_cm == native.est_com_cm
    # physics this comexp does not have is refused, not run with other physics
    stale = dataclasses.replace(native, spec=dataclasses.replace(spec, physics="pybullet/old"))
    with ResultsDB(tmp_path / "s.db") as db:
        db.add_results(None, [stale])
        (row,) = db.episodes()
        with pytest.raises(ValueError, match="cannot replay it"):
            package.replay(db, row["id"])


def test_spec_round_trips_through_the_stored_json(tmp_path: Path) -> None:
    est = EstimatorSettings(w=(2.0, 0.25), rotation_source="oracle", d_metric="distance_px")
    r = make_result(estimator=est, izz_scale=10.0)
    with ResultsDB(tmp_path / "s.db") as db:
        db.add_results(None, [r])
        (row,) = db.episodes()
    spec = spec_from_json(row["spec"])
    assert spec == r.spec and isinstance(spec.estimator, EstimatorSettings)
    assert spec.estimator.w == (2.0, 0.25) and isinstance(spec.outline_cm[0], tuple)
    assert episode_key(spec) == row["episode_key"]
    with pytest.raises(ValueError, match="fields this comexp does not know: warp"):
        spec_from_json(canonical_json({**dataclasses.asdict(r.spec), "warp": 9}))


def test_load_results_gives_dataframes_grouped_like_the_tables(tmp_path: Path) -> None:
    oracle = EstimatorSettings(rotation_source="oracle")
    results = [make_result(com_index=i, error_cm=0.1 * (i + 1)) for i in range(4)]
    results += [make_result(com_index=i, error_cm=2.0, estimator=oracle) for i in range(3)]
    path = tmp_path / "r.db"
    with ResultsDB(path) as db:
        db.add_results(db.start_sweep(job_name="j"), results)
        tables = condition_tables(db)
    df = package.load_results(path)
    assert isinstance(df, pd.DataFrame) and len(df) == 7
    assert {"error_cm", "speed_cm_s", "object", "condition", "condition_slug"} <= set(df.columns)
    means = df[df.status == "ok"].groupby("condition")["error_cm"].agg(["mean", "std", "count"])
    assert sorted(means.index) == sorted(t.condition.label() for t in tables)
    for t in tables:
        m = means.loc[t.condition.label()]
        assert m["count"] == t.overall.n and m["mean"] == pytest.approx(t.overall.mean)
        assert m["std"] == pytest.approx(t.overall.std)  # pandas' std is ddof=1 too
    pushes = package.load_results(path, table="pushes")
    assert len(pushes) == 7 * 5 and {"episode_id", "rotation_deg"} <= set(pushes.columns)
    sweeps = package.load_results(path, "sweeps")
    assert list(sweeps["job_name"]) == ["j"]
    with pytest.raises(ValueError, match="unknown table 'runs'"):
        package.load_results(path, "runs")


def test_readme_notebook_example_runs(job_db: Path, tmp_path: Path, monkeypatch) -> None:
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    (block,) = [b for b in blocks if "load_results" in b]
    results = tmp_path / "results"
    results.mkdir()
    shutil.copy(job_db, results / "comexp.db")
    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(compile(block, "README.md", "exec"), scope)  # noqa: S102 - our own document
    assert isinstance(scope["df"], pd.DataFrame) and len(scope["df"]) == 1
    assert (tmp_path / "errors.png").read_bytes()[:4] == b"\x89PNG"


def test_show_draws_an_episode(job_db: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "episode.png"
    assert dbcli(["--db", str(job_db), "show", "1", "--out", str(out)]) == 0
    assert capsys.readouterr().out == f"{out}\n"
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000
    with ResultsDB(job_db, readonly=True) as db:
        row, pushes = db.episode(1), db.pushes(1)
    import json

    pixel_m, regions = reconstruct_regions(json.loads(row["spec"]), row["estimator"], pushes)
    assert len(regions) == len(pushes) + 1
    # the rebuilt region follows the stored one: sizes within a few pixels, and its final
    # centroid within two pixels of the stored estimate
    for region, p in zip(regions[1:], pushes, strict=True):
        assert abs(len(region) - p["region_px"]) <= max(5, 0.1 * p["region_px"])
    centroid_cm = regions[-1].mean(axis=0) * 100.0
    est = np.array([row["est_com_x_cm"], row["est_com_y_cm"]])
    assert math.dist(centroid_cm, est) < 2 * pixel_m * 100.0
