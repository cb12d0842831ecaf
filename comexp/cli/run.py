"""`comexp`: run experiment jobs (Hydra app; one job = one (backend, floor, speed)).

    comexp                                   # floor=iso speed=40: 1,600 episodes
    comexp -m floor=iso,aniso speed=40,4     # the whole study, 4 jobs
    comexp --cfg job                         # print the resolved config
    comexp -m floor=iso,aniso --cfg job      # print every job's config
    comexp --help

Bad input is rejected before anything is written: `ValidateCallback` checks every job of a run
or multirun before Hydra creates an output folder, and `main` reduces Hydra's and our own
errors to one line and a non-zero exit. `--cfg` with `-m` (which Hydra refuses) prints every
job's config from the same callback (`ShowJobs`). Hydra's public APIs only (callbacks, the
config loader's sweep configs, the override parser): no `hydra._internal`, nothing patched.
The driver alone writes the database, as results arrive; rerunning a command skips the
episodes already stored.
"""

from __future__ import annotations

import contextlib
import copy
import itertools
import logging
import os
import shlex
import subprocess
import sys
import urllib.parse
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf, open_dict, read_write

from comexp.experiment.config import (
    ConfigError,
    ExperimentConfig,
    PreparedJob,
    prepare_job,
    simulator_options,
)
from comexp.experiment.grid import expand_grid
from comexp.experiment.objects import yaml_error_line
from comexp.experiment.task import EpisodeSpec

log = logging.getLogger("comexp")

EXIT_BAD_INPUT = 2
EXIT_FAILED = 1
EXIT_INTERRUPTED = 130
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


# --- validation before Hydra writes anything ----------------------------------------------


class Abort(BaseException):  # noqa: N818 - not an error class: a controlled exit
    """Carries a one-line message and exit code to `main`.

    A BaseException on purpose: Hydra turns a callback's exceptions into warnings and wraps a
    job's exceptions with extra output; this passes through both untouched.
    """

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.message = message
        self.code = code


def _sweep_job_overrides(config: DictConfig) -> list[list[str]] | None:
    """The override lists of every job Hydra's basic sweeper (the default) will launch, in its
    launch order: the cartesian product of the sweeps of `hydra.sweeper.params` and of the
    command line, one value per key. None for other sweepers, whose jobs are only known while
    they run. Public APIs only: the config's group choices and Hydra's override parser."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    if OmegaConf.select(config, "hydra.runtime.choices")["hydra/sweeper"] != "basic":
        return None
    params = OmegaConf.select(config, "hydra.sweeper.params") or {}
    args = [f"{k}={v}" for k, v in params.items()]
    args += list(OmegaConf.to_container(config.hydra.overrides.task, resolve=False))
    values: dict[str, list[str]] = {}  # key -> its "key=value" choices; a later one wins
    for override in OverridesParser.create().parse_overrides(args):
        key = override.get_key_element()
        if not override.is_sweep_override():
            values[key] = [f"{key}={override.get_value_element_as_str()}"]
        elif override.is_discrete_sweep():
            values[key] = [f"{key}={v}" for v in override.sweep_string_iterator()]
        else:
            raise HydraException(f"the basic sweeper does not sweep {override.value_type.name}")
    return [list(job) for job in itertools.product(*values.values())]


def probe_resources(exp: ExperimentConfig) -> None:
    """What the job needs outside itself, probed once before anything is written: a database
    location that can hold the database, and a Ray address where something listens. Raises
    `ConfigError` naming the key."""
    from comexp.results.store import check_location
    from comexp.workers.session import check_ray_address

    try:
        check_location(exp.db)
    except ValueError as e:
        raise ConfigError(f"db: {e}") from None
    try:
        check_ray_address(exp.ray.address)
    except ValueError as e:
        raise ConfigError(f"ray.address: {e}") from None


class ValidateCallback(Callback):
    """Checks every job's config (types, values, objects) and probes its database location
    and Ray address (`probe_resources`), once per job, up front; with `--cfg` and `-m`, prints
    every job's config instead (`ShowJobs`)."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        try:
            probe_resources(prepare_job(config).cfg)
        except ConfigError as e:
            raise Abort(str(e), EXIT_BAD_INPUT) from None

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        from hydra.core.global_hydra import GlobalHydra

        jobs = _sweep_job_overrides(config)
        if jobs is None:
            if _show_jobs is not None:
                raise Abort("--cfg with -m works with Hydra's basic sweeper only", EXIT_BAD_INPUT)
            return
        loader = GlobalHydra.instance().config_loader()
        job_cfgs = []
        for overrides in jobs:
            try:
                job_cfgs.append(loader.load_sweep_config(config, list(overrides)))
            except Exception as e:
                raise Abort(_hydra_error_line(e), EXIT_BAD_INPUT) from None
        if _show_jobs is not None:
            _show_jobs.print(jobs, job_cfgs)
            raise Abort("", 0)  # printed: nothing runs, nothing is created
        probed: set[tuple[str, str | None]] = set()  # jobs share a database and Ray: once each
        for overrides, job_cfg in zip(jobs, job_cfgs, strict=True):
            try:
                exp = prepare_job(job_cfg).cfg
                if (exp.db, exp.ray.address) not in probed:
                    probe_resources(exp)
                    probed.add((exp.db, exp.ray.address))
            except ConfigError as e:
                where = " ".join(overrides)
                raise Abort(f"{e} (job: {where})" if where else str(e), EXIT_BAD_INPUT) from None


