"""A local Ray kept running between jobs, on the user's request (`comexp-ray start`), so that a
small job does not pay Ray's start (~3 s) and its workers' (~1 s) every time.

`comexp-ray start` starts a Ray head of its own (`ray start --head --block`, public flags only:
no dashboard, no autoscaler monitor, no log monitor) in a private temp dir, with token auth
whose token lives in a record only the user can read (`KeptRay`, `record_path()`), and says
so; `comexp-ray stop` ends exactly its processes. A job on a local Ray (`ray.address` null)
finds the record and connects (`comexp.workers.session.ensure_ray`); its workers stay up in
that Ray for the next job of the same backend and physics (`comexp.workers.pool`).

A record is trusted only when it is ours and alive: owned by this user and readable by no one
else, its `ray start` process running with its temp dir, and written by this comexp from this
Python; a record that fails any of these is reported and not used (a stale one, whose process
is gone, is removed). Ray reads its auth settings once, when it is imported, so the package
exports the kept Ray's token when it is imported (`export_auth`, from `comexp/__init__.py`),
before anything imports Ray; a user's own RAY_AUTH_* settings win.

Ray-free on purpose: the package imports it before Ray.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import importlib.util
import json
import os
import re
import secrets
import signal
import socket
import stat
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

AUTH_KEYS = ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH")
START_TIMEOUT_S = 60.0
STOP_GRACE_S = 3.0  # `comexp-ray stop`: then what is left of the kept Ray is killed


DIR_ENV = "COMEXP_RAY_DIR"  # another folder for the record and Ray's files (tests, a 2nd one)


def base_dir() -> Path:
    """This user's folder for the kept Ray's record and files (short: Ray's unix sockets live
    below it); `COMEXP_RAY_DIR` names another."""
    if os.environ.get(DIR_ENV):
        return Path(os.environ[DIR_ENV])
    uid = os.getuid() if hasattr(os, "getuid") else 0
    return Path(tempfile.gettempdir()) / f"comexp-ray-{uid}"


def record_path() -> Path:
    return base_dir() / "kept.json"


def _version() -> str:
    try:
        return metadata.version("comexp")
    except metadata.PackageNotFoundError:
        return "unknown"


@dataclass(frozen=True)
class KeptRay:
    """The record of a kept Ray: where it listens, its `ray start` process, its temp dir and
    token, and which comexp and Python started it."""

    address: str
    pid: int
    temp_dir: str
    token: str
    cpus: int
    comexp: str
    python: str
    started: str

    def owns_pid(self) -> bool:
        """Whether `pid` is still this record's `ray start` (a pid is reused once it ends)."""
        return f"--temp-dir={self.temp_dir}" in _cmdline(self.pid).split()

    def problem(self) -> str | None:
        """Why this record is not to be trusted (None: it is ours, and alive)."""
        if not _alive(self.pid):
            return f"its Ray (pid {self.pid}) is gone"
        if not self.owns_pid():
            return f"pid {self.pid} is not its `ray start` any more"
        if self.python != sys.executable or self.comexp != _version():
            return f"it was started by another comexp ({self.comexp}, {self.python})"
        return None


def load(tidy: bool = True) -> tuple[KeptRay | None, str | None]:
    """The kept Ray when its record is trusted; else None and why not (None: no record).
    `tidy`: a stale record (its Ray gone) is removed once it has been reported."""
    path = record_path()
    try:
        st = path.stat()
    except FileNotFoundError:
        return None, None
    if hasattr(os, "getuid") and (st.st_uid != os.getuid() or st.st_mode & 0o077):
        return None, f"{path} is not this user's alone: ignored"
    try:
        kept = KeptRay(**json.loads(path.read_text()))
    except (OSError, ValueError, TypeError) as e:
        return None, f"{path} is unreadable ({type(e).__name__}): ignored"
    why = kept.problem()
    if why is None:
        return kept, None
    if tidy and not _alive(kept.pid):
        with contextlib.suppress(OSError):
            path.unlink()  # stale: its Ray is gone
    return None, f"the kept Ray recorded in {path} is not used: {why}"


def export_auth() -> None:
    """Put a trusted kept Ray's token in this process's environment (before Ray is imported:
    it reads its auth settings then), unless the user set Ray's auth themselves."""
    if any(os.environ.get(k) for k in AUTH_KEYS) or not record_path().exists():
        return
    kept, _ = load(tidy=False)  # a stale record is reported where it would be used
    if kept is not None:
        os.environ["RAY_AUTH_MODE"] = "token"
        os.environ["RAY_AUTH_TOKEN"] = kept.token


