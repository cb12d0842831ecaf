"""Replay of recorded pushes (comexp/real/replay.py, `comexp-real replay`): the round trip
(simulate, log, read, estimate, replay: the same push again on the backend that made it), the
protocol driving a given path as it drives the straight push, a start that overlaps the
outline, one-line errors, and the replay of the shared MIT pushes on every backend."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from test_real_logs import SHARED, needs_shared

from comexp.cli.real import main
from comexp.experiment.config import make_simulator
from comexp.real.estimate import estimate_all
from comexp.real.fit import fit_com
from comexp.real.logs import (
    make_object,
    make_push,
    push_contact,
    read_pushes,
    write_plain_object,
    write_plain_push,
)
from comexp.real.replay import (
    START_GAP_M,
    Surface,
    _clear_start,
    friction_floor,
    geometry_spread,
    object_scene,
    record_push,
    replay_all,
    summarise,
)
from comexp.sim.protocol import push
from comexp.sim.scene import PushCommand

BOX = np.array([[-0.05, -0.03], [0.05, -0.03], [0.05, 0.03], [-0.05, 0.03]])
COM = (0.012, -0.006)
SURFACE = Surface("surface", 0.3, 0.4)
# (offset of the push line from the box's middle, angle to the normal): turns of both signs
PUSHES = [(0.0, 0.0), (0.015, 0.0), (-0.02, 0.3), (0.01, -0.5)]


@pytest.fixture(scope="module")
def planar():
    sim = make_simulator("planar")
    yield sim
    sim.close()


def _box():
    return make_object(
        "box", BOX, Path("box"), true_com_m=COM, mass_kg=0.5, pusher_radius_m=0.005,
        height_m=0.03,
    )  # fmt: skip


def _straight(offset_m: float, angle_rad: float) -> PushCommand:
    d = (math.cos(angle_rad), math.sin(angle_rad))
    return PushCommand((-0.05 - 0.006, offset_m), d, 0.04, 0.05)


def _log_pushes(planar, root: Path, surface: Surface) -> list[float]:
    """PUSHES simulated on planar with the box at COM on `surface`, logged in the plain layout
    under root; their turns (deg)."""
    obj = _box()
    write_plain_object(root / "box", BOX, COM, 0.5, 0.005, 0.03)
    turns = []
    for i, (offset, angle) in enumerate(PUSHES):
        planar.build(object_scene(obj, surface))
        cols, outcome = record_push(planar, _straight(offset, angle))
        assert outcome.ok
        turns.append(outcome.true_rotation_deg)
        write_plain_push(root / "box" / "pushes" / f"p{i}.csv", cols)
    return turns


def test_a_given_path_drives_the_pusher_as_the_straight_push(planar):
    """`PushCommand.along` with the straight push's own path: the same steps, the same
    outcome, to the bit."""
    cmd = _straight(0.015, 0.2)
    dt = planar.settings.timestep_s
    n = math.ceil(cmd.travel_m / (cmd.speed_m_s * dt) - 1e-9)
    travelled = np.minimum(cmd.speed_m_s * dt * np.arange(1, n + 1), cmd.travel_m)
    path = np.asarray(cmd.start_xy_m) + travelled[:, None] * np.asarray(cmd.direction_xy)
    along = PushCommand.along(cmd.start_xy_m, path, dt)
    assert along.travel_m == pytest.approx(cmd.travel_m, abs=1e-15)
    assert along.speed_m_s == pytest.approx(cmd.speed_m_s, rel=1e-12)
    outcomes = []
    for c in (cmd, along):
        planar.build(object_scene(_box(), SURFACE))
        outcomes.append(push(planar, c))
    a, b = outcomes
    assert a.ok and abs(a.true_rotation_deg) > 1.0
    assert (a.pose_after, a.steps, a.true_rotation_deg) == (
        b.pose_after,
        b.steps,
        b.true_rotation_deg,
    )


def test_round_trip_simulate_log_read_estimate_replay(planar, tmp_path):
    """Pushes simulated on planar, logged in the plain layout, read back, estimated and
    replayed on planar: the replay gives the simulation's turn and final position again
    (rounding only), for the recorded path and the idealised push alike."""
    turns = _log_pushes(planar, tmp_path, SURFACE)
    assert min(turns) < -2.0 and max(turns) > 2.0  # both signs: a sign flip would show

    rec = read_pushes(tmp_path)
    (est,) = estimate_all(rec, "paper", pixel_m=0.002)
    assert est.pushes == len(PUSHES) and est.error_cm is not None
    for path in ("recorded", "ideal"):
        replayed = replay_all(planar, rec.objects, rec.pushes, {"surface": SURFACE}, path)
        for r, turn in zip(replayed, turns, strict=True):
            assert r.status == "ok" and r.start_shift_mm == 0.0
            assert r.turn_recorded_deg == pytest.approx(turn, abs=1e-9)
            assert r.turn_simulated_deg == pytest.approx(turn, abs=1e-9)
            assert r.position_error_mm < 1e-9
            assert r.stay_error_mm > 10.0
        s = summarise(replayed)
        assert s.sign_right == s.turning == len(PUSHES)
        assert s.position_error_median_mm < 1e-9 < s.stay_position_error_median_mm


def test_the_friction_floor_finds_each_push_its_own_friction(planar, tmp_path):
    """Pushes simulated with SURFACE's friction, logged and read back: over a grid holding
    that pair, `friction_floor` replays every push with it (no error left, by position and by
    turn), and no pair of the grid, the surface's or another, replays a push better than the
    floor says."""
    _log_pushes(planar, tmp_path, SURFACE)
    rec = read_pushes(tmp_path)
    mu_floor, mu_pusher = (0.15, SURFACE.mu_floor), (SURFACE.mu_pusher, 0.1)
    floor = friction_floor(planar, rec.objects, rec.pushes, mu_floor=mu_floor,
                           mu_pusher=mu_pusher)  # fmt: skip
    assert len(floor.pairs) == 4 and len(floor.position) == len(floor.turn) == len(PUSHES)
    true_pair = (SURFACE.mu_floor, SURFACE.mu_pusher)
    assert floor.best_pair(lambda s: s.position_error_p90_mm) == true_pair
    assert floor.pairs[true_pair].position_error_p90_mm < 1e-9
    assert all(r.position_error_mm < 1e-9 for r in floor.position)
    assert all(abs(r.turn_error_deg) < 1e-9 for r in floor.turn)
    other = replay_all(planar, rec.objects, rec.pushes, {"surface": Surface("surface", 0.15, 0.1)})
    assert all(r.position_error_mm > 0.05 for r in other)  # the grid's pairs differ
    for r, f in zip(other, floor.position, strict=True):
        assert f.position_error_mm <= r.position_error_mm


def test_a_push_turns_the_object_toward_its_line_offset(planar, tmp_path):
    """`PushContact.line_offset_m`: pushes simulated on planar turn the box counter-clockwise
    where the CoM lies left of the pusher's line (positive offset), clockwise where right."""
    turns = _log_pushes(planar, tmp_path, SURFACE)
    rec = read_pushes(tmp_path)
    obj = rec.objects["box"]
    offsets = [push_contact(p, obj).line_offset_m(obj.true_com_m) for p in rec.pushes]
    assert len(offsets) == len(PUSHES) and min(offsets) < -0.005 and max(offsets) > 0.005
    for offset, turn in zip(offsets, turns, strict=True):
        assert abs(turn) < 1.0 if abs(offset) < 0.001 else offset * turn > 0


