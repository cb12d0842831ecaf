"""Figures in the spirit of the paper's Figs. 3-5, drawn from the results database, plus the
Izz figure, a backend comparison and one episode drawn in its object's frame.

Every figure groups episodes with `comexp.results.reports.group_episodes` (the one grouping
rule) and pools only the columns its caption names:

- `error_per_object_<condition>.png` (Figs. 3, 4): per object and all objects, one box per
  speed side by side; frictions and Izz pooled (as the paper's tables); the paper's
  all-objects mean is marked (red star) where the condition is the paper's.
- `friction_influence_<condition>.png` (Fig. 5): per floor and pusher friction, one box per
  speed; Izz pooled.
- `izz_influence_<condition>.png`: per Izz scale (and floor), one box per speed; frictions
  pooled.
- `backends_<condition>.png`: per floor and speed, one box per backend on the same condition
  (drawn when at least two backends ran it); frictions and Izz pooled.

Errors are skewed (bounded below by 0), so every figure draws box plots: median, IQR box,
whiskers at 1.5 IQR, outliers, and the mean as a white dot; never a mean +- std bar that would
reach below zero. n (ok episodes) is written above each box. Only ok episodes are drawn; the
number of failed ones is in each caption. Titles are short (what is drawn, backend and
floor); the caption under the axes gives the condition, what was pooled and what was excluded,
and the file name the condition's slug. matplotlib's object API (no pyplot) keeps this headless
and thread-safe (Agg).
"""

from __future__ import annotations

import json
import math
import textwrap
from collections import defaultdict
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
import shapely  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from comexp.method.estimator import EstimatorSettings, update_region  # noqa: E402
from comexp.method.frames import CameraSpec  # noqa: E402
from comexp.method.observation import hull_region  # noqa: E402
from comexp.results.filters import EpisodeFilter  # noqa: E402
from comexp.results.identity import from_json  # noqa: E402
from comexp.results.reports import (  # noqa: E402
    ALL_OBJECTS,
    EPISODE_COLUMNS,
    FRICTION_COLUMNS,
    PAPER_POOL,
    Condition,
    fmt_num,
    group_episodes,
    natural_key,
    ok_error,
    paper_mean_cm,
    pooled_values,
    tables_from_rows,
)
from comexp.results.store import ResultsDB  # noqa: E402

_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")


def speed_name(speed_cm_s: float) -> str:
    kind = {40.0: " (dynamic)", 4.0: " (quasi-static)"}.get(float(speed_cm_s), "")
    return f"{fmt_num(speed_cm_s)} cm/s{kind}"


def _sort_any(v: Any) -> tuple:
    return tuple((0, x) if isinstance(x, int | float) else (1, str(x)) for x in v)


Rows = list[dict[str, Any]]


def _panels(
    rows: Rows, pool: Sequence[str], axes: Sequence[str]
) -> dict[Condition, dict[Condition, Rows]]:
    """group_episodes(rows, pool), then the groups per panel (the condition without `axes`)."""
    out: dict[Condition, dict[Condition, Rows]] = defaultdict(dict)
    for cond, group in group_episodes(rows, pool).items():
        out[cond.pooling(axes)][cond] = group
    return dict(out)


_CHAR_IN = 8 * 0.6 / 72  # width of one tick-label character at 8 pt, inches (about)
_BOX_EXPLAINED = "box = IQR, line = median, dot = mean, number = ok episodes"


