"""`comexp-db`: numbers agree with the episodes table, reading changes nothing, errors are clean."""

from __future__ import annotations

import contextlib
import csv
import io
import sqlite3
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from test_db import make_result, sha256_file
from test_reports import study_results

from comexp.cli.query import main
from comexp.results.store import ResultsDB


@pytest.fixture
def study_path(tmp_path: Path) -> Path:
    path = tmp_path / "results" / "comexp.db"
    with ResultsDB(path) as db:
        sid = db.start_sweep(command_line="comexp -m floor=iso,aniso", config_yaml="floor: iso\n")
        db.add_results(sid, study_results())
    return path


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def direct_stats(path: Path, where: str = "1=1") -> dict[tuple, list[float]]:
    """Errors grouped by (condition..., object), read with plain sqlite3, not with comexp."""
    conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    q = (
        "SELECT backend, floor, mu_floor_x, mu_floor_y, mu_pusher, speed_cm_s, izz_scale, object, "
        f"error_cm FROM episodes WHERE status = 'ok' AND {where}"
    )
    groups: dict[tuple, list[float]] = defaultdict(list)
    for *key, err in conn.execute(q):
        groups[tuple(key)].append(err)
        groups[(*key[:7], "all")].append(err)
    conn.close()
    return groups


def test_table_csv_agrees_with_the_episodes_table(study_path: Path, capsys) -> None:
    code, out, err = run(capsys, "--db", str(study_path), "table", "--format", "csv")
    assert code == 0 and err == ""
    rows = list(csv.DictReader(io.StringIO(out)))
    expected = direct_stats(study_path)
    assert len(rows) == len(expected) == 10 * 2 * 4  # conditions x Izz x (3 objects + all)
    for r in rows:
        key = (
            r["backend"],
            r["floor"],
            float(r["mu_floor_x"]),
            float(r["mu_floor_y"]),
            float(r["mu_pusher"]),
            float(r["speed_cm_s"]),
            float(r["izz_scale"]),
            r["object"],
        )
        errs = expected[key]
        assert int(r["n"]) == len(errs)
        assert float(r["mean"]) == pytest.approx(np.mean(errs), abs=1e-6)
        if len(errs) > 1:
            assert float(r["std"]) == pytest.approx(np.std(errs, ddof=1), abs=1e-6)
        else:
            assert r["std"] == ""
        assert float(r["max"]) == pytest.approx(max(errs), abs=1e-6)
        assert float(r["min"]) == pytest.approx(min(errs), abs=1e-6)
    failed = {
        (r["floor"], r["mu_floor_x"], r["speed_cm_s"], r["izz_scale"], r["object"]): r for r in rows
    }
    assert failed[("iso", "0.1", "4", "10", "obj2")]["n_failed"] == "1"
    assert failed[("iso", "0.1", "4", "1", "obj2")]["n_failed"] == "0"
    assert failed[("iso", "0.1", "40", "10", "obj2")]["n_failed"] == "0"


def test_table_filters_select_conditions(study_path: Path, capsys) -> None:
    db = str(study_path)
    code, out, _ = run(capsys, "--db", db, "table", "--mu-floor", "1", "--format", "csv")
    assert code == 0
    rows = list(csv.DictReader(io.StringIO(out)))
    assert {(r["floor"], r["mu_floor_x"], r["mu_floor_y"]) for r in rows} == {("iso", "1", "1")}
    code, out, _ = run(
        capsys, "--db", db, "table", "--floor", "aniso", "--mu-floor-x", "1", "--speed", "40"
    )
    assert code == 0
    assert out.count("### ") == 2  # Izz 1 and 10: never pooled
    assert (
        "### pybullet, floor aniso mu_floor_x=1 mu_floor_y=0.1, mu_pusher=0.5, speed 40 cm/s, "
        "Izz x10, rotation vision\n"
    ) in out
    assert "| object | n | mean | std | max | min |" in out
    code, out, _ = run(capsys, "--db", db, "summary", "--format", "csv", "--speed", "4")
    rows = list(csv.DictReader(io.StringIO(out)))
    assert len(rows) == 10
    assert {(r["izz_scale"], r["n_failed"], r["n_ok"]) for r in rows} == {
        ("1", "0", "9"),
        ("10", "1", "8"),
    }


