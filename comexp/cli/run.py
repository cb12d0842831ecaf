"""`comexp`: run experiment jobs (Hydra app; one job = one (backend, floor, speed)).

    comexp                                   # floor=iso speed=40: 1,600 episodes
    comexp -m floor=iso,aniso speed=40,4     # the whole study, 4 jobs
    comexp --cfg job                         # print the resolved config
    comexp -m floor=iso,aniso --cfg job      # print every job's config
    comexp --help

Bad input is rejected before anything is written: `ValidateCallback` checks every job of a run
or multirun before Hydra creates an output folder, and `main` reduces Hydra's and our own
errors to one line and a non-zero exit. The driver alone writes the database, as results
arrive; rerunning a command skips the episodes already stored.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shlex
import subprocess
import sys
import urllib.parse
from importlib import metadata
from pathlib import Path
from typing import Any

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from comexp.experiment.config import ConfigError, PreparedJob, prepare_job, simulator_options
from comexp.experiment.grid import expand_grid
from comexp.experiment.objects import yaml_error_line

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
    """The override lists of every job the basic sweeper will launch (None for other
    sweepers, whose jobs are only known while they run)."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    target = OmegaConf.select(config, "hydra.sweeper._target_")
    if target != "hydra._internal.core_plugins.basic_sweeper.BasicSweeper":
        return None
    params = OmegaConf.select(config, "hydra.sweeper.params") or {}
    args = [f"{k}={v}" for k, v in params.items()]
    args += list(OmegaConf.to_container(config.hydra.overrides.task, resolve=False))
    parsed = OverridesParser.create().parse_overrides(args)
    return [job for batch in BasicSweeper.split_arguments(parsed, None) for job in batch]


class ValidateCallback(Callback):
    """Checks every job's config (types, values, objects, database location) up front."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        try:
            prepare_job(config)
        except ConfigError as e:
            raise Abort(str(e), EXIT_BAD_INPUT) from None

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        from hydra.core.global_hydra import GlobalHydra

        jobs = _sweep_job_overrides(config)
        if jobs is None:
            return
        loader = GlobalHydra.instance().config_loader()
        for overrides in jobs:
            try:
                job_cfg = loader.load_sweep_config(config, list(overrides))
            except Exception as e:
                raise Abort(_hydra_error_line(e), EXIT_BAD_INPUT) from None
            try:
                prepare_job(job_cfg)
            except ConfigError as e:
                where = " ".join(overrides)
                raise Abort(f"{e} (job: {where})" if where else str(e), EXIT_BAD_INPUT) from None


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


def run_job(cfg: DictConfig) -> dict[str, Any]:
    """Validate, expand the grid, run what is not stored yet, write the job's reports."""
    from comexp.results.identity import episode_key
    from comexp.results.store import redact_url
    from comexp.workers.driver import Progress, run_and_store
    from comexp.workers.pool import EpisodePool
    from comexp.workers.session import ensure_ray

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
            # Ray first: a cluster that cannot be joined leaves no sweep row behind
            # (`prepare_job` has already rejected an address where nothing listens).
            ensure_ray(exp.ray.address, exp.workers, log_to_driver=exp.ray.log_to_driver)
            hc = HydraConfig.get()
            job_cfg = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
            sweep_id = db.start_sweep(
                command_line=_scrub(shlex.join(["comexp", *sys.argv[1:]]), exp.db),
                config_yaml=_scrub(OmegaConf.to_yaml(job_cfg, resolve=True), exp.db),
                job_name=Path(hc.runtime.output_dir).name,  # ties the sweep to its folder
                versions=_versions(),
                git_rev=_git_rev(),
            )
            pool = EpisodePool(
                exp.backend.name,
                exp.workers,
                batch_size=exp.execution.batch_size,
                max_retries=exp.execution.max_retries,
                replace_timeout_s=exp.execution.restart_timeout_s,
                episode_timeout_s=exp.execution.episode_timeout_s,
                backend_options=simulator_options(exp),
            )
            with pool:
                stats = run_and_store(
                    pool,
                    todo,
                    lambda rs: db.add_results(sweep_id, rs),
                    progress=Progress(len(todo), desc=label),
                )
            failures = ", ".join(f"{k} {v}" for k, v in stats.failures.most_common())
            print(
                f"{label}: ran {stats.done} episodes in {stats.wall_s:.1f} s "
                f"({stats.failed} failed{': ' + failures if failures else ''}), "
                f"stored {stats.stored}"
            )
            summary.update(ran=stats.done, failed=stats.failed, stored=stats.stored)
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

    try:
        return run_job(cfg)
    except ConfigError as e:
        raise Abort(str(e), EXIT_BAD_INPUT) from None
    except PoolError as e:
        raise Abort(str(e), EXIT_FAILED) from None


