"""The paper's claims, tested on stored results: paired comparisons with bootstrap intervals.

Gao et al. claim that (1) dynamic pushing (40 cm/s) estimates the CoM better than
quasi-static pushing (4 cm/s), on the isotropic and on the anisotropic floor; (2) the floor's
and the pusher's friction matter less for dynamic pushing; (3) a 10x larger Izz hurts
quasi-static pushing. Each claim here is a difference of mean errors between episodes that
differ only in the compared variable: *paired* by (object, CoM, and every other grid value),
so that object and CoM difficulty cancel.

Uncertainty is a two-level cluster bootstrap, objects then CoMs within each drawn object
(the 20 objects and their 10 CoMs are the sampled units; an episode's conditions are not
independent draws): 2,000 replicates with a fixed seed, the 2.5 / 97.5 percentiles. A claim
*holds* when the whole interval lies on its side of zero, *fails* when the whole interval
lies on the other side, and is *inconclusive* otherwise.

Everything else that can change a result (backend, physics identity, estimator settings,
camera rate, protocol) separates studies by `comexp.results.reports.group_episodes`, the one
grouping rule; a claim never pairs episodes across those.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from comexp.results import paper
from comexp.results.reports import (
    CONDITION_COLUMNS,
    FRICTION_COLUMNS,
    Condition,
    group_episodes,
    markdown_table,
)
from comexp.results.reports import json_number as num

# The columns a claim varies; the others define a study (see the module docstring).
VARIED = ("speed_cm_s", "izz_scale", *FRICTION_COLUMNS)
DYNAMIC_CM_S, QUASI_STATIC_CM_S = 40.0, 4.0
# The episode columns the claims read (`comexp-db claims` asks the database for these).
CLAIM_COLUMNS = (*CONDITION_COLUMNS, "object", "com_index", "status", "error_cm")
N_BOOTSTRAP = 2000

# A paired sample: per (object, com) cluster, the per-pair values of each quantity.
Clusters = dict[tuple[str, int], dict[str, list[float]]]


@dataclass(frozen=True)
class ClaimResult:
    """One claim on one study: the statistic (cm), its bootstrap interval, and the verdict."""

    claim: str
    backend: str
    floor: str
    statistic: str  # what `value_cm` is, in words
    value_cm: float
    low_cm: float
    high_cm: float
    n_pairs: int
    side: int  # +1: the claim says value > 0; -1: value < 0

    @property
    def verdict(self) -> str:
        if not math.isfinite(self.low_cm):
            return "no data"
        if self.side * self.low_cm > 0 and self.side * self.high_cm > 0:
            return "holds"
        if self.side * self.low_cm < 0 and self.side * self.high_cm < 0:
            return "fails"
        return "inconclusive"


@dataclass(frozen=True)
class MeanResult:
    """A study's all-episodes mean error at one speed, with its bootstrap interval, against
    the paper's all-objects mean for that floor and speed."""

    backend: str
    floor: str
    speed_cm_s: float
    mean_cm: float
    low_cm: float
    high_cm: float
    n: int
    paper_cm: float | None


def _ok(r: Mapping) -> bool:
    e = r.get("error_cm")
    return r.get("status") == "ok" and e is not None and math.isfinite(float(e))


def _pair_key(r: Mapping, without: Sequence[str]) -> tuple:
    return tuple(r[c] for c in ("object", "com_index", *VARIED) if c not in without)


def _paired(
    rows: Iterable[Mapping], column: str, levels: tuple, fixed: Mapping[str, object] | None = None
) -> Clusters:
    """Per (object, com) cluster, `error(levels[1]) - error(levels[0])` for every pair of ok
    episodes that differ only in `column` (friction pairs count as one column)."""
    cols = ("mu_floor_x", "mu_floor_y") if column == "floor_mu" else (column,)
    by_key: dict[tuple, dict] = defaultdict(dict)
    for r in rows:
        if not _ok(r) or any(r[c] != v for c, v in (fixed or {}).items()):
            continue
        level = tuple(r[c] for c in cols) if len(cols) > 1 else r[cols[0]]
        if level in levels:
            by_key[_pair_key(r, cols)][level] = float(r["error_cm"])
    out: Clusters = defaultdict(lambda: defaultdict(list))
    for key, errs in by_key.items():
        if len(errs) == 2:
            out[(key[0], key[1])]["d"].append(errs[levels[1]] - errs[levels[0]])
    return out


