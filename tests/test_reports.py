"""Aggregated tables (paper Tables II/III form), job reports and plots from a synthetic study."""

from __future__ import annotations

import csv
import dataclasses
import io
import itertools
import math
from pathlib import Path

import numpy as np
import pytest
from test_db import make_result

from comexp.db import EpisodeFilter, ResultsDB
from comexp.episode import EpisodeResult, EstimatorSettings
from comexp.plots import make_plots
from comexp.reports import (
    Condition,
    ErrorStats,
    condition_tables,
    natural_key,
    paper_markdown,
    paper_tables,
    summary_csv,
    table_markdown,
    tables_csv,
    write_job_reports,
)

OBJECTS = ("obj1", "obj2", "obj10")
FRICTIONS = (
    ("iso", 0.1, 0.1, 0.1),
    ("iso", 1.0, 1.0, 0.1),
    ("iso", 0.1, 0.1, 1.0),
    ("aniso", 0.1, 1.0, 0.5),
    ("aniso", 1.0, 0.1, 0.5),
)


def study_results(seed: int = 0) -> list[EpisodeResult]:
    """A small study: 3 objects x 3 CoMs x 2 Izz x 2 speeds x 5 frictions, a few failures."""
    rng = np.random.default_rng(seed)
    out = []
    for (floor, fx, fy, mp), speed, obj, com, izz in itertools.product(
        FRICTIONS, (40.0, 4.0), OBJECTS, range(3), (1.0, 10.0)
    ):
        failure = None
        if obj == "obj2" and com == 2 and izz == 10.0 and speed == 4.0:
            failure = "tipped" if floor == "iso" else "left_view"
        scale = 0.5 if speed == 40.0 else 1.5
        out.append(
            make_result(
                object=obj,
                com_index=com,
                floor=floor,
                mu_floor_x=fx,
                mu_floor_y=fy,
                mu_pusher=mp,
                speed_cm_s=speed,
                izz_scale=izz,
                error_cm=float(rng.gamma(2.0, scale / 2)),
                failure=failure,
            )
        )
    return out


@pytest.fixture
def study_db(tmp_path: Path):
    db = ResultsDB(tmp_path / "study.db")
    db.add_results(db.start_sweep(job_name="study"), study_results())
    yield db
    db.close()


def test_error_stats() -> None:
    s = ErrorStats.of([1.0, 2.0, 4.0])
    assert (s.n, s.mean, s.max, s.min) == (3, pytest.approx(7 / 3), 4.0, 1.0)
    assert s.std == pytest.approx(np.std([1.0, 2.0, 4.0]))
    empty = ErrorStats.of([])
    assert empty.n == 0 and math.isnan(empty.mean)
    assert sorted(["obj10", "obj2", "obj1"], key=natural_key) == ["obj1", "obj2", "obj10"]


def test_condition_tables_match_a_direct_computation(study_db: ResultsDB) -> None:
    tables = condition_tables(study_db)
    assert len(tables) == len(FRICTIONS) * 2
    rows = study_db.episodes()
    for t in tables:
        c = t.condition
        mine = [
            r
            for r in rows
            if (r["backend"], r["floor"], r["mu_floor_x"], r["mu_floor_y"], r["mu_pusher"])
            == (c.backend, c.floor, c.mu_floor_x, c.mu_floor_y, c.mu_pusher)
            and r["speed_cm_s"] == c.speed_cm_s
        ]
        assert len(mine) == 3 * 3 * 2
        assert [o for o, _, _ in t.rows] == list(OBJECTS)
        for obj, stats, n_failed in t.rows:
            errs = [r["error_cm"] for r in mine if r["object"] == obj and r["status"] == "ok"]
            assert stats.n == len(errs)
            assert stats.mean == pytest.approx(np.mean(errs))
            assert stats.std == pytest.approx(np.std(errs))
            assert (stats.max, stats.min) == (max(errs), min(errs))
            assert n_failed == sum(r["object"] == obj and r["status"] == "failed" for r in mine)
        ok = [r["error_cm"] for r in mine if r["status"] == "ok"]
        assert t.overall.n == len(ok) and t.overall.mean == pytest.approx(np.mean(ok))
        expected_failed = 1 if c.speed_cm_s == 4.0 else 0
        assert t.n_failed == expected_failed
        if expected_failed:
            reason = "tipped" if c.floor == "iso" else "left_view"
            assert t.failures == {reason: 1}
            assert f"1 failed episode(s) excluded: {reason} 1" in table_markdown(t)


