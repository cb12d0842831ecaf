"""The notebook API: `run` (a job, as the command line runs it), `load_results` (pandas) and
`replay`.

    import comexp
    df = comexp.run(["backend=planar", "grid.objects=[l_shape]"])  # this job's episodes
    df = comexp.load_results("results/comexp.db")            # one row per episode
    result = comexp.replay("results/comexp.db", episode_id=12)  # run it again, in-process

`load_results` adds a `condition` column (the label of `comexp.results.reports.group_episodes`'s
grouping rule), so a notebook groups exactly as the tables and plots do.
"""

from __future__ import annotations

import codecs
import contextlib
import dataclasses
import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
import typing
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from comexp.results.schema import EPISODES, PUSHES, SWEEPS
from comexp.results.store import ResultsDB

if TYPE_CHECKING:
    import pandas as pd

    from comexp.experiment.task import EpisodeResult, EpisodeSpec

TABLES = {"episodes": EPISODES, "pushes": PUSHES, "sweeps": SWEEPS}
DbLike = ResultsDB | str | os.PathLike[str]


def _open(db: DbLike) -> tuple[ResultsDB, bool]:
    if isinstance(db, ResultsDB):
        return db, False
    return ResultsDB(db, readonly=True), True


def load_results(db: DbLike, table: str = "episodes") -> pd.DataFrame:
    """One stored table as a pandas DataFrame (read-only). `episodes` gets two more columns:
    `condition` (the grouping rule's label) and `condition_slug` (its short unique name)."""
    from sqlalchemy import select

    if table not in TABLES:
        raise ValueError(f"unknown table {table!r}; choose one of {', '.join(TABLES)}")
    handle, owned = _open(db)
    try:
        t = TABLES[table]
        with handle.engine.connect() as conn:
            rows = [dict(m) for m in conn.execute(select(t).order_by(t.c.id)).mappings()]
    finally:
        if owned:
            handle.close()
    return _frame(rows, table)


def _frame(rows: list[dict[str, Any]], table: str = "episodes") -> pd.DataFrame:
    import pandas as pd

    t = TABLES[table]
    df = pd.DataFrame(rows, columns=[c.name for c in t.c])
    if table == "episodes":
        from comexp.results.reports import condition_of

        conds = [condition_of(r) for r in rows]
        df["condition"] = pd.Series([c.label() for c in conds], index=df.index, dtype=object)
        df["condition_slug"] = pd.Series([c.slug() for c in conds], index=df.index, dtype=object)
    return df