# --- `--cfg` with `-m`: every job's config ---------------------------------------------------


@dataclass(frozen=True)
class ShowJobs:
    """`--cfg TYPE [-p PACKAGE] [--resolve]` with `-m`: Hydra refuses the pair, but "what will
    this sweep run?" is a fair question. `main` takes these flags off the command line and runs
    the multirun; `ValidateCallback.on_multirun_start` composes every job, prints one YAML
    document per job in launch order, each headed by its overrides, and stops before the
    sweeper launches anything. Like `--cfg` alone, it checks types, not values."""

    cfg_type: str  # job | hydra | all
    package: str | None = None
    resolve: bool = False

    @classmethod
    def split(cls, argv: list[str]) -> tuple[ShowJobs, list[str]] | None:
        """(the request, `argv` without its flags) when `argv` has both `-m` and `--cfg`."""
        if not any(a in ("-m", "--multirun") for a in argv):
            return None
        found: dict[str, str] = {}
        rest: list[str] = []
        args = iter(argv)
        for a in args:
            flag, eq, value = a.partition("=")
            name = {"-c": "cfg", "--cfg": "cfg", "-p": "package", "--package": "package"}.get(flag)
            if name is not None and flag.startswith("--") and eq:
                found[name] = value
            elif name is not None and not eq:
                found[name] = next(args, "")
            elif a == "--resolve":
                found["resolve"] = "1"
            else:
                rest.append(a)
        if found.get("cfg") not in ("job", "hydra", "all"):
            return None  # no --cfg (or a bad one: Hydra's own parser says so)
        return cls(found["cfg"], found.get("package"), "resolve" in found), rest

    def print(self, jobs: list[list[str]], job_cfgs: list[DictConfig]) -> None:
        docs = []
        for num, (job, job_cfg) in enumerate(zip(jobs, job_cfgs, strict=True)):
            with open_dict(job_cfg):  # as Hydra's basic launcher and run_job do (nothing created)
                job_cfg.hydra.job.id = num
                job_cfg.hydra.job.num = num
                sweep = job_cfg.hydra.sweep
                job_cfg.hydra.runtime.output_dir = str(
                    Path(str(sweep.dir), str(sweep.subdir)).absolute()
                )
            HydraConfig.instance().set_config(job_cfg)  # for `${hydra:...}` when resolving
            OmegaConf.set_readonly(job_cfg.hydra, None)
            node: Any = self._part(job_cfg)
            if self.package not in (None, "_global_"):
                node = OmegaConf.select(node, self.package)
                if node is None:
                    raise Abort(f"package {self.package!r} not found in config", EXIT_BAD_INPUT)
            if OmegaConf.is_config(node):
                body = OmegaConf.to_yaml(node, resolve=self.resolve)
            else:
                body = f"{node}\n"
            docs.append(f"# job {num}: {' '.join(job)}\n{body}")
        sys.stdout.write("---\n".join(docs))

    def _part(self, cfg: DictConfig) -> DictConfig:
        """What `--cfg TYPE` shows: the job's own config, Hydra's node (less its help
        texts), or both."""
        cfg = copy.deepcopy(cfg)
        with open_dict(cfg), read_write(cfg):
            if self.cfg_type == "job":
                del cfg["hydra"]
            elif self.cfg_type == "hydra":
                for key in [k for k in cfg if k != "hydra"]:
                    del cfg[key]
                del cfg.hydra["hydra_help"]
                del cfg.hydra["help"]
        return cfg


