"""``vislam tune``'s engine side: the noise search's rounds on a Dask cluster, and its outputs.

:func:`run_tune` drives :class:`vislam.core.tune.NoiseSearch`: the candidates of each
round are submitted together to the engine (:mod:`vislam.tools.cluster`: a LocalCluster,
a running scheduler, or this process), each a SLAM run scored by
:func:`vislam.core.tune.evaluate_candidate`; the scores decide the next round. Workers
load the dataset from its path (once per worker process) — on a cluster the file must be
visible under the same absolute path (see :mod:`vislam.tools.cluster`).

Outputs (:func:`write_tune_outputs`, all or nothing through
:class:`~vislam.tools.outputs.OutputStage`):

* ``tuned.yaml`` — an options file for ``vislam run --config``: the base options file's
  values (``--config``), if any, with the three tuned noises;
* ``tune.json`` — every evaluated candidate with its objective and counts, the chosen
  values, the run time, and ``vislam check``'s signal-based estimates of the same
  noises (:func:`vislam.core.check.estimate_white_noise`,
  :func:`~vislam.core.check.estimate_pixel_noise`) for comparison;
* ``tune.png`` — the objective against each searched noise.
"""

from __future__ import annotations

import functools
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import yaml

from vislam.core.options import FilterOptions
from vislam.core.sequence import Sequence
from vislam.core.tune import DEFAULT_NU, TUNED_FIELDS, Candidate, NoiseSearch, SearchSpace, TuneScore, \
    evaluate_candidate
from vislam.errors import ConfigError
from vislam.tools.jsonio import dumps, json_safe
from vislam.tools.outputs import OutputStage

__all__ = ["TUNED_YAML", "TUNE_JSON", "TUNE_PNG", "TuneResult", "run_tune", "check_estimates", "evaluate_source",
           "write_tune_outputs", "tuned_yaml_text", "plot_objective"]

logger = logging.getLogger(__name__)

TUNED_YAML = "tuned.yaml"
TUNE_JSON = "tune.json"
TUNE_PNG = "tune.png"


@functools.lru_cache(maxsize=2)
def _load(path: str) -> Sequence:
    """The dataset of ``path``, loaded once per (worker) process."""
    from vislam.tools.dataset_io import load_sequence

    return load_sequence(path)


def evaluate_source(source, candidate: Candidate, base: Mapping[str, Any], frames: int | None,
                    nu: float) -> TuneScore:
    """One task: score ``candidate`` on ``source`` (a dataset path, or a Sequence).
    ``base``: FilterOptions values besides the tuned ones. Any error of the run becomes
    the score's ``error`` (objective −inf), so a bad candidate never ends the search."""
    t0 = time.perf_counter()
    try:
        sequence = _load(str(source)) if isinstance(source, (str, Path)) else source
        options = FilterOptions.from_dict(dict(base), source="base options")
        return evaluate_candidate(sequence, candidate, options, frames=frames, nu=nu)
    except Exception as exc:  # noqa: BLE001 - recorded, not raised
        logger.debug("candidate %s failed", candidate, exc_info=True)
        return TuneScore(candidate, error=" ".join(f"{type(exc).__name__}: {exc}".split()),
                         seconds=time.perf_counter() - t0)


def check_estimates(sequence: Sequence) -> dict[str, Any]:
    """``vislam check``'s signal-based estimates of the tuned noises (no filter run):
    IMU white noise per axis (variogram nugget) and the tracks' pixel noise."""
    from vislam.core.check import estimate_pixel_noise, estimate_white_noise

    u = sequence.velocities()
    sv, sv_se = estimate_white_noise(u[:, :3])
    sw, sw_se = estimate_white_noise(u[:, 3:])
    pix = estimate_pixel_noise(sequence)
    return {"velocity_noise_mps": sv.tolist(), "velocity_noise_mps_se": sv_se.tolist(),
            "angular_noise_radps": sw.tolist(), "angular_noise_radps_se": sw_se.tolist(),
            "pixel_noise_px": pix.get("sigma_px"), "pixel_outlier_share": pix.get("outlier_share"),
            "method": "vislam.core.check: variogram nugget of the velocities per axis; pixel sigma from third "
                      "differences along tracks"}


def _check_scalar(check: Mapping[str, Any], name: str) -> float | None:
    """check's estimate of the noise ``name`` as one number (the RMS of its per-axis
    values), None when check has none."""
    est = check.get(name)
    if est is None:
        return None
    return float(np.sqrt(np.mean(np.square(est)))) if isinstance(est, list) else float(est)


