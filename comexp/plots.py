"""Figures in the spirit of the paper's Figs. 3-5, drawn from the results database.

- `error_per_object_<backend>_<floor>.png` (Figs. 3, 4): per object, mean +- std of error_cm,
  one bar per speed side by side (dynamic 40 cm/s next to quasi-static 4 cm/s), all frictions
  of that floor pooled.
- `friction_influence_<backend>.png` (Fig. 5): per friction condition (floor mu, pusher mu),
  box plots of error_cm over all objects, one box per speed side by side.

Only ok episodes are drawn; the number of failed ones is printed in each title so that a clean
plot cannot hide failures. matplotlib's object API (no pyplot) keeps this headless and
thread-safe (Agg).
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

from matplotlib.figure import Figure  # noqa: E402

from comexp.db import EpisodeFilter, ResultsDB  # noqa: E402
from comexp.reports import ErrorStats, fmt_num, natural_key  # noqa: E402

_COLUMNS = (
    "backend",
    "floor",
    "mu_floor_x",
    "mu_floor_y",
    "mu_pusher",
    "speed_cm_s",
    "object",
    "status",
    "error_cm",
)
_SPEED_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")


def speed_name(speed_cm_s: float) -> str:
    kind = {40.0: " (dynamic)", 4.0: " (quasi-static)"}.get(float(speed_cm_s), "")
    return f"{fmt_num(speed_cm_s)} cm/s{kind}"


def _ok(r: dict[str, Any]) -> bool:
    return r["status"] == "ok" and r["error_cm"] is not None


def plot_error_per_object(rows: list[dict[str, Any]], out_dir: Path) -> list[Path]:
    by_floor: dict[tuple[str, str], list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        by_floor[(r["backend"], r["floor"])].append(r)
    paths = []
    for (backend, floor), group in sorted(by_floor.items()):
        speeds = sorted({r["speed_cm_s"] for r in group}, reverse=True)
        objects = sorted({r["object"] for r in group}, key=natural_key)
        n_failed = sum(not _ok(r) for r in group)
        width = 0.8 / len(speeds)
        fig = Figure(figsize=(max(6.0, 0.55 * len(objects) + 2), 4.2), layout="constrained")
        ax = fig.add_subplot()
        for i, v in enumerate(speeds):
            stats = [
                ErrorStats.of(
                    [
                        r["error_cm"]
                        for r in group
                        if r["object"] == o and r["speed_cm_s"] == v and _ok(r)
                    ]
                )
                for o in objects
            ]
            xs = [j + (i - (len(speeds) - 1) / 2) * width for j in range(len(objects))]
            ax.bar(
                xs,
                [s.mean if s.n else 0.0 for s in stats],
                width,
                yerr=[s.std if s.n else 0.0 for s in stats],
                capsize=2,
                color=_SPEED_COLORS[i % len(_SPEED_COLORS)],
                label=speed_name(v),
            )
        ax.set_xticks(range(len(objects)), objects, rotation=45, ha="right")
        ax.set_ylabel("CoM error (cm), mean ± std")
        ax.set_ylim(bottom=0)
        ax.set_title(
            f"{backend}, {floor} floor: error per object ({n_failed} failed episodes excluded)"
        )
        ax.legend()
        path = out_dir / f"error_per_object_{backend}_{floor}.png"
        fig.savefig(path, dpi=110)
        paths.append(path)
    return paths


def _friction_label(r: dict[str, Any]) -> tuple[Any, ...]:
    return (r["floor"], r["mu_floor_x"], r["mu_floor_y"], r["mu_pusher"])


def _friction_text(key: tuple[Any, ...]) -> str:
    floor, fx, fy, p = key
    f = f"mu_f={fmt_num(fx)}" if fx == fy else f"mu_f=({fmt_num(fx)},{fmt_num(fy)})"
    return f"{floor}\n{f}\nmu_p={fmt_num(p)}"


def plot_friction_influence(rows: list[dict[str, Any]], out_dir: Path) -> list[Path]:
    by_backend: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        by_backend[r["backend"]].append(r)
    paths = []
    for backend, group in sorted(by_backend.items()):
        speeds = sorted({r["speed_cm_s"] for r in group}, reverse=True)
        frictions = sorted({_friction_label(r) for r in group})
        n_failed = sum(not _ok(r) for r in group)
        width = 0.8 / len(speeds)
        fig = Figure(figsize=(max(6.0, 1.4 * len(frictions) + 2), 4.5), layout="constrained")
        ax = fig.add_subplot()
        handles = []
        for i, v in enumerate(speeds):
            data, pos = [], []
            for j, fk in enumerate(frictions):
                errs = [
                    r["error_cm"]
                    for r in group
                    if _ok(r) and r["speed_cm_s"] == v and _friction_label(r) == fk
                ]
                if errs:
                    data.append(errs)
                    pos.append(j + (i - (len(speeds) - 1) / 2) * width)
            if not data:
                continue
            color = _SPEED_COLORS[i % len(_SPEED_COLORS)]
            bp = ax.boxplot(
                data,
                positions=pos,
                widths=width * 0.9,
                patch_artist=True,
                medianprops={"color": "black"},
                showfliers=True,
                manage_ticks=False,
            )
            for box in bp["boxes"]:
                box.set_facecolor(color)
                box.set_alpha(0.6)
            handles.append((bp["boxes"][0], speed_name(v)))
        ax.set_xticks(range(len(frictions)), [_friction_text(f) for f in frictions], fontsize=8)
        ax.set_xlim(-0.6, len(frictions) - 0.4)
        ax.set_ylabel("CoM error (cm)")
        ax.set_ylim(bottom=0)
        ax.set_title(
            f"{backend}: influence of floor and pusher friction ({n_failed} failed excluded)"
        )
        if handles:
            ax.legend([h for h, _ in handles], [t for _, t in handles])
        path = out_dir / f"friction_influence_{backend}.png"
        fig.savefig(path, dpi=110)
        paths.append(path)
    return paths


def make_plots(db: ResultsDB, out_dir: str | Path, flt: EpisodeFilter | None = None) -> list[Path]:
    """Write all figures for the selected episodes; returns the PNG paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = db.episodes(flt, columns=_COLUMNS, order_by_id=False)
    if not rows:
        return []
    return plot_error_per_object(rows, out) + plot_friction_influence(rows, out)
