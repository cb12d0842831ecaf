"""Run one job: the service behind the `comexp` command and the notebook's `comexp.run`.

A job is one (backend, floor, speed) of the study. `run_job` takes it from a checked config
(`comexp.experiment.config.prepare_job`) to stored episodes and reports: the grid
(`expand_grid`), what the database already holds (resume: an episode is stored once, by its
key), the workers (the kernels warmed beside Ray's start, the pool of the last job reused when
it is the same), the run with results stored as they arrive, the sweep's provenance (command
line, resolved config, package versions, git revision) and the job's reports. It returns what
it did (`JobResult`), its grid's keys included, so that a caller reads back exactly this job's
rows. The database password is redacted in one place (`comexp.results.store.redact`) for every
line and file the job writes.

The adapters are thin: the Hydra app (`comexp.cli.run`) gives the composed config and Hydra's
output folder; `comexp.run` (`comexp.api`) composes the config with Hydra's compose API.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import subprocess
import sys
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from comexp.episode.task import EpisodeResult, EpisodeSpec
from comexp.experiment.config import ConfigError, ExperimentConfig, PreparedJob
from comexp.experiment.grid import expand_grid
from comexp.results.identity import episode_key
from comexp.results.reports import write_job_reports
from comexp.results.store import ResultsDB, check_location, redact, redact_url
from comexp.workers.driver import Progress, run_and_store
from comexp.workers.kept import available as kept_available
from comexp.workers.kernel_cache import warm_kernel_cache
from comexp.workers.pool import close_job_pool, job_pool
from comexp.workers.session import check_ray_address, ensure_ray, kept_session
from comexp.workers.settings import LOCAL

log = logging.getLogger("comexp")

# the packages whose versions a sweep records (its provenance)
VERSIONED_PACKAGES = (
    "comexp",
    "numpy",
    "scipy",
    "shapely",
    "opencv-python-headless",
    "pybullet",
    "mujoco",
    "hydra-core",
    "omegaconf",
    "ray",
    "sqlalchemy",
    "numba",
    "pandas",
    "psycopg",
)


@dataclass
class JobResult:
    """What a job did: its grid (`keys`, in grid order), what was already stored, what ran,
    and the reports it wrote."""

    label: str  # e.g. "planar iso 40 cm/s"
    db: str  # the database, as configured (a URL may hold a password: print `redact_url`)
    keys: list[str]
    skipped: int  # grid episodes already stored before the job
    ran: int = 0
    failed: int = 0
    stored: int = 0
    failures: collections.Counter[str] = field(default_factory=collections.Counter)
    first_failure: str = ""  # the first failed episode, in one line (what and why)
    reports: list[Path] = field(default_factory=list)

    @property
    def episodes(self) -> int:
        return len(self.keys)

    @property
    def all_failed(self) -> bool:
        """Episodes ran and none of them finished: a job to fix, not to report."""
        return self.ran > 0 and self.failed == self.ran


def job_label(exp: ExperimentConfig) -> str:
    return f"{exp.backend.name} {exp.floor.name} {exp.speed:g} cm/s"


def probe_resources(exp: ExperimentConfig) -> None:
    """What the job needs outside itself, probed once before anything is written: a database
    location that can hold the database, and a Ray address where something listens. Raises
    `ConfigError` naming the key."""
    try:
        check_location(exp.db)
    except ValueError as e:
        raise ConfigError(f"db: {e}") from None
    try:
        check_ray_address(exp.ray.address)
    except ValueError as e:
        raise ConfigError(f"ray.address: {e}") from None


def open_db(url: str) -> ResultsDB:
    """Open (creating) the results database, or fail with a one-line `ConfigError`."""
    try:
        db = ResultsDB(url)
    except Exception as e:  # OSError, SQLAlchemy errors: say what and where
        msg = redact(str(e).splitlines()[0], url)
        raise ConfigError(f"db: cannot open {redact_url(url)!r}: {msg}") from None
    try:
        db.check_writable()
    except (ValueError, OSError) as e:
        db.close()
        raise ConfigError(f"db: {redact(str(e).splitlines()[0], url)}") from None
    return db


def run_job(
    job: PreparedJob,
    *,
    output_dir: str | Path,
    command_line: str,
    config_yaml: str,
    progress_bar: bool | None = None,
) -> JobResult:
    """Run the job's episodes that are not stored yet, store them, write the job's reports
    into `output_dir`. `command_line` and `config_yaml` are the sweep's provenance (stored
    with the password redacted); `progress_bar`: a bar (True), log lines (False) or as
    `Progress` decides (None). Raises `ConfigError` (bad database) and the workers' errors
    (`SessionError`, `PoolError`): one line each."""
    exp = job.cfg
    specs = expand_grid(exp, job.objects, estimator=job.estimator)
    label = job_label(exp)
    db = open_db(exp.db)
    try:
        keys = [episode_key(s) for s in specs]
        stored = db.stored_keys(keys)
        retried = db.failed_keys(keys) if exp.retry == "failed" else set()
        todo = [s for s, k in zip(specs, keys, strict=True) if k not in stored or k in retried]
        result = JobResult(label, exp.db, keys, skipped=len(specs) - len(todo))
        log.info(
            "%s: %d episodes, %d already stored, %d to run%s (db %s)",
            label,
            len(specs),
            len(stored),
            len(todo),
            f" ({len(retried)} failed, retried)" if retried else "",
            redact_url(exp.db),
        )
        if todo:
            provenance = {
                "command_line": redact(command_line, exp.db),
                "config_yaml": redact(config_yaml, exp.db),
                "job_name": Path(output_dir).name,  # ties the sweep to its folder
            }
            _run_todo(job, db, todo, result, provenance, progress_bar, replace=bool(retried))
        else:
            failed = len(db.failed_keys(keys))
            hint = f" ({failed} failed: retry=failed reruns them)" if failed else ""
            print(f"{label}: all {len(specs)} episodes already stored{hint}")
        # a job that ran nothing has nothing new to report: no new report files
        paths, text = write_job_reports(db, output_dir, keys, job=label, files=bool(todo))
        if text:
            print(text)
        if paths:
            print(f"reports ({len(paths)} files): {output_dir}")
        result.reports = paths
        return result
    finally:
        db.close()


def _run_todo(
    job: PreparedJob,
    db: ResultsDB,
    todo: list[EpisodeSpec],
    result: JobResult,
    provenance: dict[str, str],
    progress_bar: bool | None,
    *,
    replace: bool = False,
) -> None:
    """Run `todo` on a pool of `workers` and store the results under a new sweep. Local
    workers load the kernels a warm-up compiles, beside Ray's start (a Ray of the job's own)
    or before the workers start (the kept Ray, whose warm workers have them already)."""
    exp = job.cfg

    def start_ray() -> None:
        ensure_ray(exp.ray.address, exp.workers, log_to_driver=exp.ray.log_to_driver)

    # Ray first: a cluster that cannot be joined leaves no sweep row behind
    # (`probe_resources` has already rejected an address where nothing listens).
    own_ray = exp.ray.address == LOCAL or (exp.ray.address is None and not kept_available())
    if own_ray:
        warm_kernel_cache(job.simulator, todo[0], meanwhile=start_ray)
    else:
        start_ray()
    # the last job's workers carry over when this job's are the same (`job_pool`), and on a
    # kept Ray an earlier command's do
    pool = job_pool(job.simulator, exp.workers, exp.execution)
    if kept_session() is not None and not pool.warm_workers():
        warm_kernel_cache(job.simulator, todo[0])
    sweep_id = db.start_sweep(**provenance, versions=versions(), git_rev=git_revision())
    try:
        stats = run_and_store(
            pool,
            todo,
            (lambda rs: db.replace_failed(sweep_id, rs))
            if replace
            else (lambda rs: db.add_results(sweep_id, rs)),
            progress=Progress(len(todo), desc=result.label, tty=progress_bar),
        )
    except BaseException:
        close_job_pool()  # a run cut short leaves batches in flight: not a pool to reuse
        raise
    result.ran, result.failed, result.stored = stats.done, stats.failed, stats.stored
    result.failures = stats.failures
    failures = ", ".join(f"{k} {v}" for k, v in stats.failures.most_common())
    print(
        f"{result.label}: ran {stats.done} episodes in {stats.wall_s:.1f} s "
        f"({stats.failed} failed{': ' + failures if failures else ''}), "
        f"stored {stats.stored}"
    )
    if stats.first_failure is not None:
        result.first_failure = failure_line(stats.first_failure)
        print(f"first failure: {result.first_failure}")


def failure_line(r: EpisodeResult) -> str:
    """A failed episode in one line: which episode, its failure kind and its message's last
    line (an exception's own message ends a traceback)."""
    lines = [ln.strip() for ln in (r.detail or "").strip().splitlines() if ln.strip()]
    message = next((ln for ln in reversed(lines) if not ln.startswith(("File ", "^"))), "")
    if lines and lines[0] and not lines[0].startswith("Traceback"):
        message = lines[0]
    s = r.spec
    return f"{s.object} com {s.com_index}: {r.failure}" + (f" ({message[:200]})" if message else "")


def versions() -> dict[str, str]:
    """Python's and the versioned packages' versions (a sweep's provenance)."""
    out = {"python": sys.version.split()[0]}
    for name in VERSIONED_PACKAGES:
        with contextlib.suppress(metadata.PackageNotFoundError):
            out[name] = metadata.version(name)
    return out


def git_revision() -> str | None:
    """The source revision when comexp runs from a git checkout (read-only query)."""
    try:
        res = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=5,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return res.stdout.strip() or None if res.returncode == 0 else None


def job_config_yaml(cfg: Any) -> str:
    """The job's resolved config as YAML, without Hydra's own node (a sweep's provenance)."""
    job_cfg = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
    return OmegaConf.to_yaml(job_cfg, resolve=True)