# --------------------------------------------------------------------------- run
def run(overrides: Sequence[str] = (), *, config_dir: str | os.PathLike[str] | None = None):
    """Run one job, as `comexp OVERRIDES...` does, and return its episodes as the DataFrame
    `load_results` gives (this job's grid only, whoever stored them: a rerun returns the
    stored rows without running anything again).

    It is the command line itself: `comexp OVERRIDES` runs in a child process (the job's
    Ray, database, reports and printed lines are the command's), then this job's rows are
    read back by their episode keys. The child's output is passed on while it runs, as it
    comes, to this process's `sys.stdout` and `sys.stderr` (a notebook's cell output): its
    log lines, its progress bar (tqdm's carriage-return updates, forced on with
    `COMEXP_PROGRESS=bar`) and, on failure, its error. `config_dir` is `--config-dir` (your
    own objects: DIR/object/NAME.yaml).

    Bad input raises ValueError with the command line's one-line message; nothing is
    written then. One job per call: call it once per job of a sweep.
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    from comexp.cli import run as cli
    from comexp.workers.driver import PROGRESS_ENV

    if isinstance(overrides, str):
        raise TypeError("overrides: a list of strings, e.g. ['backend=planar', 'speed=4']")
    args = [str(a) for a in overrides]
    if any(a in ("-m", "--multirun") or a.startswith("-") for a in args):
        raise ValueError(f"comexp.run takes overrides only (one job per call), got {args}")
    try:
        parsed = OverridesParser.create().parse_overrides(args)
    except HydraException as e:
        raise ValueError(cli._hydra_error_line(e)) from None
    sweeps = [o.input_line for o in parsed if o.is_sweep_override()]
    if sweeps:
        raise ValueError(f"comexp.run runs one job; call it once per value of: {sweeps}")
    extra: list[str] = []
    if config_dir is not None:
        path = os.path.abspath(config_dir)
        if not os.path.isdir(path):
            raise ValueError(f"config_dir {path!r} not found")
        extra = ["--config-dir", path]
    env = {"RAY_USAGE_STATS_ENABLED": "0", **os.environ, PROGRESS_ENV: "bar"}
    returncode, stderr = _run_streaming(
        [sys.executable, "-u", "-c", "from comexp.cli.run import main; main()", *extra, *args],
        env,
    )
    if returncode != 0:
        lines = [ln for ln in stderr.splitlines() if ln.strip()]
        line = lines[-1] if lines else f"comexp exited with {returncode}"
        raise ValueError(line.removeprefix("comexp: error: "))
    db, keys = _job_keys(args, extra[1] if extra else None)
    with ResultsDB(db, readonly=True) as handle:
        return _frame(handle.episodes_by_keys(keys))


def _run_streaming(cmd: list[str], env: dict[str, str]) -> tuple[int, str]:
    """Run `cmd`, passing its stdout and stderr on to `sys.stdout` and `sys.stderr` as they
    come; returns the exit code and the whole stderr (`_PassedOn`)."""
    child = _PassedOn(cmd, env)
    try:
        child.pass_on()
        returncode = child.proc.wait()
    except BaseException:
        child.stop()
        raise
    finally:
        child.close()
    return returncode, "".join(child.err)


class _PassedOn:
    """A child process whose output is passed on to `sys.stdout` and `sys.stderr` as it
    comes: chunks, not lines (a progress bar's carriage-return updates end in no newline),
    read by one thread per pipe and written from the caller's thread, so that a notebook
    shows them in the running cell.

    Interrupted (Ctrl-C on a terminal, a notebook's stop button: both signal the whole
    process group, the child too), the child is left to store what it finished and exit,
    its lines still passed on; a child still running 10 s later gets SIGINT, and is killed
    30 s after that (or at once on a second interrupt)."""

    def __init__(self, cmd: list[str], env: dict[str, str]) -> None:
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
        self.pipes = {"stdout": self.proc.stdout, "stderr": self.proc.stderr}
        self.chunks: queue.Queue[tuple[str, bytes | None]] = queue.Queue()
        self.decoders = {
            n: codecs.getincrementaldecoder("utf-8")(errors="replace") for n in self.pipes
        }
        self.still_open = set(self.pipes)
        self.err: list[str] = []
        self.readers = [
            threading.Thread(
                target=self._read, args=item, daemon=True, name=f"comexp.run {item[0]}"
            )
            for item in self.pipes.items()
        ]
        for t in self.readers:
            t.start()

    def _read(self, name: str, pipe: typing.IO[bytes]) -> None:
        fd = pipe.fileno()
        try:
            while data := os.read(fd, 65536):
                self.chunks.put((name, data))
        finally:
            self.chunks.put((name, None))

    def pass_on(self, until: float | None = None) -> None:
        """Forward what arrives until both pipes close (or `until`, a monotonic time)."""
        while self.still_open:
            wait = None if until is None else until - time.monotonic()
            if wait is not None and wait <= 0:
                return
            try:
                name, data = self.chunks.get(timeout=wait)
            except queue.Empty:
                return
            if data is None:
                self.still_open.discard(name)
            text = self.decoders[name].decode(data or b"", final=data is None)
            if text:
                if name == "stderr":
                    self.err.append(text)
                stream = getattr(sys, name)
                stream.write(text)
                stream.flush()

    def _until_exit(self, grace_s: float) -> None:
        until = time.monotonic() + grace_s
        while self.proc.poll() is None and time.monotonic() < until:
            self.pass_on(min(until, time.monotonic() + 0.1))

    def stop(self) -> None:
        """The caller was interrupted: let the child finish storing, then make it."""
        try:
            self._until_exit(10.0)  # it got the same interrupt, usually
            if self.proc.poll() is None:
                self.proc.send_signal(signal.SIGINT)
                self._until_exit(30.0)
        except BaseException:  # a second interrupt, or the caller's stream fails: stop now
            pass
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()
        with contextlib.suppress(BaseException):
            self.pass_on(time.monotonic() + 1.0)  # its last lines ("interrupted; ... stored")

    def close(self) -> None:
        for t, pipe in zip(self.readers, self.pipes.values(), strict=True):
            t.join(timeout=1)
            if not t.is_alive() and pipe is not None:  # never under a reader's os.read
                pipe.close()


def _job_keys(args: list[str], config_dir: str | None) -> tuple[str, list[str]]:
    """The job's database and its grid's episode keys, composed as the command composes them
    (Hydra's compose API: the packaged config, the user's config directory first)."""
    from hydra import compose, initialize_config_module

    from comexp.experiment.config import prepare_job
    from comexp.experiment.grid import expand_grid
    from comexp.results.identity import episode_key

    search = [f"hydra.searchpath=[file://{config_dir}]"] if config_dir else []
    with initialize_config_module("comexp.conf", version_base="1.3"):
        cfg = compose("config", overrides=[*args, *search], return_hydra_config=True)
    job = prepare_job(cfg)
    specs = expand_grid(job.cfg, job.objects, estimator=job.estimator)
    return job.cfg.db, [episode_key(s) for s in specs]


def _from_json(tp: Any, value: Any) -> Any:
    """Rebuild a (nested, frozen) dataclass from its canonical JSON: lists become tuples."""
    if dataclasses.is_dataclass(tp) and isinstance(value, dict):
        hints = typing.get_type_hints(tp)
        names = {f.name for f in dataclasses.fields(tp)}
        unknown = sorted(set(value) - names)
        if unknown:
            raise ValueError(
                f"stored {tp.__name__} has fields this comexp does not know: {', '.join(unknown)}"
            )
        return tp(**{k: _from_json(hints[k], v) for k, v in value.items()})
    if isinstance(value, list):
        return tuple(_from_json(None, v) for v in value)
    if isinstance(value, dict):
        return {k: _from_json(None, v) for k, v in value.items()}
    if tp is float and isinstance(value, int):
        return float(value)
    return value


def spec_from_json(text: str) -> EpisodeSpec:
    """The stored `spec` column back as the `EpisodeSpec` that ran (estimator included)."""
    from comexp.experiment.task import EpisodeSpec

    return _from_json(EpisodeSpec, json.loads(text))


def stored_spec(db: DbLike, episode_id: int) -> tuple[EpisodeSpec, dict[str, Any]]:
    handle, owned = _open(db)
    try:
        row = handle.episode(int(episode_id))
    finally:
        if owned:
            handle.close()
    return spec_from_json(row["spec"]), row


def backend_options_for(spec: EpisodeSpec) -> dict[str, Any]:
    """The backend options (`backend.floor_friction`, `camera.renderer`) that gave a stored
    episode its physics: the ones whose `physics_identity` is the spec's. The identity keeps
    only a hash of the options, so each choice is tried. An episode stored without a pinned
    physics runs with the defaults."""
    from comexp.experiment.registry import (
        ENGINES,
        FLOOR_FRICTION_CHOICES,
        RENDERER_CHOICES,
        physics_identity,
    )

    choices: list[dict[str, str]] = [{}]
    if spec.backend in ENGINES:
        choices = [
            {"floor_friction": f, "renderer": r}
            for r in RENDERER_CHOICES
            for f in FLOOR_FRICTION_CHOICES
        ]
    if not spec.physics:
        return choices[0]
    for options in choices:
        if physics_identity(spec.backend, options=options) == spec.physics:
            return options
    mine = ", ".join(physics_identity(spec.backend, options=o) for o in choices)
    raise ValueError(
        f"the episode ran with physics {spec.physics}; this comexp's {spec.backend} offers "
        f"{mine}: it cannot replay it (check out the comexp and engine versions that stored it)"
    )


def replay(db: DbLike, episode_id: int) -> EpisodeResult:
    """Run a stored episode again, in this process, on the backend and with the backend
    options (e.g. `floor_friction=native`) it ran with. On the machine (and package
    versions) that stored it the result equals the stored one; an episode whose physics this
    comexp no longer has is refused (ValueError) rather than run with other physics."""
    from comexp.experiment.episode import run_episode
    from comexp.experiment.registry import make_simulator

    spec, row = stored_spec(db, episode_id)
    if spec.backend != row["backend"]:
        raise ValueError(f"episode {episode_id}: spec backend {spec.backend} != {row['backend']}")
    with make_simulator(row["backend"], **backend_options_for(spec)) as sim:
        return run_episode(spec, sim)
