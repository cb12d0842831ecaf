"""comexp.claims: paired claims with cluster-bootstrap intervals, on synthetic results."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from comexp.results.claims import claims_markdown, studies, study_claims, study_means

BASE = {
    "backend": "planar",
    "floor": "iso",
    "mass_kg": 0.2,
    "push_length_cm": 3.0,
    "recenter_beyond_cm": 10.0,
    "estimator": "{}",
    "physics": "planar/x",
    "camera_fps": 10.0,
    "status": "ok",
}


def _rows(error, n_objects=6, n_coms=4, **base):
    """The iso grid (2 speeds x 2 Izz x 2 floor mu x 2 pusher mu) per object and CoM, with
    error(object index, com, speed, izz, mu_floor, mu_pusher) in cm."""
    rows = []
    for o, k in itertools.product(range(n_objects), range(n_coms)):
        for speed, izz, mu_f, mu_p in itertools.product(
            (40.0, 4.0), (1.0, 10.0), (0.1, 1.0), (0.1, 1.0)
        ):
            r = dict(BASE, **base)
            r.update(
                object=f"obj{o}", com_index=k, speed_cm_s=speed, izz_scale=izz,
                mu_floor_x=mu_f, mu_floor_y=mu_f, mu_pusher=mu_p,
                error_cm=error(o, k, speed, izz, mu_f, mu_p),
            )  # fmt: skip
            rows.append(r)
    return rows


def _by_claim(rows):
    return {c.claim: c for c in study_claims(rows)}


def _difficulty(o, k):
    return 0.3 + 0.2 * o + 0.05 * k  # object and CoM difficulty: cancels in every pair


def test_paper_like_results_make_every_claim_hold():
    rng = np.random.default_rng(1)

    def err(o, k, speed, izz, mu_f, mu_p):
        slow = speed == 4.0
        e = _difficulty(o, k) + (0.5 if slow else 0.0)
        e += (0.3 if slow else 0.02) * (mu_f == 1.0) + (0.2 if slow else 0.01) * (mu_p == 1.0)
        e += 0.25 * (slow and izz == 10.0)
        return e + rng.normal(0, 0.01)

    claims = _by_claim(_rows(err))
    assert {c.verdict for c in claims.values()} == {"holds"}, claims
    dyn = claims["dynamic beats quasi-static"]
    # mean over the grid of -(0.5 + 0.28 * 1/2 + 0.19 * 1/2 + 0.25 * 1/2) = -0.86
    assert dyn.value_cm == pytest.approx(-0.86, abs=0.01)
    assert dyn.low_cm < dyn.value_cm < dyn.high_cm < 0
    assert claims["Izz x10 hurts quasi-static"].value_cm == pytest.approx(0.25, abs=0.01)
    assert claims["floor friction matters less when dynamic"].value_cm == pytest.approx(
        0.28, abs=0.01
    )


def test_the_opposite_fails_and_no_effect_is_inconclusive():
    rng = np.random.default_rng(2)
    worse_fast = _by_claim(_rows(lambda o, k, s, *a: _difficulty(o, k) + 0.2 * (s == 40.0)))
    assert worse_fast["dynamic beats quasi-static"].verdict == "fails"
    noise = _by_claim(_rows(lambda *a: 1.0 + rng.normal(0, 0.3)))
    assert noise["dynamic beats quasi-static"].verdict == "inconclusive"


def test_the_interval_comes_from_objects_and_coms_not_episodes():
    """An effect that only one object shows is not a sure effect of the speed."""
    one_object = _by_claim(_rows(lambda o, k, s, *a: 1.0 - 2.0 * (o == 0 and s == 40.0)))
    dyn = one_object["dynamic beats quasi-static"]
    assert dyn.value_cm == pytest.approx(-2.0 / 6)
    assert dyn.high_cm == pytest.approx(0.0) and dyn.verdict == "inconclusive"


def test_failed_episodes_drop_their_pairs_and_the_seed_fixes_the_interval():
    rows = _rows(lambda o, k, s, *a: _difficulty(o, k) + 0.1 * (s == 4.0) + 0.01 * o * k)
    rows[0].update(status="failed", error_cm=None)
    a, b = study_claims(rows, seed=3), study_claims(rows, seed=3)
    assert a == b
    assert a[0].n_pairs == 6 * 4 * 8 - 1


def test_other_physics_is_another_study_and_means_cite_the_paper():
    rows = _rows(lambda *a: 1.0) + _rows(lambda *a: 2.0, physics="planar/y")
    groups = list(studies(rows).values())
    assert len(groups) == 2 and {len(g) for g in groups} == {6 * 4 * 16}
    means = study_means(groups[0])
    assert [m.speed_cm_s for m in means] == [40.0, 4.0]
    assert means[0].paper_cm == pytest.approx(0.629, abs=1e-3)
    text = claims_markdown(rows)
    assert text.count("dynamic beats quasi-static") == 2 and "| planar | iso | 40 |" in text


def test_three_friction_levels_are_said_not_silently_skipped():
    rows = _rows(lambda *a: 1.0) + [
        dict(r, mu_pusher=0.5) for r in _rows(lambda *a: 1.0) if r["mu_pusher"] == 1.0
    ]
    pusher = [c for c in study_claims(rows) if c.claim.startswith("pusher")]
    assert len(pusher) == 1 and pusher[0].verdict == "no data"
    assert "needs 2 friction levels, the study has 3" in pusher[0].statistic
