"""Aggregated tables (paper Tables II/III form), job reports and plots from a synthetic study:
every one of them groups with `group_episodes`, and none pools what it does not say."""

from __future__ import annotations

import csv
import dataclasses
import io
import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest
from test_db import make_result

from comexp.episode.task import EpisodeResult
from comexp.method.estimator import EstimatorSettings
from comexp.results import paper
from comexp.results.filters import EpisodeFilter
from comexp.results.identity import episode_key
from comexp.results.plots import make_plots
from comexp.results.reports import (
    CONDITION_COLUMNS,
    PAPER_POOL,
    POOLED,
    ErrorStats,
    condition_tables,
    group_episodes,
    natural_key,
    paper_markdown,
    paper_mean_cm,
    paper_tables,
    summary_csv,
    summary_text,
    table_markdown,
    tables_csv,
    write_job_reports,
)
from comexp.results.store import ResultsDB

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


def test_error_stats_use_the_sample_std() -> None:
    s = ErrorStats.of([1.0, 2.0, 4.0])
    assert (s.n, s.mean, s.max, s.min) == (3, pytest.approx(7 / 3), 4.0, 1.0)
    assert s.std == pytest.approx(np.std([1.0, 2.0, 4.0], ddof=1))
    assert s.std == pytest.approx(
        math.sqrt(((1 - 7 / 3) ** 2 + (2 - 7 / 3) ** 2 + (4 - 7 / 3) ** 2) / 2)
    )
    one = ErrorStats.of([2.0])
    assert one.n == 1 and one.mean == 2.0 and math.isnan(one.std)
    empty = ErrorStats.of([])
    assert empty.n == 0 and math.isnan(empty.mean)
    assert sorted(["obj10", "obj2", "obj1"], key=natural_key) == ["obj1", "obj2", "obj10"]


def _key(r: dict, columns=CONDITION_COLUMNS) -> tuple:
    return tuple(r[c] for c in columns)


def test_condition_tables_match_a_direct_computation(study_db: ResultsDB) -> None:
    tables = condition_tables(study_db)
    assert len(tables) == len(FRICTIONS) * 2 * 2  # frictions x speeds x Izz: never pooled
    rows = study_db.episodes()
    for t in tables:
        c = t.condition
        mine = [r for r in rows if _key(r) == c.key]
        assert len(mine) == 3 * 3
        assert [o for o, _, _ in t.rows] == list(OBJECTS)
        for obj, stats, n_failed in t.rows:
            errs = [r["error_cm"] for r in mine if r["object"] == obj and r["status"] == "ok"]
            assert stats.n == len(errs)
            assert stats.mean == pytest.approx(np.mean(errs))
            assert stats.std == pytest.approx(np.std(errs, ddof=1))
            assert (stats.max, stats.min) == (max(errs), min(errs))
            assert n_failed == sum(r["object"] == obj and r["status"] == "failed" for r in mine)
        ok = [r["error_cm"] for r in mine if r["status"] == "ok"]
        assert t.overall.n == len(ok) and t.overall.mean == pytest.approx(np.mean(ok))
        expected_failed = 1 if (c.speed_cm_s, c.izz_scale) == (4.0, 10.0) else 0
        assert t.n_failed == expected_failed
        if expected_failed:
            reason = "tipped" if c.floor == "iso" else "left_view"
            assert t.failures == {reason: 1}
            assert f"1 failed episode(s) excluded: {reason} 1" in table_markdown(t)


def test_every_condition_column_separates(tmp_path: Path) -> None:
    """Two episodes that differ in any one condition column land in two conditions."""
    base = make_result(error_cm=1.0)
    variants = {
        "backend": dict(backend="mujoco"),
        "floor": dict(floor="aniso"),
        "mu_floor_x": dict(mu_floor_x=1.0),
        "mu_floor_y": dict(mu_floor_y=1.0),
        "mu_pusher": dict(mu_pusher=1.0),
        "speed_cm_s": dict(speed_cm_s=4.0),
        "izz_scale": dict(izz_scale=10.0),
        "mass_kg": dict(mass_kg=0.5),
        "push_length_cm": dict(push_length_cm=5.0),
        "recenter_beyond_cm": dict(recenter_beyond_cm=0.0),
        "estimator": dict(estimator=EstimatorSettings(theta_T_deg=2.0)),
        "physics": dict(physics="pybullet/pybullet-3/pybullet-3.2.7/0123456789"),
        "camera_fps": dict(camera_fps=15.0),
    }
    assert set(variants) == set(CONDITION_COLUMNS)
    with ResultsDB(tmp_path / "v.db") as db:
        results = [base] + [
            dataclasses.replace(
                make_result(error_cm=2.0), spec=dataclasses.replace(base.spec, **kw)
            )
            for kw in variants.values()
        ]
        assert db.add_results(None, results) == len(results)
        tables = condition_tables(db)
        assert len(tables) == len(results)
        labels = [t.condition.label() for t in tables]
        slugs = [t.condition.slug() for t in tables]
        assert len(set(labels)) == len(set(slugs)) == len(results)
        assert any("theta_T_deg=2" in x for x in labels) and any("mass_kg=0.5" in x for x in labels)