def test_a_start_that_overlaps_the_outline_is_moved_out_along_the_normal(planar):
    planar.build(object_scene(_box(), SURFACE))
    start = np.array([-0.05 - 0.005 + 0.0003, 0.01])  # the disc 0.3 mm inside the left side
    path = start + np.array([[0.001, 0.0], [0.002, 0.0]])
    new_start, new_path, shift = _clear_start(planar, start, path)
    assert shift == pytest.approx(0.0003 + START_GAP_M, abs=1e-9)
    assert new_start == pytest.approx(start - [shift, 0.0])
    assert new_path == pytest.approx(path - [shift, 0.0])
    assert _clear_start(planar, new_start, new_path)[2] == 0.0


def _write_box(root: Path, **known) -> Path:
    planar = make_simulator("planar")
    planar.build(object_scene(_box(), SURFACE))
    cols, _ = record_push(planar, _straight(0.01, 0.0))
    planar.close()
    write_plain_object(root / "box", BOX, **known)
    write_plain_push(root / "box" / "pushes" / "p0.csv", cols)
    return root


@pytest.mark.parametrize(
    ("known", "args", "needle"),
    [
        ({"true_com_m": COM, "pusher_radius_m": 0.005, "height_m": 0.03}, [],
         "box: replay needs its mass_kg"),
        ({"true_com_m": COM}, [], "replay needs its mass_kg, height_m, pusher_radius_m"),
        ({}, ["--mu-floor", "0.2"], "give both --mu-floor and --mu-pusher, or neither"),
        ({}, ["--backend", "nosuch"], "unknown backend 'nosuch'"),
    ],
)  # fmt: skip
def test_replay_errors_are_one_line(tmp_path, capsys, known, args, needle):
    _write_box(tmp_path, **known)
    friction = [] if "--mu-floor" in args else ["--mu-floor", "0.3", "--mu-pusher", "0.4"]
    code = main(["replay", str(tmp_path), *friction, *args])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("comexp-real: error: ") and needle in err
    assert "\n" not in err


