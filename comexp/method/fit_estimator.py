"""`estimator.method=fit`: the CoM that makes a forward model reproduce the tracked paths.

`motion`'s posterior (the impulse relations of fast pushes, the slides, the net turns' signs and
sizes) times, for every slow push (the pusher at most `FitSettings.max_speed_m_s`), the
likelihood of each tracked interval under the quasi-static pushing model
(`comexp.method.quasi_static`): the object's motion predicted from the pose at the interval's
middle, the contact that pose gives, and a hypothesis (CoM, floor, pusher friction, turn gain).
The nuisance hypotheses are marginalised: the floor isotropic (prior `iso_prior`), or
anisotropic with the ratio `floor_ratios` across an axis at one of `floor_angles` directions; the
pusher's friction on `mu_p_grid`; the turn's gain on `turn_gains` (an object slow to spin up,
Izz x 10 on a slippery floor, turns less than the inertia-free model says). Told the floor and
the pusher's friction (`KnownNuisances`), it keeps those alone. Floors whose evidence
falls `prune_log` below the best are no longer evaluated; a push's evidence against any
hypothesis is capped at `push_max_log` (its intervals share one contact and one model error).

Where the pusher's disc drove the object is measured rather than assumed: its median gap to the
perceived outline over the episode's slow pushes (`offset_window_m`) makes the disc that much
larger and its contact that much earlier (`quasi_static.PusherDrive`).

The quasi-static likelihood is computed on a grid `grid_px` pixels apart and carried to
`motion`'s finer grid by nearest point. After a slow push on a floor that looks anisotropic the
next push is chosen for information (`FitEstimator.next_push`).

On a floor the intervals make look anisotropic, the estimate reads the slow pushes a second
way (`FitSettings.rollout`): each push rolled out whole through the same model from its start
pose (`quasi_static.rollout_losses`), its rest pose against the one seen. An interval's bias
stays in every interval; the rollout weighs what the push did as a whole. It refines the
estimate only (`estimate_m`): the pushes are chosen, and the regions stored, by the intervals'
posterior, for which the choice was built. Frames and units as
`ComEstimator`'s; docs/method.md, "Beyond the paper: `estimator.method=fit`", has the model, its
assumptions and where it fails.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from comexp.method.estimator import EstimatorSettings, line_cuts_region, region_from_outline
from comexp.method.geometry import douglas_peucker
from comexp.method.motion_estimator import (
    MOTION_VERSION,
    KnownNuisances,
    MotionEstimator,
    MotionPush,
    MotionSettings,
    centred_outline,
    estimate_from_paths,
)
from comexp.method.quasi_static import (
    MOMENT_ANGLES,
    ContactStep,
    PusherDrive,
    RolloutPush,
    add_step_loglik,
    footprint_samples,
    moment_table,
    predict_step,
    pressure_weights,
    rollout_losses,
    rollout_push,
    step_array,
)

# The model's revision (with motion's, whose posterior it multiplies): pinned in fit episodes'
# keys like motion's (`EstimatorSettings.motion_version`). fit-2: the contact's offset measured;
# fit-3: the floor's pressure centred under the candidate CoM (its clipping had pulled it inward);
# fit-4: the estimate refined by the rollout reading; fit-5: only where the floor looks
# anisotropic; fit-6: the rollout's contact search proven the full one's (fit-5's local search
# could miss a closer part of a concave outline).
FIT_VERSION = f"fit-6+{MOTION_VERSION}"


@dataclass(frozen=True)
class FitSettings:
    """Knobs of the fit estimator (docs/method.md, "`estimator.method=fit`")."""

    max_speed_m_s: float = 0.1  # pushes at most this fast are read as quasi-static
    max_gap_m: float = 0.002  # an interval counts while the pusher is this close to the outline
    # ... from the pusher's offset: the median gap between its disc and the perceived outline
    # while it drove the object, over the episode's slow pushes, gaps within this window
    # (`quasi_static.PusherDrive.gaps_m`; 0: no offset). The perceived outline lies ~1.2 mm inside
    # the true one (vision), and pybullet's contact keeps the object ~1 mm off the disc: the
    # contact is then timed and placed where the object was driven
    offset_window_m: float = 0.005
    rel_model: float = 0.2  # relative model error of an interval's predicted motion
    weight: float = 1.0  # the quasi-static log-likelihood's weight
    floor_ratios: tuple[float, ...] = (3.0, 10.0)
    floor_angles: int = 12
    mu_p_grid: tuple[float, ...] = (0.1, 0.25, 0.5, 1.0)
    turn_gains: tuple[float, ...] = (0.35, 0.6, 1.0)
    iso_prior: float = 0.5  # the floor's prior: isotropic, or one of the anisotropic ones
    prune_log: float = 12.0
    # a push's summed log-likelihood can make no hypothesis less likely than the push's best
    # by more than this (a push the model misreads cannot rule the true CoM out)
    push_max_log: float = 10.0
    footprint_samples: int = 64  # where the floor presses: the limit surface's samples
    grid_px: int = 2  # the model's CoM grid: every this many pixels of the region
    # after a slow push, the next one is the valid push whose predicted motion differs most
    # across the posterior's `info_points` likeliest CoMs (the best nuisance hypothesis)
    choose_for_information: bool = True
    info_points: int = 48
    # the rollout reading of the estimate (on a floor that looks anisotropic): every slow push
    # replayed through the same model from its start pose (`quasi_static.rollout_losses`), its
    # rest pose (and, weighted `rollout_path_weight`, its tracked poses) against what was seen;
    # False: the intervals alone
    rollout: bool = True
    rollout_rel_model: float = 0.2  # the rollout's error relative to the motion it predicts
    rollout_path_weight: float = 0.0
    rollout_step_m: float = 0.001  # the pusher's travel per integration step
    # the nuisance hypotheses it marginalises: every one is rolled out at the posterior's
    # `rollout_screen_points` likeliest CoMs; those within `rollout_screen_log` of the best
    # (at most `rollout_hypotheses`) at the model grid's CoMs that hold `rollout_mass` of it
    rollout_screen_points: int = 3
    rollout_screen_log: float = 10.0
    rollout_hypotheses: int = 6
    rollout_mass: float = 0.999
    rollout_outline_tol_m: float = 0.0001  # the outline it rolls against, simplified this far


class FitEstimator(MotionEstimator):
    """`estimator.method=fit` (module docstring). Needs the outline and the pusher's radius
    (an episode gives both); without them it is `motion`."""

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
        fit: FitSettings | None = None,
        nuisances: KnownNuisances | None = None,
    ) -> None:
        super().__init__(
            region_m,
            contacts_m,
            normals,
            pixel_m,
            settings or EstimatorSettings(method="fit"),
            outline_m=outline_m,
            pusher_radius_m=pusher_radius_m,
            motion=motion,
            nuisances=nuisances,
        )
        fs = self.fit = fit or FitSettings()
        self.outline = None if outline_m is None else np.asarray(outline_m, dtype=float)
        self.pusher_radius_m = pusher_radius_m
        self.coarse = _lattice(self.footprint, self.pixel_m, fs.grid_px)
        self.samples = (
            footprint_samples(self.outline, fs.footprint_samples)
            if self.outline is not None
            else self.footprint
        )
        self.pressure = pressure_weights(self.samples, self.coarse)
        angles = [math.pi * k / fs.floor_angles for k in range(fs.floor_angles)]
        floors = [(1.0, 0.0)] + [(r, a) for r in fs.floor_ratios for a in angles]
        mu_p = fs.mu_p_grid
        if nuisances is not None:  # told: the one floor and pusher friction (the gains stay:
            # they stand for the model's error, not for a parameter of the scene)
            angle, ratio = nuisances.floor
            floors, mu_p = [(ratio, angle)], (nuisances.mu_pusher,)
        self.ratios = np.array([r for r, _ in floors])
        self.axes = np.array([a for _, a in floors])
        self.active = np.ones(len(floors), dtype=np.bool_)
        aniso = (1.0 - fs.iso_prior) / max(len(floors) - 1, 1)
        self.log_prior = np.log(np.where(self.ratios == 1.0, fs.iso_prior, aniso))
        if len(floors) == 1:
            self.log_prior = np.zeros(1)
        self.mu_p = np.asarray(mu_p, dtype=float)
        self.gains = np.asarray(fs.turn_gains, dtype=float)
        self.loglik = np.zeros((len(self.coarse), len(floors), len(self.mu_p), len(self.gains)))
        self.steps_used = 0
        self._evidence: tuple[tuple[int, bytes], np.ndarray] | None = None  # `_floor_evidence`'s
        self._slow = False  # the last push was read with the quasi-static model
        self._travel_m = 0.0
        self._gaps: list[float] = []  # the pusher's gaps while driving (`PusherDrive.gaps_m`)
        from scipy.spatial import cKDTree  # here: its import (0.3 s) only where fit runs

        self.to_coarse = cKDTree(self.coarse).query(self.points)[1]
        ms = self.motion
        self.noise = np.array(
            [
                math.sqrt(2) * ms.sigma_move_m,  # an interval's two frames' errors
                math.sqrt(2) * math.radians(ms.sigma_turn_deg),
                fs.rel_model,
            ]
        )
        # the rollout reading's state: the slow pushes, the estimate it gives (per push count)
        self._rollouts: list[RolloutPush] = []
        self._rolled: tuple[int, np.ndarray] | None = None
        self._table: np.ndarray | None = None  # `_tabulate`'s
        self._tabulated = np.zeros(0, dtype=np.bool_)
        self._roll_outline = (
            None
            if self.outline is None
            else douglas_peucker(self.outline, fs.rollout_outline_tol_m)
        )
        self.rollouts_run = 0  # rollouts evaluated (cost accounting: bench, tests)

    def observe(
        self,
        contact_m: np.ndarray,
        direction: np.ndarray,
        rotation_deg: float,
        line_direction: np.ndarray | None = None,
    ) -> str:
        """`motion`'s update, then a slow push's quasi-static intervals (kept, too, for the
        rollout reading of `estimate_m`); the posterior is `motion`'s times the intervals'
        evidence over every slow push so far."""
        path = self._path
        label = super().observe(contact_m, direction, rotation_deg, line_direction)
        fs = self.fit
        steps: list[ContactStep] = []
        self._slow = not (
            path is None
            or self.outline is None
            or self.pusher_radius_m is None
            or path.t_end_s is None
            or not path.speed_m_s <= fs.max_speed_m_s
        )
        if self._slow:
            steps = self._read_slow_push(path, contact_m, direction)
        if self.steps_used:
            from scipy.special import logsumexp

            self._prune()
            n = len(self.coarse)
            prior = self.log_prior[None, self.active, None, None]
            qs = logsumexp((self.loglik[:, self.active] + prior).reshape(n, -1), axis=1)
            ll = np.log(self.weights + 1e-300) + fs.weight * qs[self.to_coarse]
            p = np.exp(ll - ll.max())
            self.weights = p / p.sum()
        return f"{label}-qs" if steps and len(label) <= 13 else label

    @property
    def estimate_m(self) -> np.ndarray:
        """The posterior's mean, refined by the rollout reading once slow pushes were seen on a
        floor they make look anisotropic (on an isotropic one the intervals read the pushes as
        well: measured, whole jobs, docs/method.md)."""
        if not (self._rollouts and self._floor_looks_anisotropic()):
            return self.weights @ self.points
        if self._rolled is None or self._rolled[0] != len(self._rollouts):
            self._rolled = (len(self._rollouts), self._rollout_weights() @ self.points)
        return self._rolled[1].copy()

    def _read_slow_push(self, path, contact_m, direction) -> list[ContactStep]:
        """Adds a slow push's intervals to `loglik` and keeps it for the rollout; returns
        the intervals read."""
        fs = self.fit
        self._travel_m = max(0.0, (path.t_end_s - path.t_contact_s) * path.speed_m_s)
        drive = PusherDrive(
            path.pose_before,
            path.t_s,
            path.poses,
            np.asarray(contact_m, dtype=float),
            np.asarray(direction, dtype=float),
            path.t_contact_s,
            path.t_end_s,
            path.speed_m_s,
            self.outline,
            self.pusher_radius_m,
        )
        offset = 0.0
        if fs.offset_window_m > 0:  # the setup's, pooled over the episode's slow pushes
            self._gaps.extend(drive.gaps_m(fs.offset_window_m))
            offset = float(np.median(self._gaps)) if self._gaps else 0.0
        steps = drive.steps(fs.max_gap_m, offset_m=offset)
        push_ll = np.zeros_like(self.loglik)
        for step in steps:
            add_step_loglik(
                self.coarse,
                self.samples,
                self.pressure,
                self.ratios,
                self.axes,
                self.mu_p,
                self.gains,
                self.active,
                step_array(step),
                self.noise,
                push_ll,
            )
        if steps:
            idx = np.flatnonzero(self.active)
            best = push_ll[:, idx].max()
            self.loglik += np.maximum(push_ll, best - fs.push_max_log)
        self.steps_used += len(steps)
        if fs.rollout:
            end = path.poses[-1] if path.extra.get("recentred") and path.poses else path.pose_after
            push = rollout_push(drive, end, offset)
            if push is not None:
                self._rollouts.append(push)
        return steps

    # --- the rollout reading ------------------------------------------------------------------

    def _hypotheses(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every (floor, pusher friction) pair: ratio, world axis, friction, and the index of
        its ratio in the moment table's ratios (hypothesis h = floor * len(mu_p) + friction)."""
        nm = len(self.mu_p)
        ratios = np.repeat(self.ratios, nm)
        axes = np.repeat(self.axes, nm)
        mus = np.tile(self.mu_p, len(self.ratios))
        index = np.searchsorted(np.unique(self.ratios), ratios)
        return ratios, axes, mus, index

    def _tabulate(self, g: np.ndarray) -> None:
        """The limit surface's moment table (`quasi_static.moment_table`) for the grid points g,
        those not yet tabulated: a rollout needs it only where it runs."""
        ratios = np.unique(self.ratios)
        if self._table is None:
            self._table = np.zeros((len(self.coarse), len(ratios), MOMENT_ANGLES + 1))
            self._tabulated = np.zeros(len(self.coarse), dtype=np.bool_)
        new = g[~self._tabulated[g]]
        if len(new):
            self._table[new] = moment_table(
                self.samples, self.pressure[new], self.coarse[new], ratios, MOMENT_ANGLES
            )
            self._tabulated[new] = True

    def _losses(self, k: int, g: np.ndarray, h: np.ndarray) -> np.ndarray:
        """Push k's rollout losses for the (candidate, hypothesis) pairs (g[i], h[i])."""
        self._tabulate(np.unique(g))
        ratios, axes, mus, index = self._hypotheses()
        p, fs, ms = self._rollouts[k], self.fit, self.motion
        noise = np.array(
            [
                math.sqrt(2) * ms.sigma_move_m,  # the start's and the end's errors
                math.sqrt(2) * math.radians(ms.sigma_turn_deg),
                fs.rollout_rel_model,
            ]
        )
        out = np.empty(len(g))
        rollout_losses(
            self._roll_outline,
            self.coarse,
            self._table,
            ratios,
            axes,
            mus,
            index,
            np.ascontiguousarray(g, dtype=np.int64),
            np.ascontiguousarray(h, dtype=np.int64),
            p.packed(),
            p.t_s,
            p.poses,
            p.end,
            noise,
            fs.rollout_path_weight,
            fs.rollout_step_m,
            out,
        )
        self.rollouts_run += len(g)
        return out

    def _rollout_weights(self) -> np.ndarray:
        """The posterior times the rollout reading's evidence: every hypothesis (floor, pusher
        friction) is screened, all slow pushes rolled out at the `rollout_screen_points`
        likeliest CoMs; the best (`rollout_screen_log`, at most `rollout_hypotheses`) are
        rolled out at the grid's CoMs that hold `rollout_mass` of the posterior (the rest keep
        none) and marginalised under their prior. As for the intervals, a push can make no
        pair less likely than its best by more than `push_max_log`."""
        from scipy.special import logsumexp

        fs = self.fit
        nm, n = len(self.mu_p), len(self.coarse)
        nh = len(self.ratios) * nm
        log_prior = np.repeat(self.log_prior, nm) - math.log(nm)
        mass = np.bincount(self.to_coarse, weights=self.weights, minlength=n)
        kept = np.arange(nh)
        if nh > 1:
            top = np.argsort(mass)[::-1][: fs.rollout_screen_points]
            g, h = np.repeat(top, nh), np.tile(np.arange(nh), len(top))
            loss = sum(self._losses(k, g, h) for k in range(len(self._rollouts)))
            ll = np.log(mass[top] + 1e-300)[:, None] - 0.5 * loss.reshape(len(top), nh)
            ev = logsumexp(ll, axis=0) + log_prior
            order = np.argsort(ev)[::-1][: fs.rollout_hypotheses]
            kept = order[ev[order] >= ev[order[0]] - fs.rollout_screen_log]
        order = np.argsort(mass)[::-1]
        held = np.searchsorted(np.cumsum(mass[order]), fs.rollout_mass * mass.sum()) + 1
        live = np.sort(order[:held])  # the grid points that hold the posterior
        g, h = np.tile(live, len(kept)), np.repeat(kept, len(live))
        ll = log_prior[kept][:, None].repeat(len(live), axis=1)
        for k in range(len(self._rollouts)):
            push_ll = -0.5 * self._losses(k, g, h).reshape(len(kept), len(live))
            ll += np.maximum(push_ll, push_ll.max() - fs.push_max_log)
        term = np.full(n, -np.inf)
        term[live] = logsumexp(ll, axis=0)
        lw = np.log(self.weights + 1e-300) + term[self.to_coarse]
        p = np.exp(lw - lw.max())
        return p / p.sum()

    def next_push(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Algorithm 1 against the posterior (`motion`'s), or, after a slow push on a floor the
        pushes so far say is anisotropic, the valid push (its line cuts the credible region,
        reachable) that informs most: the largest spread of its predicted turn and
        displacement across the likeliest CoMs, each over its noise (vision plus the model's
        error). On isotropic floors Algorithm 1's region-splitting pushes did better."""
        choice = super().next_push()
        if choice is None or not (self.fit.choose_for_information and self._slow):
            return choice
        region = self.region()
        valid = np.zeros(len(self.contacts), dtype=bool)
        idx = np.flatnonzero(self.allowed)
        valid[idx] = line_cuts_region(region, self.contacts[idx], self.normals[idx])
        if not valid.any() or self._yaw_now is None:
            return choice
        score = self._information(np.flatnonzero(valid))
        if score is None:
            return choice
        j = int(np.flatnonzero(valid)[int(np.argmax(score))])
        return self.contacts[j].copy(), self.normals[j].copy()

    def _information(self, candidates: np.ndarray) -> np.ndarray | None:
        """Each candidate push's spread of predicted outcomes over the likeliest CoMs under the
        likeliest anisotropic floor and its best pusher friction and gain; None while the floor
        is as likely isotropic as not."""
        fs = self.fit
        top = np.argsort(self.weights)[::-1][: fs.info_points]
        G, w = self.points[top], self.weights[top] / self.weights[top].sum()
        if not self._floor_looks_anisotropic():
            return None  # isotropic as likely: Algorithm 1's splits inform more (measured)
        ev = self._floor_evidence()
        aniso = self.ratios != 1.0
        j = int(np.flatnonzero(aniso)[np.argmax(ev[aniso])])
        m, k = np.unravel_index(int(np.argmax(self.loglik[:, j].max(0))), self.loglik.shape[2:])
        pressure = pressure_weights(self.samples, G)
        sd, st, rel = self.noise
        out = np.empty(len(candidates))
        for i, c in enumerate(candidates):
            P, N = self.contacts[c], self.normals[c]
            step = ContactStep(P, N, N, self._yaw_now, self._travel_m, np.zeros(2), 0.0)
            d, turn = predict_step(
                G, self.samples, pressure, self.ratios[j], self.axes[j], self.mu_p[m], step
            )
            turn = turn * self.gains[k]
            var_t = w @ (turn - w @ turn) ** 2
            var_d = w @ ((d - w @ d) ** 2).sum(1)
            out[i] = var_t / (st**2 + rel**2 * (w @ turn**2)) + var_d / (
                sd**2 + rel**2 * (w @ (d**2).sum(1))
            )
        return out

    def _floor_evidence(self) -> np.ndarray:
        """Each floor's log evidence (its prior included; -inf once pruned); kept until `loglik`
        or the active floors change (a push asks for it several times)."""
        from scipy.special import logsumexp

        key = (self.steps_used, self.active.tobytes())  # `loglik` grows with every step read
        if self._evidence is None or self._evidence[0] != key:
            n = len(self.coarse)
            ev = np.full(len(self.active), -np.inf)
            idx = np.flatnonzero(self.active)
            ev[idx] = self.log_prior[idx] + logsumexp(
                self.loglik[:, idx].transpose(1, 0, 2, 3).reshape(len(idx), n, -1), axis=(1, 2)
            )
            self._evidence = (key, ev)
        return self._evidence[1].copy()

    def _floor_looks_anisotropic(self) -> bool:
        """Whether the intervals so far make an anisotropic floor likelier than an isotropic
        one (the push choice's gate and the rollout's)."""
        ev = self._floor_evidence()
        post = np.exp(ev - ev.max())
        aniso = self.ratios != 1.0
        return bool(post[aniso].sum() > post[~aniso].sum())

    def _prune(self) -> None:
        """Stop evaluating floors whose evidence is `prune_log` below the best one's."""
        ev = self._floor_evidence()
        self.active &= ev >= ev.max() - self.fit.prune_log


def estimate_com_fit(
    outline_m: np.ndarray,
    pushes: list[MotionPush] | tuple[MotionPush, ...],
    pixel_m: float,
    pusher_radius_m: float,
    fit: FitSettings | None = None,
):
    """The fit estimator on a robot's observed pushes (`MotionPush`es, world frame, as for
    `estimate_com_motion`, whose `WorldEstimate` it returns): `outline_m` centred on its area
    centroid; each push's `speed_m_s` and `t_end_s` tell the model how the pusher drove (a push
    without them, or faster than `FitSettings.max_speed_m_s`, adds `motion`'s terms only)."""
    outline = centred_outline(outline_m)
    region0 = region_from_outline(outline, pixel_m)
    none = np.zeros((0, 2))
    est = FitEstimator(
        region0, none, none, pixel_m, outline_m=outline, pusher_radius_m=pusher_radius_m, fit=fit
    )
    return estimate_from_paths(est, pushes)


def _lattice(region: np.ndarray, pixel_m: float, every: int) -> np.ndarray:
    """The region's points (a pixel grid) on every `every`-th row and column."""
    if every <= 1 or len(region) == 0:
        return region
    ij = np.rint((region - region.min(0)) / pixel_m).astype(int)
    keep = (ij % every == 0).all(1)
    return region[keep] if keep.any() else region
