"""Old databases keep working: a database of each earlier schema layout (tests/fixtures/
schema_*.sql, written by make_old_schemas.py from the old models in git history) is readable
by `comexp-db` and `load_results` without being changed, and a job (a writable handle)
upgrades it in place, keeping every stored row, filling the new columns from the stored spec."""

from __future__ import annotations

import hashlib
import sqlite3
from pathlib import Path

import pytest
from test_db import make_result

from comexp.api import load_results
from comexp.cli.query import main
from comexp.results import migrations
from comexp.results.schema import EPISODES, PUSHES, SCHEMA_VERSION
from comexp.results.store import ResultsDB

FIXTURES = Path(__file__).resolve().parent / "fixtures"
LAYOUTS = {"v1": 1, "v2": 2, "v3": 3, "v4early": 4, "v4": 4}


def _db(tmp_path: Path, layout: str) -> Path:
    path = tmp_path / f"{layout}.db"
    conn = sqlite3.connect(path)
    conn.executescript((FIXTURES / f"schema_{layout}.sql").read_text())
    conn.close()
    return path


def _columns(path: Path, table: str) -> list[str]:
    with sqlite3.connect(path) as c:
        return [r[1] for r in c.execute(f"PRAGMA table_info({table})")]


def _version(path: Path) -> str:
    with sqlite3.connect(path) as c:
        return c.execute("SELECT value FROM comexp_meta WHERE key = 'schema'").fetchone()[0]


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_every_schema_version_has_a_fixture_and_a_migration() -> None:
    assert sorted(set(LAYOUTS.values()) - {SCHEMA_VERSION}) == list(range(1, SCHEMA_VERSION))
    assert sorted(migrations.MIGRATIONS) == list(range(1, SCHEMA_VERSION))
    for layout, version in LAYOUTS.items():
        assert f"VALUES('schema','{version}')" in (FIXTURES / f"schema_{layout}.sql").read_text()


@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_an_old_database_is_read_as_it_is(tmp_path: Path, layout: str, capsys) -> None:
    path = _db(tmp_path, layout)
    before = _digest(path)
    df = load_results(path)
    assert list(df.object) == ["l_shape", "l_shape", "t_shape"]
    assert list(df.status) == ["ok", "ok", "failed"] and df.error_cm.iloc[1] == 0.7
    assert list(df.columns)[: len(EPISODES.c)] == [c.name for c in EPISODES.c]
    assert (df.camera_fps == (30.0 if layout.startswith("v4") else 0.0)).all()  # from the spec
    assert (df.physics == "").all() and (df.worker == "").all()
    recenter = df.recenter_beyond_cm.tolist()
    assert recenter == ([None] * 3 if layout == "v1" else [10.0] * 3) or layout == "v1"
    pushes = load_results(path, "pushes")
    assert len(pushes) == 5 + 5 + 2 and (pushes.n_frames == 0).all()
    for argv in (["summary"], ["table", "--format", "json"], ["paper"], ["claims"],
                 ["episodes", "--columns", "all"], ["sweeps"], ["sweeps", "--show", "1"],
                 ["show", "1", "--out", str(tmp_path / "e.png")],
                 ["plot", "--out", str(tmp_path / "plots")]):  # fmt: skip
        code = main(["--db", str(path), *argv])
        out, err = capsys.readouterr()
        assert code == 0, (argv, err)
        assert out and err.count("\n") == 1, (argv, err)
        assert err.startswith(f"comexp-db: note: {path} has schema version {LAYOUTS[layout]}")
        assert "a job writing to it upgrades the file" in err
    assert _digest(path) == before and _version(path) == str(LAYOUTS[layout])


@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_a_job_upgrades_an_old_database_in_place(tmp_path: Path, layout: str) -> None:
    path = _db(tmp_path, layout)
    old_rows = load_results(path)
    with ResultsDB(path) as db:  # what a job opens
        assert db.schema_note is not None and "in place" in db.schema_note
        assert f"schema version {LAYOUTS[layout]} " in db.schema_note
        sid = db.start_sweep(command_line="comexp")
        assert db.add_results(sid, [make_result(object="u_shape")]) == 1
        assert db.add_results(sid, [make_result(object="l_shape", error_cm=0.4)]) == 0  # stored
    assert _version(path) == str(SCHEMA_VERSION)
    # added columns come last (ALTER TABLE ADD COLUMN); readers select them by name
    assert sorted(_columns(path, "episodes")) == sorted(c.name for c in EPISODES.c)
    assert sorted(_columns(path, "pushes")) == sorted(c.name for c in PUSHES.c)
    new_rows = load_results(path)
    assert len(new_rows) == 4 and list(new_rows.object)[:3] == list(old_rows.object)
    keep = [c for c in old_rows.columns if c != "created_at"]

    def plain(df):  # None and NaN alike (a column's dtype changes with the new row)
        df = df[keep].astype(object)
        return df.where(df.notna(), None).to_dict("records")

    assert plain(new_rows.iloc[:3]) == plain(old_rows)
    with ResultsDB(path) as db:  # opened again: nothing more to do
        assert db.schema_note is None
    with ResultsDB(path, readonly=True) as db:
        assert db.schema_note is None and db.count() == 4


def test_a_newer_database_is_refused_in_one_line(tmp_path: Path, capsys) -> None:
    path = tmp_path / "new.db"
    with ResultsDB(path) as db:
        db.add_results(None, [make_result()])
    with sqlite3.connect(path) as c:
        c.execute("UPDATE comexp_meta SET value = ? WHERE key = 'schema'", (SCHEMA_VERSION + 1,))
    with pytest.raises(ValueError, match=f"schema version {SCHEMA_VERSION + 1}, this comexp"):
        ResultsDB(path)
    assert main(["--db", str(path), "summary"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "use a newer comexp" in err


def test_an_upgrade_that_fails_changes_nothing(tmp_path: Path, monkeypatch) -> None:
    path = _db(tmp_path, "v2")

    def broken(conn, added):
        raise RuntimeError("disk full")

    monkeypatch.setattr(migrations, "_add_column", broken)
    with pytest.raises(RuntimeError, match="disk full"):
        ResultsDB(path)
    monkeypatch.undo()
    assert _version(path) == "2" and "physics" not in _columns(path, "episodes")
    assert load_results(path).shape[0] == 3
