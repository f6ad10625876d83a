"""Monte Carlo consistency of the filter (``vislam consistency``): NEES over simulator seeds.

One task per seed: simulate a drive (:func:`vislam.core.simulate.simulate_drive`) with
IMU and pixel noise, run the filter over it (:func:`vislam.core.consistency.filter_nees`)
and return its per-frame pose and landmark NEES. The tasks run on the batch engine of
:mod:`vislam.tools.cluster` (a local Dask cluster by default, any scheduler by address,
or in this process); the client averages the runs frame by frame and compares with the
95 % chi-square band of the average of N runs, ``chi2.ppf([0.025, 0.975], N·dof)/N``.

By default the filter is told the simulator's true noise
(:func:`vislam.core.consistency.true_noise_options`); ``filter_noise="default"`` runs
it with the options given (FilterOptions defaults unless a config says otherwise).

Outputs (:func:`write_consistency`, all or nothing): ``consistency.json`` and
``consistency.png`` (NEES over time on a log scale, bands shaded).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vislam.core.options import FilterOptions
from vislam.errors import ConfigError, EstimationError

__all__ = ["ConsistencySettings", "ConsistencyResult", "run_consistency", "write_consistency", "consistency_task",
           "FILTER_NOISE_CHOICES", "JSON_FILE", "FIGURE_FILE"]

logger = logging.getLogger(__name__)

FILTER_NOISE_CHOICES = ("true", "default")
JSON_FILE = "consistency.json"
FIGURE_FILE = "consistency.png"


@dataclass(frozen=True)
class ConsistencySettings:
    """What to simulate and how to run the filter.

    The simulator's noise defaults are those of the dense KITTI files (0.5 m/s and
    0.05 rad/s of white noise per velocity sample and axis) with its own 0.5 px pixel
    noise."""

    runs: int = 20
    frames: int = 250
    first_seed: int = 0
    mode: str = "slam"
    filter_noise: str = "true"
    velocity_noise_mps: float = 0.5
    angular_noise_radps: float = 0.05
    pixel_noise_px: float = 0.5

    def __post_init__(self):
        if isinstance(self.runs, bool) or not isinstance(self.runs, int) or self.runs < 1:
            raise ConfigError(f"--runs must be an integer >= 1, got {self.runs!r}")
        if isinstance(self.frames, bool) or not isinstance(self.frames, int) or self.frames < 10:
            raise ConfigError(f"--frames must be an integer >= 10, got {self.frames!r}")
        from vislam.core.simulate import check_simulation_memory

        check_simulation_memory(self.frames, "--frames")  # per run; say it before any worker starts
        if self.first_seed < 0:
            raise ConfigError(f"--first-seed must be >= 0, got {self.first_seed!r}")
        if self.filter_noise not in FILTER_NOISE_CHOICES:
            raise ConfigError(f"--filter-noise must be one of {', '.join(FILTER_NOISE_CHOICES)}, "
                              f"got {self.filter_noise!r}")
        from vislam.core.consistency import CONSISTENCY_MODES

        if self.mode not in CONSISTENCY_MODES:
            raise ConfigError(f"--mode must be one of {', '.join(CONSISTENCY_MODES)}, got {self.mode!r}")
        from vislam.core.options import MAX_STD, MIN_PIXEL_STD

        flags = {"velocity_noise_mps": "--sim-velocity-noise", "angular_noise_radps": "--sim-angular-noise",
                 "pixel_noise_px": "--sim-pixel-noise"}
        for name, flag in flags.items():
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0 or value > MAX_STD:
                raise ConfigError(f"{flag} must be a finite number in [0, {MAX_STD:g}], got {value!r}")
        if self.pixel_noise_px < MIN_PIXEL_STD:  # the filter is told it (--filter-noise true): V = σ² I must be PD
            raise ConfigError(f"--sim-pixel-noise must be at least {MIN_PIXEL_STD:g} px, got {self.pixel_noise_px!r}")

    def simulation_options(self, seed: int):
        from vislam.core.simulate import SimulationOptions

        return SimulationOptions(seed=seed, n_frames=self.frames, velocity_noise_mps=self.velocity_noise_mps,
                                 angular_noise_radps=self.angular_noise_radps, pixel_noise_px=self.pixel_noise_px)


def consistency_task(settings: ConsistencySettings, seed: int, options: dict) -> dict:
    """One Monte Carlo run (a task on a worker): plain arrays, cheap to send back."""
    from vislam.core.consistency import filter_nees, true_noise_options
    from vislam.core.simulate import simulate_drive

    sim = settings.simulation_options(seed)
    opts = FilterOptions.from_dict(options)
    if settings.filter_noise == "true":
        opts = true_noise_options(sim, opts)
    tic = time.perf_counter()
    trace = filter_nees(simulate_drive(sim), opts, settings.mode)
    return {"seed": seed, "pose_nees": trace.pose_nees, "landmark_nees": trace.landmark_nees,
            "landmark_count": trace.landmark_count, "position_error_m": trace.position_error_m,
            "depth_bins_m": trace.depth_bins_m, "landmark_depth_nees": trace.landmark_depth_nees,
            "landmark_depth_count": trace.landmark_depth_count, "error": trace.error,
            "seconds": time.perf_counter() - tic, "options": opts.to_dict()}


@dataclass
class ConsistencyResult:
    """Frame-by-frame averages over the runs and their summary."""

    settings: ConsistencySettings
    seeds: list
    pose_nees: np.ndarray  # (T,) average over runs (NaN where no run has a value)
    landmark_nees: np.ndarray  # (T,)
    pose_band: tuple
    landmark_band: tuple
    per_run_pose_nees_mean: list
    per_run_landmark_nees_mean: list
    per_run_rms_position_error_m: list
    depth_bins_m: np.ndarray
    landmark_depth_nees: np.ndarray
    landmark_depth_count: np.ndarray
    options_told: dict
    errors: list = field(default_factory=list)
    seconds: float = 0.0
    engine: str = ""

    @staticmethod
    def _share_inside(values: np.ndarray, band) -> float:
        ok = np.isfinite(values)
        if not np.any(ok):
            return float("nan")
        v = values[ok]
        return float(np.mean((v >= band[0]) & (v <= band[1])))

    @property
    def pose_nees_mean(self) -> float:
        """Mean over frames (and runs) of the pose NEES (6 for a consistent filter)."""
        return float(np.nanmean(self.pose_nees)) if np.any(np.isfinite(self.pose_nees)) else float("nan")

    @property
    def landmark_nees_mean(self) -> float:
        v = self.landmark_nees
        return float(np.nanmean(v)) if np.any(np.isfinite(v)) else float("nan")

    @property
    def pose_share_inside_band(self) -> float:
        return self._share_inside(self.pose_nees, self.pose_band)

    @property
    def landmark_share_inside_band(self) -> float:
        return self._share_inside(self.landmark_nees, self.landmark_band)

    def to_dict(self) -> dict:
        s = self.settings
        told = self.options_told
        return {
            "pose_nees_mean": self.pose_nees_mean,
            "landmark_nees_mean": self.landmark_nees_mean,
            "pose_share_inside_band": self.pose_share_inside_band,
            "landmark_share_inside_band": self.landmark_share_inside_band,
            "pose_nees_median": float(np.nanmedian(self.pose_nees)) if np.any(np.isfinite(self.pose_nees))
            else float("nan"),
            "pose_band_95": list(self.pose_band),
            "landmark_band_95": list(self.landmark_band),
            "pose_dof": 6,
            "landmark_dof": 3,
            "runs": len(self.seeds),
            "frames": s.frames,
            "seeds": list(self.seeds),
            "mode": s.mode,
            "filter_noise": s.filter_noise,
            "simulator_noise": {"velocity_noise_mps": s.velocity_noise_mps,
                                "angular_noise_radps": s.angular_noise_radps, "pixel_noise_px": s.pixel_noise_px},
            "noise_told": {k: told.get(k) for k in ("velocity_noise_mps", "angular_noise_radps", "pixel_noise_px")},
            "landmark_parametrization": told.get("landmark_parametrization"),
            "ekf": told.get("ekf"),
            "per_run": [{"seed": seed, "pose_nees_mean": p, "landmark_nees_mean": lm, "rms_position_error_m": e}
                        for seed, p, lm, e in zip(self.seeds, self.per_run_pose_nees_mean,
                                                  self.per_run_landmark_nees_mean,
                                                  self.per_run_rms_position_error_m)],
            "landmark_nees_by_depth": [{"depth_from_m": lo, "depth_to_m": hi, "nees_mean": n, "count": c}
                                       for lo, hi, n, c in zip(self.depth_bins_m[:-1], self.depth_bins_m[1:],
                                                               self.landmark_depth_nees, self.landmark_depth_count)],
            "pose_nees_per_frame": self.pose_nees,
            "landmark_nees_per_frame": self.landmark_nees,
            "errors": self.errors,
            "seconds": self.seconds,
            "engine": self.engine,
            "definitions": "pose NEES: d^T P^-1 d with d = log(imu_T_world_true imu_T_world_est^-1) (left "
                           "perturbation of the inverse pose, (v, w) order), 6 dof; landmark NEES: per frame the "
                           "mean over the landmarks in the state of e^T P^-1 e (e = p_true - p_est, P the marginal "
                           "position covariance), 3 dof; both averaged over runs frame by frame; band: "
                           "chi2.ppf([0.025, 0.975], N dof) / N for N runs; the means are over frames 1..T-1.",
        }


def _nanmean_rows(a: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        n = np.sum(np.isfinite(a), axis=0)
        s = np.nansum(a, axis=0)
        return np.where(n > 0, s / np.maximum(n, 1), np.nan)


def run_consistency(settings: ConsistencySettings, engine, options: FilterOptions | None = None,
                    on_run=None) -> ConsistencyResult:
    """Run the Monte Carlo on ``engine`` (see :func:`vislam.tools.cluster.open_engine`);
    ``on_run(seed, done, total)`` is called as runs finish. A run whose filter failed
    counts with the frames it finished (its error is listed); a task that raised is an
    EstimationError for the whole command (a bug, not a statistic)."""
    from vislam.core.consistency import chi2_band

    options = options or FilterOptions()
    seeds = list(range(settings.first_seed, settings.first_seed + settings.runs))
    tic = time.perf_counter()
    futures = {engine.submit(consistency_task, settings, seed, options.to_dict()): seed for seed in seeds}
    results = {}
    try:
        for fut in engine.as_completed(list(futures)):
            seed = futures[fut]
            try:
                results[seed] = fut.result()
            except Exception as exc:
                raise EstimationError(f"consistency run of seed {seed} failed: "
                                      f"{type(exc).__name__}: {' '.join(str(exc).split())}") from exc
            if on_run is not None:
                on_run(seed, len(results), len(seeds))
    except BaseException:
        engine.cancel(list(futures))
        raise
    rows = [results[s] for s in seeds]
    pose = np.array([r["pose_nees"] for r in rows])
    lm = np.array([r["landmark_nees"] for r in rows])
    # the first frame's pose is known exactly (no NEES); pad nothing else
    pose_mean = _nanmean_rows(pose)
    lm_mean = _nanmean_rows(lm)
    n = len(seeds)
    depth_n = np.sum([r["landmark_depth_count"] for r in rows], axis=0)
    depth_sum = np.sum([np.nan_to_num(r["landmark_depth_nees"]) * r["landmark_depth_count"] for r in rows], axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        depth_nees = np.where(depth_n > 0, depth_sum / np.maximum(depth_n, 1), np.nan)

    def mean_or_nan(a):
        return float(np.nanmean(a)) if np.any(np.isfinite(a)) else float("nan")

    return ConsistencyResult(
        settings=settings, seeds=seeds, pose_nees=pose_mean, landmark_nees=lm_mean,
        pose_band=chi2_band(n, 6), landmark_band=chi2_band(n, 3),
        per_run_pose_nees_mean=[mean_or_nan(r["pose_nees"]) for r in rows],
        per_run_landmark_nees_mean=[mean_or_nan(r["landmark_nees"]) for r in rows],
        per_run_rms_position_error_m=[float(np.sqrt(np.nanmean(r["position_error_m"] ** 2)))
                                      if np.any(np.isfinite(r["position_error_m"])) else float("nan") for r in rows],
        depth_bins_m=np.asarray(rows[0]["depth_bins_m"]), landmark_depth_nees=depth_nees,
        landmark_depth_count=depth_n, options_told=rows[0]["options"],
        errors=[f"seed {r['seed']}: {r['error']}" for r in rows if r["error"]],
        seconds=time.perf_counter() - tic, engine=getattr(engine, "name", ""))


def plot_consistency(path, result: ConsistencyResult) -> None:
    """NEES over time (log y) with the 95 % bands shaded: pose (6 dof) and landmarks (3 dof)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = result.settings
    t = np.arange(result.pose_nees.size) / 10.0  # the simulator runs at 10 Hz
    series = [(result.pose_nees, result.pose_band, 6, "pose NEES (6 dof)", "tab:blue"),
              (result.landmark_nees, result.landmark_band, 3, "landmark NEES (3 dof, mean over landmarks in the "
               "state)", "tab:green")]
    series = [p for p in series if np.any(np.isfinite(p[0]))] or series[:1]  # localization: no landmarks
    fig, axes = plt.subplots(len(series), 1, figsize=(9, 3.5 * len(series) + 0.5), sharex=True,
                             constrained_layout=True, squeeze=False)
    axes = axes[:, 0]
    panels = [(ax, *p) for ax, p in zip(axes, series)]
    n = len(result.seeds)
    for ax, values, band, dof, label, color in panels:
        ok = np.isfinite(values) & (values > 0)
        ax.axhspan(band[0], band[1], color="0.85", label=f"95 % band of the mean of {n} runs "
                   f"[{band[0]:.2f}, {band[1]:.2f}]")
        ax.axhline(dof, color="k", lw=0.8, ls="--", label=f"ideal ({dof})")
        if np.any(ok):
            ax.plot(t[ok], values[ok], color=color, lw=1.2,
                    label=f"{label}, mean over runs (overall {np.nanmean(values):.2f})")
            lo = min(np.nanmin(values[ok]), band[0]) / 1.5
            hi = max(np.nanmax(values[ok]), band[1]) * 1.5
            ax.set_ylim(lo, hi)
        ax.set_yscale("log")
        ax.set_ylabel("NEES (dimensionless)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(loc="upper left", fontsize=8)
    axes[-1].set_xlabel("time since the first frame (s)")
    told = result.options_told
    fig.suptitle(f"Filter consistency, {s.mode}, {n} simulated drives x {s.frames} frames; filter told "
                 f"{'the true noise' if s.filter_noise == 'true' else 'its own noise'}: "
                 f"{_fmt(told.get('velocity_noise_mps'))} m/s, {_fmt(told.get('angular_noise_radps'))} rad/s, "
                 f"{_fmt(told.get('pixel_noise_px'))} px; landmarks {told.get('landmark_parametrization')}",
                 fontsize=9)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _fmt(v) -> str:
    if isinstance(v, (list, tuple)):
        return "/".join(f"{x:g}" for x in v)
    return f"{v:g}" if isinstance(v, (int, float)) else str(v)


def write_consistency(result: ConsistencyResult, out_dir) -> list[Path]:
    """``consistency.json`` and ``consistency.png`` into ``out_dir`` (all or nothing)."""
    from vislam.tools.jsonio import dumps
    from vislam.tools.outputs import OutputStage

    with OutputStage(out_dir) as stage:
        stage.path(JSON_FILE).write_text(dumps(result.to_dict()) + "\n", encoding="utf-8")
        plot_consistency(stage.path(FIGURE_FILE), result)
        return stage.commit(order=(JSON_FILE, FIGURE_FILE), remove_stale=())