def _bootstrap(
    clusters: Clusters, statistic: Callable[[Mapping[str, float]], float], seed: int
) -> tuple[float, float, float, int]:
    """(value, low, high, n) of `statistic` over cluster-weighted means, objects then CoMs."""
    if not clusters:
        nan = float("nan")
        return nan, nan, nan, 0
    names = sorted({q for c in clusters.values() for q in c})
    keys = sorted(clusters)
    sums = np.array([[sum(clusters[k].get(q, ())) for q in names] for k in keys])
    counts = np.array([[len(clusters[k].get(q, ())) for q in names] for k in keys], dtype=float)
    objects = sorted({k[0] for k in keys})
    members = [np.array([i for i, k in enumerate(keys) if k[0] == o]) for o in objects]

    def values(weights: np.ndarray) -> np.ndarray:
        """`statistic` for each row of cluster weights (one row per replicate)."""
        n = weights @ counts
        means = np.divide(weights @ sums, n, out=np.full(n.shape, np.nan), where=n > 0)
        return np.array([statistic(dict(zip(names, m, strict=True))) for m in means])

    # Replicate weights, all at once: draw objects, then as many CoMs of each drawn object.
    rng = np.random.default_rng(seed)
    sizes = np.array([len(m) for m in members])
    padded = np.zeros((len(objects), sizes.max()), dtype=int)
    for i, m in enumerate(members):
        padded[i, : len(m)] = m
    drawn = rng.integers(0, len(objects), (N_BOOTSTRAP, len(objects)))
    n_drawn = sizes[drawn][..., None]
    pick = (rng.random((N_BOOTSTRAP, len(objects), sizes.max())) * n_drawn).astype(int)
    used = np.arange(sizes.max()) < n_drawn
    index = padded[drawn[..., None], pick]
    w = np.zeros((N_BOOTSTRAP, len(keys)))
    rep = np.broadcast_to(np.arange(N_BOOTSTRAP)[:, None, None], index.shape)
    np.add.at(w, (rep[used], index[used]), 1.0)
    low, high = np.nanpercentile(values(w), [2.5, 97.5])
    n_pairs = int(counts.sum(axis=0).min())
    return float(values(np.ones((1, len(keys))))[0]), float(low), float(high), n_pairs


def _levels(rows: Sequence[Mapping], column: str) -> tuple:
    if column == "floor_mu":
        return tuple(sorted({(r["mu_floor_x"], r["mu_floor_y"]) for r in rows}))
    return tuple(sorted({r[column] for r in rows}))


def _merge(a: Clusters, b: Clusters, names: tuple[str, str]) -> Clusters:
    out: Clusters = defaultdict(dict)
    for src, name in ((a, names[0]), (b, names[1])):
        for k, v in src.items():
            out[k][name] = v["d"]
    return out


def study_claims(rows: Sequence[Mapping], seed: int = 0) -> list[ClaimResult]:
    """The paper's claims on one study (rows of one `group_episodes` group pooled over
    `VARIED`). A claim the study cannot test (one speed, one friction level, one Izz scale)
    is a "no data" row whose statistic says what is missing."""
    backend, floor = rows[0]["backend"], rows[0]["floor"]
    out: list[ClaimResult] = []

    def add(claim: str, statistic: str, side: int, clusters: Clusters, fn) -> None:
        v, lo, hi, n = _bootstrap(clusters, fn, seed)
        out.append(ClaimResult(claim, backend, floor, statistic, v, lo, hi, n, side))

    def missing(claim: str, side: int, why: str) -> None:
        add(claim, why, side, {}, lambda m: float("nan"))

    stored = sorted({float(r["speed_cm_s"]) for r in rows}, reverse=True)
    absent = [s for s in (DYNAMIC_CM_S, QUASI_STATIC_CM_S) if s not in stored]
    has = f"the study has {', '.join(f'{s:g}' for s in stored)} cm/s"
    needs_speeds = f"needs {DYNAMIC_CM_S:g} and {QUASI_STATIC_CM_S:g} cm/s, {has}"

    claim = "dynamic beats quasi-static"
    if absent:
        missing(claim, -1, needs_speeds)
    else:
        speeds = (QUASI_STATIC_CM_S, DYNAMIC_CM_S)
        add(
            claim,
            "mean error 40 - 4 cm/s",
            -1,
            _paired(rows, "speed_cm_s", speeds),
            lambda m: m.get("d", float("nan")),
        )
    for column, label in (("floor_mu", "floor"), ("mu_pusher", "pusher")):
        claim = f"{label} friction matters less when dynamic"
        levels = _levels(rows, column)
        if len(levels) != 2:
            why = f"needs 2 friction levels, the study has {len(levels)}"
            if len(levels) > 2:  # e.g. the paper's aniso run (mu_p 0.5) stored beside the grid's
                why += ": store such runs in separate databases"
            missing(claim, +1, why)
            continue
        if absent:
            missing(claim, +1, needs_speeds)
            continue
        fast = _paired(rows, column, levels, {"speed_cm_s": DYNAMIC_CM_S})
        slow = _paired(rows, column, levels, {"speed_cm_s": QUASI_STATIC_CM_S})
        add(
            claim,
            f"abs. effect at 4 - at 40 cm/s ({_level_text(levels)})",
            +1,
            _merge(slow, fast, ("slow", "fast")),
            lambda m: abs(m.get("slow", float("nan"))) - abs(m.get("fast", float("nan"))),
        )
    claim = "Izz x10 hurts quasi-static"
    izz = _levels(rows, "izz_scale")
    if len(izz) != 2:
        missing(claim, +1, f"needs 2 Izz scales, the study has {len(izz)}")
    elif QUASI_STATIC_CM_S not in stored:
        missing(claim, +1, f"needs {QUASI_STATIC_CM_S:g} cm/s, {has}")
    else:
        add(
            claim,
            f"mean error Izz x{izz[1]:g} - x{izz[0]:g} at 4 cm/s",
            +1,
            _paired(rows, "izz_scale", izz, {"speed_cm_s": QUASI_STATIC_CM_S}),
            lambda m: m.get("d", float("nan")),
        )
    return out


