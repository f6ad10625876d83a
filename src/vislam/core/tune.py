"""Noise tuning without ground truth: the predictive likelihood of the SLAM filter's innovations.

Before each update the EKF predicts every observation z_i of a landmark in its state as
N(ẑ_i, S_i), ``S_i = H_i Σ H_iᵀ + V`` (pose, landmark and pixel noise together). How
well those predictions match what the camera then sees scores the noise settings: too
little IMU noise and the predictions are overconfident (large rᵀS⁻¹r), too much and
they are needlessly vague (large log det S). The score of one candidate
(:func:`evaluate_candidate`) is the mean, over the observations, of a robust predictive
log-density:

* **every** predicted observation of an in-state landmark counts, *before* the gate —
  a candidate cannot improve its score by gating the observations it predicts badly;
* a Student-t density (``nu`` degrees of freedom, scale matrix S_i) instead of the
  Gaussian, so the ~10 % gross outliers of the real tracks cost a bounded, logarithmic
  amount instead of dominating the sum::

      ℓ_i = log Γ((ν+4)/2) − log Γ(ν/2) − 2 log(νπ) − ½ log det S_i − (ν+4)/2 · log(1 + r_iᵀS_i⁻¹r_i / ν)

* observations that are not predicted because the candidate rejected their landmark
  earlier (or whose landmark is behind the camera) are charged as if they had landed
  on the gate (``r ᵀS⁻¹r = χ²₄`` gate quantile, the candidate's mean log det S): a
  candidate cannot improve its score by rejecting landmarks either.

It is a proper density in S, so shrinking the noise does not pay: for S → 0 the score
goes to −∞ (as ν log σ).

The search (:class:`NoiseSearch`) is log-spaced: a coarse grid over the velocity and
angular noise, a line over the pixel noise, then a compass (pattern) search: each
round polls every noise × and ÷ a step around the best so far (with a pattern move and
the maximum of a quadratic fitted to the scores near the best); the step is kept while a
round improves the best and halved when it does not, and the search ends when the
smallest step's round does not improve (or after ``max_polls`` rounds); a last
candidate at the fitted quadratic's maximum (or the per-axis parabola vertex). The
candidates of each round are independent runs, so a caller can evaluate them in
parallel (:mod:`vislam.tools.tune` does, on Dask).

Pure computation: no I/O.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass
from typing import Any, Iterable

import numpy as np
from scipy.special import gammaln
from threadpoolctl import threadpool_limits

from vislam.core.corrections import apply_corrections
from vislam.core.filters import SlamFilter
from vislam.core.options import FilterOptions
from vislam.core.sequence import Sequence
from vislam.core.updaters import innovation_covariances
from vislam.errors import ConfigError, EstimationError

logger = logging.getLogger(__name__)

__all__ = ["TUNED_FIELDS", "DEFAULT_NU", "student_t_logpdf", "InnovationLikelihood", "Candidate", "TuneScore",
           "evaluate_candidate", "SearchSpace", "NoiseSearch"]

#: The FilterOptions fields tuned (scalars: one value for the three axes).
TUNED_FIELDS = ("velocity_noise_mps", "angular_noise_radps", "pixel_noise_px")
#: Degrees of freedom of the Student-t predictive density.
DEFAULT_NU = 4.0
_D = 4  # dimension of a stereo observation


def student_t_logpdf(nis: np.ndarray, logdet_S: np.ndarray, nu: float = DEFAULT_NU, d: int = _D) -> np.ndarray:
    """Log-density of a d-variate Student-t with ``nu`` degrees of freedom and scale
    matrix S at a point whose squared Mahalanobis distance is ``nis`` = rᵀS⁻¹r.
    ``nu = inf`` is the Gaussian −½ (nis + log det 2πS)."""
    nis = np.asarray(nis, dtype=np.float64)
    logdet_S = np.asarray(logdet_S, dtype=np.float64)
    if math.isinf(nu):
        return -0.5 * (nis + logdet_S + d * math.log(2 * math.pi))
    c = gammaln(0.5 * (nu + d)) - gammaln(0.5 * nu) - 0.5 * d * math.log(nu * math.pi)
    return c - 0.5 * logdet_S - 0.5 * (nu + d) * np.log1p(nis / nu)


class InnovationLikelihood:
    """The innovation observer (``filter.diagnostics.innovation_hook``) that sums the robust predictive
    log-density of every observation of an in-state landmark, before gating."""

    def __init__(self, nu: float = DEFAULT_NU, gate_nis: float = math.inf):
        self.nu = float(nu)
        self.gate_nis = gate_nis
        self.loglik_sum = 0.0
        self.logdet_sum = 0.0
        self.nis_sum_in_gate = 0.0
        self.n_predicted = 0  # in front of the camera: with a density
        self.n_behind = 0
        self.n_in_gate = 0

    def __call__(self, r, Hp, Hl, blocks, V, in_front, nis) -> None:
        P_pp, P_ps, P_ss = blocks
        f = np.asarray(in_front, dtype=bool)
        self.n_behind += int(f.size - np.count_nonzero(f))
        if not np.any(f):
            return
        Hp, Hl, nis = Hp[f], Hl[f], nis[f]
        S = innovation_covariances(Hp, Hl, (P_pp, P_ps[f], P_ss[f]), V)  # as slam_predict_nis
        sign, logdet = np.linalg.slogdet(S)
        good = (sign > 0) & np.isfinite(logdet) & np.isfinite(nis)
        self.n_behind += int(good.size - np.count_nonzero(good))
        logdet, nis = logdet[good], nis[good]
        self.loglik_sum += float(student_t_logpdf(nis, logdet, self.nu).sum())
        self.logdet_sum += float(logdet.sum())
        self.n_predicted += int(good.sum())
        inside = nis <= self.gate_nis
        self.n_in_gate += int(inside.sum())
        self.nis_sum_in_gate += float(nis[inside].sum())


@dataclass(frozen=True)
class Candidate:
    """One noise setting (scalars for the three axes)."""

    velocity_noise_mps: float
    angular_noise_radps: float
    pixel_noise_px: float

    @classmethod
    def from_log10(cls, x) -> "Candidate":
        return cls(*(float(f"{10.0 ** v:.4g}") for v in x))

    @property
    def log10(self) -> np.ndarray:
        return np.log10([self.velocity_noise_mps, self.angular_noise_radps, self.pixel_noise_px])

    def options(self, base: FilterOptions | None = None) -> FilterOptions:
        return (base or FilterOptions()).replace(**self.to_dict())

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


@dataclass
class TuneScore:
    """The score of one candidate (see the module docstring); ``objective`` is the mean
    robust predictive log-density per observation (higher is better; −inf for a run
    that failed)."""

    candidate: Candidate
    objective: float = -math.inf
    loglik_sum: float = 0.0
    n_predicted: int = 0
    n_penalized: int = 0  # rejected landmarks' and behind-camera observations
    in_gate_share: float = float("nan")
    nis_mean_in_gate: float = float("nan")
    logdet_mean: float = float("nan")
    frames: int = 0
    seconds: float = 0.0
    error: str | None = None
    round: int = -1

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out.update(out.pop("candidate"))
        return out


def evaluate_candidate(sequence: Sequence, candidate: Candidate, base: FilterOptions | None = None,
                       frames: int | None = None, nu: float = DEFAULT_NU) -> TuneScore:
    """Run the SLAM filter with ``candidate``'s noise on the first ``frames`` frames of
    ``sequence`` (all by default) and score its innovations. A numerical failure of the
    filter gives objective −inf and ``error``; never raises for that."""
    options = candidate.options(base)
    seq = apply_corrections(sequence, options)
    filt = SlamFilter(seq.calibration, options)
    hook = InnovationLikelihood(nu, options.gate_threshold)
    filt.diagnostics.innovation_hook = hook
    score = TuneScore(candidate)
    stop = seq.n_frames if frames is None else min(int(frames), seq.n_frames)
    tic = time.perf_counter()
    try:
        # small matrices: one BLAS thread is fastest (see vislam.core.estimators.run)
        with threadpool_limits(limits=1, user_api="blas"):
            for frame in seq.frames(0, stop):
                filt.step(frame)
            filt.drain()
    except EstimationError as exc:
        score.error = str(exc)
    score.seconds = time.perf_counter() - tic
    score.frames = stop
    score.n_predicted = hook.n_predicted
    score.n_penalized = hook.n_behind + filt.diagnostics.observations_of_rejected
    if hook.n_predicted:
        score.logdet_mean = hook.logdet_sum / hook.n_predicted
        score.in_gate_share = hook.n_in_gate / hook.n_predicted
        if hook.n_in_gate:
            score.nis_mean_in_gate = hook.nis_sum_in_gate / hook.n_in_gate
    if score.error is None and hook.n_predicted:
        penalty = float(student_t_logpdf(min(options.gate_threshold, 1e6), score.logdet_mean, nu))
        score.loglik_sum = hook.loglik_sum + score.n_penalized * penalty
        score.objective = score.loglik_sum / (hook.n_predicted + score.n_penalized)
    elif score.error is None:
        score.error = "no observation of a landmark in the state was predicted"
    return score


# ----------------------------------------------------------------------------- search


@dataclass(frozen=True)
class SearchSpace:
    """Ranges (inclusive) of the search, and its shape."""

    velocity_noise_mps: tuple[float, float] = (0.005, 2.0)
    angular_noise_radps: tuple[float, float] = (1e-4, 0.2)
    pixel_noise_px: tuple[float, float] = (0.5, 5.0)
    #: Points of the coarse grid per IMU noise (velocity x angular).
    coarse_points: int = 4
    #: Points of the pixel-noise line.
    pixel_points: int = 4
    #: Step sizes of the compass search after the coarse grid and the pixel line: the
    #: first is half the coarse spacing, each next one half the one before. A step is
    #: polled (6 runs: every noise × and ÷ it; after a round that moved the best, one
    #: more at the same move repeated; one at the maximum of a quadratic fitted to the
    #: scores near the best) until a round no longer improves the best.
    refine_rounds: int = 3
    #: At most this many compass rounds in all.
    max_polls: int = 10
    #: Try a final candidate: the maximum of the quadratic fitted near the best at the
    #: smallest step, or else the per-axis parabola vertex of the last round.
    parabola: bool = True

    def __post_init__(self):
        for name in TUNED_FIELDS:
            lo, hi = getattr(self, name)
            if not (0 < lo <= hi and math.isfinite(hi)):
                raise ConfigError(f"search range of {name} must be 0 < low <= high, got {lo!r}..{hi!r}")
        if self.coarse_points < 2 or self.pixel_points < 1 or self.refine_rounds < 0 or self.max_polls < 0:
            raise ConfigError("search: coarse_points >= 2, pixel_points >= 1, refine_rounds >= 0, max_polls >= 0 "
                              "expected")

    @property
    def bounds_log10(self) -> np.ndarray:
        """(3, 2) log10 bounds."""
        return np.log10([getattr(self, n) for n in TUNED_FIELDS])

    @property
    def max_runs(self) -> int:
        polls = self.max_polls if self.refine_rounds else 0
        return self.coarse_points**2 + self.pixel_points + 8 * polls + int(self.parabola)


class NoiseSearch:
    """The candidates of each round, from the scores of the rounds before.

    Usage::

        search = NoiseSearch(space, start_pixel_noise_px=2.0)
        while (batch := search.next_round()):
            search.tell([evaluate(c) for c in batch])   # in parallel
        best = search.best

    Rounds: (0) the coarse log grid of velocity × angular noise at the starting pixel
    noise; (1) a log line of pixel noise at the best of (0); (2..) compass search around
    the best so far: each noise multiplied and divided by a step that starts at half the
    coarse spacing. The step is kept while the rounds improve the best, so the search
    walks toward a maximum far from the grid's best point instead of shrinking before it
    gets there, and halved after a round that does not: ``refine_rounds`` step sizes in
    all, at most ``max_polls`` rounds. Each round also tries, after a round that moved
    the best, the same move once more (a Hooke-Jeeves pattern move, along ridges of
    correlated noises), and the maximum of a quadratic fitted to the scores near the
    best (:meth:`_quadratic_proposal`). (last) The fitted quadratic's maximum at the
    smallest step, or else the per-axis parabola vertex. Candidates evaluated before
    (same rounded values) are not run again.
    """

    def __init__(self, space: SearchSpace | None = None, start_pixel_noise_px: float = 2.0):
        self.space = space or SearchSpace()
        lo, hi = self.space.pixel_noise_px
        self.start_px = float(min(max(start_pixel_noise_px, lo), hi))
        self.scores: dict[Candidate, TuneScore] = {}
        self.rounds: list[list[Candidate]] = []
        b = self.space.bounds_log10
        n = self.space.coarse_points
        self._coarse_step = (b[:2, 1] - b[:2, 0]) / (n - 1)
        self._step: np.ndarray | None = None
        self._stage = "coarse"
        self._sizes = 0  # step sizes begun
        self._polls = 0  # compass rounds run
        self._last_center: Candidate | None = None  # the center of the last compass round
        self._last_step: np.ndarray | None = None

    # --- bookkeeping -----------------------------------------------------------------
    @property
    def best(self) -> TuneScore | None:
        ok = [s for s in self.scores.values() if math.isfinite(s.objective)]
        return max(ok, key=lambda s: s.objective) if ok else None

    def tell(self, scores: Iterable[TuneScore]) -> None:
        r = len(self.rounds) - 1
        for s in scores:
            s.round = r if s.round < 0 else s.round
            self.scores[s.candidate] = s

    def _clip(self, x: np.ndarray) -> np.ndarray:
        b = self.space.bounds_log10
        return np.clip(x, b[:, 0], b[:, 1])

    def _new(self, xs: Iterable[np.ndarray]) -> list[Candidate]:
        out: list[Candidate] = []
        for x in xs:
            c = Candidate.from_log10(self._clip(np.asarray(x, dtype=np.float64)))
            if c not in self.scores and c not in out:
                out.append(c)
        return out

    # --- rounds ------------------------------------------------------------------------
    def next_round(self) -> list[Candidate]:
        """The candidates of the next round ([] when the search is over)."""
        batch = self._plan()
        if batch:
            self.rounds.append(batch)
        return batch

    def _plan(self) -> list[Candidate]:
        sp = self.space
        b = sp.bounds_log10
        if self._stage == "coarse":
            self._stage = "pixel"
            gv = np.linspace(b[0, 0], b[0, 1], sp.coarse_points)
            gw = np.linspace(b[1, 0], b[1, 1], sp.coarse_points)
            px = math.log10(self.start_px)
            return self._new(np.array([v, w, px]) for v in gv for w in gw)
        best = self.best
        if best is None:
            return []  # every run failed
        x0 = best.candidate.log10
        if self._stage == "pixel":
            self._stage = "refine"
            n = sp.pixel_points
            self._px_step = (b[2, 1] - b[2, 0]) / max(n - 1, 1)
            xs = [np.array([x0[0], x0[1], p]) for p in np.linspace(b[2, 0], b[2, 1], n)] if n > 1 else []
            batch = self._new(xs)
            if batch:
                return batch
        if self._stage == "refine":
            while True:
                if self._step is None:  # the first compass round
                    if sp.refine_rounds == 0:
                        break
                    self._step = np.array([*self._coarse_step, self._px_step]) / 2
                    self._sizes = 1
                elif best.candidate == self._last_center:  # the last round did not improve
                    if self._sizes >= sp.refine_rounds:
                        break
                    self._step = self._step / 2
                    self._sizes += 1
                if self._polls >= sp.max_polls:
                    break
                self._polls += 1
                xs = []
                if self._last_center is not None and best.candidate != self._last_center:
                    # Hooke-Jeeves pattern move: the last round's move once more (walks
                    # along a ridge of correlated noises faster than the compass alone)
                    xs.append(2 * x0 - self._last_center.log10)
                self._last_center, self._last_step = best.candidate, self._step.copy()
                model = self._quadratic_proposal(x0, self._step)
                if model is not None:
                    xs.append(model)
                for d in range(3):
                    for sign in (-1.0, 1.0):
                        x = x0.copy()
                        x[d] += sign * self._step[d]
                        xs.append(x)
                batch = self._new(xs)
                if batch:
                    return batch
                # every poll point was run before: it cannot improve; next step size
            self._stage = "parabola"
        if self._stage == "parabola":
            self._stage = "done"
            if sp.parabola and best is not None and self._last_step is not None:
                x = self._quadratic_proposal(x0, self._last_step / 2)
                if x is None:
                    x = self._parabola(best.candidate, self._last_step)
                if x is not None:
                    return self._new([x])
        return []

    def _quadratic_proposal(self, x0: np.ndarray, step: np.ndarray) -> np.ndarray | None:
        """The maximum of a quadratic fitted (weighted least squares, log space scaled by
        ``step``) to the scores evaluated near ``x0``, at most two steps from ``x0``; None
        when there are too few points or the fit is not concave."""
        b = self.space.bounds_log10
        active = np.nonzero(b[:, 1] > b[:, 0])[0]
        k = active.size
        n_par = 1 + k + k * (k + 1) // 2
        pts = [(s.candidate.log10, s.objective) for s in self.scores.values() if math.isfinite(s.objective)]
        if len(pts) < n_par + 2:
            return None
        X = np.array([p[0] for p in pts])[:, active]
        y = np.array([p[1] for p in pts])
        d = (X - x0[active]) / step[active]
        r2 = np.sum(d * d, axis=1)
        near = r2 <= 9.0  # within three steps
        if np.count_nonzero(near) < n_par + 2:
            return None
        d, y, w = d[near], y[near], np.exp(-r2[near] / 8.0)
        iu = np.triu_indices(k)
        A = np.column_stack([np.ones(len(d)), d, (d[:, :, None] * d[:, None, :])[:, iu[0], iu[1]]])
        sw = np.sqrt(w)
        coef, *_ = np.linalg.lstsq(A * sw[:, None], y * sw, rcond=None)
        g = coef[1:1 + k]
        H = np.zeros((k, k))
        H[iu] = coef[1 + k:]
        H = H + H.T  # f = c + gᵀd + dᵀ U d with U upper triangular: Hessian U + Uᵀ
        if not np.all(np.linalg.eigvalsh(H) < 0):
            return None
        dstar = -np.linalg.solve(H, g)
        norm = float(np.linalg.norm(dstar))
        if norm > 2.0:
            dstar *= 2.0 / norm
        x = x0.copy()
        x[active] += dstar * step[active]
        return x

    def _parabola(self, center: Candidate, step: np.ndarray) -> np.ndarray | None:
        """Per noise, the vertex of the parabola through (−step, 0, +step) around
        ``center`` (log10), clipped to ±step; None when a point is missing."""
        x0 = center.log10
        f0 = self.scores.get(center)
        if f0 is None or not math.isfinite(f0.objective):
            return None
        x = x0.copy()
        for d in range(3):
            vals = []
            for sign in (-1.0, 1.0):
                xs = x0.copy()
                xs[d] += sign * step[d]
                s = self.scores.get(Candidate.from_log10(self._clip(xs)))
                vals.append(s.objective if s is not None else math.nan)
            fm, fp = vals
            if not (math.isfinite(fm) and math.isfinite(fp)):
                continue
            curv = fm + fp - 2 * f0.objective
            if curv < 0:  # a maximum
                x[d] = x0[d] + float(np.clip(0.5 * step[d] * (fm - fp) / curv, -step[d], step[d]))
        return x if np.any(np.abs(x - x0) > 1e-9) else None

    def history(self) -> list[TuneScore]:
        """Every score, in the order of the rounds."""
        return sorted(self.scores.values(), key=lambda s: s.round)