def test_filtered_tables_and_csv(study_db: ResultsDB) -> None:
    tables = condition_tables(
        study_db, EpisodeFilter(floor="aniso", mu_floor_x=1.0, speed_cm_s=4, izz_scale=10)
    )
    assert len(tables) == 1
    c = tables[0].condition
    assert (c.backend, c.floor, c.mu_floor_x, c.mu_floor_y, c.mu_pusher, c.speed_cm_s) == (
        "pybullet",
        "aniso",
        1.0,
        0.1,
        0.5,
        4.0,
    )
    parsed = list(csv.DictReader(io.StringIO(tables_csv(tables))))
    assert [r["object"] for r in parsed] == [*OBJECTS, "all"]
    assert parsed[1]["n"] == "2" and parsed[1]["n_failed"] == "1"
    assert parsed[0]["mu_floor_x"] == "1" and parsed[0]["speed_cm_s"] == "4"
    assert parsed[0]["izz_scale"] == "10" and parsed[0]["push_length_cm"] == "3"
    assert float(parsed[-1]["mean"]) == pytest.approx(tables[0].overall.mean, abs=1e-6)
    (summary,) = list(csv.DictReader(io.StringIO(summary_csv(tables))))
    assert list(summary)[: len(CONDITION_COLUMNS)] == list(CONDITION_COLUMNS)
    assert summary["n_ok"] == "8" and summary["n_failed"] == "1"
    assert summary["failures"] == "left_view:1"
    assert summary["std"] == f"{tables[0].overall.std:.6f}"
    assert '"rotation_source":"vision"' in summary["estimator"]


def test_estimator_variants_are_not_pooled_and_labels_name_them(tmp_path: Path) -> None:
    with ResultsDB(tmp_path / "v.db") as db:
        oracle = EstimatorSettings(rotation_source="oracle")
        db.add_results(
            None,
            [make_result(error_cm=1.0), make_result(error_cm=3.0, estimator=oracle)],
        )
        tables = condition_tables(db)
        assert sorted(t.overall.mean for t in tables) == [1.0, 3.0]
        by_mean = {t.overall.mean: t.condition.label() for t in tables}
        assert "rotation oracle" in by_mean[3.0] and "rotation vision" in by_mean[1.0]
        assert len({t.condition.slug() for t in tables}) == 2
        # a filter to one variant: its label still names it
        (one,) = condition_tables(db, EpisodeFilter(rotation_source="oracle"))
        assert "rotation oracle" in one.condition.label() and one.overall.mean == 3.0


def test_rows_stored_before_the_frame_rule_are_labelled_every_frame() -> None:
    """A row stored before `track_step_deg` existed tracked every frame: its label says so,
    so that it is not shown under the same label as a row with the new default."""
    from comexp.results.identity import canonical_json
    from comexp.results.reports import Condition, estimator_changes

    new = json.loads(canonical_json(EstimatorSettings()))
    old = {k: v for k, v in new.items() if k not in ("track_step_deg", "track_gap_s")}
    assert estimator_changes(json.dumps(new)) == {}
    assert estimator_changes(json.dumps(old)) == {"track_step_deg": 0}
    core = dict(backend="planar", floor="iso", mu_floor_x=0.1, mu_floor_y=0.1, mu_pusher=0.1)
    core.update(speed_cm_s=40.0, izz_scale=1.0)
    labels = {Condition.of({**core, "estimator": json.dumps(e)}).label() for e in (new, old)}
    assert len(labels) == 2 and any("track_step_deg=0" in t for t in labels)


def test_rows_stored_before_the_driving_frame_rule_are_labelled_every_driving_frame() -> None:
    """A row stored before `track_drive_mm` existed tracked every frame while the pusher
    drove: it is labelled `track_drive_mm=0`, not shown as a row of today's default."""
    from comexp.results.identity import canonical_json
    from comexp.results.reports import estimator_changes

    new = json.loads(canonical_json(EstimatorSettings()))
    old = {k: v for k, v in new.items() if k != "track_drive_mm"}
    assert estimator_changes(json.dumps(old)) == {"track_drive_mm": 0.0}
    assert estimator_changes(json.dumps({**new, "track_drive_mm": 0.0})) == {"track_drive_mm": 0.0}