def test_episodes_filter_and_export(study_path: Path, capsys) -> None:
    db = str(study_path)
    code, out, _ = run(capsys, "--db", db, "episodes", "--status", "failed", "--format", "csv")
    rows = list(csv.DictReader(io.StringIO(out)))
    assert code == 0 and len(rows) == 5 and {r["object"] for r in rows} == {"obj2"}
    assert {r["failure"] for r in rows} == {"tipped", "left_view"}
    code, out, _ = run(capsys, "--db", db, "episodes", "--failure", "tipped", "--limit", "2")
    assert code == 0 and out.count("| tipped |") == 2
    code, out, _ = run(
        capsys, "--db", db, "episodes", "--object", "obj10", "--columns", "all", "--format", "csv"
    )
    rows = list(csv.DictReader(io.StringIO(out)))
    assert len(rows) == 60 and "episode_key" in rows[0] and "estimator" in rows[0]
    code, out, _ = run(capsys, "--db", db, "sweeps")
    assert code == 0 and "comexp -m floor=iso,aniso" in out and "| 180 | 175 |" in out
    code, out, _ = run(capsys, "--db", db, "sweeps", "--show", "1")
    assert code == 0 and "config:\n  floor: iso" in out


def test_reading_leaves_the_database_byte_identical(study_path: Path, tmp_path: Path, capsys):
    wal = Path(f"{study_path}-wal")
    writer = ResultsDB(study_path)  # a writer holds the file open: the WAL is live
    assert writer.add_results(None, [make_result(object="obj99", com_index=i) for i in range(3)])
    try:
        for state in ("writer open", "writer closed"):
            before = {p: sha256_file(p) for p in (study_path, wal) if p.exists()}
            if state == "writer open":
                assert wal.stat().st_size > 0  # the new rows live in the WAL only
            for argv in (
                ["table"],
                ["table", "--format", "csv"],
                ["summary"],
                ["paper"],
                ["episodes", "--format", "csv"],
                ["sweeps"],
                ["plot", "--out", str(tmp_path / "plots")],
            ):
                code, _, err = run(capsys, "--db", str(study_path), *argv)
                assert code == 0, (state, argv, err)
            after = {p: sha256_file(p) for p in (study_path, wal) if p.exists()}
            assert after[study_path] == before[study_path], state
            if wal in before:
                assert after[wal] == before[wal], state
            else:  # SQLite may leave an empty WAL beside a checkpointed file: no data in it
                assert wal not in after or wal.stat().st_size == 0, state
            writer.close()
    finally:
        writer.close()
    assert sorted(p.name for p in (tmp_path / "plots").iterdir()) == [
        "error_per_object_pybullet_aniso.png",
        "error_per_object_pybullet_iso.png",
        "friction_influence_pybullet.png",
        "izz_influence_pybullet.png",
    ]


@pytest.mark.parametrize(
    ("argv", "exit_code", "message"),
    [
        (["table", "--speed", "fast"], 2, "argument --speed: not a number: 'fast'"),
        (["table", "--speed", "-4"], 2, "must be a finite number >= 0"),
        (["table", "--format", "xls"], 2, "invalid choice: 'xls'"),
        (["table", "--mu-floor", "1", "--mu-floor-x", "1"], 1, "either mu_floor"),
        (["episodes", "--columns", "id,bogus"], 1, "unknown episode column(s) bogus"),
        (["show", "999", "--out", "x.png"], 1, "no episode with id 999 (stored ids 1..180)"),
        (["show", "1", "--out", "x.txt"], 1, "name an image file"),
        (["show", "1", "--out", "/nonexistent/x.png"], 1, "does not exist"),
        (["show", "0", "--out", "x.png"], 2, "must be > 0"),
        (["episodes", "--status", "maybe"], 2, "invalid choice: 'maybe'"),
        (["sweeps", "--show", "7"], 1, "no sweep with id 7"),
        (["frobnicate"], 2, "invalid choice: 'frobnicate'"),
    ],
)
def test_bad_filters_fail_cleanly(study_path: Path, capsys, argv, exit_code, message) -> None:
    with pytest.raises(SystemExit) if exit_code == 2 else contextlib.nullcontext() as info:
        code = main(["--db", str(study_path), *argv])
    if exit_code == 2:
        code = info.value.code
    _, err = capsys.readouterr()
    assert code == exit_code
    assert err.count("\n") == 1 and err.startswith("comexp-db") and message in err


