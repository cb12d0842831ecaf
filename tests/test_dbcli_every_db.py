"""Every `comexp-db` command on every database a user can have: one job (one speed, one floor,
one backend), one episode, only failures, an empty database, a job just started (a sweep row
and no episode) and a database still being written (a writer holds an open transaction).
Each command gives a result, or one line saying what is missing; never a traceback."""

from __future__ import annotations

import itertools
import json
import sqlite3
from collections.abc import Iterator
from pathlib import Path

import pytest
from test_db import make_result

from comexp.cli.query import main
from comexp.results.store import ResultsDB


def _job(floor: str = "iso", speed: float = 40.0, backend: str = "planar") -> list:
    """One job's grid in small: 2 objects x 2 CoMs x Izz {1, 10} x floor mu x pusher mu."""
    out = []
    frictions = ((0.1, 0.1), (1.0, 1.0)) if floor == "iso" else ((0.1, 1.0), (1.0, 0.1))
    for obj, com, izz, (fx, fy), mp in itertools.product(
        ("l_shape", "rect_12x4"), range(2), (1.0, 10.0), frictions, (0.1, 1.0)
    ):
        out.append(
            make_result(
                object=obj,
                com_index=com,
                backend=backend,
                floor=floor,
                mu_floor_x=fx,
                mu_floor_y=fy,
                mu_pusher=mp,
                speed_cm_s=speed,
                izz_scale=izz,
                error_cm=0.3 + 0.1 * com + 0.05 * izz + 0.2 * fx + 0.1 * mp,
                failure="tipped" if (obj, com, izz, mp) == ("l_shape", 1, 10.0, 1.0) else None,
            )
        )
    return out


def _write(path: Path, batches: list[list]) -> None:
    with ResultsDB(path) as db:
        for results in batches:
            sid = db.start_sweep(command_line="comexp", config_yaml="floor: iso\n")
            if results:
                db.add_results(sid, results)


DATABASES = {
    "one_job": lambda: [_job()],  # iso, 40 cm/s, one backend: what `make run` leaves
    "one_speed": lambda: [_job("iso"), _job("aniso")],
    "one_floor": lambda: [_job("iso", 40.0), _job("iso", 4.0)],
    "one_backend": lambda: [_job(f, s) for f in ("iso", "aniso") for s in (40.0, 4.0)],
    "two_backends": lambda: [_job(backend="planar"), _job(backend="pybullet")],
    "one_episode": lambda: [_job()[:1]],
    "only_failures": lambda: [[make_result(failure="sim_unstable", com_index=i) for i in range(3)]],
    "job_started": lambda: [[]],  # a sweep row, no episode yet
    "empty": lambda: [],
}