def test_filtered_tables_and_csv(study_db: ResultsDB) -> None:
    tables = condition_tables(study_db, EpisodeFilter(floor="aniso", mu_floor_x=1.0, speed_cm_s=4))
    assert [t.condition for t in tables] == [Condition("pybullet", "aniso", 1.0, 0.1, 0.5, 4.0)]
    parsed = list(csv.DictReader(io.StringIO(tables_csv(tables))))
    assert [r["object"] for r in parsed] == [*OBJECTS, "all"]
    assert parsed[1]["n"] == "5" and parsed[1]["n_failed"] == "1"
    assert parsed[0]["mu_floor_x"] == "1" and parsed[0]["speed_cm_s"] == "4"
    assert float(parsed[-1]["mean"]) == pytest.approx(tables[0].overall.mean, abs=1e-6)
    summary = list(csv.DictReader(io.StringIO(summary_csv(tables))))
    assert summary == [
        {
            "backend": "pybullet",
            "floor": "aniso",
            "mu_floor_x": "1",
            "mu_floor_y": "0.1",
            "mu_pusher": "0.5",
            "speed_cm_s": "4",
            "n_ok": "17",
            "n_failed": "1",
            "mean": f"{tables[0].overall.mean:.6f}",
            "std": f"{tables[0].overall.std:.6f}",
            "max": f"{tables[0].overall.max:.6f}",
            "min": f"{tables[0].overall.min:.6f}",
            "failures": "left_view:1",
        }
    ]


def test_estimator_variants_are_not_pooled(tmp_path: Path) -> None:
    with ResultsDB(tmp_path / "v.db") as db:
        oracle = EstimatorSettings(rotation_source="oracle")
        db.add_results(
            None,
            [make_result(error_cm=1.0), make_result(error_cm=3.0, estimator=oracle)],
        )
        tables = condition_tables(db)
        assert sorted(t.overall.mean for t in tables) == [1.0, 3.0]
        assert all(
            "oracle" in t.condition.label() or "vision" in t.condition.label() for t in tables
        )
        assert len({t.condition.slug() for t in tables}) == 2
        (one,) = condition_tables(db, EpisodeFilter(rotation_source="oracle"))
        assert one.condition.estimator == "" and one.overall.mean == 3.0


def test_protocol_variants_are_not_pooled(tmp_path: Path) -> None:
    """Episodes with another push length or re-centring rule are another experiment."""
    with ResultsDB(tmp_path / "p.db") as db:
        base = make_result(error_cm=1.0)
        longer = dataclasses.replace(
            make_result(error_cm=3.0), spec=dataclasses.replace(base.spec, push_length_cm=5.0)
        )
        never = dataclasses.replace(
            make_result(error_cm=2.0), spec=dataclasses.replace(base.spec, recenter_beyond_cm=0.0)
        )
        assert db.add_results(None, [base, longer, never]) == 3
        tables = condition_tables(db)
        assert sorted(t.overall.mean for t in tables) == [1.0, 2.0, 3.0]
        assert {r["recenter_beyond_cm"] for r in db.episodes()} == {0.0, 10.0}


def test_paper_form_puts_speeds_side_by_side(study_db: ResultsDB) -> None:
    tables = paper_tables(study_db, EpisodeFilter(floor="iso"))
    assert list(tables) == [("pybullet", "iso")]
    by_speed = tables[("pybullet", "iso")]
    assert sorted(by_speed) == [4.0, 40.0]
    assert by_speed[40.0].overall.n == 3 * 3 * 2 * 3  # three iso friction pairs pooled
    assert by_speed[4.0].n_failed == 3
    text = paper_markdown(tables)
    header = next(line for line in text.splitlines() if line.startswith("| object"))
    assert header.index("mean @40") < header.index("mean @4 ")


def test_write_job_reports(study_db: ResultsDB, tmp_path: Path) -> None:
    out = tmp_path / "job"
    paths, text = write_job_reports(study_db, out, floor="iso", speed_cm_s=4.0)
    names = sorted(p.name for p in paths)
    assert len(names) == 3 * 2 + 2 and "summary.md" in names and "summary.csv" in names
    assert all(p.parent == out and p.stat().st_size > 0 for p in paths)
    assert "errors_pybullet_iso_fx1_fy1_p0.1_v4.md" in names
    assert len(text.splitlines()) == 3 and "1 failed" in text and "aniso" not in text
    summary = (out / "summary.md").read_text()
    assert summary.count("### ") == 3 and "tipped 1" in summary
    empty_paths, empty_text = write_job_reports(study_db, tmp_path / "none", backend="mujoco")
    assert "no episodes" in empty_text and len(empty_paths) == 2


def test_plots_write_pngs(study_db: ResultsDB, tmp_path: Path) -> None:
    paths = make_plots(study_db, tmp_path / "plots")
    names = sorted(p.name for p in paths)
    assert names == [
        "error_per_object_pybullet_aniso.png",
        "error_per_object_pybullet_iso.png",
        "friction_influence_pybullet.png",
    ]
    for p in paths:
        data = p.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    assert make_plots(study_db, tmp_path / "none", EpisodeFilter(backend="mujoco")) == []