@dataclass
class TuneResult:
    """What :func:`run_tune` found."""

    source: str
    best: TuneScore
    scores: list[TuneScore]
    rounds: int
    check: dict[str, Any]
    base: dict[str, Any]
    frames: int | None
    nu: float
    space: SearchSpace
    engine: str
    seconds: float
    notes: list[str] = field(default_factory=list)

    @property
    def tuned(self) -> dict[str, float]:
        return self.best.candidate.to_dict()

    def to_dict(self) -> dict[str, Any]:
        check = self.check
        ratio = {}
        for name in TUNED_FIELDS:
            est = _check_scalar(check, name)
            if est is None:
                continue
            ratio[name] = {"tune": self.tuned[name], "check": est,
                           "tune_over_check": self.tuned[name] / est if est > 0 else None}
        return {
            "source": self.source,
            "tuned": self.tuned,
            "objective": self.best.objective,
            "objective_definition": ("mean Student-t predictive log-density per observation of the SLAM filter's "
                                     f"innovations before gating (nu = {self.nu:g}); observations of rejected "
                                     "landmarks charged at the gate"),
            "frames": self.frames,
            "runs": len(self.scores),
            "rounds": self.rounds,
            "seconds": self.seconds,
            "run_seconds_total": float(sum(s.seconds for s in self.scores)),
            "engine": self.engine,
            "search_space": asdict(self.space),
            "base_options": self.base,
            "check_estimates": check,
            "comparison_with_check": ratio,
            "candidates": [s.to_dict() for s in self.scores],
            "notes": list(self.notes),
        }


def run_tune(source, engine=None, base: Mapping[str, Any] | None = None, frames: int | None = None,
             space: SearchSpace | None = None, nu: float = DEFAULT_NU,
             on_round: Callable[[int, list[TuneScore], TuneScore | None], None] | None = None,
             sequence: Sequence | None = None) -> TuneResult:
    """Search the noise of ``source`` (a dataset path; or pass ``sequence`` to tune an
    in-memory recording) on ``engine`` (default: this process). ``base``: other
    FilterOptions values (e.g. an options file's). ``on_round(i, scores, best)`` after
    each round. Raises ConfigError for bad settings; EstimationError when every
    candidate failed."""
    from vislam.errors import EstimationError
    from vislam.tools.cluster import SequentialEngine

    engine = engine or SequentialEngine()
    base = dict(base or {})
    for name in TUNED_FIELDS:
        base.pop(name, None)
    options = FilterOptions.from_dict(base, source="base options")
    if frames is not None and frames < 2:
        raise ConfigError(f"--frames must be >= 2, got {frames}")
    t0 = time.perf_counter()
    if sequence is None:
        sequence = _load(str(source))
    task_source = sequence if source is None else str(source)
    check = check_estimates(sequence)
    search = NoiseSearch(space, start_pixel_noise_px=FilterOptions().pixel_noise_px)
    i = 0
    futures: list = []
    try:
        while batch := search.next_round():
            futures = [engine.submit(evaluate_source, task_source, c, base, frames, nu) for c in batch]
            scores = [f.result() for f in futures]
            search.tell(scores)
            if on_round:
                on_round(i, scores, search.best)
            i += 1
    except BaseException:
        engine.cancel(futures)
        raise
    best = search.best
    scores = search.history()
    if best is None:
        from vislam.core.sequence import frame_times_not_seconds

        odd = frame_times_not_seconds(sequence.timestamps_s)
        hint = "" if odd is None or odd[1] is None else (
            f"; the recording's frames are {odd[0]:.4g} apart: with time stamps in {odd[1][1]}, add "
            f"timestamp_scale {odd[1][0]:g} to the base options (--config), or run `vislam check DATA`")
        raise EstimationError(f"{source}: every candidate failed; first error: "
                              f"{scores[0].error if scores else '?'}{hint}")
    notes = []
    for name, (lo, hi) in ((n, getattr(search.space, n)) for n in TUNED_FIELDS):
        value = best.candidate.to_dict()[name]
        if lo == hi:
            notes.append(f"{name} = {value:g} kept (not searched)")
        elif value <= lo * 1.0001 or value >= hi * 0.9999:
            notes.append(f"{name} = {value:g} is at the edge of the searched range [{lo:g}, {hi:g}]")
    notes += _systematic_error_notes(best.candidate.to_dict(), check, options)
    return TuneResult(str(source) if source is not None else sequence.name, best, scores, i, check,
                      options_dict(base), frames, nu, search.space, engine.name, time.perf_counter() - t0, notes)


#: tune's IMU noise this many times above both check's white-noise estimate and the
#: filter's default is reported (see _systematic_error_notes).
SYSTEMATIC_RATIO = 3.0