def test_group_episodes_pools_only_what_it_is_told(study_db: ResultsDB) -> None:
    rows = study_db.episodes()
    groups = group_episodes(rows, PAPER_POOL)
    assert len(groups) == 2 * 2  # (iso, aniso) x 2 speeds
    for cond in groups:
        assert all(cond[c] is POOLED for c in PAPER_POOL)
        assert cond.estimator is not POOLED and cond.backend == "pybullet"
    with pytest.raises(ValueError, match="unknown condition column"):
        group_episodes(rows, ("object",))


def test_paper_form_puts_speeds_side_by_side(study_db: ResultsDB) -> None:
    tables = paper_tables(study_db, EpisodeFilter(floor="iso"))
    assert len(tables) == 1
    (by_speed,) = tables.values()
    assert sorted(by_speed) == [4.0, 40.0]
    assert by_speed[40.0].overall.n == 3 * 3 * 2 * 3  # three iso friction pairs, 2 Izz pooled
    assert by_speed[4.0].n_failed == 3
    text = paper_markdown(tables)
    header = next(line for line in text.splitlines() if line.startswith("| object"))
    assert header.index("mean @40") < header.index("mean @4 ")
    assert "izz_scale pooled over {1, 10}" in text
    # the study's iso grid has a third friction pair, so it is not the paper's condition
    assert "paper (all objects)" not in text


def test_paper_all_objects_means_come_from_the_tables() -> None:
    assert {k: round(v, 4) for k, v in paper.ALL_OBJECTS_MEAN_CM.items()} == {
        ("iso", 40.0): 0.6287,
        ("iso", 4.0): 1.3989,
        ("aniso", 40.0): 0.6889,
        ("aniso", 4.0): 2.359,
    }
    assert all(len(v) == 20 for v in paper.TABLE_MEANS_CM.values())
    # spot checks against the paper's Tables II (obj1, obj20) and III (obj4, obj20)
    assert paper.TABLE_MEANS_CM[("iso", 40.0)][0] == 0.489
    assert paper.TABLE_MEANS_CM[("iso", 4.0)][19] == 1.862
    assert paper.TABLE_MEANS_CM[("aniso", 40.0)][3] == 0.598
    assert paper.TABLE_MEANS_CM[("aniso", 4.0)][19] == 3.319


def _paper_grid(floor: str, **spec_changes) -> list[EpisodeResult]:
    pairs = sorted(paper.FLOOR_PAIRS[floor])
    out = []
    for (fx, fy), mp, izz, speed in itertools.product(
        pairs, sorted(paper.PUSHER_MU[floor]), sorted(paper.IZZ_SCALES), (40.0, 4.0)
    ):
        r = make_result(
            floor=floor, mu_floor_x=fx, mu_floor_y=fy, mu_pusher=mp, izz_scale=izz, speed_cm_s=speed
        )
        if spec_changes:
            r = dataclasses.replace(r, spec=dataclasses.replace(r.spec, **spec_changes))
        out.append(r)
    return out


def test_paper_values_are_marked_where_the_condition_matches(tmp_path: Path) -> None:
    with ResultsDB(tmp_path / "p.db") as db:
        db.add_results(None, _paper_grid("iso") + _paper_grid("aniso"))
        db.add_results(None, _paper_grid("iso", push_length_cm=5.0))
        tables = paper_tables(db)
        marks = {
            (cond.floor, cond.push_length_cm, v): paper_mean_cm(t)
            for cond, by_speed in tables.items()
            for v, t in by_speed.items()
        }
        assert marks == {
            ("iso", 3.0, 40.0): paper.ALL_OBJECTS_MEAN_CM[("iso", 40.0)],
            ("iso", 3.0, 4.0): paper.ALL_OBJECTS_MEAN_CM[("iso", 4.0)],
            ("aniso", 3.0, 40.0): paper.ALL_OBJECTS_MEAN_CM[("aniso", 40.0)],
            ("aniso", 3.0, 4.0): paper.ALL_OBJECTS_MEAN_CM[("aniso", 4.0)],
            ("iso", 5.0, 40.0): None,  # another push protocol is not the paper's condition
            ("iso", 5.0, 4.0): None,
        }
        text = paper_markdown(tables)
        assert text.count("paper (all objects)") == 2  # iso and aniso; not the 5 cm pushes
        assert "| 0.629 |" in text and "| 2.359 |" in text
        # a pusher friction the paper's aniso run did not use: not the paper's grid
        db.add_results(
            None, [make_result(floor="aniso", mu_floor_x=0.1, mu_floor_y=1.0, mu_pusher=1.0)]
        )
        (by_speed,) = paper_tables(db, EpisodeFilter(floor="aniso")).values()
        assert paper_mean_cm(by_speed[40.0]) is None  # the extra episode ran at 40 cm/s
        assert paper_mean_cm(by_speed[4.0]) == paper.ALL_OBJECTS_MEAN_CM[("aniso", 4.0)]


