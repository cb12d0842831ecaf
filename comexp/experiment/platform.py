"""What needs Linux, said once, with one clear line elsewhere.

Linux-only parts of comexp (everything else is plain Python, NumPy, Ray and SQLAlchemy):

- `backend=mujoco`: headless rendering through EGL on Mesa (`MUJOCO_GL=egl`, set in
  backends/mujoco_sim.py) and the compiled step loop, which loads `libmujoco.so*` beside the
  mujoco package (backends/mujoco_steps.py). On macOS or Windows the wheel ships a .dylib or a
  .dll and EGL is absent: `check_backend` refuses the backend in one line before a job starts.
- The per-episode time limit (`execution.episode_timeout_s`): SIGALRM in the worker's main
  thread (POSIX: Linux and macOS). Without SIGALRM (Windows) the worker keeps only its
  watchdog thread, which ends a worker whose episode overruns the limit plus its grace
  period (the pool then retries the batch, and finally stores `worker_died`).
- The join node of a cluster dies with its driver through prctl(PR_SET_PDEATHSIG) (Linux
  only; elsewhere it is stopped at the driver's exit, not on a SIGKILL).
- `make run` / `make test` install system packages with apt-get (Debian, Ubuntu).
"""

from __future__ import annotations

import sys

# backend -> what it needs that only Linux has
LINUX_ONLY_BACKENDS = {
    "mujoco": "headless EGL rendering and the compiled step loop's libmujoco.so lookup",
}


def check_backend(backend: str, platform: str | None = None) -> None:
    """ValueError (one line) when `backend` cannot run on this operating system."""
    platform = sys.platform if platform is None else platform
    need = LINUX_ONLY_BACKENDS.get(backend)
    if need is not None and not platform.startswith("linux"):
        raise ValueError(
            f"backend={backend} runs on Linux only ({need}); this is {platform}: use "
            "backend=planar or backend=pybullet, or the docker image (docker/)"
        )


def has_sigalrm() -> bool:
    """Whether the per-episode time limit can use SIGALRM (POSIX) besides its watchdog."""
    import signal

    return hasattr(signal, "SIGALRM") and hasattr(signal, "setitimer")