def start(cpus: int) -> KeptRay:
    """Start a kept Ray with `cpus` CPUs (RuntimeError, one line, when it cannot start or one
    runs already)."""
    kept, _ = load()
    if kept is not None:
        raise RuntimeError(f"a kept Ray runs already at {kept.address} (pid {kept.pid})")
    base = base_dir()
    base.mkdir(mode=0o700, parents=True, exist_ok=True)
    temp_dir = tempfile.mkdtemp(prefix="kept-", dir=base)
    port, token = _free_port(), secrets.token_hex(32)
    env = {**os.environ, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": token}
    env.update(RAY_USAGE_STATS_ENABLED="0", PYTHONUNBUFFERED="1")
    cmd = [
        sys.executable, "-m", "ray.scripts.scripts", "start", "--head", f"--port={port}",
        f"--num-cpus={cpus}", "--num-gpus=0", "--include-dashboard=false",
        "--disable-usage-stats", "--include-log-monitor=false", f"--temp-dir={temp_dir}",
        # the autoscaler monitor has nothing to scale on one machine (a hidden flag of `ray
        # start`; no public switch: ray-project/ray#46732)
        "--no-monitor", "--block",
    ]  # fmt: skip
    log = Path(temp_dir) / "ray-start.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            cmd, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, env=env,
            start_new_session=True,  # not the terminal's: it outlives the command on purpose
        )  # fmt: skip
    address = _wait_started(proc, log)
    kept = KeptRay(
        address, proc.pid, temp_dir, token, cpus, _version(), sys.executable,
        time.strftime("%Y-%m-%dT%H:%M:%S"),
    )  # fmt: skip
    _write(kept)
    return kept


def stop() -> KeptRay | None:
    """Stop the kept Ray (every process of its session) and remove its record; the record
    stopped, None when there was none."""
    path = record_path()
    try:
        kept = KeptRay(**json.loads(path.read_text()))
    except (OSError, ValueError, TypeError):
        return None
    if _alive(kept.pid) and kept.owns_pid():
        # every process of its session: the workers run in process groups of their own, and
        # Ray's own processes take up to Ray's grace period (16 s) to heed `ray start`'s stop
        _signal_all(_session_pids(kept.pid), signal.SIGTERM)
        deadline = time.monotonic() + STOP_GRACE_S
        while _session_pids(kept.pid) and time.monotonic() < deadline:
            time.sleep(0.1)
        _signal_all(_session_pids(kept.pid), signal.SIGKILL)
    path.unlink(missing_ok=True)
    return kept


def _write(kept: KeptRay) -> None:
    path = record_path()
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, stat.S_IRUSR | stat.S_IWUSR)
    with os.fdopen(fd, "w") as f:
        json.dump(dataclasses.asdict(kept), f)


def _wait_started(proc: subprocess.Popen, log: Path) -> str:
    """Until `ray start` says its head runs; the address it gives (`--address='HOST:PORT'`)."""
    deadline = time.monotonic() + START_TIMEOUT_S
    while True:
        text = log.read_text(errors="replace") if log.exists() else ""
        found = re.search(r"--address='([^']+)'", text)
        if "Ray runtime started" in text and found:
            return found[1]
        if proc.poll() is not None or time.monotonic() > deadline:
            lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
            _signal_all(_session_pids(proc.pid), signal.SIGKILL)
            raise RuntimeError(f"`ray start` did not start: {lines[-1] if lines else '?'}")
        time.sleep(0.2)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("", 0))
        return int(s.getsockname()[1])


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return False  # another user's process: not ours
    state = _proc_field(pid, "State:")
    return not state.startswith("Z")


def _session_pids(sid: int) -> list[int]:
    """The live processes of session `sid` (`start` gives `ray start` a session of its own)."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            fields = (d / "stat").read_text().rpartition(")")[2].split()
        except OSError:
            continue
        if len(fields) > 3 and int(fields[3]) == sid and fields[0] != "Z":
            out.append(int(d.name))
    return out


def _signal_all(pids: list[int], sig: int) -> None:
    for pid in pids:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, sig)


def _proc_field(pid: int, name: str) -> str:
    try:
        with open(f"/proc/{pid}/status") as f:
            return next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith(name)), "")
    except OSError:
        return ""


def _cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def code_stamp(target: str = "") -> str:
    """The code a worker runs, cheaply: every module file of comexp (and of the backend's
    module `target`, a plug-in's) by path, size and modification time."""
    packages = ("comexp", "comexp.backends", "comexp.workers")
    roots = {Path(importlib.util.find_spec(p).origin).parent for p in packages}
    files = sorted(f for root in roots for f in root.rglob("*.py"))
    spec = importlib.util.find_spec(target.rpartition(".")[0]) if "." in target else None
    if spec is not None and spec.origin:
        files.append(Path(spec.origin))
    h = hashlib.sha256()
    for f in files:
        st = f.stat()
        h.update(f"{f}:{st.st_size}:{st.st_mtime_ns};".encode())
    return h.hexdigest()[:16]


def available() -> bool:
    """Whether a trusted kept Ray runs (a job on a local Ray will use it)."""
    return record_path().exists() and load()[0] is not None
