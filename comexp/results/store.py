"""Results database: one row per episode, one per push, one per sweep (SQLAlchemy 2).

SQLite in WAL mode is the embedded default; any SQLAlchemy URL works too. PostgreSQL needs
the psycopg 3 driver (``pip install 'comexp[postgres]'``); a ``postgresql://`` URL uses it.
A password in a URL is never printed or stored: `redact_url` is what goes into messages.
Why the SQLite details matter:
- the driver alone writes, in short ``BEGIN IMMEDIATE`` transactions with a long busy timeout,
  so two writers (two sweeps on one file) queue instead of failing with "database is locked";
- readers open the file with ``mode=ro`` (the query command must never change results), and WAL
  lets them read while a sweep is writing;
- every episode has a UNIQUE ``episode_key`` (a hash of its whole spec), and inserts use
  ``ON CONFLICT DO NOTHING``, so a resumed or raced sweep never stores an episode twice.
"""

from __future__ import annotations

import logging
import os
import random
import sqlite3
import tempfile
import time
import urllib.parse
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from sqlalchemy import (
    Engine,
    Integer,
    create_engine,
    delete,
    event,
    func,
    insert,
    inspect,
    select,
    update,
)
from sqlalchemy.engine import URL, make_url
from sqlalchemy.exc import IntegrityError, OperationalError, SQLAlchemyError
from sqlalchemy.pool import StaticPool

from comexp.episode.task import EpisodeResult
from comexp.results import migrations
from comexp.results.filters import EpisodeFilter
from comexp.results.identity import episode_key
from comexp.results.schema import (
    EPISODES,
    META,
    PUSHES,
    SCHEMA_VERSION,
    SWEEPS,
    Base,
    episode_row,
    push_row,
    utcnow,
)

log = logging.getLogger("comexp.results.store")
BUSY_TIMEOUT_MS = 60_000  # a writer waits this long for the other writer's short transaction
_IN_CHUNK = 500  # keys per IN (...) clause, well under SQLite's bound-parameter limit
_SCHEMA_LOCK_ID = 0x636F6D6578  # "comex": PostgreSQL advisory lock taken while creating tables


# --------------------------------------------------------------------------- database
POSTGRES_HINT = "pip install 'comexp[postgres]' (psycopg 3)"


def _is_url(target: str) -> bool:
    return "://" in target


def normalize_url(url: str | URL) -> URL:
    """`postgresql://` means psycopg 3 here (SQLAlchemy's own default would be psycopg2)."""
    u = make_url(url)
    if u.drivername in ("postgresql", "postgres"):
        u = u.set(drivername="postgresql+psycopg")
    return u


def redact_url(url: str | os.PathLike[str]) -> str:
    """The database location as it may be printed, logged or stored: no password."""
    text = os.fspath(url)
    if not _is_url(text):
        return text
    try:
        u = make_url(text)
    except Exception:  # noqa: BLE001 - not a URL SQLAlchemy understands: hide after the scheme
        scheme, _, rest = text.partition("://")
        return f"{scheme}://***@{rest.rpartition('@')[2]}" if "@" in rest else text
    return u.render_as_string(hide_password=True) if u.password else text


def url_password(url: str) -> str | None:
    """The password written in a URL (to scrub it from files), None when there is none."""
    if not _is_url(url):
        return None
    try:
        return make_url(url).password
    except Exception:  # noqa: BLE001
        return None


def redact(text: str, url: str | os.PathLike[str]) -> str:
    """`text` with the database URL's password replaced (the URL itself by its redacted form):
    the one redaction of every line and file a job writes."""
    url = os.fspath(url)
    password = url_password(url)
    if not password:
        return text
    text = text.replace(url, redact_url(url))
    for form in {password, urllib.parse.quote(password, safe=""), urllib.parse.quote(password)}:
        text = text.replace(form, "***")
    return text


def _create_engine(url: str | URL, **kwargs: Any) -> Engine:
    """`create_engine` with a one-line error when the database's driver is not installed."""
    u = normalize_url(url)
    try:
        return create_engine(u, **kwargs)
    except ImportError as exc:
        backend = u.get_backend_name()
        hint = POSTGRES_HINT if backend == "postgresql" else f"install a driver for {backend}"
        raise ValueError(f"no database driver for {backend} ({exc.name}): {hint}") from None


