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
Each job is the job service's (`comexp.experiment.job.run_job`): this module adapts Hydra to
it (the composed config, the output folder, the command line, one-line errors).
"""

from __future__ import annotations

import contextlib
import copy
import itertools
import logging
import os
import shlex
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
import yaml
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf, open_dict, read_write
from omegaconf.errors import OmegaConfBaseException

from comexp.experiment.config import ConfigError, hydra_error_line, prepare_job
from comexp.experiment.job import JobResult, job_config_yaml, probe_resources, run_job
from comexp.results.store import redact, url_password
from comexp.workers.pool import PoolError, close_job_pool
from comexp.workers.session import SessionError

log = logging.getLogger("comexp")

EXIT_BAD_INPUT = 2
EXIT_FAILED = 1
EXIT_INTERRUPTED = 130


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


class ValidateCallback(Callback):
    """Checks every job's config (types, values, objects) and probes its database location
    and Ray address (`probe_resources`), once per job, up front; with `--cfg` and `-m`, prints
    every job's config instead (`ShowJobs`)."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        try:
            job = prepare_job(config)
            probe_resources(job.cfg)
        except ConfigError as e:
            raise Abort(str(e), EXIT_BAD_INPUT) from None
        _prepared[job_config_yaml(config)] = job  # the job `_app` runs: checked once

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
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
                raise Abort(hydra_error_line(e), EXIT_BAD_INPUT) from None
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
_all_failed: list[str] = []  # the jobs of this command whose every episode failed
_prepared: dict[str, Any] = {}  # a run's job as `ValidateCallback` checked it, by its config


# --- one job ---------------------------------------------------------------------------------


def _scrub_hydra_files(url: str) -> None:
    """Hydra saved the job's config (and a multirun's) before the job started: take the
    database password out of those files; the URL stays, with *** for the password."""
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
                clean = redact(text, url)
                if clean != text:
                    f.write_text(clean)


@hydra.main(config_path="pkg://comexp.conf", config_name="config", version_base="1.3")
def _app(cfg: DictConfig) -> JobResult:
    """One job: the job service (`comexp.experiment.job.run_job`) on the composed config, its
    reports in Hydra's output folder."""
    if _show_jobs is not None:  # `ValidateCallback` prints and stops before any job runs
        raise Abort("--cfg with -m: a job started (is hydra.callbacks.validate set?)", 1)
    try:
        job = _prepared.pop(job_config_yaml(cfg), None) or prepare_job(cfg)
        _scrub_hydra_files(job.cfg.db)
        result = run_job(
            job,
            output_dir=HydraConfig.get().runtime.output_dir,
            command_line=shlex.join(["comexp", *sys.argv[1:]]),
            config_yaml=job_config_yaml(cfg),
        )
        if result.all_failed:  # the command exits non-zero once every job has run
            _all_failed.append(f"{result.label}: every episode failed ({result.first_failure})")
        return result
    except ConfigError as e:
        raise Abort(str(e), EXIT_BAD_INPUT) from None
    except (PoolError, SessionError) as e:
        raise Abort(str(e), EXIT_FAILED) from None


# --- error reporting ----------------------------------------------------------------------------


def _die(message: str, code: int) -> None:
    print(f"comexp: error: {message}", file=sys.stderr)
    sys.exit(code)


class RedactFilter(logging.Filter):
    """Shows the database URLs of this command's `db=URL` overrides with *** for their
    passwords in every log record a handler emits (Hydra's launcher lists each job's
    overrides, our own lines name the database). Installed on Hydra's console and job log
    handlers by conf/config.yaml's `hydra.hydra_logging` and `hydra.job_logging`."""

    def __init__(self) -> None:
        super().__init__()
        argv = sys.argv[1:]
        urls = [a.partition("=")[2] for a in argv if a.lstrip("+~").startswith("db=")]
        self.urls = [u for url in urls for u in url.split(",") if url_password(u)]

    def filter(self, record: logging.LogRecord) -> bool:
        if not self.urls:
            return True
        text = record.getMessage()
        clean = text
        for url in self.urls:
            clean = redact(clean, url)
        if clean != text:
            record.msg, record.args = clean, ()
        return True


def _run_app() -> None:
    """Hydra's app (every job of a multirun), then the workers the last job kept closed."""
    try:
        _app()
    finally:
        close_job_pool(keep_warm=True)  # a kept Ray keeps them warm; any other Ray ends them


def main() -> None:
    """Console script. Hydra would print multi-line errors; we ask it to raise (unless the
    user set HYDRA_FULL_ERROR=1 to see everything) and print one line instead."""
    user_full = os.environ.get("HYDRA_FULL_ERROR") == "1"
    os.environ["HYDRA_FULL_ERROR"] = "1"
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    global _show_jobs
    show = ShowJobs.split(sys.argv[1:])
    if show is not None:
        _show_jobs, sys.argv[1:] = show
    _all_failed.clear()
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
        _die(hydra_error_line(e), EXIT_BAD_INPUT)
    except ValueError as e:
        # Hydra's own command-line checks (e.g. `--info` with `-m`) raise plain ValueErrors
        if user_full or not str(e).startswith(_HYDRA_USAGE_ERRORS):
            raise
        _die(str(e).splitlines()[0], EXIT_BAD_INPUT)
    if _all_failed:
        _die("; ".join(_all_failed), EXIT_FAILED)


_HYDRA_USAGE_ERRORS = ("Only one of --run, --multirun", "The --resolve flag can only be used")


if __name__ == "__main__":
    main()
