"""What the bench scripts share; not a benchmark of its own.

The scripts import it as `from common import ...` (`python bench/X.py` puts bench/ first on
the module path by itself); no script imports another script. It holds:

- the job's episodes as `comexp` expands them (`job_specs`) and the simulator its workers
  build (`job_simulator`, `job_backend_options`), and a strided slice of the episodes that
  keeps every object and condition (`strided`);
- a simulator of a bench's own subclass of the backend's class (`bench_simulator`): a bench
  that times or records an engine's calls overrides them in a mixin of its own and calls
  `super()`, the package itself untouched;
- one worker's thread pools (`use_one_cpu`), the engines' C++ prints silenced
  (`engine_stdout_silenced`), the backend's source digest (`source_digest`), a warm-up pass
  (`warm_up`), a module loaded from a file (`load_module`), and the /proc readings of a
  process tree (`descendants`, `cpu_seconds`, `memory_kb`, `proc_name`);
- a table of figures written as docs/data/NAME.json with its provenance (`write_table`: what
  bench/docs_tables.py renders into the docs).

Light at import: the episode loop (Numba, OpenCV, the engines) is imported by the functions
that run episodes, not here, so that bench/memory.py's driver imports `job_specs` as
`comexp`'s driver does.
"""

from __future__ import annotations

import collections
import datetime
import functools
import hashlib
import importlib
import importlib.util
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
from importlib import metadata
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from comexp.episode.task import EpisodeSpec
    from comexp.sim.scene import SimSettings
    from comexp.sim.simulator import Simulator, SimulatorSpec

# --- the job ---------------------------------------------------------------------------------


@functools.lru_cache(maxsize=8)
def _prepared_job(backend: str, floor: str, speed: float, overrides: tuple[str, ...]) -> Any:
    """The job `comexp` would prepare (Hydra config, validation, objects). The database
    setting points at a temp dir so nothing is probed or created under results/. Prepared
    once per process and job: `job_specs` and `job_simulator` of one job share it."""
    from hydra import compose, initialize_config_module

    from comexp.experiment.config import prepare_job

    db = os.path.join(tempfile.gettempdir(), "comexp-bench-unused.db")
    args = [f"backend={backend}", f"floor={floor}", f"speed={speed:g}", f"db={db}", *overrides]
    with initialize_config_module("comexp.conf", version_base="1.3"):
        cfg = compose("config", overrides=args, return_hydra_config=True)
    return prepare_job(cfg)


def _job(backend: str, floor: str, speed: float, overrides: Sequence[str]) -> Any:
    return _prepared_job(backend, floor, float(speed), tuple(overrides))


def job_specs(
    backend: str, floor: str = "iso", speed: float = 40.0, overrides: Sequence[str] = ()
) -> list[EpisodeSpec]:
    """All episodes of one job, expanded exactly as `comexp` does (grid order)."""
    from comexp.experiment.grid import expand_grid

    job = _job(backend, floor, speed, overrides)
    return expand_grid(job.cfg, job.objects, estimator=job.estimator)


def job_simulator(
    backend: str, floor: str = "iso", speed: float = 40.0, overrides: Sequence[str] = ()
) -> SimulatorSpec:
    """The simulator `comexp` hands its workers for this job (`EpisodePool`'s): its class and
    options. Another one would run another physics than the episodes name, and a worker
    refuses every such episode (`physics_mismatch`)."""
    return _job(backend, floor, speed, overrides).simulator


def job_backend_options(
    backend: str, floor: str = "iso", speed: float = 40.0, overrides: Sequence[str] = ()
) -> dict[str, Any]:
    """The backend options of the job's simulator (`job_simulator`), as `make_simulator`'s
    keyword arguments."""
    return dict(job_simulator(backend, floor, speed, overrides).options)