def sqlite_file(target: str | os.PathLike[str]) -> Path | None:
    """The file behind a database location when it is SQLite: a plain path, or a sqlite://
    URL naming a file; None for another database or SQLite in memory. The one parser of a
    location, for opening it and for checking it before a run."""
    text = os.fspath(target)
    if not _is_url(text):
        return Path(text).expanduser()
    u = make_url(text)
    if u.get_backend_name() != "sqlite":
        return None
    db = u.database or ""
    if db in ("", ":memory:") or db.startswith("file:"):
        return None
    return Path(db)  # as SQLite opens it: no ~ expansion in a URL


def check_location(target: str | os.PathLike[str]) -> None:
    """Fail early, leaving nothing behind, when an SQLite file could not be created or written
    (ValueError, one line); other databases are checked when connecting.

    Probes for real (permission bits lie for root and on read-only mounts): an existing file
    is opened for update, otherwise a temporary file is created in the nearest existing parent.
    """
    path = sqlite_file(target)
    if path is None:
        return
    if path.is_dir():
        raise ValueError(f"{str(path)!r} is a directory, not a database file")
    if path.exists():
        try:
            with open(path, "r+b") as f:
                head = f.read(16)
        except OSError as e:
            raise ValueError(f"cannot write to {str(path)!r}: {e.strerror}") from None
        if head and head != b"SQLite format 3\x00":
            raise ValueError(f"{str(path)!r} exists and is not an SQLite database")
        return
    parent = path.absolute().parent
    if not parent.exists() and not parent.parent.is_dir():
        # the file's own folder is made (results/ on a first run); a deeper missing tree is
        # more likely a mistyped path than a request to create it
        raise ValueError(
            f"cannot create {str(path)!r}: the folder {str(parent.parent)!r} does not exist"
        )
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise ValueError(f"cannot create {str(path)!r}: {str(parent)!r} is not a directory")
    try:
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as e:
        raise ValueError(
            f"cannot create {str(path)!r}: {str(parent)!r} is not writable ({e.strerror})"
        ) from None


