"""Results database: schema contract, idempotent writes, read-only opening, two writers."""

from __future__ import annotations

import dataclasses
import hashlib
import os
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from sqlalchemy import create_engine, inspect
from sqlalchemy.dialects import postgresql

from comexp.episode.task import EpisodeResult, EpisodeSpec, PushRecord
from comexp.method.estimator import EstimatorSettings
from comexp.results.filters import EpisodeFilter
from comexp.results.identity import episode_key
from comexp.results.schema import EPISODES
from comexp.results.store import ResultsDB, check_location, sqlite_file

EPISODE_COLUMNS = [
    "id",
    "sweep_id",
    "backend",
    "floor",
    "mu_floor_x",
    "mu_floor_y",
    "mu_pusher",
    "speed_cm_s",
    "izz_scale",
    "object",
    "com_index",
    "true_com_x_cm",
    "true_com_y_cm",
    "est_com_x_cm",
    "est_com_y_cm",
    "error_cm",
    "n_pushes",
    "status",
    "failure",
    "wall_s",
]
PUSH_COLUMNS = [
    "episode_id",
    "k",
    "contact_x_cm",
    "contact_y_cm",
    "dir_x",
    "dir_y",
    "rotation_deg",
    "rotation_true_deg",
    "decision",
    "region_px",
    "n_frames",
    "region_cm",
]
SQUARE = ((-3.0, -3.0), (3.0, -3.0), (3.0, 3.0), (-3.0, 3.0))


def make_result(
    *,
    object: str = "obj1",
    com_index: int = 0,
    backend: str = "pybullet",
    floor: str = "iso",
    mu_floor_x: float = 0.1,
    mu_floor_y: float = 0.1,
    mu_pusher: float = 0.1,
    speed_cm_s: float = 40.0,
    izz_scale: float = 1.0,
    error_cm: float | None = 0.5,
    failure: str | None = None,
    estimator: EstimatorSettings | None = None,
) -> EpisodeResult:
    """Synthetic episode: the true CoM depends on the com index; the estimate is error_cm off."""
    com = (0.1 * com_index, -0.05 * com_index)
    spec = EpisodeSpec(
        backend=backend,
        floor=floor,
        mu_floor_x=mu_floor_x,
        mu_floor_y=mu_floor_y,
        mu_pusher=mu_pusher,
        speed_cm_s=speed_cm_s,
        izz_scale=izz_scale,
        object=object,
        outline_cm=SQUARE,
        height_cm=2.0,
        com_index=com_index,
        com_cm=com,
        estimator=estimator or EstimatorSettings(),
    )
    ok = failure is None
    pushes = tuple(
        PushRecord(k, 3.0, 0.1 * k, -1.0, 0.0, 2.0 + k, 2.1 + k, "ccw" if k % 2 else "cw", 900 - k)
        for k in range(5 if ok else 2)
    )
    return EpisodeResult(
        spec=spec,
        status="ok" if ok else "failed",
        failure=failure,
        est_com_cm=(com[0] + error_cm, com[1]) if ok and error_cm is not None else None,
        error_cm=error_cm if ok else None,
        n_pushes=len(pushes),
        pushes=pushes,
        wall_s=0.1,
        sim_time_s=1.5,
    )


