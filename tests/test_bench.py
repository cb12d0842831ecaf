"""The bench scripts' own helpers: a bench that measures other physics than the job's, or
whose episodes all fail, prints figures that mean nothing."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

from episode_profile import job_backend_options, job_specs  # noqa: E402

from comexp.experiment.simulator import physics_identity  # noqa: E402


@pytest.mark.parametrize("backend", ["planar", "pybullet", "mujoco"])
def test_bench_pools_run_the_physics_the_episodes_name(backend):
    """bench/scaling.py and bench/memory.py start their pools with these options; without
    them every worker refused every episode as `physics_mismatch`, and the benches printed
    the timings of 200 refusals."""
    spec = job_specs(backend)[0]
    assert physics_identity(backend, options=job_backend_options(backend)) == spec.physics
    assert physics_identity(backend) != spec.physics or backend == "planar"