_show_jobs: ShowJobs | None = None  # set by `main` for `--cfg` with `-m`


# --- one job -----------------------------------------------------------------------------------


def _versions() -> dict[str, str]:
    out = {"python": sys.version.split()[0]}
    for name in VERSIONED_PACKAGES:
        with contextlib.suppress(metadata.PackageNotFoundError):
            out[name] = metadata.version(name)
    return out


def _git_rev() -> str | None:
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


def open_db(url: str) -> Any:
    """Open (creating) the results database, or fail with a one-line `ConfigError`."""
    from comexp.results.store import ResultsDB, redact_url

    try:
        db = ResultsDB(url)
    except Exception as e:  # OSError, SQLAlchemy errors: say what and where
        msg = _scrub(str(e).splitlines()[0], url)
        raise ConfigError(f"db: cannot open {redact_url(url)!r}: {msg}") from None
    try:
        db.check_writable()
    except (ValueError, OSError) as e:
        db.close()
        raise ConfigError(f"db: {_scrub(str(e).splitlines()[0], url)}") from None
    return db


def _scrub(text: str, url: str) -> str:
    """`text` with the database URL's password replaced (the URL itself by its redacted form)."""
    from comexp.results.store import redact_url, url_password

    password = url_password(url)
    if not password:
        return text
    text = text.replace(url, redact_url(url))
    for form in {password, urllib.parse.quote(password, safe=""), urllib.parse.quote(password)}:
        text = text.replace(form, "***")
    return text


def _scrub_hydra_files(url: str) -> None:
    """Hydra saved the job's config (and a multirun's) before the job started: take the
    database password out of those files; the URL stays, with *** for the password."""
    from comexp.results.store import url_password

    if not url_password(url):
        return
    hc = HydraConfig.get()
    dirs = [Path(hc.runtime.output_dir) / (hc.output_subdir or ".hydra")]
    if hc.mode is not None and hc.mode.name == "MULTIRUN":
        dirs.append(Path(hc.sweep.dir))
    for d in dirs:
        for f in (*d.glob("*.yaml"), *d.glob("*.log")):
            with contextlib.suppress(OSError):
                text = f.read_text()
                clean = _scrub(text, url)
                if clean != text:
                    f.write_text(clean)


