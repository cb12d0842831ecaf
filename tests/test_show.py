"""`comexp-db show`: the figure draws the region the estimator really kept after each push
(the hull every push stores), so its sizes, the true CoM and the estimate agree with the
stored episode; an episode stored without it is redrawn, and the figure says so plainly.

The episode is the study's first one (planar, arrow CoM 0, iso mu 0.1, pusher mu 0.1, Izz 1,
40 cm/s): redrawn from its stored pushes, its last region was 102 px where the episode kept 1,
with the estimate outside the drawn region."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import shapely

from comexp.backends.physics_settings import physics_identity
from comexp.episode.loop import run_episode
from comexp.episode.task import EpisodeSpec
from comexp.experiment.config import load_backend, make_simulator
from comexp.experiment.grid import episode_seed
from comexp.experiment.objects import com_point, load_objects
from comexp.results import plots
from comexp.results.store import ResultsDB


def _first_study_episode():
    arrow = load_objects(["arrow"])["arrow"]
    physics = physics_identity("planar", load_backend("planar")._target_)
    return EpisodeSpec.for_object(
        arrow,
        0,
        com_point(arrow, 0),
        backend="planar",
        floor="iso",
        mu_floor_x=0.1,
        mu_floor_y=0.1,
        mu_pusher=0.1,
        speed_cm_s=40.0,
        izz_scale=1.0,
        seed=episode_seed(0, "arrow", 0),
        physics=physics,
    )


def test_show_draws_the_region_each_push_kept(tmp_path: Path) -> None:
    with make_simulator("planar") as sim:
        result = run_episode(_first_study_episode(), sim)
    assert result.status == "ok", result.detail
    with ResultsDB(tmp_path / "r.db") as db:
        db.add_results(None, [result])
        (row,) = db.episodes()
        pushes = db.pushes(row["id"])
    hulls = [np.asarray(json.loads(p["region_cm"])) for p in pushes]
    assert len(hulls) == result.n_pushes > 0
    # the estimate is the kept region's mean: it lies in (or on) the last hull drawn
    last = hulls[-1]
    est = shapely.Point(row["est_com_x_cm"], row["est_com_y_cm"])
    if len(last) >= 3:
        assert shapely.Polygon(last).buffer(1e-6).contains(est)
    else:
        assert shapely.LineString(np.vstack([last, last])).distance(est) < 1e-3
    out = plots.plot_episode(row, pushes, tmp_path / "ep.png")
    assert out.read_bytes()[:4] == b"\x89PNG"


def test_an_episode_without_its_kept_regions_is_said_to_be_redrawn(tmp_path, monkeypatch):
    with make_simulator("planar") as sim:
        result = run_episode(_first_study_episode(), sim)
    with ResultsDB(tmp_path / "r.db") as db:
        db.add_results(None, [result])
        (row,) = db.episodes()
        pushes = [{**p, "region_cm": None} for p in db.pushes(row["id"])]  # an older comexp
    titles: list[str] = []
    real_title = plots.Figure.suptitle

    def keep(self, t, **kw):
        titles.append(t)
        return real_title(self, t, **kw)

    monkeypatch.setattr(plots.Figure, "suptitle", keep)
    plots.plot_episode(row, pushes, tmp_path / "ep.png")
    assert "REDRAWN from the stored pushes" in titles[-1]