def _box_figure(
    *,
    cells: Mapping[tuple[Any, Any], list[float]],  # (x key, series key) -> errors
    xkeys: Sequence[Any],
    xlabel: Callable[[Any], str],
    series: Sequence[Any],
    series_label: Callable[[Any], str],
    title: str,
    caption: str,
    path: Path,
    marks: Mapping[tuple[Any, Any], float] | None = None,
    xtitle: str = "",
) -> Path:
    """Box plots, one group per x key and one box per series. The title is short (what is
    drawn, and the core of the condition); the condition in full, what was pooled and what
    was excluded go into the caption under the axes. Tick labels never overlap: the figure
    widens with the number of boxes and the labels' length (up to 16 in), beyond that the
    labels are turned 35 deg."""
    width = 0.8 / max(1, len(series))
    labels = [xlabel(x) for x in xkeys]
    longest = max((len(line) for text in labels for line in text.split("\n")), default=1)
    fig_w = max(6.5, (0.2 + 0.22 * max(1, len(series))) * len(xkeys) + 1.5)
    fits_w = longest * _CHAR_IN / 0.9 * len(xkeys) + 1.5  # width at which labels fit flat
    turn = fits_w > max(fig_w, 16.0)  # else widen the figure (up to 16 in) rather than turn
    fig_w = min(24.0, fig_w if turn else max(fig_w, fits_w))
    fig = Figure(figsize=(fig_w, 5.2 + (0.06 * longest if turn else 0.0)), layout="constrained")
    ax = fig.add_subplot()
    top = max((max(v) for v in cells.values() if v), default=1.0)
    handles = _draw_boxes(ax, cells, xkeys, series, series_label, width, top)
    star = None
    for (x, s), value in (marks or {}).items():
        if x in xkeys and s in series:
            i, j = list(series).index(s), list(xkeys).index(x)
            p = j + (i - (len(series) - 1) / 2) * width
            star = ax.scatter([p], [value], marker="*", s=90, color="red", zorder=5)
    if star is not None:
        handles.append((star, "paper, all objects (mean)"))
    if turn:
        ax.set_xticks(
            range(len(xkeys)),
            [t.replace("\n", ", ") for t in labels],
            fontsize=8,
            rotation=35,
            ha="right",
            rotation_mode="anchor",
        )
    else:
        ax.set_xticks(range(len(xkeys)), labels, fontsize=8)
    ax.set_xlim(-0.6, len(xkeys) - 0.4)
    ax.set_ylim(bottom=0, top=top * 1.12)
    ax.set_ylabel("CoM error (cm)")
    if xtitle:
        ax.set_xlabel(xtitle)
    ax.set_title(title, fontsize=11)
    ax.grid(axis="y", alpha=0.3)
    if handles:
        ax.legend([h for h, _ in handles], [t for _, t in handles], fontsize=8)
    chars = max(40, int(fig_w * 72 / (7 * 0.55)))
    fig.supxlabel(
        "\n".join(textwrap.wrap(f"{caption}. {_BOX_EXPLAINED}.", chars)),
        fontsize=7,
        color="0.3",
    )
    fig.savefig(path, dpi=110)
    return path


def _draw_boxes(
    ax: Any,
    cells: Mapping[tuple[Any, Any], list[float]],
    xkeys: Sequence[Any],
    series: Sequence[Any],
    series_label: Callable[[Any], str],
    width: float,
    top: float,
) -> list[tuple[Any, str]]:
    """One box per (x key, series) cell with errors, side by side within each x group, the
    number of episodes above each; returns the legend's (artist, label) of every series drawn."""
    handles = []
    for i, s in enumerate(series):
        data, pos = [], []
        for j, x in enumerate(xkeys):
            errs = cells.get((x, s), [])
            if errs:
                data.append(errs)
                pos.append(j + (i - (len(series) - 1) / 2) * width)
        if not data:
            continue
        color = _COLORS[i % len(_COLORS)]
        bp = ax.boxplot(
            data,
            positions=pos,
            widths=width * 0.85,
            patch_artist=True,
            showmeans=True,
            meanprops={"marker": "o", "markerfacecolor": "white", "markeredgecolor": "black"},
            medianprops={"color": "black"},
            flierprops={"markersize": 3},
            manage_ticks=False,
        )
        for box in bp["boxes"]:
            box.set_facecolor(color)
            box.set_alpha(0.6)
        for p, errs in zip(pos, data, strict=True):
            ax.text(p, max(errs) + 0.02 * top, f"{len(errs)}", ha="center", va="bottom", fontsize=6)
        handles.append((bp["boxes"][0], series_label(s)))
    return handles


def _core_label(cond: Condition) -> str:
    """The short part of a condition for a title: backend, floor, pusher friction, speed, Izz
    (those not pooled)."""
    return ", ".join(cond.label().split(", ")[: _n_core_parts(cond)]) or "all conditions"


def _n_core_parts(cond: Condition) -> int:
    return len(cond.label().split(", ")) - len(cond.extras())


def _detail_label(cond: Condition) -> str:
    """The rest of a condition for a caption: rotation source, estimator knobs, protocol, and
    the physics by its version name (its full identity, with the hash, is in the database)."""
    parts = []
    for part in cond.extras():
        if part.startswith("physics="):
            bits = part.removeprefix("physics=").split("/")
            part = f"physics {bits[1] if len(bits) > 1 else bits[0]}"
        parts.append(part)
    return ", ".join(parts)


def _caption(panel: Condition, groups: Mapping[Condition, Rows], pool: Sequence[str]) -> str:
    parts = [p for p in (_core_label(panel), _detail_label(panel)) if p]
    pooled = _pooled_caption(groups, pool)
    text = "; ".join(parts)
    if pooled:
        text += f"; pooled: {pooled}"
    return f"{text}; {_failed(groups)} failed episodes excluded"