def _run_todo(
    cfg: DictConfig, exp: ExperimentConfig, db: Any, todo: list[EpisodeSpec], label: str
) -> dict[str, int]:
    """Run the job's episodes not stored yet on a pool of `exp.workers` and store them under
    a new sweep; the kernels (a local job's workers then load them) beside Ray's start."""
    from comexp.workers.driver import Progress, run_and_store
    from comexp.workers.kernel_cache import warm_kernel_cache
    from comexp.workers.pool import close_job_pool, job_pool
    from comexp.workers.session import ensure_ray

    options = simulator_options(exp)

    def start_ray() -> None:
        ensure_ray(exp.ray.address, exp.workers, log_to_driver=exp.ray.log_to_driver)

    # Ray first: a cluster that cannot be joined leaves no sweep row behind
    # (`probe_resources` has already rejected an address where nothing listens).
    if exp.ray.address is None:  # local workers load the kernels this compiles
        warm_kernel_cache(exp.backend.name, todo[0], options, meanwhile=start_ray)
    else:
        start_ray()
    hc = HydraConfig.get()
    job_cfg = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
    sweep_id = db.start_sweep(
        command_line=_scrub(shlex.join(["comexp", *sys.argv[1:]]), exp.db),
        config_yaml=_scrub(OmegaConf.to_yaml(job_cfg, resolve=True), exp.db),
        job_name=Path(hc.runtime.output_dir).name,  # ties the sweep to its folder
        versions=_versions(),
        git_rev=_git_rev(),
    )
    # the last job's workers carry over when this job's are the same (`job_pool`)
    pool = job_pool(
        exp.backend.name,
        exp.workers,
        batch_size=exp.execution.batch_size,
        max_retries=exp.execution.max_retries,
        replace_timeout_s=exp.execution.restart_timeout_s,
        episode_timeout_s=exp.execution.episode_timeout_s,
        backend_options=options,
    )
    try:
        stats = run_and_store(
            pool,
            todo,
            lambda rs: db.add_results(sweep_id, rs),
            progress=Progress(len(todo), desc=label),
        )
    except BaseException:
        close_job_pool()  # a run cut short leaves batches in flight: not a pool to reuse
        raise
    failures = ", ".join(f"{k} {v}" for k, v in stats.failures.most_common())
    print(
        f"{label}: ran {stats.done} episodes in {stats.wall_s:.1f} s "
        f"({stats.failed} failed{': ' + failures if failures else ''}), "
        f"stored {stats.stored}"
    )
    return {"ran": stats.done, "failed": stats.failed, "stored": stats.stored}


def run_job(cfg: DictConfig) -> dict[str, Any]:
    """Validate, expand the grid, run what is not stored yet, write the job's reports (the
    validate callback has probed the database location and Ray before Hydra wrote anything)."""
    from comexp.results.identity import episode_key
    from comexp.results.store import redact_url

    job: PreparedJob = prepare_job(cfg)
    exp = job.cfg
    _scrub_hydra_files(exp.db)
    specs = expand_grid(exp, job.objects, estimator=job.estimator)
    label = f"{exp.backend.name} {exp.floor.name} {exp.speed:g} cm/s"
    db = open_db(exp.db)
    try:
        keys = [episode_key(s) for s in specs]
        stored = db.stored_keys(keys)
        todo = [s for s, k in zip(specs, keys, strict=True) if k not in stored]
        log.info(
            "%s: %d episodes, %d already stored, %d to run (db %s)",
            label,
            len(specs),
            len(specs) - len(todo),
            len(todo),
            redact_url(exp.db),
        )
        summary: dict[str, Any] = {"episodes": len(specs), "skipped": len(specs) - len(todo)}
        if todo:
            summary.update(_run_todo(cfg, exp, db, todo, label))
        else:
            print(f"{label}: all {len(specs)} episodes already stored")
        from comexp.results.reports import write_job_reports

        out_dir = HydraConfig.get().runtime.output_dir
        paths, text = write_job_reports(db, out_dir, keys, job=label)
        if text:
            print(text)
        if paths:
            print(f"reports ({len(paths)} files): {out_dir}")
        summary["reports"] = [str(p) for p in paths]
        return summary
    finally:
        db.close()


@hydra.main(config_path="pkg://comexp.conf", config_name="config", version_base="1.3")
def _app(cfg: DictConfig) -> dict[str, Any]:
    from comexp.workers.pool import PoolError

    if _show_jobs is not None:  # `ValidateCallback` prints and stops before any job runs
        raise Abort("--cfg with -m: a job started (is hydra.callbacks.validate set?)", 1)
    try:
        return run_job(cfg)
    except ConfigError as e:
        raise Abort(str(e), EXIT_BAD_INPUT) from None
    except PoolError as e:
        raise Abort(str(e), EXIT_FAILED) from None