EMPTY_CSV_HEADER = "id,sweep_id,backend,floor,mu_floor_x"


@pytest.mark.parametrize(
    ("argv", "note"),
    [
        (["table", "--backend", "bullet"], "backend=bullet matches nothing (stored: pybullet)"),
        (["table", "--mu-floor", "0.5"], "mu_floor=0.5 matches nothing (stored: 0.1, 1)"),
        (["table", "--floor", "aniso", "--mu-pusher", "1"], "match nothing together"),
        (["summary", "--format", "csv", "--object", "nope"], "object=nope matches nothing"),
        (["paper", "--speed", "7"], "speed_cm_s=7 matches nothing"),
        (["episodes", "--status", "failed", "--speed", "40", "--format", "csv"], "together"),
        (["plot", "--backend", "mujoco", "--out", "PLOTS"], "backend=mujoco matches nothing"),
    ],
)
def test_a_filter_matching_nothing_is_an_empty_result(
    study_path: Path, tmp_path: Path, capsys, argv, note
) -> None:
    """Not an error in a query tool: exit 0, a CSV keeps its header, a note on stderr."""
    argv = [str(tmp_path / "plots") if a == "PLOTS" else a for a in argv]
    code, out, err = run(capsys, "--db", str(study_path), *argv)
    assert code == 0
    assert err.count("\n") == 1 and err.startswith("comexp-db: note: ") and note in err
    if argv[0] == "episodes":
        assert out.startswith(EMPTY_CSV_HEADER) and out.count("\n") == 1
    elif argv[0] == "summary":
        assert out.startswith("backend,floor,") and out.count("\n") == 1
    elif argv[0] == "plot":
        assert out == "" and not any((tmp_path / "plots").iterdir())
    assert "| obj1 |" not in out


def test_missing_or_foreign_database_fails_cleanly(tmp_path: Path, capsys) -> None:
    code, _, err = run(capsys, "--db", str(tmp_path / "nope.db"), "table")
    assert code == 1 and err == f"comexp-db: error: database not found: {tmp_path / 'nope.db'}\n"
    assert not (tmp_path / "nope.db").exists()
    junk = tmp_path / "junk.db"
    junk.write_bytes(b"x" * 4096)
    code, _, err = run(capsys, "--db", str(junk), "summary")
    assert code == 1 and err.count("\n") == 1 and "not a database" in err
    empty = tmp_path / "empty.db"
    ResultsDB(empty).close()
    code, out, err = run(capsys, "--db", str(empty), "table", "--format", "csv")
    assert code == 0 and "no episodes stored" in err and out.startswith("backend,")
    code, out, err = run(capsys, "--db", str(empty), "sweeps")
    assert code == 0 and "no sweeps stored" in err and out.startswith("| id |")


def test_console_script_is_installed_and_prints_no_traceback(tmp_path: Path) -> None:
    script = Path(sys.executable).parent / "comexp-db"
    assert script.exists(), "comexp-db console script missing: reinstall the package"
    proc = subprocess.run(
        [str(script), "--db", str(tmp_path / "missing.db"), "summary"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.startswith("comexp-db: error: database not found")
    assert "Traceback" not in proc.stderr and proc.stderr.count("\n") == 1


def test_claims_print_means_and_verdicts(study_path: Path, capsys) -> None:
    code, out, err = run(capsys, "--db", str(study_path), "claims", "--floor", "iso")
    assert code == 0, err
    assert "| backend | floor | speed cm/s | n | mean error cm | 95% CI | paper |" in out
    assert "dynamic beats quasi-static" in out and "| aniso |" not in out
    assert out.count("**") % 2 == 0 and any(v in out for v in ("holds", "fails", "inconclusive"))


def test_help_of_every_command_prints() -> None:
    """argparse formats help lazily: a stray % in one help text broke `comexp-db --help`."""
    import subprocess
    import sys

    from comexp.cli.query import build_parser

    parser = build_parser()
    parser.format_help()
    for action in parser._subparsers._group_actions:  # every subcommand's own help
        for sub in action.choices.values():
            sub.format_help()
    r = subprocess.run([sys.executable, "-m", "comexp.cli.query", "--help"], capture_output=True)
    assert r.returncode == 0, r.stderr