def _failed(groups: Mapping[Condition, Rows]) -> int:
    return sum(ok_error(r) is None for g in groups.values() for r in g)


def _pooled_caption(groups: Mapping[Condition, Rows], pool: Sequence[str]) -> str:
    rows = [r for g in groups.values() for r in g]
    vals = pooled_values(rows, pool)
    parts = []
    if "mu_floor_x" in vals and "mu_floor_y" in vals:
        pairs = zip(vals.pop("mu_floor_x"), vals.pop("mu_floor_y"), strict=True)
        parts.append(
            "floor (mu_x, mu_y) {"
            + ", ".join(f"({fmt_num(a)}, {fmt_num(b)})" for a, b in pairs)
            + "}"
        )
    parts += [f"{c} {{{', '.join(fmt_num(v) for v in vs)}}}" for c, vs in vals.items()]
    return "; ".join(parts)


def plot_error_per_object(rows: Rows, out_dir: Path) -> list[Path]:
    paths = []
    for panel, groups in _panels(rows, PAPER_POOL, ("speed_cm_s",)).items():
        cells: dict[tuple[Any, Any], list[float]] = defaultdict(list)
        marks: dict[tuple[Any, Any], float] = {}
        for cond, group in groups.items():
            for r in group:
                e = ok_error(r)
                if e is not None:
                    cells[(r["object"], cond.speed_cm_s)].append(e)
                    cells[(ALL_OBJECTS, cond.speed_cm_s)].append(e)
            if (mark := _paper_mark(group)) is not None:
                marks[(ALL_OBJECTS, cond.speed_cm_s)] = mark
        objects = sorted({r["object"] for g in groups.values() for r in g}, key=natural_key)
        speeds = sorted({c.speed_cm_s for c in groups}, reverse=True)
        paths.append(
            _box_figure(
                cells=cells,
                xkeys=[*objects, ALL_OBJECTS],
                xlabel=str,
                series=speeds,
                series_label=speed_name,
                title=f"CoM error per object: {_core_label(panel)}",
                caption=_caption(panel, groups, PAPER_POOL),
                path=out_dir / f"error_per_object_{panel.slug()}.png",
                marks=marks,
                xtitle="object",
            )
        )
    return paths


def _paper_mark(group: Rows) -> float | None:
    """The paper's all-objects mean for a group pooled as its tables are, where the group is
    the paper's condition (`reports.paper_mean_cm`)."""
    (table,) = tables_from_rows(group, PAPER_POOL)
    return paper_mean_cm(table)


def _friction_text(key: tuple[Any, ...]) -> str:
    floor, fx, fy, p = key
    f = f"mu_f={fmt_num(fx)}" if fx == fy else f"mu_f=({fmt_num(fx)},{fmt_num(fy)})"
    return f"{floor}\n{f}\nmu_p={fmt_num(p)}"


def _by_axis(
    rows: Rows,
    pool: Sequence[str],
    axes: Sequence[str],
    xkey: Callable[[Condition], Any],
    skey: Callable[[Condition], Any],
) -> list[tuple[Condition, dict[Condition, Rows], dict[tuple[Any, Any], list[float]]]]:
    out = []
    for panel, groups in _panels(rows, pool, axes).items():
        cells: dict[tuple[Any, Any], list[float]] = defaultdict(list)
        for cond, group in groups.items():
            cells[(xkey(cond), skey(cond))] += [e for r in group if (e := ok_error(r)) is not None]
        out.append((panel, groups, cells))
    return out


def _influence(
    rows: Rows,
    out_dir: Path,
    *,
    pool: Sequence[str],
    factor: Sequence[str],
    what: str,
    name: str,
    xlabel: Callable[[tuple[Any, ...]], str],
    xtitle: str,
) -> list[Path]:
    """One figure per panel: the error per value of `factor` (with the floor), one box per
    speed, the `pool` columns pooled (and said so in the title)."""
    axes = ("floor", *factor, "speed_cm_s")
    paths = []
    for panel, groups, cells in _by_axis(
        rows,
        pool,
        axes,
        lambda c: (c.floor, *(c[f] for f in factor)),
        lambda c: c.speed_cm_s,
    ):
        xkeys = sorted({x for x, _ in cells}, key=_sort_any)
        speeds = sorted({c.speed_cm_s for c in groups}, reverse=True)
        paths.append(
            _box_figure(
                cells=cells,
                xkeys=xkeys,
                xlabel=xlabel,
                series=speeds,
                series_label=speed_name,
                title=f"Influence of {what}: {_core_label(panel)}",
                caption=_caption(panel, groups, pool),
                path=out_dir / f"{name}_{panel.slug()}.png",
                xtitle=xtitle,
            )
        )
    return paths


