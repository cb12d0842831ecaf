"""`comexp-db ... --format json`: every listing as one strict JSON document whose numbers are
the CSV's (and the database's), with null where the CSV has an empty cell."""

from __future__ import annotations

import csv
import io
import json
import math
import sqlite3
from pathlib import Path

import pytest
from test_dbcli_every_db import _job, _write
from test_reports import study_results

from comexp.cli.query import main


@pytest.fixture(scope="module")
def study(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("json") / "comexp.db"
    _write(path, [study_results()])
    return path


@pytest.fixture(scope="module")
def one_job(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("json1") / "comexp.db"
    _write(path, [_job()])
    return path


def _out(capsys, *argv: str) -> str:
    code = main(list(argv))
    out, err = capsys.readouterr()
    assert code == 0 and err == "", err
    return out


def _num(text: str) -> float | None:
    return None if text == "" else float(text)


@pytest.mark.parametrize("command", ["table", "summary"])
def test_json_rows_are_the_csv_rows(study: Path, command: str, capsys) -> None:
    rows = json.loads(_out(capsys, "--db", str(study), command, "--format", "json"))
    table = list(
        csv.DictReader(io.StringIO(_out(capsys, "--db", str(study), command, "--format", "csv")))
    )
    assert len(rows) == len(table) > 0
    stats = ("n", "mean", "std", "max", "min") if command == "table" else ("n_ok", "mean", "std")
    for j, c in zip(rows, table, strict=True):
        assert j["backend"] == c["backend"] and j["floor"] == c["floor"]
        assert j["speed_cm_s"] == float(c["speed_cm_s"]) and j["izz_scale"] == float(c["izz_scale"])
        assert isinstance(j["estimator"], dict) and j["estimator"]["rotation_source"] == "vision"
        for s in stats:
            want = _num(c[s])
            assert (j[s] is None) if want is None else j[s] == pytest.approx(want, abs=1e-6)
        if command == "table":
            assert j["object"] == c["object"] and j["n_failed"] == int(c["n_failed"])
        else:
            assert sum(j["failures"].values()) == j["n_failed"] == int(c["n_failed"])


def test_episodes_json_equals_the_database(study: Path, capsys) -> None:
    out = _out(capsys, "--db", str(study), "episodes", "--format", "json", "--columns", "all")
    rows = json.loads(out)
    conn = sqlite3.connect(f"file:{study}?mode=ro", uri=True)
    conn.row_factory = sqlite3.Row
    stored = [dict(r) for r in conn.execute("SELECT * FROM episodes ORDER BY id")]
    conn.close()
    assert len(rows) == len(stored) == len(study_results())
    for j, s in zip(rows, stored, strict=True):
        assert set(j) == set(s)
        for k, v in s.items():
            if k == "created_at":
                assert j[k].startswith(v[:19].replace(" ", "T"))
            elif isinstance(v, float) and math.isnan(v):
                assert j[k] is None
            else:
                assert j[k] == v, k


def test_paper_claims_and_sweeps_json(study: Path, one_job: Path, capsys) -> None:
    paper = json.loads(_out(capsys, "--db", str(study), "paper", "--format", "json"))
    alls = [r for r in paper if r["object"] == "all"]
    assert {(r["floor"], r["speed_cm_s"]) for r in alls} == {
        (f, s) for f in ("iso", "aniso") for s in (40.0, 4.0)
    }
    assert all("mu_pusher" not in r and set(r["pooled"]) == {"mu_floor_x", "mu_floor_y",
               "mu_pusher", "izz_scale"} for r in paper)  # fmt: skip
    assert all("paper_mean" in r for r in alls)

    claims = json.loads(_out(capsys, "--db", str(one_job), "claims", "--format", "json"))
    assert [m["speed_cm_s"] for m in claims["means"]] == [40.0]
    assert {c["verdict"] for c in claims["claims"]} == {"no data"}
    assert all(c["value_cm"] is None and "needs" in c["statistic"] for c in claims["claims"])

    sweeps = json.loads(_out(capsys, "--db", str(study), "sweeps", "--format", "json"))
    assert [s["id"] for s in sweeps] == [1] and sweeps[0]["n_episodes"] == len(study_results())
    one = json.loads(_out(capsys, "--db", str(study), "sweeps", "--show", "1", "--format", "json"))
    assert one["config"] == "floor: iso\n" and isinstance(one["versions"], dict)


def test_an_empty_selection_is_an_empty_list(study: Path, capsys) -> None:
    code = main(["--db", str(study), "table", "--object", "nothing", "--format", "json"])
    out, err = capsys.readouterr()
    assert code == 0 and json.loads(out) == [] and "matches nothing" in err