def sha256_file(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture
def db(tmp_path: Path):
    d = ResultsDB(tmp_path / "sub" / "results.db")
    yield d
    d.close()


def test_schema_columns_and_indexes(db: ResultsDB) -> None:
    insp = inspect(db.engine)
    episode_cols = [c["name"] for c in insp.get_columns("episodes")]
    assert episode_cols[: len(EPISODE_COLUMNS)] == EPISODE_COLUMNS
    for extra in ("episode_key", "seed", "sim_time_s", "w1", "w2", "theta_T_deg", "C_bw_px"):
        assert extra in episode_cols
    for extra in ("n_push", "rotation_source", "estimator", "detail", "created_at"):
        assert extra in episode_cols
    push_cols = {c["name"] for c in insp.get_columns("pushes")}
    assert set(PUSH_COLUMNS) | {"id"} == push_cols
    sweep_cols = {c["name"] for c in insp.get_columns("sweeps")}
    assert {"id", "started_at", "command_line", "config", "job_name", "versions", "git_rev"} <= (
        sweep_cols
    )
    indexed = {tuple(ix["column_names"]) for ix in insp.get_indexes("episodes")}
    assert ("backend", "floor", "speed_cm_s", "mu_floor_x", "mu_floor_y", "mu_pusher") in indexed
    assert any(cols[0] == "object" for cols in indexed)
    uniques = [u["column_names"] for u in insp.get_unique_constraints("episodes")]
    assert ["episode_key"] in uniques
    with db.engine.connect() as conn:
        assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"


def test_episode_key_covers_every_spec_field_and_ignores_int_float_spelling() -> None:
    base = make_result().spec
    k = episode_key(base)
    assert k == episode_key(make_result().spec)
    assert k == episode_key(dataclasses.replace(base, speed_cm_s=40, izz_scale=1))
    changed = [
        dataclasses.replace(base, seed=1),
        dataclasses.replace(base, mass_kg=0.3),
        dataclasses.replace(base, com_cm=(0.0, 1e-12)),
        dataclasses.replace(base, outline_cm=SQUARE[::-1]),
        dataclasses.replace(base, estimator=EstimatorSettings(rotation_source="oracle")),
        dataclasses.replace(base, estimator=EstimatorSettings(w=(1.0, 0.25))),
    ]
    keys = {episode_key(s) for s in changed}
    assert len(keys) == len(changed) and k not in keys

    @dataclasses.dataclass(frozen=True)
    class SpecWithNewField(EpisodeSpec):
        new_knob: float = 0.0

    fields = {f.name: getattr(base, f.name) for f in dataclasses.fields(base)}
    assert episode_key(SpecWithNewField(**fields, new_knob=0.5)) != episode_key(
        SpecWithNewField(**fields, new_knob=0.25)
    )


def test_add_results_is_idempotent_and_stores_everything(db: ResultsDB) -> None:
    sid = db.start_sweep(
        command_line="comexp floor=iso",
        config_yaml="floor: iso\n",
        job_name="job0",
        versions={"numpy": "2.4"},
        git_rev="abc123",
    )
    results = [make_result(com_index=i, error_cm=0.1 * (i + 1)) for i in range(3)]
    results.append(make_result(com_index=3, failure="tipped"))
    results[0] = dataclasses.replace(results[0], worker="127.0.0.3:4242")
    assert db.add_results(sid, results) == 4
    # Twice, and with a duplicate inside the batch: nothing new but the one new episode.
    again = [*results, make_result(com_index=9), make_result(com_index=9)]
    assert db.add_results(sid, again) == 1
    assert db.add_results(sid, []) == 0
    assert db.count() == 5
    rows = db.episodes()
    assert len({r["episode_key"] for r in rows}) == 5
    first = rows[0]
    assert first["sweep_id"] == sid
    assert first["true_com_x_cm"] == 0.0 and first["est_com_x_cm"] == pytest.approx(0.1)
    assert first["worker"] == "127.0.0.3:4242"
    assert first["w1"] == 1.0 and first["w2"] == 0.5 and first["rotation_source"] == "vision"
    assert '"theta_T_deg":1' in first["estimator"]
    failed = db.episodes(EpisodeFilter(status="failed"))
    assert [(r["com_index"], r["failure"], r["error_cm"]) for r in failed] == [(3, "tipped", None)]
    pushes = db.pushes(first["id"])
    assert [p["k"] for p in pushes] == list(range(5))
    assert pushes[1]["decision"] == "ccw" and pushes[1]["region_px"] == 899
    assert sum(len(db.pushes(r["id"])) for r in rows) == 4 * 5 + 2
    (sweep,) = db.sweeps()
    assert sweep["versions"] == {"numpy": "2.4"} and sweep["n_episodes"] == 5
    assert sweep["n_ok"] == 4 and sweep["git_rev"] == "abc123"


def test_unique_key_is_enforced_by_the_database(db: ResultsDB) -> None:
    db.add_results(None, [make_result()])
    row = {k: v for k, v in db.episodes()[0].items() if k != "id"}
    with pytest.raises(Exception, match="UNIQUE"), db.engine.begin() as conn:
        conn.execute(EPISODES.insert().values(**row))
    assert db.count() == 1


def test_stored_keys_chunks_large_in_clauses(db: ResultsDB) -> None:
    results = [make_result(object=f"obj{i % 7}", com_index=i) for i in range(1200)]
    assert db.add_results(None, results[:1100]) == 1100
    keys = [episode_key(r.spec) for r in results]
    assert db.stored_keys(keys) == set(keys[:1100])
    assert db.stored_keys([]) == set()


def test_filters_match_floats_and_reject_nonsense(db: ResultsDB) -> None:
    db.add_results(
        None,
        [
            make_result(floor="aniso", mu_floor_x=0.1, mu_floor_y=1.0, mu_pusher=0.5),
            make_result(floor="aniso", mu_floor_x=1.0, mu_floor_y=0.1, mu_pusher=0.5),
            make_result(mu_floor_x=1.0, mu_floor_y=1.0, speed_cm_s=4.0),
        ],
    )
    assert db.count(EpisodeFilter(mu_floor=1.0)) == 1
    assert db.count(EpisodeFilter(mu_floor_x=1.0)) == 2
    assert db.count(EpisodeFilter(floor="aniso", mu_floor_y=1.0)) == 1
    assert db.count(EpisodeFilter(speed_cm_s=4)) == 1
    assert db.count(EpisodeFilter(mu_pusher=0.1 + 0.2 - 0.2)) == 1  # 0.10000000000000003
    with pytest.raises(ValueError, match="either mu_floor"):
        EpisodeFilter(mu_floor=1.0, mu_floor_x=1.0)
    with pytest.raises(ValueError, match="status"):
        EpisodeFilter(status="maybe")
    with pytest.raises(ValueError, match="unknown episode column"):
        db.episodes(columns=["nope"])


def test_readonly_open_is_read_only(db: ResultsDB, tmp_path: Path) -> None:
    db.add_results(None, [make_result()])
    ro = ResultsDB(db.path, readonly=True)
    try:
        assert ro.count() == 1
        with pytest.raises(ValueError, match="read-only"):
            ro.add_results(None, [make_result(com_index=1)])
        with pytest.raises(ValueError, match="^cannot write database at .*: opened read-only$"):
            ro.check_writable()
        with (
            pytest.raises(Exception, match="readonly|read-only|query_only"),
            ro.engine.begin() as c,
        ):
            c.exec_driver_sql("DELETE FROM episodes")
    finally:
        ro.close()
    assert db.count() == 1
    with pytest.raises(ValueError, match="database not found"):
        ResultsDB(tmp_path / "missing.db", readonly=True)
    other = tmp_path / "other.db"
    create_engine(f"sqlite:///{other}").connect().exec_driver_sql("CREATE TABLE t (x)").close()
    with pytest.raises(ValueError, match="not a comexp results database"):
        ResultsDB(other, readonly=True)


def test_check_writable_reports_one_line(tmp_path: Path) -> None:
    ResultsDB(tmp_path / "ok.db").check_writable()
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with pytest.raises(ValueError) as info:
        ResultsDB(blocker / "r.db")
    msg = str(info.value)
    assert msg.startswith(f"cannot write database at {blocker / 'r.db'}: ") and "\n" not in msg
    garbage = tmp_path / "garbage.db"
    garbage.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(
        ValueError, match="^cannot write database at .*garbage.db: .*not a database"
    ):
        ResultsDB(garbage)


def test_url_form_and_postgres_statement() -> None:
    mem = ResultsDB("sqlite+pysqlite:///:memory:")
    # A pooled :memory: engine gives each connection its own database; one connection is enough
    # to see that URLs are accepted and the schema is created.
    mem.check_writable()
    mem.close()
    from sqlalchemy.dialects.postgresql import insert as pg_insert

    stmt = pg_insert(EPISODES).on_conflict_do_nothing(index_elements=["episode_key"])
    sql = str(stmt.compile(dialect=postgresql.dialect()))
    assert "ON CONFLICT (episode_key) DO NOTHING" in sql


WRITER = textwrap.dedent(
    """
    import sys, time
    sys.path.insert(0, {tests!r})
    from test_db import make_result
    from pathlib import Path
    from comexp.results.store import ResultsDB
    go = Path({path!r} + ".go")
    Path({path!r} + ".ready-" + sys.argv[1]).parent.mkdir(parents=True, exist_ok=True)
    Path({path!r} + ".ready-" + sys.argv[1]).touch()
    while not go.exists():  # start both writers at the same instant: they race for the schema
        time.sleep(0.001)
    db = ResultsDB({path!r})
    db.check_writable()
    sid = db.start_sweep(command_line="writer " + sys.argv[1], job_name=sys.argv[1])
    start, stop, step = (int(a) for a in sys.argv[2:5])
    for i in range(start, stop, step):
        batch = [make_result(object=f"obj{{j % 20}}", com_index=j) for j in range(i, i + step)]
        db.add_results(sid, batch)
        time.sleep(float(sys.argv[5]))
    db.close()
    print("done")
    """
)


def _writer(tmp_path: Path, path: Path, name: str, start: int, stop: int, step: int, pause: float):
    script = tmp_path / "writer.py"
    tests = str(Path(__file__).parent)
    script.write_text(WRITER.format(tests=tests, path=str(path)))
    args = [sys.executable, str(script), name, str(start), str(stop), str(step), str(pause)]
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _start_writers(path: Path, *names: str) -> None:
    """Release writers (waiting on a go file) once all of them have imported everything."""
    deadline = time.monotonic() + 60
    while not all(Path(f"{path}.ready-{n}").exists() for n in names):
        assert time.monotonic() < deadline, "writer processes did not start"
        time.sleep(0.01)
    Path(f"{path}.go").touch()


def test_two_writer_processes_neither_lose_rows_nor_lock(tmp_path: Path) -> None:
    path = tmp_path / "new" / "shared.db"
    # Both processes race to create the file and schema, then to insert episodes 200..399.
    a = _writer(tmp_path, path, "a", 0, 400, 20, 0.0)
    b = _writer(tmp_path, path, "b", 200, 600, 20, 0.0)
    _start_writers(path, "a", "b")
    for p in (a, b):
        out, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
        assert "locked" not in err and out.strip() == "done"
    with ResultsDB(path, readonly=True) as ro:
        rows = ro.episodes(columns=["com_index"])
        assert sorted(r["com_index"] for r in rows) == list(range(600))
        assert len(ro.sweeps()) == 2
    with ResultsDB(path) as rw, rw.engine.connect() as conn:
        assert conn.exec_driver_sql("PRAGMA integrity_check").scalar() == "ok"


def test_readonly_reader_works_during_a_writer(tmp_path: Path) -> None:
    path = tmp_path / "live.db"
    ResultsDB(path).close()
    writer = _writer(tmp_path, path, "w", 0, 600, 10, 0.01)
    _start_writers(path, "w")
    counts = []
    try:
        while writer.poll() is None:
            with ResultsDB(path, readonly=True) as ro:
                counts.append(ro.count())
                ro.stored_keys(["x"])
    finally:
        _, err = writer.communicate(timeout=120)
    assert writer.returncode == 0, err
    assert len(counts) >= 2 and counts == sorted(counts)
    with ResultsDB(path, readonly=True) as ro:
        assert ro.count() == 600


def _without_root_privileges() -> list[str]:
    """Command prefix that makes directory permissions bind even when the tests run as root."""
    if os.geteuid() != 0:
        return []
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("running as root without setpriv: cannot make a directory unwritable")
    return [setpriv, "--inh-caps=-all", "--bounding-set=-all", "--"]


def test_readonly_open_of_wal_database_in_unwritable_directory(tmp_path: Path) -> None:
    """No -shm file and no way to create one: the clean (checkpointed) file is still readable."""
    root = tmp_path / "ro"
    root.mkdir()
    path = root / "r.db"
    with ResultsDB(path) as rw:
        rw.add_results(None, [make_result(), make_result(com_index=1, failure="tipped")])
    assert not Path(f"{path}-wal").exists()  # the last writer checkpointed and removed it
    digest = sha256_file(path)
    code = textwrap.dedent(
        f"""
        import sqlite3
        from comexp.results.store import ResultsDB
        try:  # plain mode=ro must fail here, else this test would not test the fallback
            sqlite3.connect("file:{path}?mode=ro", uri=True).execute("select 1 from episodes")
            print("plain-ok")
        except sqlite3.OperationalError:
            print("plain-failed")
        print(ResultsDB({str(path)!r}, readonly=True).count())
        """
    )
    root.chmod(0o555)
    try:
        proc = subprocess.run(
            [*_without_root_privileges(), sys.executable, "-c", code],
            capture_output=True,
            text=True,
            timeout=60,
        )
    finally:
        root.chmod(0o755)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["plain-failed", "2"]
    assert sha256_file(path) == digest
    assert sorted(p.name for p in root.iterdir()) == ["r.db"]


def test_file_names_with_uri_characters(tmp_path: Path) -> None:
    path = tmp_path / "we?ird#dir" / "r%20 x.db"
    with ResultsDB(path) as rw:
        rw.add_results(None, [make_result()])
    assert sorted(p.name for p in path.parent.iterdir()) == ["r%20 x.db"]
    with ResultsDB(path, readonly=True) as ro:
        assert ro.count() == 1


# --- the database location ---------------------------------------------------------------


def test_sqlite_file_forms() -> None:
    """The one parser of a location: what the pre-run check probes is what opening opens."""
    assert sqlite_file("results/a.db") == Path("results/a.db")
    assert sqlite_file("sqlite:///results/a.db") == Path("results/a.db")
    assert sqlite_file("sqlite+pysqlite:////tmp/a.db") == Path("/tmp/a.db")
    assert sqlite_file("sqlite://") is None
    assert sqlite_file("postgresql://u@h/db") is None


def test_db_location_checks_create_nothing(tmp_path: Path) -> None:
    check_location(str(tmp_path / "new" / "a.db"))  # its own folder: made by the job
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="the folder .* does not exist"):
        check_location(str(tmp_path / "new" / "deeper" / "a.db"))  # a missing tree: refused
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="directory"):
        check_location(str(tmp_path))
    (tmp_path / "notes.txt").write_text("not a database")
    with pytest.raises(ValueError, match="not an SQLite database"):
        check_location(str(tmp_path / "notes.txt"))
    with pytest.raises(ValueError, match="cannot create"):
        check_location("/proc/comexp/a.db")
    check_location("postgresql://user@localhost/comexp")  # checked when connecting


def test_location_check_and_opening_agree_on_the_file(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path}/u.db"
    assert sqlite_file(url) == tmp_path / "u.db"
    with ResultsDB(url) as db:
        assert db.path == sqlite_file(url)
    check_location(url)  # an SQLite file now: accepted
    assert sqlite_file("sqlite:///~/a.db") == Path("~/a.db")  # SQLite does not expand ~ either
