"""Schema migrations: a database written by an earlier comexp keeps working.

`MIGRATIONS[v]` upgrades a database at schema version `v` to `v + 1`. Every change so far added
columns, so each migration adds its columns (when missing: every step can run twice) with a
value for the rows already stored, taken from the stored `spec` JSON when that field is in it,
else the value that describes what the old comexp did:

- 1 -> 2: `episodes.worker` ('' : not recorded), `episodes.recenter_beyond_cm` (the spec's, else
  NULL: not recorded);
- 2 -> 3: `episodes.physics` (the spec's, else '': the physics was not pinned; `replay` runs
  such an episode with the backend's default options);
- 3 -> 4: `pushes.n_frames` (0: the measured turn came from the images before and after, the
  only way before tracking) and `episodes.camera_fps` (the spec's, else 0). Early version-4
  files lack `episodes.camera_fps` (it came later under the same number): `upgrade` adds any
  column a migration adds that is still missing at the current version;
- 4 -> 5: `pushes.region_cm` (NULL: the region the estimator kept was not stored; `comexp-db
  show` redraws it from the stored pushes and says so).

A job (a writable `ResultsDB`) upgrades the file in place, in the transaction that opens it, and
records the new version; a reader (`comexp-db`, `load_results`) of an old SQLite file works on an
upgraded copy in memory and leaves the file as it is. Adding a version: bump
`schema.SCHEMA_VERSION`, add its step here, and a fixture under tests/fixtures/
(`make_old_schemas.py` writes them from git history).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from sqlalchemy import Connection, bindparam, inspect, select, text, update

from comexp.results.schema import EPISODES, META, PUSHES, SCHEMA_VERSION


@dataclass(frozen=True)
class Added:
    """A column added to an existing table: the value stored rows get, or the `spec` field
    to take it from when present (`fallback` otherwise)."""

    table: str
    column: str
    fallback: Any
    from_spec: str | None = None


@dataclass(frozen=True)
class Migration:
    what: str
    columns: tuple[Added, ...]


MIGRATIONS: dict[int, Migration] = {
    1: Migration(
        "episodes.worker, episodes.recenter_beyond_cm",
        (
            Added("episodes", "worker", ""),
            Added("episodes", "recenter_beyond_cm", None, from_spec="recenter_beyond_cm"),
        ),
    ),
    2: Migration("episodes.physics", (Added("episodes", "physics", "", from_spec="physics"),)),
    3: Migration(
        "pushes.n_frames, episodes.camera_fps",
        (
            Added("pushes", "n_frames", 0),
            Added("episodes", "camera_fps", 0.0, from_spec="camera_fps"),
        ),
    ),
    4: Migration("pushes.region_cm", (Added("pushes", "region_cm", None),)),
}
_TABLES = {"episodes": EPISODES, "pushes": PUSHES}


class SchemaError(ValueError):
    """A database this comexp cannot read or upgrade (one line)."""


def stored_version(conn: Connection) -> int | None:
    """The schema version a database records (None: no comexp_meta table or row)."""
    if "comexp_meta" not in inspect(conn).get_table_names():
        return None
    value = conn.execute(select(META.c.value).where(META.c.key == "schema")).scalar()
    return None if value is None else int(value)


def missing_columns(conn: Connection) -> list[str]:
    """`table.column` of every column the current models have and the database lacks."""
    insp = inspect(conn)
    out = []
    for name, table in _TABLES.items():
        have = {c["name"] for c in insp.get_columns(name)}
        out += [f"{name}.{c.name}" for c in table.c if c.name not in have]
    return out


def needs_upgrade(conn: Connection) -> bool:
    """A comexp database (it records its version) of another layout than this comexp's."""
    version = stored_version(conn)
    if version is None:
        return False
    return version != SCHEMA_VERSION or bool(missing_columns(conn))


def upgrade(conn: Connection, log: Callable[[str], None] | None = None) -> str | None:
    """Bring the database on `conn` to `SCHEMA_VERSION`, inside the caller's transaction.
    Returns one line saying what changed (None when nothing did); SchemaError when the file
    is newer than this comexp or a column is missing that no migration adds."""
    version = stored_version(conn)
    if version is None:
        return None
    if version > SCHEMA_VERSION:
        raise SchemaError(
            f"schema version {version}, this comexp reads and writes {SCHEMA_VERSION}: "
            "use a newer comexp"
        )
    steps = [MIGRATIONS[v] for v in range(version, SCHEMA_VERSION)]
    before = set(missing_columns(conn))
    # every step's columns, once more for the early files of the current version
    for step in [*steps, *MIGRATIONS.values()]:
        for added in step.columns:
            if f"{added.table}.{added.column}" in missing_columns(conn):
                _add_column(conn, added)
    left = missing_columns(conn)
    if left:
        raise SchemaError(f"columns no migration adds: {', '.join(left)}")
    if version != SCHEMA_VERSION:
        conn.execute(update(META).where(META.c.key == "schema").values(value=str(SCHEMA_VERSION)))
    if not before:
        return None if version == SCHEMA_VERSION else f"schema version {version} upgraded"
    added = ", ".join(sorted(before))
    if version == SCHEMA_VERSION:
        return f"schema version {version} completed (added {added})"
    return f"schema version {version} upgraded to {SCHEMA_VERSION} (added {added})"


def _add_column(conn: Connection, added: Added) -> None:
    table = _TABLES[added.table]
    col = table.c[added.column]
    prep = conn.dialect.identifier_preparer
    ddl = f"ALTER TABLE {prep.format_table(table)} ADD COLUMN {prep.format_column(col)} "
    ddl += col.type.compile(dialect=conn.dialect)
    if added.fallback is not None:
        ddl += f" DEFAULT {_literal(added.fallback)}"
        if not col.nullable:
            ddl += " NOT NULL"
    conn.execute(text(ddl))
    if added.from_spec is None:
        return
    values = []
    for id_, spec in conn.execute(select(table.c.id, table.c.spec)):
        try:
            stored = json.loads(spec)
        except (TypeError, ValueError):
            continue
        if isinstance(stored, dict) and stored.get(added.from_spec) is not None:
            values.append({"_id": id_, "_v": stored[added.from_spec]})
    if values:
        stmt = update(table).where(table.c.id == bindparam("_id"))
        conn.execute(stmt.values({added.column: bindparam("_v")}), values)


def _literal(v: Any) -> str:
    if isinstance(v, str):
        return "'" + v.replace("'", "''") + "'"
    return repr(v)