def strided(specs: Sequence[EpisodeSpec], n: int) -> list[EpisodeSpec]:
    """n episodes spread over the whole grid: a fixed, reproducible slice, in grid order.

    The grid is object-major with the 8 conditions (Izz x floor mu x pusher mu) innermost,
    so a plain stride of 1600 / n (a multiple of 8 for n = 200, 40) would pick one condition
    only. The step is the first integer >= len / n that is coprime with len (indices taken
    modulo len stay distinct); for len = 1600 it is odd and not a multiple of 5, so
    consecutive picks also cycle through all 8 conditions."""
    total = len(specs)
    n = min(n, total)
    step = max(1, math.ceil(total / n))
    while math.gcd(step, total) != 1:
        step += 1
    return [specs[i] for i in sorted((k * step) % total for k in range(n))]


# --- simulators --------------------------------------------------------------------------------


def backend_spec(backend: str, **options: Any) -> SimulatorSpec:
    """The built-in backend `backend` (its config group option's class) with `options`."""
    from comexp.experiment.config import load_backend
    from comexp.sim.simulator import SimulatorSpec

    return SimulatorSpec(backend, load_backend(backend)._target_, options)


def bench_simulator(
    simulator: SimulatorSpec | str,
    *mixins: type,
    settings: SimSettings | None = None,
    **options: Any,
) -> Simulator:
    """A simulator of `simulator`'s backend class extended by `mixins` (a bench's classes
    that override some of its methods and call `super()`): the class `(*mixins, backend)`,
    made as `SimulatorSpec.make` makes the backend's. `simulator` is a `SimulatorSpec`
    (`job_simulator`) or a built-in backend's name, then with `options`."""
    spec = backend_spec(simulator, **options) if isinstance(simulator, str) else simulator
    base = spec.simulator_class()
    if not mixins:
        return spec.make(settings)
    name = "".join(m.__name__ for m in mixins) + base.__name__
    cls = type(name, (*mixins, base), {"__module__": __name__})
    return cls(settings, **dict(spec.options))


