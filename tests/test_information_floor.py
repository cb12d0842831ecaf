"""How much the pushes of an episode say about the CoM when the forward model is exact: the
referee (planar) itself, told the true floor, pusher friction, Izz and outline, replays each
push of a `fit` episode from its start pose for candidate CoMs, and the CoM whose replays land
where the object came to rest is kept. Start and final poses carry vision-sized noise (0.5 mm,
0.3 deg: `MotionSettings.sigma_move_m`, `sigma_turn_deg`). A long study (`-m slow`)."""

from __future__ import annotations

import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

SIGMA_M = 0.0005
SIGMA_DEG = 0.3


def _record(spec, sim):
    """The `fit` episode of `spec` on `sim`, and each push's (true start pose, command, true
    pose at rest)."""
    from comexp.episode.loop import run_episode
    from comexp.sim.protocol import push

    records = []

    def recording_push(s, cmd, *args, **kwargs):
        before = s.true_pose()
        out = push(s, cmd, *args, **kwargs)
        records.append((before, cmd, s.true_pose()))
        return out

    return run_episode(spec, sim, push=recording_push), records


def _replay_loss(referee, spec, com_cm, starts, commands, finals) -> float:
    """Sum over the pushes of the replayed rest pose's squared distance from the observed one,
    in units of the noise; a CoM the referee cannot hold up or push counts as far off."""
    from comexp.episode.task import build_scene
    from comexp.sim.protocol import push

    loss = 0.0
    for start, cmd, (x, y, yaw) in zip(starts, commands, finals, strict=True):
        scene = replace(build_scene(replace(spec, com_cm=tuple(com_cm))), initial_pose=start)
        try:
            referee.build(scene)
        except ValueError:  # the CoM outside the footprint's support
            return math.inf
        if not push(referee, cmd).ok:
            return math.inf
        p = referee.true_pose()
        turn = math.degrees(math.remainder(p.yaw_rad - yaw, math.tau))
        loss += ((p.x_m - x) ** 2 + (p.y_m - y) ** 2) / SIGMA_M**2 + (turn / SIGMA_DEG) ** 2
    return loss


def _referee_estimate_cm(referee, spec, records, rng) -> np.ndarray:
    """The posterior mean (exp(-loss / 2)) over a 1 mm grid around the best point of a 5 mm
    grid over the outline."""
    from scipy.spatial import cKDTree

    from comexp.method.estimator import region_from_outline
    from comexp.method.frames import Pose2D

    def noisy(p):
        return Pose2D(
            p.x_m + rng.normal(0, SIGMA_M),
            p.y_m + rng.normal(0, SIGMA_M),
            p.yaw_rad + math.radians(rng.normal(0, SIGMA_DEG)),
        )

    starts = [noisy(b) for b, _, _ in records]
    finals = [(p.x_m, p.y_m, p.yaw_rad) for p in (noisy(a) for _, _, a in records)]
    commands = [c for _, c, _ in records]
    outline = np.array(spec.outline_cm) / 100.0
    coarse = region_from_outline(outline, 0.005) * 100.0
    losses = [_replay_loss(referee, spec, g, starts, commands, finals) for g in coarse]
    best = coarse[int(np.argmin(losses))]
    fine = best + np.array([(i, j) for i in range(-6, 7) for j in range(-6, 7)]) * 0.1
    inside = region_from_outline(outline, 0.001) * 100.0
    fine = fine[cKDTree(inside).query(fine)[0] < 0.08]
    loss = np.array([_replay_loss(referee, spec, g, starts, commands, finals) for g in fine])
    w = np.exp(-0.5 * (loss - loss.min()))
    return (w / w.sum()) @ fine


@pytest.mark.slow
@pytest.mark.parametrize(("floor", "speed_cm_s"), [("aniso", 4.0), ("aniso", 40.0), ("iso", 40.0)])
def test_an_exact_model_finds_the_com_from_the_pushes_fit_chose(floor, speed_cm_s):
    """Planar, 8 episodes spread over the grid: the pushes `fit` chose, read through the exact
    model, place the CoM within a millimetre or two (measured, mean against fit's on the same
    episodes: anisotropic 4 cm/s 0.12 cm against 1.20; anisotropic 40 cm/s 0.07 against 0.64;
    isotropic 40 cm/s 0.05 against 0.17). So what keeps `fit` above its goals there (1, 0.35
    and 0.12 cm) is its models, not what the pushes show."""
    from common import bench_simulator, job_simulator, job_specs, strided

    from comexp.experiment.config import make_simulator

    specs = strided(job_specs("planar", floor, speed_cm_s, ["estimator=fit"]), 8)
    sim = bench_simulator(job_simulator("planar", floor, speed_cm_s))
    referee = make_simulator("planar")
    rng = np.random.default_rng(0)
    exact, fit = [], []
    for spec in specs:
        result, records = _record(spec, sim)
        assert result.status == "ok", (result.failure, result.detail)
        est = _referee_estimate_cm(referee, spec, records, rng)
        exact.append(float(np.hypot(*(est - np.array(spec.com_cm)))))
        fit.append(result.error_cm)
    assert np.mean(exact) < 0.3
    assert np.mean(exact) < 0.6 * np.mean(fit)