class ResultsDB:
    """Writable (driver) or read-only (queries) handle on the results database."""

    def __init__(self, url_or_path: str | os.PathLike[str], *, readonly: bool = False) -> None:
        target = os.fspath(url_or_path)
        self.readonly = readonly
        # one line when the database had an earlier schema: upgraded in place (writable), or
        # read through an upgraded copy in memory (read-only); None otherwise
        self.schema_note: str | None = None
        self.url: str | URL
        self.path = sqlite_file(target)
        if _is_url(target):
            self.url = target
        else:  # built, not parsed: a file name may contain '?', '#' or '%'
            self.url = URL.create("sqlite+pysqlite", database=str(self.path))
        self.where = (
            str(self.path)
            if self.path is not None
            else make_url(self.url).render_as_string(hide_password=True)
        )
        self.is_sqlite = make_url(self.url).get_backend_name() == "sqlite"
        if readonly:
            self.engine = self._open_readonly()
        else:
            self.engine = self._open_writable()

    # ----------------------------------------------------------------- opening
    def _open_writable(self) -> Engine:
        try:
            if self.path is not None:
                self.path.parent.mkdir(parents=True, exist_ok=True)
            engine = _create_engine(self.url)
            if self.is_sqlite:
                _install_sqlite_hooks(engine, begin="BEGIN IMMEDIATE", wal=True)
            with engine.begin() as conn:  # serialised: two processes may create the schema
                if conn.dialect.name == "postgresql":
                    # concurrent CREATE TABLEs collide in PostgreSQL's catalog (duplicate key
                    # in pg_type): one creator at a time; the lock ends with the transaction
                    conn.exec_driver_sql(f"SELECT pg_advisory_xact_lock({_SCHEMA_LOCK_ID})")
                Base.metadata.create_all(conn)
                version = conn.execute(select(META.c.value).where(META.c.key == "schema")).scalar()
                if version is None:
                    conn.execute(insert(META).values(key="schema", value=str(SCHEMA_VERSION)))
                else:
                    note = migrations.upgrade(conn)  # in this transaction: all or nothing
                    if note is not None:
                        self.schema_note = f"{self.where}: {note}, in place"
                        log.warning("%s", self.schema_note)
            return engine
        except (OSError, SQLAlchemyError, ValueError) as exc:
            raise ValueError(f"cannot write database at {self.where}: {_reason(exc)}") from exc

    def _open_readonly(self) -> Engine:
        engine = self._open_readonly_engine()
        try:
            with engine.connect() as conn:
                stale = migrations.needs_upgrade(conn)
                version = migrations.stored_version(conn)
        except SQLAlchemyError as exc:
            engine.dispose()
            raise ValueError(f"cannot read database {self.where}: {_reason(exc)}") from exc
        if not stale:
            return engine
        if version is not None and version > SCHEMA_VERSION:
            engine.dispose()
            raise ValueError(
                f"{self.where}: schema version {version}, this comexp reads {SCHEMA_VERSION}: "
                "use a newer comexp"
            )
        if not self.is_sqlite:
            engine.dispose()
            raise ValueError(
                f"{self.where}: schema version {version}, this comexp reads {SCHEMA_VERSION}: "
                "run a job on it once (that upgrades it in place), then read it"
            )
        return self._upgraded_copy(engine, version)

    def _upgraded_copy(self, engine: Engine, version: int | None) -> Engine:
        """An old SQLite database, copied into memory (a consistent snapshot, even while a
        writer is busy) and upgraded there; the file stays as it is."""
        raw = engine.raw_connection()
        try:
            mem = sqlite3.connect(":memory:", check_same_thread=False)
            raw.driver_connection.backup(mem)
        finally:
            raw.close()
            engine.dispose()
        copy = create_engine("sqlite://", creator=lambda: mem, poolclass=StaticPool)
        _install_sqlite_hooks(copy, begin="BEGIN", wal=False)
        with copy.begin() as conn:
            note = migrations.upgrade(conn)
        mem.execute("PRAGMA query_only = 1")
        self.schema_note = (
            f"{self.where} has schema version {version} (this comexp: {SCHEMA_VERSION}): read "
            f"through an upgraded copy in memory ({note}); a job writing to it upgrades the file"
        )
        log.info("%s", self.schema_note)
        return copy

    def _open_readonly_engine(self) -> Engine:
        if self.path is not None:
            if not self.path.is_file():
                raise ValueError(f"database not found: {self.path}")
            engine = self._readonly_sqlite(immutable=False)
            try:
                self._check_schema(engine)
            except OperationalError as exc:
                # A WAL file cannot be opened read-only when its -shm index is missing and the
                # directory is not writable. If no -wal file exists either, the main file holds
                # everything (the last writer checkpointed), so reading it as immutable is safe.
                engine.dispose()
                wal = Path(str(self.path) + "-wal")
                if wal.exists() or os.access(self.path.parent, os.W_OK):
                    raise ValueError(f"cannot read database {self.path}: {_reason(exc)}") from exc
                engine = self._readonly_sqlite(immutable=True)
                try:
                    self._check_schema(engine)
                except OperationalError as exc2:
                    raise ValueError(f"cannot read database {self.path}: {_reason(exc2)}") from exc2
            return engine
        kwargs: dict[str, Any] = {}
        if make_url(self.url).get_backend_name() == "postgresql":
            # every transaction of this handle is READ ONLY: the server refuses writes
            kwargs["connect_args"] = {"options": "-c default_transaction_read_only=on"}
        engine = _create_engine(self.url, **kwargs)
        if self.is_sqlite:
            _install_sqlite_hooks(engine, begin="BEGIN", wal=False, query_only=True)
        try:
            self._check_schema(engine)
        except SQLAlchemyError as exc:
            raise ValueError(f"cannot read database {self.where}: {_reason(exc)}") from exc
        return engine

    def _readonly_sqlite(self, *, immutable: bool) -> Engine:
        assert self.path is not None
        query = {"mode": "ro", "uri": "true"} | ({"immutable": "1"} if immutable else {})
        uri_path = "file:" + urllib.parse.quote(self.path.resolve().as_posix())
        engine = _create_engine(URL.create("sqlite+pysqlite", database=uri_path, query=query))
        _install_sqlite_hooks(engine, begin="BEGIN", wal=False, query_only=True)
        return engine

    def _check_schema(self, engine: Engine) -> None:
        names = set(inspect(engine).get_table_names())
        missing = {"episodes", "pushes", "sweeps"} - names
        if missing:
            raise ValueError(
                f"{self.where} is not a comexp results database (missing tables: "
                f"{', '.join(sorted(missing))})"
            )

    def close(self) -> None:
        self.engine.dispose()

    def __enter__(self) -> ResultsDB:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------- writing
    def check_writable(self) -> None:
        """Fail early (before hours of simulation) if results could not be stored."""
        if self.readonly:
            raise ValueError(f"cannot write database at {self.where}: opened read-only")
        try:
            with self.engine.connect() as conn, conn.begin() as tx:
                conn.execute(update(META).where(META.c.key == "schema").values(value=META.c.value))
                tx.rollback()
        except SQLAlchemyError as exc:
            raise ValueError(f"cannot write database at {self.where}: {_reason(exc)}") from exc

    def start_sweep(
        self,
        *,
        command_line: str = "",
        config_yaml: str = "",
        job_name: str = "",
        versions: dict[str, Any] | None = None,
        git_rev: str | None = None,
    ) -> int:
        self._require_writable()
        with self.engine.begin() as conn:
            row = conn.execute(
                insert(SWEEPS)
                .values(
                    started_at=utcnow(),
                    command_line=command_line,
                    config=config_yaml,
                    job_name=job_name,
                    versions=dict(versions or {}),
                    git_rev=git_rev,
                    host=os.uname().nodename if hasattr(os, "uname") else "",
                )
                .returning(SWEEPS.c.id)
            )
            return int(row.scalar_one())

    def stored_keys(self, keys: Iterable[str]) -> set[str]:
        """The subset of `keys` already stored (the resume check)."""
        wanted = list(dict.fromkeys(keys))
        found: set[str] = set()
        with self.engine.connect() as conn:
            for i in range(0, len(wanted), _IN_CHUNK):
                chunk = wanted[i : i + _IN_CHUNK]
                q = select(EPISODES.c.episode_key).where(EPISODES.c.episode_key.in_(chunk))
                found.update(conn.execute(q).scalars())
        return found

    def add_results(self, sweep_id: int | None, results: Sequence[EpisodeResult]) -> int:
        """Store a batch in one transaction; returns how many were new (stored keys are skipped)."""
        self._require_writable()
        rows: dict[str, dict[str, Any]] = {}
        pushes: dict[str, list[dict[str, Any]]] = {}
        for r in results:
            key = episode_key(r.spec)
            if key not in rows:
                rows[key] = episode_row(sweep_id, key, r)
                pushes[key] = [push_row(p) for p in r.pushes]
        if not rows:
            return 0
        with self.engine.begin() as conn:
            ids = self._insert_new_episodes(conn, list(rows.values()))
            push_rows = [
                {"episode_id": ids[key], **p} for key in rows if key in ids for p in pushes[key]
            ]
            if push_rows:
                conn.execute(insert(PUSHES), push_rows)
        return len(ids)

    def replace_failed(self, sweep_id: int | None, results: Sequence[EpisodeResult]) -> int:
        """Store a batch of reruns of failed episodes (`retry=failed`) in one transaction: each
        stored row that is still `failed` is updated in place (its id kept, its pushes
        replaced); a result whose key is not stored is inserted as `add_results` does. Never
        two rows of one key. Returns how many rows were written."""
        self._require_writable()
        rows = {episode_key(r.spec): r for r in results}
        if not rows:
            return 0
        with self.engine.begin() as conn:
            q = select(EPISODES.c.episode_key, EPISODES.c.id).where(
                EPISODES.c.episode_key.in_(list(rows)), EPISODES.c.status == "failed"
            )
            failed = {key: int(id_) for key, id_ in conn.execute(q)}
            for key, id_ in failed.items():
                values = episode_row(sweep_id, key, rows[key])
                conn.execute(update(EPISODES).where(EPISODES.c.id == id_).values(**values))
                conn.execute(delete(PUSHES).where(PUSHES.c.episode_id == id_))
                pushes = [{"episode_id": id_, **push_row(p)} for p in rows[key].pushes]
                if pushes:
                    conn.execute(insert(PUSHES), pushes)
        rest = [r for key, r in rows.items() if key not in failed]
        return len(failed) + (self.add_results(sweep_id, rest) if rest else 0)

    def failed_keys(self, keys: Iterable[str]) -> set[str]:
        """The subset of `keys` stored as failed (what `retry=failed` reruns)."""
        wanted = list(dict.fromkeys(keys))
        found: set[str] = set()
        with self.engine.connect() as conn:
            for i in range(0, len(wanted), _IN_CHUNK):
                chunk = wanted[i : i + _IN_CHUNK]
                q = select(EPISODES.c.episode_key).where(
                    EPISODES.c.episode_key.in_(chunk), EPISODES.c.status == "failed"
                )
                found.update(conn.execute(q).scalars())
        return found

    def _insert_new_episodes(self, conn: Any, rows: list[dict[str, Any]]) -> dict[str, int]:
        """Insert rows whose key is not stored yet; returns {key: new id}. Relies on UNIQUE."""
        dialect = conn.dialect.name
        if dialect in ("sqlite", "postgresql"):
            if dialect == "sqlite":
                from sqlalchemy.dialects.sqlite import insert as dialect_insert
            else:
                from sqlalchemy.dialects.postgresql import insert as dialect_insert
            stmt = (
                dialect_insert(EPISODES)
                .on_conflict_do_nothing(index_elements=["episode_key"])
                .returning(EPISODES.c.id, EPISODES.c.episode_key)
            )
            ids: dict[str, int] = {}
            for i in range(0, len(rows), _IN_CHUNK):
                result = conn.execute(stmt, rows[i : i + _IN_CHUNK])
                ids.update({key: int(id_) for id_, key in result})
            return ids
        # Other databases: insert one by one inside a savepoint, skipping duplicates.
        ids = {}
        for row in rows:
            try:
                with conn.begin_nested():
                    new_id = conn.execute(
                        insert(EPISODES).values(**row).returning(EPISODES.c.id)
                    ).scalar_one()
                ids[row["episode_key"]] = int(new_id)
            except IntegrityError:
                continue
        return ids

    def _require_writable(self) -> None:
        if self.readonly:
            raise ValueError(f"cannot write database at {self.where}: opened read-only")

    # ----------------------------------------------------------------- reading
    def episodes(
        self,
        flt: EpisodeFilter | None = None,
        *,
        columns: Sequence[str] | None = None,
        limit: int | None = None,
        order_by_id: bool = True,
    ) -> list[dict[str, Any]]:
        """Episode rows as dicts (all columns unless `columns` names some), filtered."""
        flt = flt or EpisodeFilter()
        if columns is None:
            cols = list(EPISODES.c)
        else:
            unknown = [c for c in columns if c not in EPISODES.c]
            if unknown:
                raise ValueError(f"unknown episode column(s): {', '.join(unknown)}")
            cols = [EPISODES.c[c] for c in columns]
        q = select(*cols).where(*flt.clauses())
        if order_by_id:
            q = q.order_by(EPISODES.c.id)
        if limit is not None:
            q = q.limit(limit)
        with self.engine.connect() as conn:
            return [dict(m) for m in conn.execute(q).mappings()]

    def episodes_by_keys(
        self, keys: Iterable[str], *, columns: Sequence[str] | None = None
    ) -> list[dict[str, Any]]:
        """The stored episodes among `keys` (a job's own grid), by id."""
        cols = list(EPISODES.c) if columns is None else [EPISODES.c[c] for c in columns]
        wanted = list(dict.fromkeys(keys))
        out: list[dict[str, Any]] = []
        with self.engine.connect() as conn:
            for i in range(0, len(wanted), _IN_CHUNK):
                chunk = wanted[i : i + _IN_CHUNK]
                q = select(*cols, EPISODES.c.id.label("_id")).where(
                    EPISODES.c.episode_key.in_(chunk)
                )
                out += [dict(m) for m in conn.execute(q).mappings()]
        out.sort(key=lambda r: r["_id"])
        for r in out:
            del r["_id"]
        return out

    def episode(self, episode_id: int) -> dict[str, Any]:
        """One episode row (all columns); ValueError naming the stored range when absent."""
        with self.engine.connect() as conn:
            row = conn.execute(select(EPISODES).where(EPISODES.c.id == episode_id)).mappings()
            found = row.first()
            if found is None:
                ids = select(func.min(EPISODES.c.id), func.max(EPISODES.c.id))
                lo, hi = conn.execute(ids).one()
                stored = "none stored" if lo is None else f"stored ids {lo}..{hi}"
                raise ValueError(f"no episode with id {episode_id} ({stored})")
            return dict(found)

    def sweep(self, sweep_id: int) -> dict[str, Any] | None:
        """One sweep row (all columns), None when absent."""
        with self.engine.connect() as conn:
            q = select(SWEEPS).where(SWEEPS.c.id == sweep_id)
            found = conn.execute(q).mappings().first()
            return None if found is None else dict(found)

    def count(self, flt: EpisodeFilter | None = None) -> int:
        flt = flt or EpisodeFilter()
        q = select(func.count()).select_from(EPISODES).where(*flt.clauses())
        with self.engine.connect() as conn:
            return int(conn.execute(q).scalar_one())

    def distinct(self, column: str) -> list[Any]:
        """Stored values of one episode column (to tell a user what a filter could match)."""
        if column not in EPISODES.c:
            raise ValueError(f"unknown episode column: {column}")
        col = EPISODES.c[column]
        with self.engine.connect() as conn:
            return list(conn.execute(select(col).distinct().order_by(col)).scalars())

    def pushes(self, episode_id: int) -> list[dict[str, Any]]:
        q = select(PUSHES).where(PUSHES.c.episode_id == episode_id).order_by(PUSHES.c.k)
        with self.engine.connect() as conn:
            return [dict(m) for m in conn.execute(q).mappings()]

    def sweeps(self) -> list[dict[str, Any]]:
        """Sweeps with their episode counts (ok / failed)."""
        ok = func.sum((EPISODES.c.status == "ok").cast(Integer))
        counts = (
            select(
                EPISODES.c.sweep_id,
                func.count().label("n_episodes"),
                ok.label("n_ok"),
            )
            .group_by(EPISODES.c.sweep_id)
            .subquery()
        )
        q = (
            select(SWEEPS, counts.c.n_episodes, counts.c.n_ok)
            .outerjoin(counts, counts.c.sweep_id == SWEEPS.c.id)
            .order_by(SWEEPS.c.id)
        )
        with self.engine.connect() as conn:
            out = []
            for m in conn.execute(q).mappings():
                d = dict(m)
                d["n_episodes"] = int(d["n_episodes"] or 0)
                d["n_ok"] = int(d["n_ok"] or 0)
                out.append(d)
            return out