def plot_friction_influence(rows: Rows, out_dir: Path) -> list[Path]:
    return _influence(
        rows,
        out_dir,
        pool=("izz_scale",),
        factor=FRICTION_COLUMNS,
        what="friction",
        name="friction_influence",
        xlabel=_friction_text,
        xtitle="floor; floor friction mu_f; pusher friction mu_p",
    )


def plot_izz_influence(rows: Rows, out_dir: Path) -> list[Path]:
    return _influence(
        rows,
        out_dir,
        pool=FRICTION_COLUMNS,
        factor=("izz_scale",),
        what="Izz",
        name="izz_influence",
        xlabel=lambda k: f"{k[0]}\nIzz x{fmt_num(k[1])}",
        xtitle="floor; Izz scale",
    )


def plot_backends(rows: Rows, out_dir: Path) -> list[Path]:
    """Backends side by side on the same condition (only where two or more ran it)."""
    axes = ("backend", "floor", "speed_cm_s")
    paths = []
    for panel, groups, cells in _by_axis(
        rows,
        PAPER_POOL,
        axes,
        lambda c: (c.floor, c.speed_cm_s),
        lambda c: c.backend,
    ):
        backends = sorted({c.backend for c in groups})
        per_x: dict[Any, set[str]] = defaultdict(set)
        for x, b in cells:
            per_x[x].add(b)
        xkeys = sorted((x for x, bs in per_x.items() if len(bs) > 1), key=_sort_any)
        if len(backends) < 2 or not xkeys:
            continue
        marks = {}
        for cond, group in groups.items():
            if (mark := _paper_mark(group)) is not None:
                marks[((cond.floor, cond.speed_cm_s), cond.backend)] = mark
        paths.append(
            _box_figure(
                cells=cells,
                xkeys=xkeys,
                xlabel=lambda k: f"{k[0]}\n{speed_name(k[1])}",
                series=backends,
                series_label=str,
                title="Backends on the same condition",
                caption=_caption(panel, groups, PAPER_POOL),
                path=out_dir / f"backends_{panel.slug() or 'all'}.png",
                marks=marks,
                xtitle="floor and speed",
            )
        )
    return paths


def make_plots(db: ResultsDB, out_dir: str | Path, flt: EpisodeFilter | None = None) -> list[Path]:
    """Write all figures for the selected episodes; returns the PNG paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = db.episodes(flt, columns=EPISODE_COLUMNS, order_by_id=False)
    if not rows:
        return []
    return (
        plot_error_per_object(rows, out)
        + plot_friction_influence(rows, out)
        + plot_izz_influence(rows, out)
        + plot_backends(rows, out)
    )


# --------------------------------------------------------------------------- one episode
def reconstruct_regions(
    spec: Mapping[str, Any], estimator_json: str, pushes: Sequence[Mapping[str, Any]]
) -> tuple[float, list[np.ndarray]]:
    """The CoM region before and after each push, in the object frame (m), rebuilt from the
    stored pushes: the hull's pixel grid at the top face's pixel size, then Algorithm 2 with
    each stored contact, direction and measured rotation. The grid's anchor differs from the
    one the episode's first image gave, so sizes can differ from `region_px` by a few pixels."""
    cam = CameraSpec()
    pixel_m = cam.model().pixel_size_m(cam.height_m - float(spec["height_cm"]) / 100.0)
    outline_m = np.asarray(spec["outline_cm"], dtype=float) / 100.0
    hull = np.asarray(shapely.convex_hull(shapely.Polygon(outline_m)).exterior.coords)[:-1]
    settings = from_json(EstimatorSettings, json.loads(estimator_json))
    region = hull_region(hull, pixel_m)
    regions = [region]
    for p in pushes:
        region, _ = update_region(
            region,
            (p["contact_x_cm"] / 100.0, p["contact_y_cm"] / 100.0),
            (p["dir_x"], p["dir_y"]),
            p["rotation_deg"],
            settings,
            pixel_m,
        )
        regions.append(region)
    return pixel_m, regions