def source_digest(backend: str) -> str:
    """Short hash of the backend's source file: the backends change under active work, so
    every figure is tied to the exact engine code it measured."""
    from comexp.experiment.config import load_backend

    module = importlib.import_module(load_backend(backend)._target_.rpartition(".")[0])
    with open(module.__file__ or "", "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()[:12]


def warm_up(specs: Sequence[EpisodeSpec], sim: Simulator) -> int:
    """Run the first episode of each object once, untimed (the engine's one-offs per object:
    compilation, scene caches, MuJoCo's renderer per geometry); returns how many ran."""
    from comexp.episode.loop import run_episode

    first: dict[str, EpisodeSpec] = {}
    for s in specs:
        first.setdefault(s.object, s)
    for s in first.values():
        run_episode(s, sim)
    return len(first)


def use_one_cpu() -> None:
    """This process's thread pools as a pool worker's (`comexp.workers.actor.use_one_cpu`):
    the figures are one worker's, and OpenCV's spinning threads would add to its CPU."""
    from comexp.workers.actor import use_one_cpu as worker_threads

    worker_threads()


# --- the process -------------------------------------------------------------------------------


@contextmanager
def engine_stdout_silenced(enabled: bool = True) -> Iterator[None]:
    """Send file descriptor 1 to /dev/null: pybullet's C++ prints a URDF warning per build
    straight to the fd, bypassing sys.stdout, which would bury the figures."""
    if not enabled:
        yield
        return
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        sys.stdout.flush()
        _libc_fflush()  # C stdio buffers still hold engine text meant for /dev/null
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def _libc_fflush() -> None:
    import ctypes

    with suppress(OSError, AttributeError):
        ctypes.CDLL(None).fflush(None)


def load_module(name: str, path: str | os.PathLike[str]) -> ModuleType:
    """The module in the file `path`, imported as `name` (a version of a module kept beside
    the package's, never in its place: registered under its own name)."""
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load {path} as a module")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up while a class is made
    spec.loader.exec_module(module)
    return module


# --- /proc: a process tree's CPU and memory (bench/memory.py, bench/scaling.py) ------------

CLK_TCK = os.sysconf("SC_CLK_TCK")


def _read(path: str) -> str | None:
    try:
        with open(path) as f:
            return f.read()
    except OSError:  # the process ended between listing and reading
        return None


def _stat_fields(pid: int) -> list[str] | None:
    """Fields of /proc/pid/stat after the command name (which may contain spaces)."""
    text = _read(f"/proc/{pid}/stat")
    if text is None:
        return None
    return text[text.rfind(")") + 2 :].split()


def descendants(root: int) -> list[int]:
    """root and every process below it (Ray's gcs_server, raylet, workers, agents)."""
    children: dict[int, list[int]] = collections.defaultdict(list)
    for name in os.listdir("/proc"):
        if name.isdigit():
            f = _stat_fields(int(name))
            if f is not None:
                children[int(f[1])].append(int(name))  # f[1] = ppid
    out, todo = [], [root]
    while todo:
        pid = todo.pop()
        out.append(pid)
        todo.extend(children.get(pid, ()))
    return out


def cpu_seconds(pid: int) -> float | None:
    """User + system CPU time of one process so far."""
    f = _stat_fields(pid)
    if f is None:
        return None
    return (int(f[11]) + int(f[12])) / CLK_TCK  # utime, stime


def proc_name(pid: int) -> str:
    """A readable name: Ray sets actor processes' titles to ray::<Class>..., infrastructure
    binaries keep their names, Python agents are named by their script."""
    cmd = _read(f"/proc/{pid}/cmdline") or ""
    parts = [p for p in cmd.split("\0") if p]
    if not parts:
        return (_read(f"/proc/{pid}/comm") or "?").strip()
    first = parts[0]
    if first.startswith("ray::"):  # ray::EpisodeWorker.run_batch -> ray::EpisodeWorker
        return first.split()[0].split(".")[0]
    base = os.path.basename(first)
    if base.startswith("python"):
        script = next((p for p in parts[1:] if p.endswith(".py")), None)
        if script is None and "-m" in parts[1:-1]:  # python -m ray.scripts.scripts start ...
            return " ".join(parts[parts.index("-m") + 1 :][:2])
        return os.path.basename(script) if script else base
    return base


def memory_kb(pid: int) -> dict[str, int] | None:
    """VmRSS, VmHWM (peak RSS) and PSS of one process, in kB."""
    status = _read(f"/proc/{pid}/status")
    if status is None:
        return None
    out = {"rss": 0, "hwm": 0, "pss": 0}
    for line in status.splitlines():
        if line.startswith("VmRSS:"):
            out["rss"] = int(line.split()[1])
        elif line.startswith("VmHWM:"):
            out["hwm"] = int(line.split()[1])
    rollup = _read(f"/proc/{pid}/smaps_rollup") or ""
    for line in rollup.splitlines():
        if line.startswith("Pss:"):
            out["pss"] = int(line.split()[1])
            break
    return out


# --- the docs' data --------------------------------------------------------------------------

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "docs" / "data"


def machine() -> dict[str, Any]:
    """What the figures were measured on: CPU model, cores, Python."""
    model = platform.processor() or ""
    try:
        with open("/proc/cpuinfo") as f:
            model = next((ln.split(":", 1)[1].strip() for ln in f if "model name" in ln), model)
    except OSError:
        pass
    return {"cpu": model, "cores": os.cpu_count(), "python": platform.python_version()}


def code_version() -> dict[str, Any]:
    rev = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
    ).stdout.strip()
    dirty = subprocess.run(
        ["git", "status", "--porcelain", "--untracked-files=no"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    ).stdout.strip()
    return {"comexp": metadata.version("comexp"), "git": rev + ("+changes" if dirty else "")}


def write_table(
    name: str,
    columns: Sequence[str],
    rows: Sequence[Sequence[Any]],
    command: str,
    **provenance: Any,
) -> Path:
    """docs/data/NAME.json: the table, the command that measured it, and its provenance (the
    code version, machine and date; `provenance`: more, e.g. the studies' own revisions)."""
    DATA.mkdir(parents=True, exist_ok=True)
    path = DATA / f"{name}.json"
    meta = {**code_version(), "machine": machine(), "date": datetime.date.today().isoformat()}
    meta.update(provenance)
    data = {"meta": meta, "command": command, "columns": list(columns), "rows": list(rows)}
    path.write_text(json.dumps(data, indent=1, default=float) + "\n")
    return path