@pytest.fixture(scope="module")
def databases(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("dbs")
    out = {}
    for name, make in DATABASES.items():
        path = root / f"{name}.db"
        _write(path, make())
        out[name] = path
    return out


@pytest.fixture(scope="module")
def being_written(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """One job's episodes stored, and a writer in the middle of storing the next batch: its
    transaction (a new sweep, episodes) is open, the WAL file holds its pages."""
    path = tmp_path_factory.mktemp("writing") / "comexp.db"
    _write(path, [_job()[:10]])
    writer = sqlite3.connect(path, isolation_level=None)
    writer.execute("BEGIN IMMEDIATE")
    writer.execute("INSERT INTO sweeps (started_at, command_line, config, job_name, versions, "
                   "host) VALUES ('2026-01-01', 'comexp', '', 'x', '{}', 'h')")  # fmt: skip
    writer.execute("DELETE FROM pushes WHERE episode_id = 1")
    assert Path(str(path) + "-wal").exists()
    yield path
    writer.rollback()
    writer.close()


def _commands(out_dir: Path) -> dict[str, list[str]]:
    return {
        "table": ["table"],
        "table_csv": ["table", "--format", "csv"],
        "table_json": ["table", "--format", "json"],
        "summary": ["summary"],
        "summary_csv": ["summary", "--format", "csv"],
        "summary_json": ["summary", "--format", "json"],
        "paper": ["paper"],
        "paper_json": ["paper", "--format", "json"],
        "claims": ["claims"],
        "claims_json": ["claims", "--format", "json"],
        "episodes": ["episodes"],
        "episodes_csv": ["episodes", "--format", "csv"],
        "episodes_json": ["episodes", "--format", "json"],
        "sweeps": ["sweeps"],
        "sweeps_json": ["sweeps", "--format", "json"],
        "sweeps_show": ["sweeps", "--show", "1"],
        "sweeps_show_json": ["sweeps", "--show", "1", "--format", "json"],
        "plot": ["plot", "--out", str(out_dir / "plots")],
        "show": ["show", "1", "--out", str(out_dir / "episode.png")],
    }


COMMANDS = list(_commands(Path("x")))
# An error exit is right only where the user asked for something the database does not hold.
EXPECTED_ERRORS = {
    ("empty", "sweeps_show"): "no sweep with id 1",
    ("empty", "sweeps_show_json"): "no sweep with id 1",
    ("empty", "show"): "no episode with id 1 (none stored)",
    ("job_started", "show"): "no episode with id 1 (none stored)",
}


def _check(code: int, out: str, err: str, expected_error: str | None, command: str = "") -> None:
    assert "Traceback" not in err and "Traceback" not in out
    lines = err.splitlines()
    assert len(lines) <= 1, err  # at most one line saying what is missing
    assert all(line.startswith("comexp-db: ") for line in lines), err
    if expected_error is not None:
        assert code == 1 and out == "", (out, err)
        assert err.startswith(f"comexp-db: error: {expected_error}"), err
    else:
        assert code == 0, err
        assert out.strip() or err.strip(), "neither a result nor a note"
        if "--format json" in command:
            json.loads(out)  # one strict JSON document, even when empty


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("name", list(DATABASES))
def test_every_command_on_every_database(
    databases: dict[str, Path], name: str, command: str, tmp_path: Path, capsys
) -> None:
    argv = ["--db", str(databases[name]), *_commands(tmp_path)[command]]
    code = main(argv)
    out, err = capsys.readouterr()
    _check(code, out, err, EXPECTED_ERRORS.get((name, command)), " ".join(argv))


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_on_a_database_being_written(
    being_written: Path, command: str, tmp_path: Path, capsys
) -> None:
    argv = ["--db", str(being_written), *_commands(tmp_path)[command]]
    code = main(argv)
    out, err = capsys.readouterr()
    _check(code, out, err, None, " ".join(argv))
    if command == "sweeps":
        assert out.count("| comexp |") == 1  # the writer's sweep is not visible yet
    if command == "show":
        assert (tmp_path / "episode.png").stat().st_size > 0


def test_claims_on_one_job_say_what_is_missing(databases: dict[str, Path], capsys) -> None:
    """The bug of issue 26: one job (iso, 40 cm/s) has no dynamic-vs-quasi-static pair."""
    code = main(["--db", str(databases["one_job"]), "claims"])
    out, err = capsys.readouterr()
    assert code == 0 and err == "", err
    assert "| planar | iso | 40 |" in out  # the mean at 40 cm/s, with its interval
    assert "needs 40 and 4 cm/s, the study has 40 cm/s" in out
    assert "**no data**" in out and "**holds**" not in out


def test_claims_on_one_floor_run_every_claim(databases: dict[str, Path], capsys) -> None:
    code = main(["--db", str(databases["one_floor"]), "claims"])
    out, err = capsys.readouterr()
    assert code == 0 and err == "", err
    assert "needs" not in out and "**no data**" not in out


def test_empty_results_say_why_on_one_line(databases: dict[str, Path], capsys) -> None:
    for name in ("empty", "job_started"):
        code = main(["--db", str(databases[name]), "table"])
        out, err = capsys.readouterr()
        assert code == 0
        assert err == f"comexp-db: note: no episodes stored in {databases[name]}\n"


def test_an_unexpected_error_is_one_line_too(databases: dict[str, Path], capsys, monkeypatch):
    import comexp.cli.query as query

    def broken(*args, **kwargs):
        raise KeyError("slow")

    monkeypatch.setattr(query, "condition_tables", broken)
    monkeypatch.delenv("COMEXP_DEBUG", raising=False)
    code = main(["--db", str(databases["one_job"]), "table"])
    out, err = capsys.readouterr()
    assert code == 1 and out == ""
    assert err == (
        "comexp-db: error: internal error (KeyError: 'slow'); COMEXP_DEBUG=1 shows where\n"
    )