def _draw_hull(ax: Any, hull: np.ndarray) -> None:
    """The kept region: its hull filled (a point or a segment where it is that small)."""
    if len(hull) >= 3:
        ax.fill(hull[:, 0], hull[:, 1], color="tab:green", alpha=0.35, lw=0.8, ec="tab:green")
    else:
        ax.plot(hull[:, 0], hull[:, 1], color="tab:green", marker="o", ms=4, lw=2)


def plot_episode(
    row: Mapping[str, Any], pushes: Sequence[Mapping[str, Any]], path: str | Path
) -> Path:
    """One episode in its object's frame: outline, each push (contact, direction, measured and
    true rotation, decision), the CoM region after it, the true and the estimated CoM.

    The region after each push is the one the estimator kept: the hull each push stored
    (`pushes.region_cm`). An episode stored without it (an older comexp, a plug-in that shows
    no region) has its regions redrawn from the stored pushes, and the figure says so."""
    spec = json.loads(row["spec"])
    _, regions = reconstruct_regions(spec, row["estimator"], pushes)
    kept = [
        None if p.get("region_cm") is None else np.asarray(json.loads(p["region_cm"]))
        for p in pushes
    ]
    stored = bool(pushes) and all(h is not None for h in kept)
    outline = np.asarray(spec["outline_cm"], dtype=float)
    closed = np.vstack([outline, outline[:1]])
    n = len(regions)
    cols = min(3, n)
    nrows = math.ceil(n / cols)
    fig = Figure(figsize=(4.0 * cols, 4.0 * nrows + 0.6), layout="constrained")
    axs = fig.subplots(nrows, cols, squeeze=False)
    true = (row["true_com_x_cm"], row["true_com_y_cm"])
    est = None if row["est_com_x_cm"] is None else (row["est_com_x_cm"], row["est_com_y_cm"])
    pad = 0.25 * float(np.ptp(outline, axis=0).max())
    lo, hi = outline.min(axis=0) - pad, outline.max(axis=0) + pad
    for i, ax in enumerate(axs.ravel()):
        if i >= n:
            ax.set_axis_off()
            continue
        ax.plot(closed[:, 0], closed[:, 1], color="black", lw=1.2)
        reg = regions[i] * 100.0
        if i > 0 and stored:
            _draw_hull(ax, kept[i - 1])
        else:
            ax.scatter(reg[:, 0], reg[:, 1], s=2, color="tab:green", alpha=0.5, lw=0)
        for j, p in enumerate(pushes[:i]):
            c = np.array([p["contact_x_cm"], p["contact_y_cm"]])
            d = np.array([p["dir_x"], p["dir_y"]])
            current = j == i - 1
            color = "tab:red" if current else "0.6"
            ax.annotate(
                "",
                xy=tuple(c),
                xytext=tuple(c - 2.5 * d),
                arrowprops={"arrowstyle": "->", "color": color, "lw": 1.6 if current else 0.8},
            )
            ax.text(*(c - 2.9 * d), str(p["k"]), fontsize=7, color=color, ha="center")
        ax.plot(*true, marker="x", color="blue", ms=9, mew=2, ls="", label="true CoM")
        if est is not None and i == n - 1:
            ax.plot(*est, marker="+", color="tab:red", ms=11, mew=2, ls="", label="estimate")
        if i == 0:
            ax.set_title(f"initial region ({len(reg)} px, redrawn from the outline)", fontsize=8)
        else:
            p = pushes[i - 1]
            size = f"region {p['region_px']} px"
            if not stored:  # redrawn: its own size beside the one the episode kept
                size = f"region redrawn {len(reg)} px (kept {p['region_px']})"
            ax.set_title(
                f"push {p['k']}: measured {p['rotation_deg']:+.2f} deg, "
                f"true {p['rotation_true_deg']:+.2f} deg\n{p['decision']}: {size}",
                fontsize=8,
            )
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
        if i == n - 1:
            ax.legend(fontsize=7, loc="lower right")
    err = "" if row["error_cm"] is None else f", error {row['error_cm']:.2f} cm"
    status = row["status"] if row["failure"] is None else f"failed: {row['failure']}"
    cond = Condition.of(row)
    fig.suptitle(
        f"episode {row['id']}: {row['object']} CoM {row['com_index']} ({status}{err})\n"
        f"{'; '.join(t for t in (_core_label(cond), _detail_label(cond)) if t)}; object frame, "
        + (
            "cm; the region each push kept (its hull)"
            if stored
            else "cm; region REDRAWN from the stored pushes: it may differ from the one the "
            "episode kept"
        ),
        fontsize=9,
    )
    out = Path(path)
    fig.savefig(out, dpi=110)
    return out