def _level_text(levels: tuple) -> str:
    def one(v) -> str:
        return "/".join(f"{x:g}" for x in v) if isinstance(v, tuple) else f"{v:g}"

    return f"{one(levels[1])} vs {one(levels[0])}"


def study_means(rows: Sequence[Mapping], seed: int = 0) -> list[MeanResult]:
    """Per speed: the mean error over ok episodes with its cluster-bootstrap interval."""
    out = []
    backend, floor = rows[0]["backend"], rows[0]["floor"]
    for speed in sorted({r["speed_cm_s"] for r in rows}, reverse=True):
        clusters: Clusters = defaultdict(lambda: defaultdict(list))
        for r in rows:
            if _ok(r) and r["speed_cm_s"] == speed:
                clusters[(r["object"], r["com_index"])]["e"].append(float(r["error_cm"]))
        v, lo, hi, n = _bootstrap(clusters, lambda m: m["e"], seed)
        ref = paper.ALL_OBJECTS_MEAN_CM.get((floor, float(speed)))
        out.append(MeanResult(backend, floor, float(speed), v, lo, hi, n, ref))
    return out


def studies(rows: Iterable[Mapping]) -> dict[Condition, list[dict]]:
    """Rows grouped into studies: one group per value of everything not in `VARIED`."""
    return group_episodes(rows, pool=VARIED)


def claims_markdown(rows: Iterable[Mapping], seed: int = 0, digits: int = 3) -> str:
    """Every study's means and claims as two Markdown tables (the rows' backends and floors)."""
    means, claims = [], []
    for group in studies(rows).values():
        means += study_means(group, seed)
        claims += study_claims(group, seed)

    def cell(x: float) -> str:
        return "" if not math.isfinite(x) else f"{x:.{digits}f}"

    def ci(lo: float, hi: float) -> str:
        return "" if not (math.isfinite(lo) or math.isfinite(hi)) else f"[{cell(lo)}, {cell(hi)}]"

    mean_table = markdown_table(
        ["backend", "floor", "speed cm/s", "n", "mean error cm", "95% CI", "paper"],
        [
            [m.backend, m.floor, f"{m.speed_cm_s:g}", str(m.n), cell(m.mean_cm),
             ci(m.low_cm, m.high_cm), "" if m.paper_cm is None else cell(m.paper_cm)]
            for m in means
        ],
    )  # fmt: skip
    claim_table = markdown_table(
        ["backend", "floor", "claim", "statistic", "n pairs", "value cm", "95% CI", "verdict"],
        [
            [c.backend, c.floor, c.claim, c.statistic, str(c.n_pairs), cell(c.value_cm),
             ci(c.low_cm, c.high_cm), f"**{c.verdict}**"]
            for c in claims
        ],
    )  # fmt: skip
    return f"{mean_table}\n\n{claim_table}\n"


def claims_records(rows: Iterable[Mapping], seed: int = 0) -> dict[str, list[dict]]:
    """`claims_markdown` as JSON-ready records: {"means": [...], "claims": [...]}."""
    means, claims = [], []
    for group in studies(rows).values():
        means += [
            {"backend": m.backend, "floor": m.floor, "speed_cm_s": m.speed_cm_s, "n": m.n,
             "mean_cm": num(m.mean_cm), "low_cm": num(m.low_cm), "high_cm": num(m.high_cm),
             "paper_cm": num(m.paper_cm)}
            for m in study_means(group, seed)
        ]  # fmt: skip
        claims += [
            {"backend": c.backend, "floor": c.floor, "claim": c.claim, "statistic": c.statistic,
             "n_pairs": c.n_pairs, "value_cm": num(c.value_cm), "low_cm": num(c.low_cm),
             "high_cm": num(c.high_cm), "verdict": c.verdict}
            for c in study_claims(group, seed)
        ]  # fmt: skip
    return {"means": means, "claims": claims}


__all__ = [
    "CLAIM_COLUMNS",
    "ClaimResult",
    "MeanResult",
    "claims_markdown",
    "claims_records",
    "studies",
    "study_claims",
    "study_means",
]