# --- `--cfg` with `-m`: every job's config ---------------------------------------------------


def _show_sweep_cfg(
    self: Any,
    config_name: str | None,
    overrides: list[str],
    cfg_type: str,
    package: str | None,
    resolve: bool = False,
) -> None:
    """Stands in for `Hydra.show_cfg` when `-m` comes with `--cfg`: Hydra refuses the pair, but
    "what will this sweep run?" is a fair question. Prints one YAML document per job, in launch
    order, each headed by its overrides; like `--cfg` alone, it checks types, not values."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode
    from omegaconf import open_dict

    cfg = self.compose_config(
        config_name=config_name,
        overrides=overrides,
        run_mode=RunMode.MULTIRUN,
        with_log_configuration=False,
    )
    jobs = _sweep_job_overrides(cfg)
    if jobs is None:
        raise Abort("--cfg with -m works with Hydra's basic sweeper only", EXIT_BAD_INPUT)
    docs = []
    for num, job in enumerate(jobs):
        job_cfg = self.config_loader.load_sweep_config(cfg, list(job))
        with open_dict(job_cfg):  # as Hydra's basic launcher and run_job do (nothing created)
            job_cfg.hydra.job.id = num
            job_cfg.hydra.job.num = num
            sweep = job_cfg.hydra.sweep
            out_dir = Path(str(sweep.dir), str(sweep.subdir)).absolute()
            job_cfg.hydra.runtime.output_dir = str(out_dir)
        HydraConfig.instance().set_config(job_cfg)
        OmegaConf.set_readonly(job_cfg.hydra, None)
        node: Any = self.get_sanitized_cfg(job_cfg, cfg_type)
        if package not in (None, "_global_"):
            node = OmegaConf.select(node, package)
            if node is None:
                raise Abort(f"package {package!r} not found in config", EXIT_BAD_INPUT)
        if OmegaConf.is_config(node):
            body = OmegaConf.to_yaml(node, resolve=resolve)
        else:
            body = f"{node}\n"
        docs.append(f"# job {num}: {' '.join(job)}\n{body}")
    sys.stdout.write("---\n".join(docs))


@contextlib.contextmanager
def _cfg_per_sweep_job() -> Any:
    from hydra._internal.hydra import Hydra

    original = Hydra.show_cfg
    Hydra.show_cfg = _show_sweep_cfg  # type: ignore[method-assign]
    try:
        yield
    finally:
        Hydra.show_cfg = original  # type: ignore[method-assign]


def _split_multirun_cfg(argv: list[str]) -> list[str] | None:
    """`argv` without `-m`/`--multirun` when it also asks for `--cfg`; None otherwise."""
    multirun = [a for a in argv if a in ("-m", "--multirun")]
    show_cfg = any(a in ("-c", "--cfg") or a.startswith("--cfg=") for a in argv)
    if not (multirun and show_cfg):
        return None
    return [a for a in argv if a not in multirun]


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
    show_per_job = _split_multirun_cfg(sys.argv[1:])
    try:
        if show_per_job is None:
            _app()
        else:
            sys.argv[1:] = show_per_job
            with _cfg_per_sweep_job():
                _app()
    except Abort as e:
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
