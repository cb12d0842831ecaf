"""`estimator.method=motion`: a CoM estimator that uses what the camera saw during each push,
knowing nothing of the floor's friction or axes, the pusher's friction or Izz.

A posterior over candidate CoMs G (the hull's points on a grid `SUBPIXEL` times finer than a
pixel; no hard cut ever removes one) from, per push, in the object frame at its start:

- the impulse relation at the first tracked frame after the impact: the impact's impulse J at
  the contact P moves the CoM by d_G and turns the object by theta with theta rho^2 =
  (P - G) x d_G (rho^2 = Izz / m, profiled per episode), before the floor's friction acts;
- the impulse's direction: d_G within the pusher's friction cone about N (mu_p profiled);
- the net turn's sign, soft (a wrong sign costs probability, not the CoM);
- the net turns' sizes with `magnitude`'s one-gain model, weighed against "they say nothing"
  by their evidence (they fit on isotropic floors, mostly not on anisotropic ones).

Frames and signs as in `comexp.method.estimator` (metres, y up, CCW positive). In episodes
`run_episode` passes each push's tracked poses (`PushPath`) to `observe_path`; a robot uses
`estimate_com_motion` with `MotionPush`es in the world frame. docs/method.md, "Beyond the
paper: `estimator.method=motion`", has the model, its assumptions and failure modes.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, replace

import numpy as np

from comexp.method.estimator import (
    OUTLINE_CENTRED_TOL_M,
    SATURATION_BETAS,
    SUBPIXEL,
    EstimatorSettings,
    ObservedPush,
    WorldEstimate,
    as_pose,
    as_xy,
    choose_contact,
    floor_force_direction,
    push_candidates,
    refine_grid,
    region_from_outline,
    weighted_pca,
)
from comexp.method.frames import Pose2D
from comexp.method.geometry import centroid


@dataclass(frozen=True, eq=False)
class PushPath:
    """What a camera saw of one push, in the world frame (z up, yaw CCW about +z, metres,
    radians, seconds): the object frame's pose before the push, its poses at the tracked frames
    (`t_s` since the push command started), its pose at rest after the push, and the command:
    when the pusher reaches the contact (`t_contact_s`) and its speed."""

    pose_before: Pose2D
    t_s: tuple[float, ...]
    poses: tuple[Pose2D, ...]
    pose_after: Pose2D
    t_contact_s: float
    speed_m_s: float
    rotation_deg: float | None = None  # the unwrapped net turn, if the tracker gives it
    extra: dict = field(default_factory=dict)
    t_end_s: float | None = None  # when the pusher stopped (the command); None: unknown

    def slide(self, min_len_m: float = 0.003) -> tuple[float, float, float, float] | None:
        """The free slide after the pusher stopped, world frame: (direction of the object's
        velocity when the pusher stopped, direction of its displacement from then to rest, that
        displacement's length, how much the object turned meanwhile (rad, unsigned)), or None.
        The velocity is the origin's over the last two frames up to the stop; the end is the
        pose at rest, or the last frame if the object was put back before it was imaged
        (`extra["recentred"]`, the episode's re-centring). None without `t_end_s`, with fewer
        than two frames by then, or a slide shorter than `min_len_m`."""
        if self.t_end_s is None:
            return None
        pts = [
            (t, p) for t, p in zip(self.t_s, self.poses, strict=True) if t <= self.t_end_s + 0.005
        ]
        if len(pts) < 2:
            return None
        (t1, p1), (t2, p2) = pts[-2], pts[-1]
        v = np.array([p2.x_m - p1.x_m, p2.y_m - p1.y_m]) / max(t2 - t1, 1e-9)
        end = self.pose_after
        if self.extra.get("recentred"):  # put back before the image at rest: the last frame
            if self.t_s[-1] <= t2:
                return None  # no frame of the slide itself
            end = self.poses[-1]
        D = np.array([end.x_m - p2.x_m, end.y_m - p2.y_m])
        length = float(np.hypot(*D))
        if length < min_len_m or np.hypot(*v) < 1e-3:
            return None
        turn = abs((end.yaw_rad - p2.yaw_rad + math.pi) % (2 * math.pi) - math.pi)
        return math.atan2(v[1], v[0]), math.atan2(D[1], D[0]), length, turn

    def relative(self) -> np.ndarray:
        """(k + 2, 4): t, x, y, yaw of the object frame relative to its pose before the push
        (in that pose's frame), for the start (t = 0), every frame and the rest pose (t = inf).
        Yaws are unwrapped along the path."""
        b = self.pose_before
        rows = [(0.0, 0.0, 0.0, 0.0)]
        yaw_prev = 0.0
        for t, p in [*zip(self.t_s, self.poses, strict=True), (math.inf, self.pose_after)]:
            xy = b.to_object(np.array([p.x_m, p.y_m]))
            d = p.yaw_rad - b.yaw_rad
            d = yaw_prev + (d - yaw_prev + math.pi) % (2 * math.pi) - math.pi
            yaw_prev = d
            rows.append((t, float(xy[0]), float(xy[1]), d))
        out = np.array(rows)
        if self.rotation_deg is not None:
            out[-1, 3] = math.radians(self.rotation_deg)
        return out


# ----------------------------------------------------------------------------------------------
# the model


G_ACC = 9.81  # m/s^2

# The model's revision: bumped whenever the estimates change (pinned in motion episodes' keys,
# `EstimatorSettings.motion_version`). motion-2: the floor fitted per episode from the slides;
# motion-3: the early frames' term tempered (`MotionSettings.early_weight`), rel_model 0.15.
MOTION_VERSION = "motion-3"


@dataclass(frozen=True)
class MotionSettings:
    """Knobs of the motion estimator (docs/method.md, "`estimator.method=motion`")."""

    early_min_s: float = 0.003  # the first frame at least this long after the impact
    early_max_s: float = 0.060  # ... and at most this long (else the push has no early frame)
    # ... and only while the floor's friction (at most impulse_mu_max g) can have taken at most
    # impulse_share of the impact's speed: mu g dt <= share v0 (40 cm/s: 20 ms; 4 cm/s: 2 ms,
    # i.e. no frame: quasi-static pushes are not impulsive). Unknown speed: no limit.
    impulse_mu_max: float = 1.0
    impulse_share: float = 0.5
    sigma_turn_deg: float = 0.3  # vision noise of a tracked frame's yaw
    sigma_move_m: float = 0.0005  # vision noise of a tracked frame's position
    rel_model: float = 0.15  # relative model error of the impulse relation
    # the early frames' log-likelihood counts at this weight: their model errors are shared by
    # an episode's pushes (the same floor acts within each first frame, the same Izz and
    # tracker), so five pushes are not five independent measurements
    early_weight: float = 0.5
    rel_model_rate: float = 0.0  # ... growing by this much per second after the impact
    max_frames: int = 1
    sign_eps: float = 0.15  # chance that a net turn has the wrong sign (floor, vision)
    sign_scale_m: float = 0.002  # lever arm over which a net turn's sign becomes certain
    sign_deg: float = 1.0  # net turns at most this large say nothing about the sign
    use_early: bool = True
    use_net_size: bool = True
    net_noise_deg: float = 1.0
    net_rel_noise: float = 0.3
    net_outlier: float = 0.05
    net_prior: float = 0.5
    net_outlier_width_deg: float = 60.0
    use_direction: bool = True
    direction_frames: int = 1
    # the pusher's friction mu_p, profiled: the impulse lies within atan(mu_p) of the push
    mu_p_grid: tuple[float, ...] = (0.1, 0.25, 0.5, 1.0)
    use_net: bool = True
    # rho^2 = Izz / m about the CoM, profiled on this grid times the hull's own rho0^2
    rho2_scales: tuple[float, ...] = (0.3, 0.5, 0.7, 1.0, 1.4, 2.0, 3.0, 4.5, 7.0, 10.0, 15.0)
    # the floor, fitted per episode (`floor_hypotheses`): isotropic, or anisotropic with the
    # low-friction axis at one of floor_angles directions in [0, pi) and mu_high / mu_low one of
    # floor_ratios; weighed by the slides' directions (floor_sigma_deg of model error), each
    # turns the net turns' lines of action (`comexp.method.estimator.floor_force_direction`,
    # floor_share of the friction's turn, within the pusher's cone)
    use_floor: bool = True
    floor_angles: int = 12
    floor_ratios: tuple[float, ...] = (3.0, 10.0)
    floor_iso_prior: float = 0.5
    floor_sigma_deg: float = 8.0
    floor_turn_sigma: float = 0.5  # ... plus this times the slide's own turn (rad)
    floor_slide_outlier: float = 0.1  # chance that a slide's direction says nothing
    floor_share: float = 0.5
    floor_prune: float = 0.05  # hypotheses below this share of the best weight are dropped
    floor_sign_eps: float = 0.05  # sign_eps about the floor's lines of action
    floor_min_slide_m: float = 0.003
    # ... and only after pushes fast enough for such a slide on a floor this slippery
    # (v^2 / (2 g mu) >= floor_min_slide_m: 7.7 cm/s; at 4 cm/s no slide is used)
    floor_mu_min: float = 0.1
    # under an anisotropic floor hypothesis a net turn's gain scales with the floor's friction
    # along the push, |A N| ** floor_gain_power (relative to the episode's geometric mean)
    floor_gain_power: float = 1.0
    # Algorithm 1 scores each candidate push by its expected line of action under the best
    # floor hypothesis and pusher friction so far (`MotionEstimator.next_push`), not by N
    floor_choice: bool = True
    # told, not fitted (`KnownNuisances`): the floor as (world angle of its low-friction axis,
    # mu_high / mu_low; 1: isotropic), which replaces the slides' hypotheses, and rho^2 = Izz / m
    # about the CoM (m^2), which replaces the rho2_scales grid
    known_floor: tuple[float, float] | None = None
    known_rho2_m2: float | None = None


@dataclass(frozen=True)
class KnownNuisances:
    """What `motion` and `fit` otherwise marginalise, told: the floor's friction along the
    world's x and y (the study's floors have their axes there), the pusher's friction and
    rho^2 = Izz / m about the CoM (m^2). An episode with `nuisance_source=oracle` passes its
    true ones, which measures the models' error when only the CoM is unknown."""

    mu_floor_xy: tuple[float, float]
    mu_pusher: float
    rho2_m2: float

    def __post_init__(self) -> None:
        mx, my = self.mu_floor_xy
        if not (mx > 0 and my > 0 and self.mu_pusher >= 0 and self.rho2_m2 > 0):
            raise ValueError(f"known nuisances must be positive, got {self}")

    @property
    def floor(self) -> tuple[float, float]:
        """(world angle of the low-friction axis, mu_high / mu_low), as the models' floor
        hypotheses are written; an isotropic floor is (0, 1)."""
        mx, my = self.mu_floor_xy
        if mx == my:
            return 0.0, 1.0
        return (0.0, my / mx) if mx < my else (math.pi / 2, mx / my)

    def settings(self, ms: MotionSettings) -> MotionSettings:
        """`ms` with these values in place of their hypotheses."""
        return replace(
            ms,
            mu_p_grid=(float(self.mu_pusher),),
            known_floor=self.floor,
            known_rho2_m2=float(self.rho2_m2),
        )


@dataclass(frozen=True)
class PushFeatures:
    """What the likelihood uses of one push, in the object frame at the push's start."""

    P: np.ndarray  # contact (2,)
    N: np.ndarray  # unit push direction (2,)
    turn_net_rad: float
    # (time since the impact, yaw, origin displacement (2,)) of the frames used, earliest first
    early: tuple[tuple[float, float, np.ndarray], ...]
    yaw_rad: float = 0.0  # the object frame's world yaw at the push's start
    slide: tuple[float, float, float, float] | None = None  # `PushPath.slide`, world frame


def push_features(path: PushPath | None, P, N, rotation_deg: float, ms: MotionSettings):
    P = np.asarray(P, dtype=float)
    N = np.asarray(N, dtype=float)
    N = N / np.linalg.norm(N)
    early = []
    if path is not None and len(path.t_s):
        rel = path.relative()
        for t, x, y, yaw in rel[1:-1]:
            dt = t - path.t_contact_s
            if dt < ms.early_min_s:
                continue
            if dt > ms.early_max_s or len(early) >= ms.max_frames:
                break
            v0 = path.speed_m_s
            if math.isfinite(v0) and ms.impulse_mu_max * G_ACC * dt > ms.impulse_share * v0:
                break
            early.append((float(dt), float(yaw), np.array([x, y])))
    yaw0 = 0.0 if path is None else path.pose_before.yaw_rad
    slide = None if path is None else path.slide(ms.floor_min_slide_m)
    v0 = float("nan") if path is None else path.speed_m_s
    if math.isfinite(v0) and v0 * v0 / (2 * G_ACC * ms.floor_mu_min) < ms.floor_min_slide_m:
        slide = None  # too slow for a free slide of that length even on the slipperiest floor
    return PushFeatures(P, N, math.radians(rotation_deg), tuple(early), yaw0, slide)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def early_loglik(
    G: np.ndarray, feats: list[PushFeatures], rho2: np.ndarray, ms: MotionSettings
) -> np.ndarray:
    """log-likelihood (n, len(rho2)) of the early frames under the impulse relation.

    An impulse J at P (the pusher's impact; the floor's friction is finite, so it plays no part
    within it) gives the CoM the velocity J / m and the object the turn rate (P - G) x J / Izz:
    over the first instants the turn theta and the CoM's displacement d_G obey
    theta rho^2 = (P - G) x d_G, rho^2 = Izz / m, whatever the pusher's friction (it only tilts
    J) and the floor's. d_G follows from the tracked origin's displacement d_O and the turn:
    d_G = d_O + (R(theta) - I) G. Tempered by `early_weight` (errors shared across pushes).
    """
    out = np.zeros((len(G), len(rho2)))
    s_th = math.radians(ms.sigma_turn_deg)
    for f in feats:
        for dt, th, dO in f.early:
            rel = ms.rel_model + ms.rel_model_rate * dt
            c, s = math.cos(th), math.sin(th)
            dG = dO[None, :] + np.stack(
                [(c - 1) * G[:, 0] - s * G[:, 1], s * G[:, 0] + (c - 1) * G[:, 1]], 1
            )
            r = f.P[None, :] - G
            m = _cross(r, dG)  # (n,)
            e = th * rho2[None, :] - m[:, None]
            var = (
                (s_th * rho2[None, :]) ** 2
                + (ms.sigma_move_m * np.linalg.norm(r, axis=1))[:, None] ** 2
                + (rel * m[:, None]) ** 2
            )
            out += -0.5 * e * e / var - 0.5 * np.log(var)
    return ms.early_weight * out


def direction_loglik(G: np.ndarray, feats: list[PushFeatures], mu: np.ndarray, ms: MotionSettings):
    """log-likelihood (n, len(mu)) of the directions in which the early frames moved the CoM:
    the impulse, hence d_G, lies within the pusher's friction cone about N, |tan psi| <= mu_p
    (uniform inside, the vision noise smearing its edges)."""
    from scipy.special import ndtr

    out = np.zeros((len(G), len(mu)))
    for f in feats:
        for _dt, th, dO in f.early[: ms.direction_frames]:
            c, s = math.cos(th), math.sin(th)
            dG = dO[None, :] + np.stack(
                [(c - 1) * G[:, 0] - s * G[:, 1], s * G[:, 0] + (c - 1) * G[:, 1]], 1
            )
            a = dG @ f.N
            b = _cross(f.N[None, :], dG)  # tangential component (left of N)
            sig = ms.sigma_move_m
            # in displacement units: b uniform in [-mu a, mu a] with noise sig; a must be > 0
            hi = (mu[None, :] * np.abs(a)[:, None] - b[:, None]) / sig
            lo = (-mu[None, :] * np.abs(a)[:, None] - b[:, None]) / sig
            width = 2 * mu[None, :] * np.abs(a)[:, None] + 1e-12
            p = (ndtr(hi) - ndtr(lo)) / np.maximum(width, sig)
            p = p * ndtr(a / sig)[:, None]
            out += np.log(p + 1e-12)
    return out


def sign_loglik(G: np.ndarray, feats: list[PushFeatures], ms: MotionSettings) -> np.ndarray:
    """log-likelihood (n,) of the net turns' signs: a soft version of Algorithm 2's cut, with a
    chance `sign_eps` that the sign is wrong (the floor turned it, or vision)."""
    from scipy.special import ndtr

    out = np.zeros(len(G))
    for f in feats:
        if abs(math.degrees(f.turn_net_rad)) <= ms.sign_deg:
            continue
        lev = _cross(f.P[None, :] - G, f.N[None, :])
        p = ms.sign_eps + (1 - 2 * ms.sign_eps) * ndtr(
            np.sign(f.turn_net_rad) * lev / ms.sign_scale_m
        )
        out += np.log(p)
    return out


def net_loglik(
    G: np.ndarray,
    footprint: np.ndarray,
    feats: list[PushFeatures],
    ms: MotionSettings,
    rho2: np.ndarray | None = None,
):
    """log-likelihood (n,) of the net turns' sizes: `magnitude`'s model rot_j = k f(l_j) (one
    gain per episode, saturation profiled), with a chance `net_outlier` that a turn is
    unrelated to its lever (the floor turned it), so that no push can rule a CoM out."""
    rot = np.array([math.degrees(f.turn_net_rad) for f in feats])
    if len(rot) < 2:
        return np.zeros(len(G))
    P = np.array([f.P for f in feats])
    N = np.array([f.N for f in feats])
    if rho2 is None:
        rho2 = _rho2_of(np.asarray(footprint, dtype=float), G)
    # (pushes, candidates): the pushes' few rows summed by rows, the candidates' many by BLAS
    lev = (P[:, None, 0] - G[None, :, 0]) * N[:, None, 1] - (P[:, None, 1] - G[None, :, 1]) * N[
        :, None, 0
    ]
    var = ms.net_noise_deg**2 + (ms.net_rel_noise * rot) ** 2
    w = 1.0 / var
    amp = ((1 - ms.net_outlier) / np.sqrt(2 * np.pi * var))[:, None]
    floor_p = ms.net_outlier / ms.net_outlier_width_deg
    best = np.full(len(G), -np.inf)
    for beta in SATURATION_BETAS:
        f = lev if math.isinf(beta) else lev / (1.0 + lev * lev / (beta * rho2[None, :]))
        k = ((w * rot) @ f) / np.maximum(w @ (f * f), 1e-300)
        k = np.maximum(k, 0.0)
        r = rot[:, None] - k[None, :] * f
        inlier = amp * np.exp(-0.5 * r * r * w[:, None])
        best = np.maximum(best, np.log(inlier + floor_p).sum(axis=0))
    return best


def _rho2_of(foot: np.ndarray, G: np.ndarray) -> np.ndarray:
    """rho^2 about each candidate G of a uniform plate with the footprint's points."""
    c = foot.mean(axis=0)
    return ((foot - c) ** 2).sum(axis=1).mean() + ((G - c) ** 2).sum(axis=1)


@functools.lru_cache(maxsize=8)
def slide_turn_table(ratios: tuple[float, ...], n_alpha: int = 360) -> np.ndarray:
    """(len(ratios), n_alpha): the angle from a translating body's initial velocity to its
    displacement when it has stopped, on a floor with friction A = diag(1, ratio) along its
    axes (elliptic maximum dissipation: deceleration along -A^2 u / |A u|), the velocity at
    angle 2 pi i / n_alpha from the low-friction axis. Independent of the friction's scale
    and the speed (they scale the path, not its shape)."""
    al = np.arange(n_alpha) * 2 * math.pi / n_alpha
    out = np.zeros((len(ratios), n_alpha))
    for i, r in enumerate(ratios):
        v = np.stack([np.cos(al), np.sin(al)], 1)
        x = np.zeros_like(v)
        a1, a2 = np.array([1.0, r]), np.array([1.0, r * r])
        dt = 0.004 / max(r, 1.0)
        for _ in range(20000):
            sp = np.linalg.norm(v, axis=1)
            if sp.max() < 1e-9:
                break
            u = v / np.maximum(sp, 1e-12)[:, None]
            acc = -(a2 * u) / np.maximum(np.linalg.norm(a1 * u, axis=1), 1e-12)[:, None]
            nv = v + acc * dt
            nv[(nv * v).sum(axis=1) <= 0] = 0.0  # a slide stops, it does not reverse
            x += 0.5 * (v + nv) * dt
            v = nv
        out[i] = (np.arctan2(x[:, 1], x[:, 0]) - al + math.pi) % (2 * math.pi) - math.pi
    return out


def floor_loglik(feats: list[PushFeatures], ms: MotionSettings) -> np.ndarray:
    """log-likelihood (floor_angles, len(floor_ratios)) of the anisotropic floor hypotheses
    (low-friction axis at angle pi i / floor_angles, world frame) from the slides' directions,
    relative to the isotropic floor (0): each slide's turn from its initial velocity to its
    displacement against `slide_turn_table`'s, Gaussian with floor_sigma_deg plus the vision
    noise over the slide's length. A body that turns while it slides breaks the table's
    assumption (translation): the sigma is that model error."""
    ratios = tuple(ms.floor_ratios)
    tab = slide_turn_table((1.0, *ratios))
    n_al = tab.shape[1]
    phis = np.arange(ms.floor_angles) * math.pi / ms.floor_angles
    ll = np.zeros((len(phis), len(ratios)))
    for f in feats:
        if f.slide is None:
            continue
        av, a_d, length, turn = f.slide
        # a body that turns as it slides curves its path: its turn adds to the model error
        sig = (
            math.radians(ms.floor_sigma_deg) + ms.sigma_move_m / length + ms.floor_turn_sigma * turn
        )
        dm = (a_d - av + math.pi) % (2 * math.pi) - math.pi
        k = np.round(((av - phis) % (2 * math.pi)) / (2 * math.pi) * n_al).astype(int) % n_al
        d = (dm - tab[:, k].T + math.pi) % (2 * math.pi) - math.pi  # (phis, 1 + ratios)
        # with a chance floor_slide_outlier that a slide says nothing (uniform direction)
        e = np.log(
            (1 - ms.floor_slide_outlier)
            * np.exp(-0.5 * (d / sig) ** 2)
            / (math.sqrt(2 * math.pi) * sig)
            + ms.floor_slide_outlier / (2 * math.pi)
        )
        ll += e[:, 1:] - e[:, :1]
    return ll


def floor_hypotheses(feats: list[PushFeatures], ms: MotionSettings):
    """[(angle, ratio, log weight)]: the isotropic floor (ratio 1) and the anisotropic ones
    whose weight is at least floor_prune of the best, weights normalised over those kept; the
    known floor alone when `ms.known_floor` is set."""
    from scipy.special import logsumexp

    if ms.known_floor is not None:
        angle, ratio = ms.known_floor
        return [(float(angle), float(ratio), 0.0)]
    ll = floor_loglik(feats, ms)
    n_aniso = ll.size
    lp = math.log((1 - ms.floor_iso_prior) / n_aniso) if n_aniso else -math.inf
    hyps = [(0.0, 1.0, math.log(ms.floor_iso_prior))]
    for i in range(ll.shape[0]):
        for j, r in enumerate(ms.floor_ratios):
            hyps.append((math.pi * i / ms.floor_angles, float(r), lp + float(ll[i, j])))
    w = np.array([h[2] for h in hyps])
    keep = w >= w.max() + math.log(ms.floor_prune)
    kept = [h for h, k in zip(hyps, keep, strict=True) if k]
    norm = logsumexp([h[2] for h in kept])
    return [(a, r, lw - norm) for a, r, lw in kept]


def floor_lines(feats: list[PushFeatures], angle: float, ratio: float, mu_p: float, share: float):
    """Each push's line of action (object frame, unit) on a floor with its low-friction axis at
    world angle `angle` and mu_high / mu_low = `ratio`, pusher friction `mu_p`."""
    if ratio == 1.0:
        return [f.N for f in feats]
    return [floor_force_direction(f.N, f.yaw_rad - angle, 1.0, ratio, mu_p, share) for f in feats]


def floor_gains(feats: list[PushFeatures], angle: float, ratio: float, power: float) -> np.ndarray:
    """Each push's relative gain under a floor hypothesis: the floor's friction along the push,
    |A N| with A = diag(1, ratio) along the floor's axes (low-friction axis at world `angle`),
    to the power `power`, over the pushes' geometric mean: a push along the slippery axis turns
    the object less (the friction's torque drives the turn)."""
    a = np.array([f.yaw_rad - angle + math.atan2(f.N[1], f.N[0]) for f in feats])
    g = np.hypot(np.cos(a), ratio * np.sin(a)) ** power
    return g / np.exp(np.log(g).mean())


def floor_mixture_loglik(
    G: np.ndarray,
    footprint: np.ndarray,
    feats: list[PushFeatures],
    direction: np.ndarray,
    ms: MotionSettings,
    base: np.ndarray | None = None,
    cache: dict | None = None,
) -> np.ndarray:
    """log-likelihood (n,) of the net turns (signs and sizes) and the impulses' directions, the
    floor unknown: a mixture over `floor_hypotheses` (weighed by the slides), each with the
    pusher's friction mu_p profiled (the best per G, shared with the direction term, which
    `direction` holds per mu_p); under a floor the net turns' signs follow the lever arm about
    its lines of action (chance floor_sign_eps of the wrong one) and their sizes `magnitude`'s
    one gain about those lines, weighed against "they say nothing" as without a floor model.
    Only the values of mu_p whose evidence (the direction term over the candidates, with
    `base`, the other terms, per G) is at least floor_prune of the best's are tried."""
    from scipy.special import logsumexp

    b = np.zeros(len(G)) if base is None else base
    rho2 = _rho2_of(np.asarray(footprint, dtype=float), G)
    ev = logsumexp(b[:, None] + direction, axis=0)
    mu_keep = [i for i in range(len(ms.mu_p_grid)) if ev[i] >= ev.max() + math.log(ms.floor_prune)]
    terms = []
    h0 = len(feats) * math.log(1.0 / ms.net_outlier_width_deg) if len(feats) >= 2 else 0.0
    sms = replace(ms, sign_eps=ms.floor_sign_eps)
    for angle, ratio, lw in floor_hypotheses(feats, ms):
        per_mu = []
        for m_i in mu_keep:
            mu_p = ms.mu_p_grid[m_i]
            lines = floor_lines(feats, angle, ratio, mu_p, ms.floor_share)
            lf = [replace(f, N=np.asarray(n)) for f, n in zip(feats, lines, strict=True)]
            t = direction[:, m_i]
            if ms.use_net:
                # each push's sign term under this line, kept across pushes in `cache`
                # (keyed by the push's index and its line: the same values)
                for i, f in enumerate(lf):
                    key = (i, float(f.N[0]), float(f.N[1]))
                    term = None if cache is None else cache.get(key)
                    if term is None:
                        term = sign_loglik(G, [f], sms)
                        if cache is not None:
                            cache[key] = term
                    t = t + term
            if ms.use_net_size:
                if ratio != 1.0 and ms.floor_gain_power != 0.0 and feats:
                    gains = floor_gains(feats, angle, ratio, ms.floor_gain_power)
                    lf = [
                        replace(f, turn_net_rad=f.turn_net_rad / g)
                        for f, g in zip(lf, gains, strict=True)
                    ]
                h1 = net_loglik(G, footprint, lf, ms, rho2)
                t = t + np.logaddexp(math.log(ms.net_prior) + h1, math.log(1 - ms.net_prior) + h0)
            if ratio == 1.0:  # the lines do not depend on mu_p: one evaluation serves all
                per_mu = [t - direction[:, m_i] + direction[:, mu_keep].max(axis=1)]
                break
            per_mu.append(t)
        terms.append(lw + np.max(per_mu, axis=0))
    return logsumexp(np.array(terms), axis=0)


def _rho2_grid(foot: np.ndarray, ms: MotionSettings) -> np.ndarray:
    if ms.known_rho2_m2 is not None:
        return np.array([ms.known_rho2_m2])
    c = foot.mean(axis=0)
    return ((foot - c) ** 2).sum(axis=1).mean() * np.asarray(ms.rho2_scales)


def push_logliks(
    G: np.ndarray, footprint: np.ndarray, feats: list[PushFeatures], ms: MotionSettings
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The per-push terms summed over `feats`, before profiling: early frames (n, rho^2 grid),
    impulse directions (n, mu_p grid), net-turn signs (n,). They add up push by push, so an
    estimator keeps their running sums (`MotionEstimator`) and `motion_posterior` combines
    them."""
    foot = np.asarray(footprint, dtype=float)
    rho2 = _rho2_grid(foot, ms)
    mu = np.asarray(ms.mu_p_grid)
    early = np.zeros((len(G), len(rho2)))
    direction = np.zeros((len(G), len(mu)))
    sign = np.zeros(len(G))
    if ms.use_early:
        early = early_loglik(G, feats, rho2, ms)
        if ms.use_direction:
            direction = direction_loglik(G, feats, mu, ms)
    if ms.use_net:
        sign = sign_loglik(G, feats, ms)
    return early, direction, sign


def motion_posterior(
    G: np.ndarray,
    footprint: np.ndarray,
    feats: list[PushFeatures],
    ms: MotionSettings,
    sums: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    cache: dict | None = None,
) -> np.ndarray:
    """Weights (n,) of candidate CoMs G: exp of the summed log-likelihoods, rho^2 and mu_p
    profiled (the best per G, each shared by the episode's pushes). `sums`: `push_logliks`
    of all of `feats`, if already at hand; `cache`: a dict kept by the caller between calls
    on the same G and growing `feats` (the floor mixture's per-push sign terms)."""
    foot = np.asarray(footprint, dtype=float)
    early, direction, sign = sums if sums is not None else push_logliks(G, foot, feats, ms)
    # the floor model needs a slide to go on (none at 4 cm/s: slides under floor_min_slide_m)
    # or a known floor; without either the anisotropic hypotheses only add freedom, and
    # motion-1's terms are used
    if ms.use_floor and (ms.known_floor is not None or any(f.slide is not None for f in feats)):
        e = early.max(axis=1)
        ll = e + floor_mixture_loglik(G, foot, feats, direction, ms, base=e, cache=cache)
        p = np.exp(ll - ll.max())
        return p / p.sum()
    ll = early.max(axis=1) + direction.max(axis=1) + sign
    if ms.use_net_size:
        # two hypotheses about the net turns' sizes, weighed by their evidence: they follow
        # one gain (isotropic floors), or they say nothing (each uniform over the width)
        h1 = net_loglik(G, foot, feats, ms)
        h0 = len(feats) * math.log(1.0 / ms.net_outlier_width_deg) if len(feats) >= 2 else 0.0
        ll = ll + np.logaddexp(math.log(ms.net_prior) + h1, math.log(1 - ms.net_prior) + h0)
    p = np.exp(ll - ll.max())
    return p / p.sum()


# ----------------------------------------------------------------------------------------------
# the estimator (the `Estimator` protocol of comexp.method.estimator)

CREDIBLE = 0.95  # the posterior mass whose points count as the region (pushes must cut it)
MAX_REGION_POINTS = 1500  # Algorithm 1's validity test runs on at most this many of them


def credible_set(weights: np.ndarray, mass: float = CREDIBLE) -> np.ndarray:
    """Indices of the fewest points holding `mass` of the weights (highest first)."""
    order = np.argsort(weights)[::-1]
    k = int(np.searchsorted(np.cumsum(weights[order]), mass * weights.sum())) + 1
    return order[: max(1, min(k, len(order)))]


class MotionEstimator:
    """`estimator.method=motion`: a posterior over candidate CoMs (the hull's points on a grid
    `SUBPIXEL` times finer than a pixel) from the path of every push (`observe_path`, then
    `observe`), no hard cuts. Algorithm 1 chooses the pushes against the posterior: a push is
    valid when its line cuts the 95% credible set, scored against the posterior's mean and
    main axis. Without a path (oracle rotations, no frames) a push adds its net turn's soft
    sign only. Frames and units are `ComEstimator`'s."""

    def __init__(
        self,
        region_m: np.ndarray,
        contacts_m: np.ndarray,
        normals: np.ndarray,
        pixel_m: float,
        settings: EstimatorSettings | None = None,
        outline_m: np.ndarray | None = None,
        pusher_radius_m: float | None = None,
        motion: MotionSettings | None = None,
        nuisances: KnownNuisances | None = None,
    ) -> None:
        self.settings = settings or EstimatorSettings(method="motion")
        self.motion = motion or MotionSettings()
        if nuisances is not None:
            self.motion = nuisances.settings(self.motion)
        self.pixel_m = float(pixel_m)
        self.footprint = np.asarray(region_m, dtype=float).reshape(-1, 2)
        self.points = refine_grid(self.footprint, self.pixel_m)
        self.weights = np.full(len(self.points), 1.0 / max(len(self.points), 1))
        self.contacts, self.normals, self.allowed = push_candidates(
            contacts_m, normals, self.settings, outline_m, pusher_radius_m
        )
        self.features: list[PushFeatures] = []
        self._path: PushPath | None = None
        self._sums: tuple[np.ndarray, ...] | None = None  # running `push_logliks`
        self._yaw_now: float | None = None  # the object frame's world yaw after the last push
        self._cache: dict = {}  # `motion_posterior`'s per-push terms

    @property
    def estimate_m(self) -> np.ndarray:
        return self.weights @ self.points

    @property
    def region_px(self) -> int:
        """The 95% credible set's size in pixels (fine points / SUBPIXEL^2)."""
        return max(1, round(len(credible_set(self.weights)) / SUBPIXEL**2))

    @property
    def region_m(self) -> np.ndarray:
        """The 95% credible set's points (the episode stores their hull)."""
        return self.points[credible_set(self.weights)]

    def region(self) -> np.ndarray:
        """The 95% credible set's points (at most `MAX_REGION_POINTS`, evenly thinned)."""
        idx = np.sort(credible_set(self.weights))
        step = max(1, math.ceil(len(idx) / MAX_REGION_POINTS))
        return self.points[idx[::step]]

    def expected_lines(self) -> np.ndarray:
        """The candidate pushes' expected lines of action (unit, object frame): their normals
        turned by the best floor hypothesis so far (the slides' weights) and the best pusher
        friction (the impulses' directions), as `floor_mixture_loglik` turns the net turns'
        lines; the normals themselves before any slide, or without the floor model."""
        ms = self.motion
        if not (ms.use_floor and ms.floor_choice) or self._yaw_now is None or not self.features:
            return self.normals
        angle, ratio, _ = max(floor_hypotheses(self.features, ms), key=lambda h: h[2])
        if ratio == 1.0:
            return self.normals
        from scipy.special import logsumexp

        early, direction, _ = self._sums
        ev = logsumexp(early.max(axis=1)[:, None] + direction, axis=0)
        mu_p = ms.mu_p_grid[int(np.argmax(ev))]
        yaw = self._yaw_now - angle
        return np.array(
            [floor_force_direction(n, yaw, 1.0, ratio, mu_p, ms.floor_share) for n in self.normals]
        ).reshape(self.normals.shape)

    def next_push(self) -> tuple[np.ndarray, np.ndarray] | None:
        c, V, _ = weighted_pca(self.points, self.weights, self.pixel_m / SUBPIXEL)
        j = choose_contact(
            self.region(),
            self.contacts,
            self.expected_lines(),
            self.settings,
            self.pixel_m,
            self.allowed,
            (c, V),
        )
        if j is None:
            return None
        return self.contacts[j].copy(), self.normals[j].copy()

    def observe_path(self, path: PushPath) -> None:
        """What the camera saw of the coming `observe`'s push (world frame)."""
        self._path = path
        self._yaw_now = path.pose_after.yaw_rad

    def observe(
        self,
        contact_m: np.ndarray,
        direction: np.ndarray,
        rotation_deg: float,
        line_direction: np.ndarray | None = None,
    ) -> str:
        """Add a push (object frame; `line_direction` is ignored: the floor is unknown)."""
        f = push_features(self._path, contact_m, direction, rotation_deg, self.motion)
        self._path = None
        self.features.append(f)
        new = push_logliks(self.points, self.footprint, [f], self.motion)
        self._sums = (
            new
            if self._sums is None
            else tuple(a + b for a, b in zip(self._sums, new, strict=True))
        )
        self.weights = motion_posterior(
            self.points, self.footprint, self.features, self.motion, self._sums, self._cache
        )
        th = self.settings.theta_T_deg
        turn = "ccw" if rotation_deg > th else "cw" if rotation_deg < -th else "band"
        return f"{turn}-path" if f.early else turn


# ----------------------------------------------------------------------------------------------
# the real-robot path: poses over time per push, world frame, no simulator (docs/real_robot.md)


@dataclass(frozen=True, eq=False)
class MotionPush:
    """One push as a robot observes it, world frame (z up, yaw CCW about +z; m, rad, s): the
    contact point and push direction (inward normal; normalised here), and the path: the
    object frame's pose before the push, its poses at the camera's frames during it (`t_s`
    since the push command started; a few frames within the first 60 ms after the impact are
    what the model uses), its pose at rest after, when the pusher reached the contact
    (`t_contact_s`) and the net turn if a tracker measured it unwrapped (`rotation_deg`, else
    the yaw change along the path), and the pusher's speed (`speed_m_s`: frames too late for
    the impact to dominate at that speed are not used; None: no such check), and when the
    pusher stopped (`t_end_s`: the slide from then to rest weighs the floor hypotheses; None:
    the floor stays at its prior). Poses may be
    `Pose2D` or (x_m, y_m, yaw_rad) tuples."""

    contact_m: tuple[float, float]
    direction: tuple[float, float]
    pose_before: Pose2D
    t_s: tuple[float, ...]
    poses: tuple[Pose2D, ...]
    pose_after: Pose2D
    t_contact_s: float
    rotation_deg: float | None = None
    speed_m_s: float | None = None  # the pusher's; None: every early frame counts as impulsive
    t_end_s: float | None = None  # when the pusher stopped; None: the slide is not used

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "contact_m", as_xy(self.contact_m))
        d = np.asarray(as_xy(self.direction))
        if np.linalg.norm(d) == 0:
            raise ValueError("direction must be a non-zero vector")
        set_(self, "direction", as_xy(d / np.linalg.norm(d)))
        set_(self, "pose_before", as_pose(self.pose_before))
        set_(self, "pose_after", as_pose(self.pose_after))
        set_(self, "poses", tuple(as_pose(p) for p in self.poses))
        set_(self, "t_s", tuple(float(t) for t in self.t_s))
        if len(self.t_s) != len(self.poses):
            raise ValueError(f"{len(self.t_s)} times for {len(self.poses)} poses")
        if any(b <= a for a, b in zip(self.t_s, self.t_s[1:], strict=False)):
            raise ValueError("t_s must increase")

    def path(self) -> PushPath:
        return PushPath(
            pose_before=self.pose_before,
            t_s=self.t_s,
            poses=self.poses,
            pose_after=self.pose_after,
            t_contact_s=float(self.t_contact_s),
            speed_m_s=float("nan") if self.speed_m_s is None else float(self.speed_m_s),
            rotation_deg=self.rotation_deg,
            t_end_s=None if self.t_end_s is None else float(self.t_end_s),
        )

    def turn_deg(self) -> float:
        """The net CCW turn: measured, or the yaw change along the path (unwrapped)."""
        if self.rotation_deg is not None:
            return float(self.rotation_deg)
        return math.degrees(float(self.path().relative()[-1, 3]))

    def in_object_frame(self) -> tuple[np.ndarray, np.ndarray]:
        """(contact, direction) in the object frame at the pose before the push."""
        yaw = self.pose_before.yaw_rad
        P = self.pose_before.to_object(np.asarray(self.contact_m))
        c, s = math.cos(yaw), math.sin(yaw)
        dx, dy = self.direction
        return P, np.array([c * dx + s * dy, -s * dx + c * dy])


def estimate_com_motion(
    outline_m: np.ndarray,
    pushes: list[MotionPush] | tuple[MotionPush, ...],
    pixel_m: float,
    motion: MotionSettings | None = None,
):
    """The motion estimator on observed pushes: returns a `comexp.method.estimator.WorldEstimate`
    (`region_m` = the 95% credible set, `pushes` = the pushes as `ObservedPush`es in the object
    frame). `outline_m` is the footprint in the object frame, centred on its area centroid, as
    for `estimate_com_world`; each push is mapped into the object frame with its own pose
    before the push, and its path is read relative to that pose."""

    region0 = region_from_outline(centred_outline(outline_m), pixel_m)
    est = MotionEstimator(region0, np.zeros((0, 2)), np.zeros((0, 2)), pixel_m, motion=motion)
    return estimate_from_paths(est, pushes)


def centred_outline(outline_m: np.ndarray) -> np.ndarray:
    """`outline_m` as an array, or ValueError if it is not centred on its area centroid."""
    outline = np.asarray(outline_m, dtype=float)
    c = centroid(outline)
    if np.hypot(*c) > OUTLINE_CENTRED_TOL_M:
        raise ValueError(
            f"outline_m: its centroid is at ({c[0]:.4f}, {c[1]:.4f}) m, not at the origin: "
            "pass outline_m - centroid, and poses of the centroid"
        )
    return outline


def estimate_from_paths(est: MotionEstimator, pushes: list[MotionPush] | tuple[MotionPush, ...]):
    """`est` (a `MotionEstimator`, or one that extends it, built on the object frame's region)
    fed the observed pushes in order: the `WorldEstimate` of `estimate_com_motion`."""
    pushes = list(pushes)
    if not pushes:
        raise ValueError("an estimate needs at least one push (its pose fixes the frame)")
    local = []
    for push in pushes:
        P, N = push.in_object_frame()
        est.observe_path(push.path())
        est.observe(P, N, push.turn_deg())
        local.append(
            ObservedPush((float(P[0]), float(P[1])), (float(N[0]), float(N[1])), push.turn_deg())
        )
    com = est.estimate_m
    first = pushes[0].pose_before
    return WorldEstimate(
        com_object_m=com,
        com_world_m=first.to_world(com),
        first_pose=first,
        region_m=est.region(),
        pushes=tuple(local),
    )