# --------------------------------------------------------------------------- helpers
def _install_sqlite_hooks(
    engine: Engine, *, begin: str, wal: bool, query_only: bool = False
) -> None:
    """Take transaction control from the sqlite3 module (see SQLAlchemy's SQLite docs).

    With the driver's implicit BEGIN disabled we emit our own: ``BEGIN IMMEDIATE`` for writers
    takes the write lock up front, so a second writer waits on the busy timeout instead of
    failing on a lock upgrade (which SQLite reports as "database is locked" at once).
    """

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_conn: Any, _record: Any) -> None:
        dbapi_conn.isolation_level = None
        cur = dbapi_conn.cursor()
        cur.execute(f"PRAGMA busy_timeout = {BUSY_TIMEOUT_MS}")
        if wal:
            _ensure_wal(cur)
            cur.execute("PRAGMA synchronous = NORMAL")
        if query_only:
            cur.execute("PRAGMA query_only = 1")
        cur.execute("PRAGMA foreign_keys = ON")
        cur.close()

    @event.listens_for(engine, "begin")
    def _on_begin(conn: Any) -> None:
        conn.exec_driver_sql(begin)


def _ensure_wal(cur: Any) -> None:
    """Switch a new file to WAL. Two processes creating the file at once can make the switch
    fail with "database is locked" without SQLite's busy handler ever waiting, so retry here."""
    deadline = time.monotonic() + BUSY_TIMEOUT_MS / 1000
    while True:
        try:
            if cur.execute("PRAGMA journal_mode").fetchone()[0].lower() != "wal":
                cur.execute("PRAGMA journal_mode = WAL")
            return
        except sqlite3.OperationalError as exc:
            if "locked" not in str(exc) or time.monotonic() > deadline:
                raise
            time.sleep(random.uniform(0.005, 0.05))


def _reason(exc: BaseException) -> str:
    """One line: the driver's message without SQLAlchemy's SQL echo and background link."""
    orig = getattr(exc, "orig", None)
    text = str(orig if orig is not None else exc)
    return text.strip().splitlines()[0] if text.strip() else type(exc).__name__
