import os
from pathlib import Path

import pytest

os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
# Jobs here (and the commands they spawn) never use a kept Ray the user may run
# (`comexp-ray start`): its record is looked for in a folder of the tests' own.
os.environ["COMEXP_RAY_DIR"] = os.path.join(
    os.environ.get("TMPDIR", "/tmp"), f"comexp-tests-ray-{os.getpid()}"
)

TESTS_DIR = str(Path(__file__).resolve().parent)
# The token auth of the first local Ray this process started (RAY_AUTH_MODE, RAY_AUTH_TOKEN):
# Ray's core keeps the first token it loaded for the process' lifetime, so a later local Ray
# here with a fresh token is refused (InvalidAuthToken). Every `local_ray` reuses it.
_RAY_AUTH: dict[str, str] = {}


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray (2 CPUs) for a test module's in-process jobs, as `comexp` starts it; its
    workers import this folder's fakes (`test_workers:fake_run`). A job run in this process
    (`test_cli.comexp_in_process`) finds it started and reuses it, as the jobs of one multirun
    do, instead of paying a Ray start each. Shut down, and the environment it exported put
    back, at the module's end. test_workers' pool tests use it too."""
    import ray

    from comexp.workers.session import ensure_ray, shutdown_ray

    if ray.is_initialized():
        ray.shutdown()
    saved = dict(os.environ)  # ensure_ray exports the workers' environment
    os.environ.update(_RAY_AUTH)
    ensure_ray(None, 2, env={"PYTHONPATH": TESTS_DIR})
    _RAY_AUTH.update(
        {k: os.environ[k] for k in ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN") if k in os.environ}
    )
    yield
    shutdown_ray()
    os.environ.clear()
    os.environ.update(saved)
