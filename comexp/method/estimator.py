"""The CoM estimator: Algorithm 1 (choose the next push) and Algorithm 2 (update the CoM region)
of Gao, Elibol and Chong, as a library that needs no simulator.

Everything is planar and in the object's own frame (metres, y up, CCW positive): the region is
a set of points (the paper's pixels inside the convex hull, on a regular grid of one pixel), a
push is a contact point P and a unit push direction N (the inward contour normal), and the
measured rotation is the object's CCW yaw change during the push, in degrees.

Sign rule (derived in docs/method.md): a push along N at P applies the moment
(P - G) x N about the CoM G; by Mason's voting theorem with R_P in the middle of the friction
cone the object turns with that moment, so a CCW (positive) rotation means N x (G - P) > 0:
the CoM lies to the LEFT of the directed push line. This is the paper's Alg. 2 line 5 in a
y-up frame. (In image pixels, rows down, the same rule reads with the opposite sign.)

Use with a real robot (no simulator)::

    region = initial_region_m            # (n, 2) points inside the object's convex hull
    pushes = [ObservedPush(contact_m=(-0.04, 0.01), direction=(1.0, 0.0), rotation_deg=-7.5)]
    region, estimate = estimate_com(region, pushes, pixel_m=0.0027)

or drive Algorithm 1 step by step with `ComEstimator` (it proposes the next contact).
Pushes observed in the world frame, with the object's pose before each one, go through
`estimate_com_world` (`WorldPush`), which maps them into the object frame and returns the
estimate in both frames; `region_from_outline` and `outline_contacts` give the region and the
contact candidates of a polygon outline. Frames and units: docs/real_robot.md.

`EstimatorSettings.method="magnitude"` (ours, beyond the paper; docs/method.md, "Beyond the
paper") also uses how much the object turns: within the region the signs allow, the CoM is the
point whose lever arms (P_i - G) x N_i best explain the measured rotations with one per-episode
gain, rot_i ~ k f((P_i - G) x N_i) (f linear, or saturating as the impact's l / (rho^2 + l^2)).
Same API: `estimate_com(..., settings=EstimatorSettings(method="magnitude"))`.

Every estimator by its method name, the plug-in protocol and the factory episodes use are
`comexp.method.estimators`'.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import shapely
from numba import njit

from comexp.method.frames import Pose2D, wrap_angle
from comexp.method.geometry import ccw, centroid, simplify
from comexp.method.observation import hull_region

ROTATION_SOURCES = ("vision", "oracle")
# where motion's and fit's nuisance parameters come from: marginalised over their hypotheses
# (fitted), or the episode's true floor, pusher friction and Izz (oracle: the model's floor)
NUISANCE_SOURCES = ("fitted", "oracle")
D_METRICS = ("sine", "distance_px")
# the built-in methods (`comexp.method.estimators.BUILT_IN` has their classes)
METHODS = ("paper", "magnitude", "motion", "fit")
# Saturation lengths tried by the magnitude fit, as multiples beta of the uniform-density
# squared radius of gyration rho0^2(G) of the initial region about G: f(l) = l / (1 + l^2 /
# (beta rho0^2)); inf = the linear model. Profiled (the best per candidate G), since Izz, hence
# rho^2, is unknown to the robot (the study scales it by 1 or 10). The form is the impact's
# omega = v l / (rho^2 + l^2) (docs/method.md); the set was not tuned beyond a few trials.
SATURATION_BETAS = (1.0, 3.0, 10.0, math.inf)
# The magnitude posterior is sharper than a pixel when a push line passes through the CoM (a
# turn of 0.5 deg against a gain of ~20 deg/cm places the line within 0.3 mm), so it is
# evaluated on a grid this many times finer than the region's.
SUBPIXEL = 3


@dataclass(frozen=True)
class EstimatorSettings:
    """Knobs of Algorithms 1 and 2 (paper defaults), plus the readings of the paper's
    ambiguities (defaults = the physically right reading, see docs/method.md).

    Each field is a knob of the `estimator` config node, named on the command line as the
    paper names it where a field's metadata gives `knob` (units dropped: `estimator.theta_T`
    is `theta_T_deg`); the field names are the stored episodes' (their identity)."""

    w: tuple[float, float] = field(
        default=(1.0, 0.5), metadata={"help": "score weights [w1, w2] of d and cos (Eq. 1)"}
    )
    theta_T_deg: float = field(
        default=1.0,
        metadata={"knob": "theta_T", "help": "turns below this (deg) are the band (Alg. 2)"},
    )
    C_bw_px: float = field(
        default=10.0, metadata={"knob": "C_bw", "help": "the band's half width, px (Alg. 2)"}
    )
    n_push: int = field(default=5, metadata={"help": "pushes per episode"})
    rotation_source: str = field(
        default="vision",
        metadata={"help": "vision (the tracked images) | oracle (the true pose: evaluation)"},
    )
    # vision with frames: a frame is tracked when the predicted turn since the last one
    # reaches track_step_deg, or track_gap_s after it at the latest, and while the pusher
    # drives once it has travelled track_drive_mm since (every frame at 40 cm/s, every third
    # at 4 cm/s; `PoseTracker.wants_frame`)
    track_step_deg: float = field(
        default=10.0,
        metadata={
            "knob": "track_step",
            "help": "track a frame once the predicted turn reaches this (deg); 0: every frame",
        },
    )
    track_gap_s: float = field(
        default=0.1,
        metadata={"knob": "track_gap", "help": "track a frame this long (s) after the last"},
    )
    track_drive_mm: float = field(
        default=4.0,
        metadata={
            "knob": "track_drive",
            "help": "while the pusher drives, a frame every this many mm; 0: every frame",
        },
    )
    # --- readings of the paper's ambiguities -----------------------------------------------
    d_metric: str = field(
        default="sine",
        metadata={"help": "score term d: sine (of the angle, Alg. 1) | distance_px (Eq. 1)"},
    )
    d_signed: bool = field(
        default=False, metadata={"help": "the score's d signed (literal) instead of |d|"}
    )
    cos_signed: bool = field(
        default=False, metadata={"help": "the score's N.V1 signed (literal) instead of |N.V1|"}
    )
    band_signed: bool = field(
        default=False,
        metadata={"help": "the band deletes d >= C_bw only (literal Alg. 2 l. 16) vs |d|"},
    )
    # --- contact candidates ----------------------------------------------------------------
    contact_spacing_px: float = field(
        default=2.0,
        metadata={"knob": "contact_spacing", "help": "arc length between contact candidates, px"},
    )
    check_reachability: bool = field(
        default=True, metadata={"help": "drop contacts the pusher cannot reach along -N"}
    )
    # --- beyond the paper (docs/method.md, "Beyond the paper") -------------------------------
    method: str = field(
        default="paper",
        metadata={
            "help": "paper | magnitude (also fits how much each push turns) | motion (reads "
            "the tracked path) | fit (also a quasi-static model of slow pushes' paths) | a "
            "plug-in module:Class (docs/your_estimator.md)"
        },
    )
    mag_noise_deg: float = field(
        default=1.0,
        metadata={"knob": "mag_noise", "help": "magnitude: the turns' noise floor sigma0 (deg)"},
    )
    mag_rel_noise: float = field(
        default=0.2,
        metadata={"help": "magnitude: relative model error alpha of a turn (sigma0, alpha rot)"},
    )
    mag_floor_model: bool = field(
        default=True,
        metadata={
            "help": "magnitude: the known floor and pusher friction turn each push's line of "
            "action; false: along the push, as the paper"
        },
    )
    # motion and fit: the model's revision (`comexp.method.motion_estimator.MOTION_VERSION`,
    # `comexp.method.fit_estimator.FIT_VERSION`), pinned by the grid for their jobs so that a
    # database is never resumed across revisions; part of the episode key only when set ("" =
    # not pinned: other methods, older databases)
    motion_version: str = field(
        default="",
        metadata={
            "key_omit_default": True,
            "help": "motion, fit: the model's revision in the episode key; empty: the current one",
        },
    )
    # motion and fit: the floor (friction ratio and axes), the pusher's friction and Izz are
    # nuisances the models marginalise; `oracle` tells them the episode's true values, which
    # measures what is left when nothing is unknown but the CoM (docs/method.md)
    nuisance_source: str = field(
        default="fitted",
        metadata={
            "key_omit_default": True,
            "help": "motion, fit: fitted (the floor, pusher friction and Izz marginalised) | "
            "oracle (the episode's true ones: evaluation)",
        },
    )

    def __post_init__(self) -> None:
        if self.rotation_source not in ROTATION_SOURCES:
            raise ValueError(
                f"rotation_source must be one of {ROTATION_SOURCES}, got {self.rotation_source!r}"
            )
        if self.d_metric not in D_METRICS:
            raise ValueError(f"d_metric must be one of {D_METRICS}, got {self.d_metric!r}")
        # the one set of rules: the config checks its `estimator` node through these
        if len(self.w) != 2 or not np.all(np.isfinite(self.w)):
            raise ValueError(f"w must be two finite weights, got {list(self.w)}")
        if not (np.isfinite(self.theta_T_deg) and self.theta_T_deg >= 0):
            raise ValueError(f"theta_T_deg must be finite and >= 0, got {self.theta_T_deg!r}")
        if not (np.isfinite(self.C_bw_px) and self.C_bw_px > 0):
            raise ValueError(f"C_bw_px must be finite and > 0, got {self.C_bw_px!r}")
        if not (math.isfinite(self.track_step_deg) and self.track_step_deg >= 0):
            raise ValueError(f"track_step_deg must be finite and >= 0, got {self.track_step_deg!r}")
        if not (math.isfinite(self.track_gap_s) and self.track_gap_s > 0):
            raise ValueError(f"track_gap_s must be finite and > 0, got {self.track_gap_s!r}")
        if not (math.isfinite(self.track_drive_mm) and self.track_drive_mm >= 0):
            raise ValueError(f"track_drive_mm must be finite and >= 0, got {self.track_drive_mm!r}")
        if self.n_push < 1:
            raise ValueError(f"n_push must be >= 1, got {self.n_push}")
        if self.contact_spacing_px <= 0:
            raise ValueError("contact_spacing_px must be > 0")
        if self.method not in METHODS and not is_plugin(self.method):
            # whether a plug-in can be used is `comexp.method.estimators.resolve_estimator`'s
            raise ValueError(
                f"method must be one of {METHODS} or a plug-in 'module:Class', got {self.method!r}"
            )
        if self.nuisance_source not in NUISANCE_SOURCES:
            raise ValueError(
                f"nuisance_source must be one of {NUISANCE_SOURCES}, got {self.nuisance_source!r}"
            )
        if self.nuisance_source == "oracle" and self.method not in ("motion", "fit"):
            raise ValueError(
                f"nuisance_source=oracle needs method motion or fit, got {self.method!r}"
            )
        if not (math.isfinite(self.mag_noise_deg) and self.mag_noise_deg > 0):
            raise ValueError(f"mag_noise_deg must be > 0, got {self.mag_noise_deg!r}")
        if not (math.isfinite(self.mag_rel_noise) and self.mag_rel_noise >= 0):
            raise ValueError(f"mag_rel_noise must be >= 0, got {self.mag_rel_noise!r}")


def cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z component of a x b for (..., 2) arrays."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def pca(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroid c, principal axes V (columns, V[:, 0] the main one) and variances of a point set."""
    pts = np.asarray(points, dtype=float)
    c = pts.mean(axis=0)
    if len(pts) < 2:
        return c, np.eye(2), np.zeros(2)
    cov = np.cov((pts - c).T, bias=True)
    lam, vec = np.linalg.eigh(cov)  # ascending
    return c, vec[:, ::-1], lam[::-1]


def weighted_pca(
    points: np.ndarray, weights: np.ndarray, floor_m: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`pca` of a weighted point set (the magnitude posterior): mean, axes, variances. A point
    set is a grid, so `floor_m`^2 / 12 (a grid cell's own variance) is added to the covariance:
    a posterior sharper than the grid has no main axis to speak of."""
    pts = np.asarray(points, dtype=float)
    w = np.asarray(weights, dtype=float)
    w = w / w.sum()
    c = w @ pts
    d = pts - c
    cov = (d * w[:, None]).T @ d + np.eye(2) * floor_m**2 / 12.0
    lam, vec = np.linalg.eigh(cov)
    return c, vec[:, ::-1], lam[::-1]


def line_cuts_region(region: np.ndarray, P: np.ndarray, N: np.ndarray) -> np.ndarray:
    """For each push line (P_i, N_i): does it pass through the region, i.e. leave region points
    strictly on both sides? (M,) bool. A point whose side is NaN is on neither side.
    Compiled (`_line_cuts_kernel`): a line's scan stops at its first points on both sides,
    where the (M, n) planes of sides cost ~0.1 ms a push."""
    region = np.ascontiguousarray(region, dtype=np.float64).reshape(-1, 2)
    P = np.ascontiguousarray(P, dtype=np.float64).reshape(-1, 2)
    N = np.ascontiguousarray(N, dtype=np.float64).reshape(-1, 2)
    out = np.zeros(len(P), dtype=np.bool_)
    if len(region):
        _line_cuts_kernel(region, P, N, out)
    return out


@njit(cache=True)
def _line_cuts_kernel(region, P, N, out):
    """`line_cuts_region` into `out`: the side of every region point, cross2(N_i, r_j - P_i),
    in the arithmetic of the numpy expression it replaced (dx, dy, then N_x dy - N_y dx). A
    point whose side is NaN is on neither side."""
    for i in range(P.shape[0]):
        px, py, nx, ny = P[i, 0], P[i, 1], N[i, 0], N[i, 1]
        pos = neg = False
        for j in range(region.shape[0]):
            side = nx * (region[j, 1] - py) - ny * (region[j, 0] - px)
            if side > 0.0:
                pos = True
            elif side < 0.0:
                neg = True
            if pos and neg:
                break
        out[i] = pos and neg


def push_candidates(
    contacts_m: np.ndarray,
    normals: np.ndarray,
    settings: EstimatorSettings,
    outline_m: np.ndarray | None = None,
    pusher_radius_m: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Algorithm 1's candidates as every estimator keeps them: contacts (n x 2), unit inward
    normals, and which of them the pusher can reach (all, without an outline and a radius or
    with `check_reachability` off)."""
    contacts = np.asarray(contacts_m, dtype=float).reshape(-1, 2)
    n = np.asarray(normals, dtype=float).reshape(-1, 2)
    unit = n / np.linalg.norm(n, axis=1, keepdims=True)
    if settings.check_reachability and outline_m is not None and pusher_radius_m:
        allowed = reachable_contacts(outline_m, contacts, unit, pusher_radius_m)
    else:
        allowed = np.ones(len(contacts), dtype=bool)
    return contacts, unit, allowed


def reachable_contacts(
    outline_m: np.ndarray,
    P: np.ndarray,
    N: np.ndarray,
    pusher_radius_m: float,
    approach_m: float | None = None,
    tol_m: float = 5e-4,
) -> np.ndarray:
    """Can a round pusher of this radius come in along +N and touch P without first hitting
    the object? False for contacts deep in a notch narrower than the pusher, or shadowed by
    another part of a non-convex outline. (M,) bool.

    The pusher's disc is swept from far away (default: the outline's diameter) to where it
    touches P; it may not overlap the outline by more than `tol_m` (touching P is allowed).
    """
    P = np.asarray(P, dtype=float)
    N = np.asarray(N, dtype=float)
    if len(P) == 0:
        return np.zeros(0, dtype=bool)
    poly = shapely.Polygon(outline_m).buffer(0)
    if approach_m is None:
        ext = np.ptp(np.asarray(outline_m), axis=0)
        approach_m = float(np.hypot(*ext)) + 2 * pusher_radius_m
    r_eff = pusher_radius_m - tol_m
    near = P - N * (pusher_radius_m + tol_m)
    far = P - N * (pusher_radius_m + approach_m)
    paths = shapely.linestrings(np.stack([near, far], axis=1))
    swept = shapely.buffer(paths, r_eff)
    shapely.prepare(poly)
    return ~shapely.intersects(poly, swept)


def score_contacts(
    region: np.ndarray,
    P: np.ndarray,
    N: np.ndarray,
    settings: EstimatorSettings,
    pixel_m: float,
    centre_axes: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Eq. (1): s = w1 d + w2 cos, lower is better (Alg. 1 lines 3, 5, 6).

    d measures how far the push line passes from the region's centroid c (small d = the cut
    splits the region near its middle); cos = N . V1 is small when the push line crosses the
    region's long axis (so the region does not stay prolate). V1's sign is arbitrary, so the
    physical reading is |N . V1|; an unsigned d likewise (a line far on either side is as bad).
    `centre_axes` = (c, V) replaces the region's own (`magnitude`: the posterior's).
    """
    c, V = centre_axes if centre_axes is not None else pca(region)[:2]
    v1 = V[:, 0]
    cp = c[None, :] - P
    if settings.d_metric == "sine":
        norm = np.linalg.norm(cp, axis=1)
        d = cross2(cp / np.maximum(norm, 1e-12)[:, None], N)
    else:
        d = cross2(cp, N) / pixel_m
    if not settings.d_signed:
        d = np.abs(d)
    cos = N @ v1
    if not settings.cos_signed:
        cos = np.abs(cos)
    return settings.w[0] * d + settings.w[1] * cos


def choose_contact(
    region: np.ndarray,
    P: np.ndarray,
    N: np.ndarray,
    settings: EstimatorSettings,
    pixel_m: float,
    allowed: np.ndarray | None = None,
    centre_axes: tuple[np.ndarray, np.ndarray] | None = None,
) -> int | None:
    """Index of the best valid contact (Alg. 1 lines 3-7), None if no push line cuts the region.

    `allowed` masks out contacts that are invalid for reasons other than the region (e.g.
    unreachable, see `reachable_contacts`); `centre_axes` see `score_contacts`.
    """
    if len(P) == 0 or len(region) == 0:
        return None
    if allowed is None:
        valid = line_cuts_region(region, P, N)
    else:  # only the allowed push lines need the (contacts x region) test
        valid = np.zeros(len(P), dtype=bool)
        valid[allowed] = line_cuts_region(region, P[allowed], N[allowed])
    if not valid.any():
        return None
    s = score_contacts(region, P, N, settings, pixel_m, centre_axes)
    s = np.where(valid, s, np.inf)
    return int(np.argmin(s))


def update_region(
    region: np.ndarray,
    P: Sequence[float] | np.ndarray,
    N: Sequence[float] | np.ndarray,
    rotation_deg: float,
    settings: EstimatorSettings,
    pixel_m: float,
) -> tuple[np.ndarray, str]:
    """Algorithm 2: keep the region's points consistent with the observed rotation.

    |rotation| > theta_T: CCW keeps N x (G - P) > 0 (left of the push line), CW keeps < 0.
    Otherwise the push line passed close to the CoM: keep the band |d| < C_bw around it
    (d the point's distance to the line; C_bw converted from pixels with `pixel_m`).
    Returns the new region and the decision (`ccw`, `cw`, `band`). An update that would leave
    nothing (contradictory observations) keeps the previous region and says so in the decision
    (`ccw-empty`, ...), rather than losing the estimate.
    """
    region = np.asarray(region, dtype=float)
    P = np.asarray(P, dtype=float)
    N = np.asarray(N, dtype=float)
    N = N / np.linalg.norm(N)
    side = cross2(N, region - P)  # signed distance to the push line, + = left of it
    if abs(rotation_deg) > settings.theta_T_deg:
        decision = "ccw" if rotation_deg > 0 else "cw"
        keep = side > 0 if rotation_deg > 0 else side < 0
    else:
        decision = "band"
        bw = settings.C_bw_px * pixel_m
        # literal Alg. 2 line 15-16: d = (P_i - P) x N = -side, delete d >= C_bw
        keep = (-side < bw) if settings.band_signed else (np.abs(side) < bw)
    if not keep.any():
        return region, decision + "-empty"
    return region[keep], decision


def lever_arms(candidates: np.ndarray, P: np.ndarray, N: np.ndarray) -> np.ndarray:
    """(P_j - G_i) x N_j for every candidate CoM G_i and push j: (n, m), metres; the rotation
    has its sign (CCW positive)."""
    G = np.asarray(candidates, dtype=float).reshape(-1, 2)
    P = np.asarray(P, dtype=float).reshape(-1, 2)
    N = np.asarray(N, dtype=float).reshape(-1, 2)
    return cross2(P[None, :, :] - G[:, None, :], N[None, :, :])


def magnitude_misfit(
    candidates: np.ndarray,
    P: np.ndarray,
    N: np.ndarray,
    rotation_deg: np.ndarray,
    settings: EstimatorSettings,
    footprint_m: np.ndarray,
) -> np.ndarray:
    """How badly each candidate CoM explains the measured rotations: chi^2, (n,).

    Model: rot_j = k f(l_j) with l_j = (P_j - G) x N_j, one gain k >= 0 per episode (it holds
    the speed, friction and Izz, which are fixed within an episode), fitted in closed form per
    candidate; f(l) = l / (1 + l^2 / (beta rho0^2(G))) with beta profiled over
    `SATURATION_BETAS` (inf: linear), rho0^2(G) the squared radius of gyration of `footprint_m`
    (the initial region, uniform density) about G. Residuals are weighted by
    1 / (sigma0^2 + (alpha rot_j)^2): a large turn says less about its exact lever than a small
    one (saturation, the direction's own gain), and a turn near zero pins the line near G.
    """
    G = np.asarray(candidates, dtype=float).reshape(-1, 2)
    rot = np.asarray(rotation_deg, dtype=float).reshape(-1)
    if len(rot) == 0 or len(G) == 0:
        return np.zeros(len(G))
    foot = np.asarray(footprint_m, dtype=float).reshape(-1, 2)
    c = foot.mean(axis=0)
    rho2 = ((foot - c) ** 2).sum(axis=1).mean() + ((G - c) ** 2).sum(axis=1)  # (n,)
    lev = lever_arms(G, P, N)
    w = 1.0 / (settings.mag_noise_deg**2 + (settings.mag_rel_noise * rot) ** 2)
    best = np.full(len(G), np.inf)
    for beta in SATURATION_BETAS:
        f = lev if math.isinf(beta) else lev / (1.0 + lev * lev / (beta * rho2[:, None]))
        k = (w * rot * f).sum(axis=1) / np.maximum((w * f * f).sum(axis=1), 1e-300)
        k = np.maximum(k, 0.0)  # the object turns with the moment, never against it
        best = np.minimum(best, (w * (rot - k[:, None] * f) ** 2).sum(axis=1))
    return best


def magnitude_posterior(
    region: np.ndarray,
    P: np.ndarray,
    N: np.ndarray,
    rotation_deg: np.ndarray,
    settings: EstimatorSettings,
    footprint_m: np.ndarray,
) -> np.ndarray:
    """Weights (n,), summing to 1, of the region's points: exp(-chi^2 / 2) of
    `magnitude_misfit`, i.e. a likelihood with a uniform prior over the sign-consistent
    region."""
    chi = magnitude_misfit(region, P, N, rotation_deg, settings, footprint_m)
    p = np.exp(-(chi - chi.min()) / 2.0) if len(chi) else chi
    return p / p.sum() if len(p) else p


def refine_grid(region: np.ndarray, pixel_m: float, n: int = SUBPIXEL) -> np.ndarray:
    """Every point of a regular grid of spacing `pixel_m` replaced by the n x n points of
    spacing pixel_m / n that tile its cell: the same area, n^2 times the points."""
    o = (np.arange(n) - (n - 1) / 2.0) * pixel_m / n
    off = np.stack(np.meshgrid(o, o), axis=-1).reshape(-1, 2)
    return (np.asarray(region, dtype=float)[:, None, :] + off[None]).reshape(-1, 2)


class MagnitudePosterior:
    """The magnitude method's state: the sign-consistent region on the fine grid (the same
    Algorithm 2 updates as the region) and the observed pushes; weights and estimate on it."""

    def __init__(self, region_m: np.ndarray, pixel_m: float, settings: EstimatorSettings):
        self.settings = settings
        self.pixel_m = float(pixel_m)
        self.footprint = np.asarray(region_m, dtype=float)
        self.points = refine_grid(self.footprint, self.pixel_m)
        self.weights = np.full(len(self.points), 1.0 / max(len(self.points), 1))
        self._pushes: list[tuple[np.ndarray, np.ndarray, float]] = []

    def observe(self, contact_m: Sequence[float], direction: Sequence[float], rot_deg: float):
        P = np.asarray(contact_m, dtype=float)
        N = np.asarray(direction, dtype=float)
        N = N / np.linalg.norm(N)
        self.points, _ = update_region(self.points, P, N, rot_deg, self.settings, self.pixel_m)
        self._pushes.append((P, N, float(rot_deg)))
        Ps, Ns, rot = (np.array(x) for x in zip(*self._pushes, strict=True))
        self.weights = magnitude_posterior(self.points, Ps, Ns, rot, self.settings, self.footprint)

    @property
    def estimate_m(self) -> np.ndarray:
        return self.weights @ self.points

    def centre_axes(self) -> tuple[np.ndarray, np.ndarray]:
        """Posterior mean and principal axes, for Algorithm 1's score."""
        c, V, _ = weighted_pca(self.points, self.weights, self.pixel_m / SUBPIXEL)
        return c, V


def floor_force_direction(
    direction: Sequence[float],
    yaw_rad: float,
    mu_x: float,
    mu_y: float,
    mu_pusher: float,
    share: float = 0.5,
) -> np.ndarray:
    """The line of action to expect for a push along `direction` (object frame, unit) on a
    floor with friction mu_x, mu_y along its world axes, the object at world yaw `yaw_rad`.

    Why: on an anisotropic floor the friction of an object sliding along u is along
    -(mu_x^2 u_x, mu_y^2 u_y), not -u; the force that balances it is turned away from the push
    direction by the angle phi between u and that vector, as far as the pusher's friction cone
    (atan mu_pusher) allows, and the object turns about the line of that force, not of the
    push. `share` of phi (0.5, measured on planar pushes: docs/method.md, "Beyond the paper") is
    applied, since the object does not only translate. Isotropic floors: `direction` itself.
    """
    n = np.asarray(direction, dtype=float)
    n = n / np.linalg.norm(n)
    if mu_x == mu_y:
        return n
    th = math.atan2(n[1], n[0]) + yaw_rad  # world direction of the push
    th_f = math.atan2(mu_y**2 * math.sin(th), mu_x**2 * math.cos(th))
    phi = (th_f - th + math.pi) % (2 * math.pi) - math.pi
    cone = math.atan(max(mu_pusher, 0.0))
    phi = min(max(share * phi, -cone), cone)
    c, s = math.cos(phi), math.sin(phi)
    return np.array([c * n[0] - s * n[1], s * n[0] + c * n[1]])


@dataclass(frozen=True)
class ObservedPush:
    """One push as a robot sees it, in the object frame: contact point (m), unit push direction
    (the inward contact normal), and the measured CCW rotation of the object (deg)."""

    contact_m: tuple[float, float]
    direction: tuple[float, float]
    rotation_deg: float
    # `magnitude` only: the line of action the floor model expects for the push's force, if it
    # differs from `direction` (anisotropic floors, see `floor_force_direction`); None = along
    # `direction`. The paper's method ignores it.
    line_direction: tuple[float, float] | None = None


def estimate_com(
    region_m: np.ndarray,
    pushes: Iterable[ObservedPush],
    pixel_m: float,
    settings: EstimatorSettings | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Apply Algorithm 2 for each observed push; returns (final region, estimate).

    `region_m` is the initial CoM region: points inside the object's convex hull on a regular
    grid of spacing `pixel_m` (the pixel size that turns C_bw from pixels into metres).
    The estimate is the final region's centroid (`method="paper"`), or, with
    `method="magnitude"`, the mean of `magnitude_posterior` of all the pushes over the final
    region (sign-consistent; on a grid `SUBPIXEL` times finer).
    """
    settings = settings or EstimatorSettings()
    if settings.method not in ("paper", "magnitude"):  # motion: estimate_com_motion
        raise ValueError(
            f"estimate_com runs the methods paper and magnitude, not {settings.method!r}"
            + (
                " (use comexp.method.motion_estimator.estimate_com_motion)"
                if settings.method == "motion"
                else ""
            )
        )
    region = np.asarray(region_m, dtype=float)
    post = MagnitudePosterior(region, pixel_m, settings) if settings.method == "magnitude" else None
    for push in pushes:
        line = push.direction
        if post is not None and push.line_direction is not None:
            line = push.line_direction
        region, _ = update_region(
            region, push.contact_m, line, push.rotation_deg, settings, pixel_m
        )
        if post is not None:
            post.observe(push.contact_m, line, push.rotation_deg)
    if post is not None:
        return region, post.estimate_m
    return region, region.mean(axis=0)


class ComEstimator:
    """Algorithm 1 as a stateful object: propose a push, then report its measured rotation.

    Candidates are the sampled contour points with inward normals (object frame); with an
    outline and a pusher radius, contacts the pusher cannot reach are dropped once up front.
    With `method="magnitude"` the estimate is the posterior mean (see `estimate_com`), and
    Algorithm 1 scores push lines against the posterior's mean and main axis instead of the
    region's (validity is unchanged: the line cuts the region), so pushes aim where the CoM
    probably is, across the direction it is least certain in.
    """

    def __init__(
        self,
        region_m: np.ndarray,
        contacts_m: np.ndarray,
        normals: np.ndarray,
        pixel_m: float,
        settings: EstimatorSettings | None = None,
        outline_m: np.ndarray | None = None,
        pusher_radius_m: float | None = None,
    ) -> None:
        self.settings = settings or EstimatorSettings()
        if self.settings.method not in ("paper", "magnitude"):  # never run others as the paper
            raise ValueError(f"method {self.settings.method!r} is a plug-in: use make_estimator")
        self.region = np.asarray(region_m, dtype=float)
        self.pixel_m = float(pixel_m)
        self.posterior = (
            MagnitudePosterior(self.region, self.pixel_m, self.settings)
            if self.settings.method == "magnitude"
            else None
        )
        self.contacts, self.normals, self.allowed = push_candidates(
            contacts_m, normals, self.settings, outline_m, pusher_radius_m
        )

    @property
    def estimate_m(self) -> np.ndarray:
        if self.posterior is not None:
            return self.posterior.estimate_m
        return self.region.mean(axis=0)

    @property
    def region_px(self) -> int:
        return len(self.region)

    @property
    def region_m(self) -> np.ndarray:
        """The region's points (the episode stores their hull: `comexp-db show` draws it)."""
        return self.region

    def next_push(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(contact, direction) of the best valid push, or None when no push line cuts the
        region (or none is reachable)."""
        centre_axes = self.posterior.centre_axes() if self.posterior is not None else None
        j = choose_contact(
            self.region,
            self.contacts,
            self.normals,
            self.settings,
            self.pixel_m,
            self.allowed,
            centre_axes,
        )
        if j is None:
            return None
        return self.contacts[j].copy(), self.normals[j].copy()

    def observe(
        self,
        contact_m: np.ndarray,
        direction: np.ndarray,
        rotation_deg: float,
        line_direction: np.ndarray | None = None,
    ) -> str:
        """Algorithm 2 with the measured rotation; returns the decision (ccw, cw, band).
        `line_direction`: see `ObservedPush` (`magnitude` only; the paper ignores it)."""
        if self.posterior is not None and line_direction is not None:
            direction = line_direction
        self.region, decision = update_region(
            self.region, contact_m, direction, rotation_deg, self.settings, self.pixel_m
        )
        if self.posterior is not None:
            self.posterior.observe(contact_m, direction, rotation_deg)
        return decision


# --- the real-robot path: an outline and pushes observed in the world frame ------------------
# Frames and units, written once in docs/real_robot.md: world z up, yaw CCW about +z (rad);
# the object frame is fixed to the object, its origin at the outline's area centroid; metres.

# how far from the origin an outline's centroid may be for the outline to count as centred:
# far below a pixel (~2.7 mm), so the estimate does not depend on it
OUTLINE_CENTRED_TOL_M = 1e-4


def as_pose(pose: Pose2D | Sequence[float]) -> Pose2D:
    if isinstance(pose, Pose2D):
        return pose
    x_m, y_m, yaw_rad = (float(v) for v in pose)
    return Pose2D(x_m, y_m, yaw_rad)


def _rotate(v: Sequence[float] | np.ndarray, angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    x, y = float(v[0]), float(v[1])
    return np.array([c * x - s * y, s * x + c * y])


def as_xy(v: Sequence[float] | np.ndarray) -> tuple[float, float]:
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.shape != (2,) or not np.all(np.isfinite(a)):
        raise ValueError(f"expected a finite (x, y) pair, got {v!r}")
    return float(a[0]), float(a[1])


def region_from_outline(outline_m: np.ndarray, pixel_m: float) -> np.ndarray:
    """The paper's initial CoM region for a polygon outline: the points of a regular grid of
    spacing `pixel_m` (anchored at the frame's origin) inside the outline's convex hull, in the
    outline's frame, (n, 2) metres. Why the hull: the CoM of a non-convex object can lie
    outside its footprint (a U, a C); the paper starts from the hull's pixels."""

    outline = np.asarray(outline_m, dtype=float)
    hull = np.asarray(shapely.MultiPoint(outline).convex_hull.exterior.coords)[:-1]
    return hull_region(hull, float(pixel_m))


def outline_contacts(
    outline_m: np.ndarray,
    spacing_m: float = 0.005,
    corner_clearance_m: float = 0.005,
    corner_deg: float = 20.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Contact candidates of a polygon outline: (contacts_m (M, 2), normals (M, 2)), points
    every `spacing_m` of arc length (the first half a spacing after the first vertex) and
    their inward unit normals, i.e. the push directions, in the outline's frame.

    Points closer than `corner_clearance_m` to a corner (a vertex where the outline turns by
    more than `corner_deg`, convex or reflex) are left out: there the push direction is
    ill-defined. A polygon's normals and arc length are exact, so this samples its edges
    directly; `comexp.perception.sample_contacts` is the same rule for a contour traced in an
    image, whose normals are fitted. Either vertex order; repeated and collinear vertices are
    ignored. Feed them to `ComEstimator` (with `reachable_contacts`' pusher check).
    """
    if not (math.isfinite(spacing_m) and spacing_m > 0):
        raise ValueError(f"spacing_m must be > 0, got {spacing_m!r}")
    if not (math.isfinite(corner_clearance_m) and corner_clearance_m >= 0):
        raise ValueError(f"corner_clearance_m must be >= 0, got {corner_clearance_m!r}")
    p = simplify(ccw(outline_m))
    edges = np.roll(p, -1, axis=0) - p
    lengths = np.linalg.norm(edges, axis=1)
    t = edges / lengths[:, None]
    inward = np.stack([-t[:, 1], t[:, 0]], axis=1)  # left of a CCW traversal
    t_in = np.roll(t, 1, axis=0)  # the edge arriving at vertex i
    turn = np.degrees(np.abs(np.arctan2(cross2(t_in, t), (t_in * t).sum(axis=1))))
    corners = p[turn > corner_deg]
    starts = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    s = (np.arange(int(lengths.sum() // spacing_m)) + 0.5) * spacing_m
    edge = np.clip(np.searchsorted(starts, s, side="right") - 1, 0, len(p) - 1)
    pts = p[edge] + (s - starts[edge])[:, None] * t[edge]
    normals = inward[edge]
    if len(corners) and len(pts):
        d = np.linalg.norm(pts[:, None, :] - corners[None, :, :], axis=2).min(axis=1)
        keep = d >= corner_clearance_m
        pts, normals = pts[keep], normals[keep]
    return pts, normals


@dataclass(frozen=True)
class WorldPush:
    """One push as a robot observes it, in the world frame (docs/real_robot.md): the object's
    pose before the push (world x, y in m, yaw in rad, CCW about +z), the contact point (m)
    and the push direction (the inward contact normal; normalised here), and how much the
    object turned: either measured, `rotation_deg` (CCW positive), or from `pose_after`, the
    pose once it is at rest again (the yaw change, wrapped to (-180, 180] deg: a push that
    turns the object by more than half a turn needs `rotation_deg`). Exactly one of the two.

    Poses may be `Pose2D` or (x_m, y_m, yaw_rad) tuples; they are stored as `Pose2D`.
    `line_direction`: see `ObservedPush` (world frame here; `magnitude` only).
    """

    pose_before: Pose2D
    contact_m: tuple[float, float]
    direction: tuple[float, float]
    rotation_deg: float | None = None
    pose_after: Pose2D | None = None
    line_direction: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        set_ = object.__setattr__  # frozen: normalise the inputs once, here
        set_(self, "pose_before", as_pose(self.pose_before))
        set_(self, "contact_m", as_xy(self.contact_m))
        d = np.asarray(as_xy(self.direction))
        if np.linalg.norm(d) == 0:
            raise ValueError("direction must be a non-zero vector")
        set_(self, "direction", as_xy(d / np.linalg.norm(d)))
        if self.line_direction is not None:
            set_(self, "line_direction", as_xy(self.line_direction))
        if (self.rotation_deg is None) == (self.pose_after is None):
            raise ValueError("a WorldPush needs exactly one of rotation_deg and pose_after")
        if self.pose_after is not None:
            set_(self, "pose_after", as_pose(self.pose_after))
        elif not math.isfinite(self.rotation_deg):
            raise ValueError(f"rotation_deg must be finite, got {self.rotation_deg!r}")

    @property
    def turn_deg(self) -> float:
        """The object's CCW turn during the push, degrees: measured, or from the poses."""
        if self.rotation_deg is not None:
            return float(self.rotation_deg)
        assert self.pose_after is not None
        return math.degrees(wrap_angle(self.pose_after.yaw_rad - self.pose_before.yaw_rad))

    def in_object_frame(self) -> ObservedPush:
        """The same push in the object frame (the frame is fixed to the object, so the pose
        before the push maps it there, whatever the object did in earlier pushes)."""
        yaw = self.pose_before.yaw_rad
        contact = self.pose_before.to_object(np.asarray(self.contact_m))
        line = None if self.line_direction is None else as_xy(_rotate(self.line_direction, -yaw))
        return ObservedPush(
            contact_m=as_xy(contact),
            direction=as_xy(_rotate(self.direction, -yaw)),
            rotation_deg=self.turn_deg,
            line_direction=line,
        )


@dataclass(frozen=True, eq=False)
class WorldEstimate:
    """What `estimate_com_world` returns: the estimate in the object frame and in the world
    at the first pose, the final region (object frame), and the pushes as the object-frame
    estimator saw them."""

    com_object_m: np.ndarray  # (2,), object frame
    com_world_m: np.ndarray  # (2,), world frame, the object at `first_pose`
    first_pose: Pose2D
    region_m: np.ndarray  # (n, 2), object frame
    pushes: tuple[ObservedPush, ...]


def estimate_com_world(
    outline_m: np.ndarray,
    pushes: Iterable[WorldPush],
    pixel_m: float,
    settings: EstimatorSettings | None = None,
    max_contact_offset_m: float | None = 0.01,
) -> WorldEstimate:
    """`estimate_com` for pushes observed in the world frame.

    `outline_m` is the footprint polygon in the object frame, whose origin is the outline's
    area centroid (ValueError if it is off by more than `OUTLINE_CENTRED_TOL_M`: the poses
    would then be of another point); the region is `region_from_outline(outline_m, pixel_m)`.
    Each push is mapped into the object frame with its own pose before the push
    (`WorldPush.in_object_frame`), then Algorithm 2 runs as in `estimate_com`.

    `max_contact_offset_m`: a contact that lands farther than this from the outline in the
    object frame is refused (ValueError naming the push): almost always a frame mistake (yaw in
    degrees, clockwise, or a y-down world). None skips the check.
    """
    outline = np.asarray(outline_m, dtype=float)
    c = centroid(outline)
    if np.hypot(*c) > OUTLINE_CENTRED_TOL_M:
        raise ValueError(
            f"outline_m: its centroid is at ({c[0]:.4f}, {c[1]:.4f}) m, not at the object frame's "
            "origin: pass outline_m - centroid, and poses of the centroid "
            "(Pose2D.to_world(centroid), same yaw)"
        )
    world = list(pushes)
    if not world:
        raise ValueError("estimate_com_world needs at least one push (its pose fixes the frame)")
    local = tuple(w.in_object_frame() for w in world)
    if max_contact_offset_m is not None:
        ring = shapely.LinearRing(outline)
        for k, push in enumerate(local):
            off = ring.distance(shapely.Point(push.contact_m))
            if off > max_contact_offset_m:
                raise ValueError(
                    f"push {k}: its contact is {off * 100:.1f} cm from the outline in the object "
                    "frame: check the frames (pose yaw in rad, CCW about +z; world z up)"
                )
    region0 = region_from_outline(outline, pixel_m)
    region, com = estimate_com(region0, local, pixel_m, settings)
    first = world[0].pose_before
    return WorldEstimate(
        com_object_m=com,
        com_world_m=first.to_world(com),
        first_pose=first,
        region_m=region,
        pushes=local,
    )


def is_plugin(method: str) -> bool:
    """`method` names a plug-in class (`module:Class` or `module.Class`), not a built-in."""
    return method not in METHODS and (":" in method or "." in method)