def test_job_report_covers_the_jobs_own_episodes_only(study_db: ResultsDB, tmp_path: Path) -> None:
    """Another job's episodes in the same condition (here: an oracle estimator, and a later
    job adding episodes) never change a job's report."""
    mine = [r for r in study_results() if r.spec.floor == "iso" and r.spec.speed_cm_s == 4.0]
    keys = [episode_key(r.spec) for r in mine]
    out = tmp_path / "job"
    paths, text = write_job_reports(study_db, out, keys, job="pybullet iso 4 cm/s")
    before = {p.name: p.read_text() for p in paths}
    names = sorted(before)
    assert len(names) == 3 * 2 * 2 + 2 and "summary.md" in names and "summary.csv" in names
    assert all(p.parent == out and p.stat().st_size > 0 for p in paths)
    assert "errors_pybullet_iso_fx1_fy1_p0.1_v4_izz10.md" in names
    lines = text.splitlines()
    assert lines[0] == (
        f"report: this job's episodes only: {len(keys)} of its {len(keys)} grid episodes "
        "stored (pybullet iso 4 cm/s)"
    )
    assert len(lines) == 1 + 6 and sum("1 failed" in x for x in lines) == 3
    assert all("rotation vision" in x for x in lines[1:])
    summary = (out / "summary.md").read_text()
    assert summary.count("### ") == 6 and "tipped 1" in summary
    assert "this job's episodes only" in summary
    # a later, unrelated job in the same conditions (oracle), and extra CoMs of the same
    # estimator: the first job's report does not change
    oracle = EstimatorSettings(rotation_source="oracle")
    later = [
        dataclasses.replace(r, spec=dataclasses.replace(r.spec, estimator=oracle), error_cm=9.0)
        for r in mine
    ]
    extra = [
        make_result(floor="iso", speed_cm_s=4.0, mu_floor_x=0.1, mu_floor_y=0.1, com_index=7 + i)
        for i in range(3)
    ]
    assert study_db.add_results(None, later + extra) == len(later) + len(extra)
    paths2, text2 = write_job_reports(study_db, out, keys, job="pybullet iso 4 cm/s")
    assert {p.name: p.read_text() for p in paths2} == before and text2 == text
    empty_paths, empty_text = write_job_reports(study_db, tmp_path / "none", ["0" * 64])
    assert "0 of its 1 grid episodes" in empty_text and "no episodes" in empty_text
    assert len(empty_paths) == 2


def test_summary_text_says_what_std_is(study_db: ResultsDB) -> None:
    text = summary_text(condition_tables(study_db, EpisodeFilter(floor="iso", speed_cm_s=40)))
    assert all("(mean +- sample std)" in line for line in text.splitlines())


def test_plots_write_pngs(study_db: ResultsDB, tmp_path: Path) -> None:
    paths = make_plots(study_db, tmp_path / "plots")
    names = sorted(p.name for p in paths)
    assert names == [
        "error_per_object_pybullet_aniso.png",
        "error_per_object_pybullet_iso.png",
        "friction_influence_pybullet.png",
        "izz_influence_pybullet.png",
    ]
    for p in paths:
        data = p.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    assert make_plots(study_db, tmp_path / "none", EpisodeFilter(backend="mujoco")) == []


def test_backend_figure_needs_two_backends_on_one_condition(tmp_path: Path) -> None:
    with ResultsDB(tmp_path / "b.db") as db:
        grid = _paper_grid("iso")
        mj = [
            dataclasses.replace(r, spec=dataclasses.replace(r.spec, backend="mujoco")) for r in grid
        ]
        oracle = EstimatorSettings(rotation_source="oracle")
        other = [
            dataclasses.replace(r, spec=dataclasses.replace(r.spec, estimator=oracle)) for r in grid
        ]
        db.add_results(None, grid + mj + other)  # oracle ran on pybullet only: no pair
        paths = make_plots(db, tmp_path / "plots")
        backends = [p.name for p in paths if p.name.startswith("backends_")]
        assert backends == ["backends_all.png"]
        per_object = [p.name for p in paths if p.name.startswith("error_per_object_")]
        assert len(per_object) == 3  # pybullet vision, pybullet oracle, mujoco vision


def test_bench_study_report_uses_the_same_grouping(study_db: ResultsDB) -> None:
    import subprocess
    import sys

    script = Path(__file__).resolve().parents[1] / "bench" / "study_report.py"
    r = subprocess.run(
        [sys.executable, str(script), "--db", str(study_db.path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    for t in condition_tables(study_db, pool=PAPER_POOL):
        c = t.condition
        line = next(
            x
            for x in r.stdout.splitlines()
            if x.startswith(f"| {c.pooling(('speed_cm_s',)).label()} | {c.speed_cm_s:g} |")
        )
        assert f"| {t.overall.mean:.3f} | {t.overall.std:.3f} |" in line
    assert "## Cross-backend agreement" in r.stdout