# --- the shared MIT pushes ---------------------------------------------------------------------


def _replay_shared(capsys, backend: str) -> tuple[list[dict], str]:
    code = main(["replay", str(SHARED), "--backend", backend, "--mu-floor", "0.3",
                 "--mu-pusher", "0.25", "--format", "json"])  # fmt: skip
    out, err = capsys.readouterr()
    assert code == 0, err
    return json.loads(out), err


def _figures(records: list[dict]) -> dict[str, float]:
    ok = [r for r in records if r["status"] == "ok"]
    turning = [r for r in ok if abs(r["turn_recorded_deg"]) > 2.0]
    rel = [abs(r["turn_error_deg"]) / abs(r["turn_recorded_deg"]) * 100 for r in turning]
    pos = [r["position_error_mm"] for r in ok]
    sign = sum(np.sign(r["turn_simulated_deg"]) == np.sign(r["turn_recorded_deg"]) for r in turning)
    return {
        "wrong_signs": len(turning) - int(sign),
        "failed": len(records) - len(ok),
        "turn_pct": float(np.median(rel)),
        "pos_mm": float(np.median(pos)),
        "pos_p90_mm": float(np.percentile(pos, 90)),
    }


@needs_shared
def test_replay_of_the_shared_pushes_on_planar(capsys):
    """Every push replays, every turn over 2 deg with the recorded sign, far better than the
    object staying put. Bounds: the figures measured (19.6%, 2.69 mm, p90 6.88 mm with the
    fitted friction) with a margin for another CPU's rounding; the issue's goals are the
    xfail test below."""
    records, err = _replay_shared(capsys, "planar")
    f = _figures(records)
    assert len(records) == 50 and f["failed"] == 0 and f["wrong_signs"] == 0
    assert f["turn_pct"] < 22.0 and f["pos_mm"] < 3.0 and f["pos_p90_mm"] < 7.5
    stay = float(np.median([r["stay_error_mm"] for r in records]))
    assert stay > 8 * f["pos_mm"]
    assert {"push", "object", "backend", "turn_recorded_deg", "turn_simulated_deg",
            "position_error_mm"} <= set(records[0])  # fmt: skip
    assert "planar, recorded path: 50 pushes (0 failed): turn sign right on 45 of 45" in err


@needs_shared
@pytest.mark.xfail(
    reason="measured 19.6% / 2.69 mm / p90 6.88 mm (goals 10% / 2 mm / 4 mm); with each "
    "object's CoM fitted 19.8% / 1.95 / 6.70: the recorded force shows the floor turning the "
    "disc, which planar's even floor cannot; no friction pair for the surface meets any of "
    "the three (best 17.3% / 2.42 / 5.95 mm); docs/real_robot.md, 'What the replay shows'",
    strict=True,
)
def test_replay_goals_on_planar(capsys):
    f = _figures(_replay_shared(capsys, "planar")[0])
    assert f["turn_pct"] <= 10.0 and f["pos_mm"] <= 2.0 and f["pos_p90_mm"] <= 4.0


@needs_shared
@pytest.mark.slow
def test_no_friction_of_a_uniform_floor_meets_the_replay_goals():
    """The shared pushes replayed on every friction pair of the widened grid (100 pairs; ~1
    min). One pair for the surface, the best for each figure alone stays above its goal
    (measured 17.3% of the turn, 2.42 mm, p90 5.95 mm against 10%, 2 mm, 4 mm); with each
    push its own best pair the p90 still does (5.49 mm), and only then do the medians fall
    below theirs (1.25 mm, 1.7%)."""
    rec = read_pushes(SHARED)
    sim = make_simulator("planar")
    floor = friction_floor(sim, rec.objects, rec.pushes)
    sim.close()
    assert len(floor.pairs) == 100 and all(s.failed == 0 for s in floor.pairs.values())
    for figure, goal in ((lambda s: s.turn_error_median_pct, 10.0),
                         (lambda s: s.position_error_median_mm, 2.0),
                         (lambda s: s.position_error_p90_mm, 4.0)):  # fmt: skip
        assert figure(floor.pairs[floor.best_pair(figure)]) > goal * 1.1
    by_position, by_turn = summarise(floor.position), summarise(floor.turn)
    assert by_position.position_error_p90_mm > 5.0
    assert by_position.position_error_median_mm < 2.0 and by_turn.turn_error_median_pct < 10.0