def _systematic_error_notes(tuned: Mapping[str, float], check: Mapping[str, Any], options: FilterOptions) -> list[str]:
    """Notes for IMU noises the likelihood puts far above the white noise the signal
    shows. The filter models the IMU error as white; slowly varying errors (bias, scale,
    the INS's own drift against the camera) also enter its one-step predictions, and the
    likelihood then buys them with white noise. On the shared sparse KITTI files
    (velocities 0.3 m/s RMS off the true motion, correlated over seconds, white part
    0.04 m/s: benchmarks/velocity_truth.py) the tuned 0.22 m/s makes SLAM worse
    (sparse 0027 ATE 1.92 -> 3.90 m)."""
    out = []
    for name, unit in (("velocity_noise_mps", "m/s"), ("angular_noise_radps", "rad/s")):
        white = _check_scalar(check, name)
        if white is None:
            continue
        default = float(np.max(getattr(options, name)))
        floor = max(white, default)
        if tuned[name] > SYSTEMATIC_RATIO * floor:
            out.append(f"{name} = {tuned[name]:.3g} {unit} is {tuned[name] / floor:.0f}x the white noise vislam "
                       f"check sees in the signal ({white:.3g} {unit}; filter default {default:.3g}): the "
                       f"innovations carry slowly varying errors (bias, scale, drift of the IMU against the "
                       f"camera) that a white-noise model buys with extra noise; the tuned value can make the "
                       f"estimate worse, compare it with the default on a drive with ground truth")
    return out


def options_dict(values: Mapping[str, Any]) -> dict[str, Any]:
    return json_safe(dict(values))


# ----------------------------------------------------------------------------- outputs


def tuned_yaml_text(result: TuneResult) -> str:
    """tuned.yaml: the base options with the tuned noise (comments say where it came from)."""
    b = result.best
    lines = [f"# vislam tune: noise for {result.source}, chosen without ground truth by the predictive",
             f"# likelihood of the SLAM filter's innovations ({len(result.scores)} runs; objective "
             f"{b.objective:.4f} per observation)",
             "# use with: vislam run DATA --config tuned.yaml"]
    body = {**result.base, **result.tuned}
    return "\n".join(lines) + "\n" + yaml.safe_dump(json_safe(body), sort_keys=False, default_flow_style=None)


def write_tune_outputs(result: TuneResult, out_dir, figure: bool = True) -> list[Path]:
    """tuned.yaml, tune.json and tune.png into ``out_dir``, all or nothing."""
    with OutputStage(out_dir) as stage:
        stage.path(TUNED_YAML).write_text(tuned_yaml_text(result), encoding="utf-8")
        stage.path(TUNE_JSON).write_text(dumps(result.to_dict()) + "\n", encoding="utf-8")
        if figure:
            plot_objective(result, stage.path(TUNE_PNG))
        return stage.commit(order=(TUNED_YAML, TUNE_JSON, TUNE_PNG), remove_stale=())


_LABELS = {"velocity_noise_mps": "velocity noise σ_v (m/s)", "angular_noise_radps": "angular noise σ_ω (rad/s)",
           "pixel_noise_px": "pixel noise σ_px (px)"}


def plot_objective(result: TuneResult, path) -> None:
    """One panel per tuned noise: the objective of every candidate against that noise
    (log axis; colour: search round), the chosen value, and check's estimate."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    ok = [s for s in result.scores if math.isfinite(s.objective)]
    fig = Figure(figsize=(13, 4.4), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 3, sharey=True)
    best = result.best
    obj = np.array([s.objective for s in ok])
    # the interesting part is near the top: far-off candidates are drawn at the bottom edge
    span = max(np.ptp(np.sort(obj)[-min(len(obj), 12):]) if len(obj) else 1.0, 1e-3)
    floor = best.objective - 4 * span
    rounds = np.array([s.round for s in ok])
    n_rounds = max(result.rounds, 1)
    colour = dict(cmap="viridis", vmin=0, vmax=max(n_rounds - 1, 1), s=22)
    points = None
    for ax, name in zip(axes, TUNED_FIELDS):
        x = np.array([s.candidate.to_dict()[name] for s in ok])
        y = np.maximum(obj, floor)
        clipped = obj < floor
        points = ax.scatter(x[~clipped], y[~clipped], c=rounds[~clipped], **colour)
        if np.any(clipped):
            ax.scatter(x[clipped], y[clipped], c=rounds[clipped], marker="v", **colour)
        ax.scatter([best.candidate.to_dict()[name]], [best.objective], marker="*", s=220, color="crimson",
                   zorder=5, label=f"chosen {best.candidate.to_dict()[name]:.3g}")
        est = _check_scalar(result.check, name)
        if est is not None and est > 0:
            ax.axvline(est, color="gray", ls="--", label=f"vislam check {est:.3g}")
        ax.set_xscale("log")
        lo, hi = getattr(result.space, name)
        ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0) if hi / lo < 30 else (1.0,)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel(_LABELS[name])
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    axes[0].set_ylabel("objective: mean predictive log-density per observation")
    if points is not None:
        fig.colorbar(points, ax=list(axes), label="search round", pad=0.01, aspect=30)
    fig.suptitle(f"vislam tune {Path(result.source).name}: {len(result.scores)} runs, "
                 f"{result.frames or 'all'} frames (▼: below the plotted range)", fontsize=10)
    fig.savefig(path, format="png", dpi=110)