# --- error reporting ----------------------------------------------------------------------------


def _hydra_error_line(e: BaseException) -> str:
    """One line out of Hydra's, OmegaConf's and PyYAML's multi-line messages."""
    import yaml
    from hydra.errors import MissingConfigException

    if isinstance(e, yaml.YAMLError):
        return yaml_error_line(e)
    if isinstance(e, MissingConfigException) and e.missing_cfg_file and e.options is not None:
        group, _, name = e.missing_cfg_file.rpartition("/")
        if group:
            return f"unknown {group} {name!r} (choose one of: {', '.join(e.options)})"
    cause = e.__cause__ or e.__context__
    for err in (cause, e):
        key = getattr(err, "full_key", None)
        msg = getattr(err, "msg", None)
        if key and msg:
            return f"{key}: {str(msg).splitlines()[0]}"
    text = [t.strip() for t in str(e).splitlines() if t.strip()]
    if cause is not None and (not text or text[-1].endswith(":")):
        text += [t.strip() for t in str(cause).splitlines() if t.strip()][:1]
    return " ".join(text[:2]) if text else type(e).__name__


def _die(message: str, code: int) -> None:
    print(f"comexp: error: {message}", file=sys.stderr)
    sys.exit(code)


def _scrub_log_records(argv: list[str]) -> None:
    """A `db=URL` override with a password: every log record (Hydra's launcher lists each
    job's overrides, our own lines name the database) shows the URL with *** instead."""
    from comexp.results.store import url_password

    urls = [a.partition("=")[2] for a in argv if a.lstrip("+~").startswith("db=")]
    urls = [u for url in urls for u in url.split(",") if url_password(u)]  # multirun lists
    if not urls:
        return
    previous = logging.getLogRecordFactory()

    def factory(*args: Any, **kwargs: Any) -> logging.LogRecord:
        record = previous(*args, **kwargs)
        text = record.getMessage()
        clean = text
        for url in urls:
            clean = _scrub(clean, url)
        if clean != text:
            record.msg, record.args = clean, ()
        return record

    logging.setLogRecordFactory(factory)


def _run_app() -> None:
    """Hydra's app (every job of a multirun), then the workers the last job kept closed."""
    try:
        _app()
    finally:
        pool = sys.modules.get("comexp.workers.pool")  # imported by a job that ran
        if pool is not None:
            pool.close_job_pool()


def main() -> None:
    """Console script. Hydra would print multi-line errors; we ask it to raise (unless the
    user set HYDRA_FULL_ERROR=1 to see everything) and print one line instead."""
    import yaml
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    _scrub_log_records(sys.argv[1:])
    user_full = os.environ.get("HYDRA_FULL_ERROR") == "1"
    os.environ["HYDRA_FULL_ERROR"] = "1"
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    global _show_jobs
    show = ShowJobs.split(sys.argv[1:])
    if show is not None:
        _show_jobs, sys.argv[1:] = show
    try:
        _run_app()
    except Abort as e:
        if e.code:
            _die(e.message, e.code)
    except KeyboardInterrupt:
        _die(
            "interrupted; finished episodes are stored, run the same command to resume",
            EXIT_INTERRUPTED,
        )
    except (HydraException, OmegaConfBaseException, yaml.YAMLError) as e:
        # YAML: a config file Hydra composes (primary config, floor/, experiment/ ...)
        if user_full:
            raise
        _die(_hydra_error_line(e), EXIT_BAD_INPUT)
    except ValueError as e:
        # Hydra's own command-line checks (e.g. `--info` with `-m`) raise plain ValueErrors
        if user_full or not str(e).startswith(_HYDRA_USAGE_ERRORS):
            raise
        _die(str(e).splitlines()[0], EXIT_BAD_INPUT)


_HYDRA_USAGE_ERRORS = ("Only one of --run, --multirun", "The --resolve flag can only be used")


if __name__ == "__main__":
    main()