@needs_shared
@pytest.mark.parametrize("backend", ["pybullet", "mujoco"])
def test_engines_replay_within_1_2x_of_planar(capsys, backend):
    planar = _figures(_replay_shared(capsys, "planar")[0])
    engine = _figures(_replay_shared(capsys, backend)[0])
    assert engine["failed"] == 0 and engine["wrong_signs"] == 0
    for key in ("turn_pct", "pos_mm", "pos_p90_mm"):
        assert engine[key] <= 1.2 * planar[key], (key, engine[key], planar[key])


@needs_shared
def test_the_recorded_geometry_does_not_explain_the_replay_error():
    """The replay moved by the recorded geometry's uncertainty (1.5 mm, the dataset's README)
    changes far less than its error against the recordings (measured: 1.05 mm and 4.5% of
    the turn, medians): the goals are not below the data's floor."""
    from comexp.real.logs import read_pushes as read

    rec = read(SHARED)
    sim = make_simulator("planar")
    surfaces = {"abs": Surface("abs", 0.3, 0.25)}
    pushes = rec.pushes[::5]  # every object, and speeds from 10 to 100 mm/s
    spread = geometry_spread(sim, rec.objects, pushes, surfaces, 0.0015)
    none = geometry_spread(sim, rec.objects, pushes[:2], surfaces, 0.0)
    sim.close()
    assert len(spread) == len(pushes) and all(g.position_mm == 0.0 for g in none)
    pos = [g.position_mm for g in spread]
    assert 0.2 < float(np.median(pos)) < 2.0


# --- the fit: the CoM whose replays reproduce the pushes ------------------------------------


def test_the_fit_finds_the_com_of_pushes_simulated_with_it(planar, tmp_path):
    """Pushes simulated on planar with an off-centre CoM and a friction pair of the fit's
    grid, logged and read back: `--estimator fit` finds that CoM to within its finest step
    (1.25 mm), where the paper's method from the same pushes is farther off."""
    _log_pushes(planar, tmp_path, Surface("surface", 0.3, 0.25))
    rec = read_pushes(tmp_path)
    (fit,) = estimate_all(rec, "fit", simulator=planar)
    (paper,) = estimate_all(rec, "paper")
    assert fit.error_cm < 0.125 < paper.error_cm


def test_the_fit_needs_a_simulator_and_the_pushers_radius(planar, tmp_path):
    rec = read_pushes(_write_box(tmp_path / "a", true_com_m=COM))
    with pytest.raises(ValueError, match="needs a planar simulator"):
        estimate_all(rec, "fit")
    with pytest.raises(ValueError, match="the fit needs the pusher's radius"):
        estimate_all(rec, "fit", simulator=planar)


@needs_shared
@pytest.mark.slow
def test_the_fit_on_the_shared_pushes(capsys):
    """`comexp-real estimate --estimator fit` on the shared pushes: mean error 0.346 cm
    measured (the issue's goal 0.5 cm; the paper's method 1.19 cm); ~3 min."""
    assert main(["estimate", str(SHARED), "--estimator", "fit", "--format", "json"]) == 0
    records = json.loads(capsys.readouterr().out)
    errors = [r["error_cm"] for r in records]
    assert len(errors) == 4 and sum(errors) / 4 <= 0.5
    # a fixed offset does not explain the replay's error (docs/real_robot.md): replayed with
    # each object's fitted CoM, the turn and p90 errors stay outside the goals (measured
    # 19.8% and 6.70 mm, against 19.6% and 6.88 mm with the true CoM)
    rec = read_pushes(SHARED)
    fitted = {
        r["object"]: replace(
            rec.objects[r["object"]], true_com_m=np.array([r["com_x_cm"], r["com_y_cm"]]) / 100
        )
        for r in records
    }
    planar = make_simulator("planar")
    replayed = replay_all(planar, fitted, rec.pushes, {"abs": Surface("abs", 0.3, 0.25)})
    planar.close()
    s = summarise(replayed)
    assert s.failed == 0 and s.turn_error_median_pct > 15.0 and s.position_error_p90_mm > 5.5


def test_a_fit_whose_every_candidate_fails_is_an_error(planar):
    """A push the replay refuses whatever the CoM (its pusher starts 5 mm inside the box,
    beyond the 3 mm a recorded start may overlap): no fitted CoM, one line."""
    t = np.linspace(0.0, 1.0, 11)
    pose = np.column_stack([t, np.zeros_like(t), np.zeros_like(t), np.zeros_like(t)])
    inside = -0.05 + 0.005 - 0.005  # the disc's edge 5 mm inside the -x face
    pusher = np.column_stack([t, inside + 0.02 * t, np.zeros_like(t)])
    push = make_push("deep", _box(), Path("deep"), pose, pusher)
    with pytest.raises(ValueError, match="box: the fit found no CoM"):
        fit_com(planar, _box(), [push])
