"""Figures readable at a glance: tick labels never overlap (20 long object names, one speed as
after one job, or two), titles are short and carry no physics hash, the condition is in the
caption and in the file name."""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure
from test_db import make_result

from comexp.results.plots import make_plots
from comexp.results.store import ResultsDB

OBJECTS = sorted(p.stem for p in (Path(__file__).parents[1] / "conf" / "object").glob("*.yaml"))
PHYSICS = "planar/planar-2/numba-0.68.1/aed6d7d9bd"


def _results(speeds: tuple[float, ...], floors: tuple[str, ...]) -> list:
    rng = np.random.default_rng(0)
    out = []
    for floor, obj, com, izz, mu_f, mp, speed in itertools.product(
        floors, OBJECTS, range(2), (1.0, 10.0), (0.1, 1.0), (0.1, 1.0), speeds
    ):
        fx, fy = (mu_f, mu_f) if floor == "iso" else (mu_f, 1.1 - mu_f)
        r = make_result(
            object=obj, com_index=com, backend="planar", floor=floor, mu_floor_x=fx,
            mu_floor_y=fy, mu_pusher=mp, speed_cm_s=speed, izz_scale=izz,
            error_cm=float(rng.gamma(2.0, 0.3)),
        )  # fmt: skip
        out.append(dataclasses.replace(r, spec=dataclasses.replace(r.spec, physics=PHYSICS)))
    return out


def _overlaps(boxes: list) -> list[tuple[int, int]]:
    return [
        (i, j)
        for i, j in itertools.combinations(range(len(boxes)), 2)
        if boxes[i].overlaps(boxes[j])
    ]


@pytest.mark.parametrize(
    ("speeds", "floors"), [((40.0,), ("iso",)), ((40.0, 4.0), ("iso", "aniso"))]
)
def test_figures_are_readable(tmp_path: Path, monkeypatch, speeds, floors) -> None:
    figures: dict[str, Figure] = {}
    save = Figure.savefig

    def record(self: Figure, path, *args, **kwargs):
        figures[Path(path).name] = self
        return save(self, path, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", record)
    with ResultsDB(tmp_path / "r.db") as db:
        db.add_results(db.start_sweep(), _results(speeds, floors))
        paths = make_plots(db, tmp_path / "plots")
    assert {p.name for p in paths} == set(figures) and len(paths) == len(floors) + 2
    for name, fig in figures.items():
        assert name.startswith(("error_per_object_planar", "friction_influence_planar",
                                "izz_influence_planar"))  # fmt: skip
        (ax,) = fig.axes
        renderer = fig._get_renderer()
        labels = [t for t in ax.get_xticklabels() if t.get_text()]
        boxes = [t.get_window_extent(renderer) for t in labels]
        angle = labels[0].get_rotation()
        if angle == 0:
            assert not _overlaps(boxes), [labels[i].get_text() for i, _ in _overlaps(boxes)]
        else:  # parallel turned labels: the gap across them must exceed a line's height
            x0, x1 = (ax.transData.transform((x, 0))[0] for x in (0, 1))
            line_px = labels[0].get_fontsize() * fig.dpi / 72 * 1.2
            assert (x1 - x0) * np.sin(np.radians(angle)) > line_px, name
        fig_box = fig.bbox
        assert all(b.x0 >= 0 and b.x1 <= fig_box.x1 and b.y0 >= 0 for b in boxes), name
        title = ax.get_title()
        assert len(title) <= 60 and "\n" not in title and "physics" not in title, title
        assert "aed6d7d9bd" not in title
        caption = fig.get_supxlabel()
        assert "planar" in caption and "rotation vision" in caption and "failed" in caption
        assert "physics planar-2" in caption and "aed6d7d9bd" not in caption
        if name.startswith("error_per_object"):
            assert {t.get_text() for t in labels} == {*OBJECTS, "all"}
            floor = name.removeprefix("error_per_object_planar_").split("_")[0]
            assert f"floor {floor}" in title
