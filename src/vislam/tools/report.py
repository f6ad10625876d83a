"""The report's whole results section, regenerated in one call: :func:`generate_report`.

From a data folder laid out like the shared data (``sparse/*.npz``, ``dense/*.npz``,
``groundtruth/<stem>.txt`` — KITTI left-camera poses; any subset) it writes, all or
nothing, into the output directory:

* ``runs/<dataset>/`` — for every dataset, localization + mapping ("separately", the
  report's Figs 1–3), SLAM (Figs 4–6) and, with ``ReportSettings.smoother``, the
  sliding-window smoother and its batch refinement, with :mod:`vislam.tools.comparison`:
  the files of ``vislam run`` for each, the comparison figure, and metrics against the
  ground truth when ``groundtruth/`` has a file of the same stem (``frame="cam"``). Every
  dataset is checked first (``vislam check``, :func:`vislam.tools.auto.auto_check`, as
  ``--auto``) and runs with the check's suggestions: noise per axis, biases, conventions
  (none on a clean file: the defaults);
* ``runs/noise-<dataset>-<level>-<filter>/`` — the noise comparison (Figs 7–9) on the
  sparse datasets (EKF methods only): noise injected at each :class:`NoiseLevel`, with the
  filter left at the dataset's options and with the filter told the injected level
  (σ_filter = √(σ_dataset² + σ_added²) per axis);
* ``runs/simulator-<scene>/<variant>/`` — the moving-landmark failure (Figs 10–11) on the
  simulator: a drive with 10 % moving landmarks and 2 % outliers against the same drive
  with neither, SLAM with default options, without gating, with the robust preset and
  with the landmark motion model (the report's proposed fix), graded against the truth;
* ``figures/`` — the report-level figures (noise ATE bars, moving-landmark overviews);
  the run folders hold only the figures the report shows (every other output of each run
  is there: trajectories, map, metrics.json, summary.json);
* ``report.md`` (figures by relative path, tables in Markdown) and ``report.html`` (the
  same content, self-contained: inline CSS, figures embedded as data URIs).

:func:`generate_report` returns a :class:`ReportResult` (rows of the summary table,
figures, notes, time); ``log`` receives one line per step. Problems with one dataset or
ground-truth file become notes in the report; a folder with no usable dataset is a
:class:`~vislam.errors.DatasetError`.

The runs go to an ``engine`` (:mod:`vislam.tools.cluster`): by default they run in this
process, one after the other, each when its section needs it; with a Dask engine
(``vislam report`` starts a local cluster by default) every run is submitted up front: one
check per dataset, one task per comparison (the methods on one dataset and noise setting,
with its run folders and figure; it takes its options from the dataset's check) and per
simulated drive and SLAM variant, and the sections
take the results in the same order, so the tables and numbers are the same. The tasks
write their run folders into the output's staging directory themselves: workers on other
machines need the data folder and the output folder on a shared file system under the
same paths.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import logging
import math
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence as Seq

import numpy as np

from vislam.core.noise import NoiseSpec
from vislam.core.options import ROBUST_PRESET, FilterOptions
from vislam.core.results import RunResult
from vislam.errors import DatasetError, VislamError
from vislam.tools.auto import auto_check, auto_options, describe_suggestions
from vislam.tools.comparison import (
    COMPARISON_FIGURE,
    DEFAULT_METHODS,
    EKF_METHODS,
    ERROR_FIGURE_FILE,
    METHOD_LABELS,
    METHOD_SHORT,
    Comparison,
    dataset_record,
    describe_filter_noise,
    describe_noise,
    evaluate_run,
    ground_truth_pairs,
    load_run_ground_truth,
    run_comparison,
    stage_evaluation,
    write_comparison,
)
from vislam.tools.evaluation import MIN_COVERAGE
from vislam.tools.outputs import FIGURE, OutputStage, command_start_time, write_run_outputs
from vislam.tools.trajectory_io import TrajectoryFile

__all__ = [
    "NoiseLevel",
    "DEFAULT_NOISE_LEVELS",
    "SIMULATION_NOISE",
    "ReportSettings",
    "DatasetInput",
    "ReportRow",
    "ReportResult",
    "discover_datasets",
    "generate_report",
    "REPORT_MD",
    "REPORT_HTML",
]

logger = logging.getLogger(__name__)

REPORT_MD = "report.md"
REPORT_HTML = "report.html"
RUNS_DIR = "runs"
FIGURES_DIR = "figures"
KINDS = ("sparse", "dense")

#: IMU noise of the simulated drives of the moving-landmark section (and of the filter there).
SIMULATION_NOISE = {"velocity_noise_mps": 0.5, "angular_noise_radps": 0.05}


@dataclass(frozen=True)
class NoiseLevel:
    """Noise added in the noise comparison: white noise per axis and sample."""

    velocity_mps: float
    angular_radps: float
    pixel_px: float = 0.0

    def spec(self, seed: int) -> NoiseSpec:
        return NoiseSpec(velocity_noise_mps=self.velocity_mps, angular_noise_radps=self.angular_radps,
                         pixel_noise_px=self.pixel_px, seed=seed)

    def told(self, base: FilterOptions) -> FilterOptions:
        """``base`` with its noise model raised by this level: σ = √(σ_base² + σ_added²)
        (per axis when ``base`` has per-axis noise, e.g. from the check)."""

        def raised(value, added):
            if isinstance(value, (tuple, list)):
                return [math.hypot(v, added) for v in value]
            return math.hypot(value, added)

        return base.replace(
            velocity_noise_mps=raised(base.velocity_noise_mps, self.velocity_mps),
            angular_noise_radps=raised(base.angular_noise_radps, self.angular_radps),
            pixel_noise_px=math.hypot(base.pixel_noise_px, self.pixel_px))

    @property
    def slug(self) -> str:
        s = f"v{self.velocity_mps:g}-w{self.angular_radps:g}"
        return s + (f"-px{self.pixel_px:g}" if self.pixel_px else "")


#: The noise levels of the noise comparison; the last is the noise of the dense datasets.
DEFAULT_NOISE_LEVELS = (NoiseLevel(0.1, 0.002), NoiseLevel(0.3, 0.006), NoiseLevel(0.5, 0.05))


@dataclass(frozen=True)
class ReportSettings:
    """What :func:`generate_report` runs (defaults: the full report)."""

    #: Levels of the noise comparison (empty: no noise section).
    noise_levels: tuple[NoiseLevel, ...] = DEFAULT_NOISE_LEVELS
    #: Seed of the injected noise.
    noise_seed: int = 0
    #: Frames of the simulated drives of the moving-landmark section (0: no such section).
    simulation_frames: int = 600
    #: Seed of the simulated drives.
    simulation_seed: int = 0
    #: The sliding-window smoother and its batch refinement beside the EKF in section 1
    #: (about 4x SLAM's time per frame, plus the refinement).
    smoother: bool = True


# ----------------------------------------------------------------------------- inputs


@dataclass
class DatasetInput:
    """A dataset of the data folder and its ground truth (if any)."""

    kind: str
    path: Path
    sequence: Any = None
    ground_truth_path: Path | None = None
    ground_truth: TrajectoryFile | None = None
    #: The dataset's check (a future of :func:`_check_task`: the ``"auto"`` record).
    check: Any = None

    @property
    def stem(self) -> str:
        return self.path.stem

    @property
    def key(self) -> str:
        return f"{self.kind}-{self.stem}"

    @property
    def label(self) -> str:
        number = f"Dataset {int(self.stem)} " if self.stem.isdigit() else ""
        return f"{number}({self.kind} {self.stem})"

    @property
    def auto(self) -> dict[str, Any] | None:
        """The dataset's check record (suggestions, findings), or None before it is submitted."""
        return self.check.result() if self.check is not None else None

    @property
    def options(self) -> FilterOptions:
        """The options every run of this dataset starts from: the check's suggestions."""
        return _dataset_options(self.auto)

    def ground_truth_info(self) -> dict | None:
        if self.ground_truth is None:
            return None
        return {"path": str(self.ground_truth_path), "format": "kitti", "frame": "cam"}


def discover_datasets(data_dir) -> tuple[list[DatasetInput], list[str]]:
    """The datasets of ``data_dir`` (``sparse/*.npz``, ``dense/*.npz``), each with the
    ground-truth path ``groundtruth/<stem>.txt`` when it exists, and notes on what is
    missing. Nothing is loaded yet. Raises DatasetError when ``data_dir`` is not a
    directory."""
    data_dir = Path(data_dir)
    if not data_dir.exists():
        raise DatasetError(f"{data_dir}: no such data directory")
    if not data_dir.is_dir():
        raise DatasetError(f"{data_dir}: is not a directory (expected a folder with sparse/, dense/, groundtruth/)")
    notes = []
    found: list[DatasetInput] = []
    gt_dir = data_dir / "groundtruth"
    from vislam.tools.frontend_io import image_layout_of

    if image_layout_of(data_dir) is not None:  # the folder is one image recording (e.g. a KITTI raw drive)
        gt = next((p for p in (gt_dir / f"{data_dir.name}.txt", data_dir.parent / "groundtruth.kitti") if p.is_file()),
                  None)
        return [DatasetInput("images", data_dir, ground_truth_path=gt)], notes
    images = data_dir / "images"
    if images.is_dir():  # image folders (KITTI raw drives, EuRoC, plain), tracked first
        for p in sorted(q for q in images.iterdir() if q.is_dir() and image_layout_of(q) is not None):
            gt = gt_dir / f"{p.name}.txt"
            found.append(DatasetInput("images", p, ground_truth_path=gt if gt.is_file() else None))
    for kind in KINDS:
        folder = data_dir / kind
        if not folder.is_dir():
            notes.append(f"{folder}: not found; no {kind} datasets")
            continue
        files = sorted(p for p in folder.iterdir() if p.suffix.lower() == ".npz" and p.is_file())
        if not files:
            notes.append(f"{folder}: no .npz dataset in it")
        for p in files:
            gt = gt_dir / f"{p.stem}.txt"
            if gt.exists() and not gt.is_file():
                notes.append(f"{gt}: is not a file; no ground truth for {p}")
            found.append(DatasetInput(kind, p, ground_truth_path=gt if gt.is_file() else None))
    if not gt_dir.is_dir():
        notes.append(f"{gt_dir}: not found; no metrics against ground truth")
    else:
        stems = {d.stem for d in found}
        for p in sorted(gt_dir.glob("*.txt")):
            if p.stem not in stems:
                notes.append(f"{p}: no dataset named {p.stem}.npz; not used")
    return found, notes


# ----------------------------------------------------------------------------- results


@dataclass
class ReportRow:
    """One row of the summary table (one run)."""

    section: str
    dataset: str
    method: str
    added_noise: str
    filter_noise: str
    frames: int
    frames_processed: int
    landmarks: int | None
    landmarks_rejected: int | None
    ate_m: float | None
    kitti_t_pct: float | None
    kitti_r_deg_per_100m: float | None
    filter_seconds: float
    real_time_factor: float | None
    directory: str
    partial: bool = False
    error: str | None = None
    #: Median estimation time per frame (ms; refine: the smoother's frames).
    frame_ms_median: float | None = None
    #: Camera ground truth: ATE (m) and KITTI t (%) of the left-camera poses (the estimate
    #: as world_T_imu @ imu_T_cam with the calibration used, against the ground truth as it is).
    cam_ate_m: float | None = None
    cam_kitti_t_pct: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass
class ReportResult:
    """What :func:`generate_report` did."""

    out_dir: Path
    markdown_path: Path
    html_path: Path
    rows: list[ReportRow]
    figures: list[str]
    notes: list[str]
    datasets: list[str]
    seconds: float


def _finite(x) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def _row(section: str, dataset: str, method: str, result: RunResult, evaluation, added: str, filter_noise: str,
         directory: str) -> ReportRow:
    st = result.stats
    ts = np.asarray(result.timestamps_s)
    processed = float(ts[-1] - ts[0]) if ts.size > 1 else 0.0
    lm = result.landmarks
    seconds = st.filter_seconds + float((result.extra.get("timing") or {}).get("refine_seconds") or 0.0)
    fs = np.asarray(st.frame_seconds)
    camera = getattr(evaluation, "camera", None)
    return ReportRow(
        section, dataset, method, added, filter_noise, st.frames, st.frames_processed,
        len(lm) if lm is not None else None, int(np.count_nonzero(lm.status)) if lm is not None else None,
        _finite(evaluation.ape.rmse) if evaluation is not None else None,
        _finite(evaluation.kitti.t_pct) if evaluation is not None else None,
        _finite(evaluation.kitti.r_deg_per_100m) if evaluation is not None else None,
        seconds, seconds / processed if processed > 0 else None, directory,
        bool(result.partial), result.error, float(np.median(fs) * 1e3) if fs.size else None,
        _finite(camera.ape.rmse) if camera is not None else None,
        _finite(camera.kitti.t_pct) if camera is not None else None)


def slam_beats_separately(separate: "ReportRow", slam: "ReportRow") -> str:
    """Whether SLAM is better than localization and mapping separately, by ATE and by
    KITTI t (camera-frame metrics where the ground truth has them, else IMU-frame):
    ``"ATE yes, KITTI t no"``; ``"n/a"`` without ground truth."""
    parts = []
    for name, a, b in (("ATE", separate.cam_ate_m, slam.cam_ate_m), ("KITTI t", separate.cam_kitti_t_pct,
                                                                      slam.cam_kitti_t_pct)):
        if a is None or b is None:
            a, b = (separate.ate_m, slam.ate_m) if name == "ATE" else (separate.kitti_t_pct, slam.kitti_t_pct)
        if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)):
            continue
        parts.append(f"{name} {'yes' if b < a else 'no'}")
    return ", ".join(parts) if parts else "n/a"


def _comparison_rows(section: str, dataset: str, comparison: Comparison, directory: str) -> list[ReportRow]:
    added = describe_noise(comparison.noise, seed=False)
    return [_row(section, dataset, METHOD_SHORT[key], m.result, m.evaluation, added,
                 describe_filter_noise(comparison.options), f"{directory}/{key}")
            for key, m in comparison.methods.items()]


# ----------------------------------------------------------------------------- document


@dataclass
class _Doc:
    """A small document model rendered to both Markdown and HTML."""

    blocks: list[tuple] = field(default_factory=list)

    def h(self, level: int, text: str) -> None:
        self.blocks.append(("h", level, text))

    def p(self, text: str) -> None:
        self.blocks.append(("p", text))

    def items(self, items: Seq[str]) -> None:
        if items:
            self.blocks.append(("ul", list(items)))

    def table(self, header: Seq[str], rows: Seq[Seq[str]], align: str | None = None) -> None:
        self.blocks.append(("table", list(header), [list(r) for r in rows], align))

    def figures(self, figs: Seq[tuple[str, str]]) -> None:
        """Figures (relative path, caption) shown side by side in HTML."""
        if figs:
            self.blocks.append(("figs", list(figs)))


_INLINE = re.compile(r"`([^`]+)`|\*\*([^*]+)\*\*|\[([^\]]+)\]\(([^)]+)\)")


def _inline_html(text: str) -> str:
    out, pos = [], 0
    for m in _INLINE.finditer(text):
        out.append(html.escape(text[pos:m.start()]))
        if m.group(1) is not None:
            out.append(f"<code>{html.escape(m.group(1))}</code>")
        elif m.group(2) is not None:
            out.append(f"<strong>{html.escape(m.group(2))}</strong>")
        else:
            out.append(f'<a href="{html.escape(m.group(4), quote=True)}">{html.escape(m.group(3))}</a>')
        pos = m.end()
    out.append(html.escape(text[pos:]))
    return "".join(out)


def _md_cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _render_markdown(doc: _Doc) -> str:
    lines: list[str] = []
    for block in doc.blocks:
        kind = block[0]
        if kind == "h":
            lines += ["#" * block[1] + " " + block[2], ""]
        elif kind == "p":
            lines += [block[1], ""]
        elif kind == "ul":
            lines += [f"- {item}" for item in block[1]] + [""]
        elif kind == "table":
            _, header, rows, align = block
            align = align or "l" + "r" * (len(header) - 1)
            lines.append("| " + " | ".join(_md_cell(h) for h in header) + " |")
            lines.append("|" + "|".join("---:" if a == "r" else "---" for a in align) + "|")
            lines += ["| " + " | ".join(_md_cell(c) for c in row) + " |" for row in rows]
            lines.append("")
        elif kind == "figs":
            for path, caption in block[1]:
                lines += [f"![{caption}]({path})", "", f"*{caption}*", ""]
    return "\n".join(lines).rstrip() + "\n"


_CSS = """
body { font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; max-width: 1200px; margin: 2em auto;
       padding: 0 1em; color: #222; line-height: 1.45; }
h1 { border-bottom: 2px solid #ddd; padding-bottom: .3em; }
h2 { border-bottom: 1px solid #eee; padding-bottom: .2em; margin-top: 2em; }
table { border-collapse: collapse; margin: 1em 0; font-size: 0.88em; }
th, td { border: 1px solid #ccc; padding: .25em .6em; }
th { background: #f3f3f3; }
td.r { text-align: right; font-variant-numeric: tabular-nums; }
code { background: #f3f3f3; padding: 0 .2em; border-radius: 3px; }
.figs { display: flex; flex-wrap: wrap; gap: 1em; margin: 1em 0; }
figure { margin: 0; flex: 1 1 420px; max-width: 580px; }
figure img { width: 100%; border: 1px solid #eee; }
figcaption { font-size: 0.85em; color: #555; }
"""


def _render_html(doc: _Doc, title: str, image_root: Path) -> str:
    parts = ["<!DOCTYPE html>", '<html lang="en">', "<head>", '<meta charset="utf-8">',
             f"<title>{html.escape(title)}</title>", f"<style>{_CSS}</style>", "</head>", "<body>"]
    for block in doc.blocks:
        kind = block[0]
        if kind == "h":
            parts.append(f"<h{block[1]}>{_inline_html(block[2])}</h{block[1]}>")
        elif kind == "p":
            parts.append(f"<p>{_inline_html(block[1])}</p>")
        elif kind == "ul":
            parts.append("<ul>" + "".join(f"<li>{_inline_html(i)}</li>" for i in block[1]) + "</ul>")
        elif kind == "table":
            _, header, rows, align = block
            align = align or "l" + "r" * (len(header) - 1)
            parts.append("<table><thead><tr>" + "".join(f"<th>{_inline_html(h)}</th>" for h in header)
                         + "</tr></thead><tbody>")
            for row in rows:
                parts.append("<tr>" + "".join(f'<td class="{a}">{_inline_html(str(c))}</td>'
                                              for c, a in zip(row, align)) + "</tr>")
            parts.append("</tbody></table>")
        elif kind == "figs":
            parts.append('<div class="figs">')
            for path, caption in block[1]:
                data = base64.b64encode((image_root / path).read_bytes()).decode("ascii")
                parts.append(f'<figure><img src="data:image/png;base64,{data}" alt="{html.escape(caption, quote=True)}">'
                             f"<figcaption>{_inline_html(caption)} (<code>{html.escape(path)}</code>)</figcaption>"
                             "</figure>")
            parts.append("</div>")
    parts += ["</body>", "</html>"]
    return "\n".join(parts) + "\n"


# ----------------------------------------------------------------------------- formatting


def _n(x, spec: str) -> str:
    return "n/a" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, spec)


def _frames(row: ReportRow) -> str:
    return str(row.frames) if row.frames_processed == row.frames else f"{row.frames_processed} of {row.frames}"


def _landmarks(row: ReportRow) -> str:
    if row.landmarks is None:
        return "—"
    return f"{row.landmarks}" + (f" ({row.landmarks_rejected} rej.)" if row.landmarks_rejected else "")


SUMMARY_HEADER = ["Section", "Dataset", "Method", "Added noise", "Filter noise", "Frames", "Landmarks",
                  "Camera ATE (m)", "Camera KITTI t (%)", "IMU ATE (m)", "KITTI t (%)", "KITTI r (deg/100 m)",
                  "Filter time (s)", "RTF"]


def _summary_cells(row: ReportRow) -> list[str]:
    method = row.method + (" (partial)" if row.partial else "")
    return [row.section, row.dataset, method, row.added_noise, row.filter_noise, _frames(row), _landmarks(row),
            _n(row.cam_ate_m, ".2f"), _n(row.cam_kitti_t_pct, ".2f"),
            _n(row.ate_m, ".2f"), _n(row.kitti_t_pct, ".2f"), _n(row.kitti_r_deg_per_100m, ".3f"),
            _n(row.filter_seconds, ".2f"), _n(row.real_time_factor, ".2g")]


# ----------------------------------------------------------------------------- the report


class _Steps:
    """Numbered progress lines, one per step."""

    def __init__(self, total: int, log: Callable[[str], None] | None):
        self.total = total
        self.done = 0
        self.log = log
        self.t0 = time.perf_counter()

    def __call__(self, text: str) -> None:
        self.done += 1
        if self.log:
            elapsed = time.perf_counter() - self.t0
            self.log(f"[{self.done}/{self.total}] {text} ({elapsed:.0f} s)")


def _ate_text(comparison: Comparison) -> str:
    if comparison.ground_truth is None:
        return "no ground truth"
    return "ATE " + ", ".join(f"{METHOD_SHORT[k]} {_n(m.ate_m, '.2f')} m" for k, m in comparison.methods.items())


def _trajectory_figure_methods(methods) -> list[str]:
    """The methods whose trajectory figure section 1 shows: the refined run's figure shows
    the smoother's trajectories too, so the smoother's own only without refinement."""
    return [k for k in methods if not (k == "smoother" and "refine" in methods)]


def _dataset_run_figures(methods, has_ground_truth: bool) -> list[str]:
    """The run figures of a section-1 comparison that the report shows, as paths in its
    folder (:func:`write_comparison`'s ``run_figures``): the only ones drawn."""
    return [f"{k}/{FIGURE}" for k in _trajectory_figure_methods(methods)] + (
        [f"{k}/{ERROR_FIGURE_FILE}" for k in methods] if has_ground_truth else [])


def _method_figs(directory: str, comparison: Comparison, label: str) -> list[tuple[str, str]]:
    captions = {"separate": "IMU localization + landmark mapping (separately)", "slam": "visual-inertial SLAM",
                "smoother": "sliding-window smoother (online and final estimates)",
                "refine": "smoother with batch refinement (online, smoothed and refined)"}
    return [(f"{directory}/{k}/{FIGURE}", f"{label}: {captions[k]}")
            for k in _trajectory_figure_methods(comparison.methods)]


def _error_figs(directory: str, comparison: Comparison, label: str) -> list[tuple[str, str]]:
    if comparison.ground_truth is None:
        return []
    return [(f"{directory}/{key}/{ERROR_FIGURE_FILE}", f"{label}: error of {METHOD_LABELS[key]} against ground truth")
            for key in comparison.methods]


def generate_report(data_dir, out_dir, settings: ReportSettings | None = None,
                    log: Callable[[str], None] | None = None, start_time: float | None = None,
                    engine=None) -> ReportResult:
    """Run every experiment of the report's results section on the datasets of
    ``data_dir`` and write the report into ``out_dir`` (all or nothing; see the module
    docstring). ``log`` gets one line per step. ``engine`` runs the experiments
    (:mod:`vislam.tools.cluster`; default: this process, sequentially). Returns a
    :class:`ReportResult`.

    Raises DatasetError when ``data_dir`` holds no usable dataset, OutputError when
    ``out_dir`` cannot be written."""
    settings = settings or ReportSettings()
    t_start = time.perf_counter()
    data_dir, out_dir = Path(data_dir), Path(out_dir)
    inputs, notes = discover_datasets(data_dir)
    if not inputs:
        raise DatasetError(f"{data_dir}: no usable dataset: expected .npz files in {data_dir / 'sparse'} and/or "
                           f"{data_dir / 'dense'} (the layout of the shared data), image folders in "
                           f"{data_dir / 'images'}, or an image folder itself (docs/frontend.md)")
    usable = _load_inputs(inputs, notes, cache_dir=out_dir / "tracks")
    if not usable:
        raise DatasetError(f"{data_dir}: no usable dataset ({'; '.join(n for n in notes if n.startswith('skipped'))})")
    n_sparse = sum(d.kind == "sparse" for d in usable)
    total = (1 + len(usable) + n_sparse * 2 * len(settings.noise_levels) + (4 if settings.simulation_frames else 0)
             + 1)
    step = _Steps(total, log)
    step(f"loaded {len(usable)} dataset(s), {sum(d.ground_truth is not None for d in usable)} with ground truth")

    from vislam.tools.cluster import SequentialEngine

    engine = engine or SequentialEngine()
    with OutputStage(out_dir) as stage:
        report = _ReportBuilder(stage.staging, settings, start_time or command_start_time() or time.time(), step,
                                notes, engine)
        try:
            report.submit_all(usable)
            report.header()
            report.data_section(usable)
            report.datasets_section(usable)
            report.noise_section([d for d in usable if d.kind == "sparse"])
            report.moving_section()
            report.summary_section()
        except BaseException:
            engine.cancel(report.pending.values())
            raise
        seconds = time.perf_counter() - t_start
        report.doc.blocks.insert(1, ("p", (
            f"Generated by vislam {_version()} on {_dt.datetime.now().strftime('%Y-%m-%d %H:%M')} from "
            f"`{data_dir.resolve()}` in {seconds:.0f} s ({engine.name}): `{_command(data_dir, out_dir, settings)}`. "
            f"{len(report.rows)} runs; the per-run outputs (trajectories in TUM and KITTI format, maps as PLY and "
            f"npz, summary.json, metrics.json) are under `{RUNS_DIR}/`.")))
        (stage.staging / REPORT_MD).write_text(_render_markdown(report.doc), encoding="utf-8")
        (stage.staging / REPORT_HTML).write_text(_render_html(report.doc, "vislam report", stage.staging),
                                                 encoding="utf-8")
        stage.commit(order=(RUNS_DIR, FIGURES_DIR, REPORT_MD, REPORT_HTML), replace_directories=True)
    step(f"wrote {out_dir / REPORT_MD} and {out_dir / REPORT_HTML}")
    return ReportResult(out_dir, out_dir / REPORT_MD, out_dir / REPORT_HTML, report.rows, report.figures, notes,
                        [str(d.path) for d in usable], time.perf_counter() - t_start)


def _version() -> str:
    from vislam import __version__

    return __version__


def _command(data_dir: Path, out_dir: Path, settings: ReportSettings) -> str:
    """The command line that regenerates this report."""
    cmd = f"vislam report --data {data_dir} --out {out_dir}"
    if settings.noise_levels != DEFAULT_NOISE_LEVELS:
        cmd += " --noise-levels " + (",".join(f"{lv.velocity_mps:g}:{lv.angular_radps:g}"
                                              + (f":{lv.pixel_px:g}" if lv.pixel_px else "")
                                              for lv in settings.noise_levels) or "none")
    if settings.simulation_frames != ReportSettings.simulation_frames:
        cmd += f" --sim-frames {settings.simulation_frames}"
    if not settings.smoother:
        cmd += " --no-smoother"
    return cmd


def _load_inputs(inputs: list[DatasetInput], notes: list[str], cache_dir: Path | None = None) -> list[DatasetInput]:
    """Load every dataset and its ground truth; problems become notes. Image folders are
    tracked first, their tracks cached in ``cache_dir/<name>/tracks.npz``."""
    from vislam.tools.dataset_io import load_sequence
    from vislam.tools.frontend_io import load_recording

    usable = []
    for d in inputs:
        try:
            if d.kind == "images":
                d.sequence, _ = load_recording(d.path, None if cache_dir is None else cache_dir / d.path.name)
            else:
                d.sequence = load_sequence(d.path)
        except VislamError as exc:
            notes.append(f"skipped {d.path}: {exc}")
            continue
        if d.ground_truth_path is not None:
            try:
                d.ground_truth = load_run_ground_truth(d.ground_truth_path, d.sequence, "kitti", "cam")
            except VislamError as exc:
                notes.append(f"ground truth {d.ground_truth_path} not used for {d.path}: {exc}")
            else:
                n = ground_truth_pairs(d.ground_truth, d.sequence)
                if n < MIN_COVERAGE * d.sequence.n_frames:
                    notes.append(f"ground truth {d.ground_truth_path} covers {n} of the {d.sequence.n_frames} frames "
                                 f"of {d.path}: its metrics are over those frames only")
        usable.append(d)
    return usable


def _noise_directory(d: DatasetInput, level: NoiseLevel, told: bool) -> str:
    return f"{RUNS_DIR}/noise-{d.key}-{level.slug}-filter-{'told' if told else 'default'}"


def _check_task(sequence) -> dict[str, Any]:
    """The check of one dataset (a task): :func:`auto_check`'s record; a check that fails
    gives no suggestions (the defaults) and says why under ``"error"``."""
    try:
        return auto_check(sequence)
    except VislamError as exc:
        return {"suggested": {}, "findings": [], "check_seconds": None, "error": str(exc)}


def _dataset_options(check: dict[str, Any] | None, told: NoiseLevel | None = None) -> FilterOptions:
    """The options of a dataset's runs: its check's suggestions (``--auto``), raised by
    ``told``'s injected noise when given."""
    options = auto_options(check)
    return told.told(options) if told is not None else options


def _comparison_task(sequence, ground_truth_path, ground_truth, ground_truth_info, dataset, check,
                     told: NoiseLevel | None, noise: NoiseSpec | None, directory: Path, start_time: float,
                     methods=EKF_METHODS, run_figures=None) -> Comparison:
    """One comparison of the report, run and written into ``directory`` (a task): the
    options from the dataset's ``check`` record (and ``told``), the check's data
    corrections applied (the camera ground truth converted with each run's calibration, the
    corrected cam_T_imu: :func:`vislam.tools.comparison.evaluate_run`). ``run_figures``:
    the method folders' figures to draw (:func:`write_comparison`)."""
    options = _dataset_options(check, told)
    if options.has_data_corrections:
        from vislam.core.corrections import apply_corrections

        sequence = apply_corrections(sequence, options)
    comparison = run_comparison(sequence, options, noise=noise, ground_truth=ground_truth,
                                ground_truth_info=ground_truth_info, dataset=dataset, methods=methods, auto=check)
    write_comparison(directory, comparison, start_time=start_time, run_figures=run_figures)
    return comparison


class _ReportBuilder:
    """Runs the experiments section by section into ``root`` (a staging directory) and
    collects the document, the summary rows and the figures."""

    def __init__(self, root: Path, settings: ReportSettings, start_time: float, step: _Steps, notes: list[str],
                 engine=None):
        from vislam.tools.cluster import SequentialEngine

        self.root = root.resolve()  # absolute: tasks may run in other processes
        self.settings = settings
        self.start_time = start_time
        self.step = step
        self.notes = notes
        self.doc = _Doc()
        self.rows: list[ReportRow] = []
        self.figures: list[str] = []
        self.engine = engine or SequentialEngine()
        #: Submitted runs not yet taken by their section: directory -> future.
        self.pending: dict[str, Any] = {}
        (root / FIGURES_DIR).mkdir()

    def _submit_comparison(self, d: DatasetInput, directory: str, told: NoiseLevel | None, noise: NoiseSpec | None,
                           priority: int = 0, methods=EKF_METHODS):
        """Submit one comparison. Its method folders get only the figures the report
        shows: section 1's (:func:`_dataset_run_figures`); none for the noise runs, which
        the report shows by their comparison.png alone."""
        if d.check is None:
            d.check = self.engine.submit(_check_task, d.sequence, priority=20)
        run_figures = _dataset_run_figures(methods, d.ground_truth is not None) if noise is None else ()
        return self.engine.submit(_comparison_task, d.sequence, d.ground_truth_path if d.ground_truth is not None
                                  else None, d.ground_truth, d.ground_truth_info(),
                                  dataset_record(d.sequence, d.path, d.label), d.check, told, noise,
                                  self.root / directory, self.start_time, methods, run_figures, priority=priority)

    @property
    def dataset_methods(self) -> tuple[str, ...]:
        """The methods of section 1: the EKF's, and the smoother's unless switched off."""
        return DEFAULT_METHODS if self.settings.smoother else EKF_METHODS

    def submit_all(self, usable: list[DatasetInput]) -> None:
        """Submit every run of the report to the engine, in the order the sections take
        them (the longest first where the engine honours priorities; each dataset's check
        before its runs); a sequential engine runs each only when its section asks for it."""
        for d in usable:
            d.check = self.engine.submit(_check_task, d.sequence, priority=20)
        for d in usable:
            self.pending[f"{RUNS_DIR}/{d.key}"] = self._submit_comparison(
                d, f"{RUNS_DIR}/{d.key}", None, None, priority=5 if d.kind == "dense" else 0,
                methods=self.dataset_methods)
        if self.settings.noise_levels:
            for d in usable:
                if d.kind != "sparse":
                    continue
                for level in self.settings.noise_levels:
                    spec = level.spec(self.settings.noise_seed)
                    for told in (False, True):
                        directory = _noise_directory(d, level, told)
                        self.pending[directory] = self._submit_comparison(d, directory, level if told else None,
                                                                          spec)
        if self.settings.simulation_frames:
            self.pending.update(_submit_moving(self.engine, self.root, self.settings, self.start_time))

    def add_figures(self, figs: list[tuple[str, str]]) -> None:
        self.figures.extend(p for p, _ in figs)
        self.doc.figures(figs)

    def compare(self, d: DatasetInput, directory: str, told: NoiseLevel | None, noise: NoiseSpec | None,
                what: str, methods=EKF_METHODS) -> Comparison | None:
        """Run and write one comparison; a failure becomes a note (and None)."""
        future = self.pending.pop(directory, None) or self._submit_comparison(d, directory, told, noise,
                                                                              methods=methods)
        try:
            comparison = future.result()
        except VislamError as exc:
            self.notes.append(f"{d.label}, {what}: failed: {exc}")
            self.step(f"{d.label}, {what}: FAILED: {exc}")
            return None
        self.step(f"{d.label}, {what}: {_ate_text(comparison)}")
        return comparison

    # ------------------------------------------------------------------ sections

    def header(self) -> None:
        self.doc.h(1, "Visual-inertial SLAM — results")

    def data_section(self, usable: list[DatasetInput]) -> None:
        doc = self.doc
        doc.h(2, "Data")
        rows = []
        for d in usable:
            s = d.sequence
            auto = d.auto
            if auto.get("error"):
                self.notes.append(f"{d.path}: vislam check failed ({auto['error']}); runs with the default options")
            warned = [f"{f['severity']} {f['code']}" for f in auto["findings"] if f["severity"] != "OK"]
            rows.append([f"{d.kind}/{d.path.name}", str(s.n_frames), f"{s.duration_s:.1f}", str(s.n_landmarks),
                         f"{s.observations.n_observations / max(s.n_frames, 1):.1f}",
                         d.ground_truth_path.name if d.ground_truth is not None else "—",
                         ", ".join(warned) or ("OK" if not auto.get("error") else "failed"),
                         describe_suggestions(auto), describe_filter_noise(d.options)])
        doc.table(["Dataset", "Frames", "Duration (s)", "Landmarks", "Obs./frame", "Ground truth", "vislam check",
                   "Applied (check's suggestions)", "Filter noise"], rows, "lrrrrllll")
        doc.p("Ground truth (`groundtruth/<stem>.txt`, KITTI format) holds left-camera poses. Camera ATE: the "
              "estimate turned into left-camera poses with the `cam_T_imu` its filter used (world_T_cam = "
              "world_T_imu · imu_T_cam, after every correction; each run's summary.json records it under "
              "`calibration`), against the ground truth as it is — no transform enters the comparison twice, so "
              "it does not depend on the lever arm being right. IMU ATE: the ground truth converted to the IMU "
              "with that same `cam_T_imu`, against the IMU estimate; a wrong lever arm turns every rotation error "
              "into a position error there. Both are the position RMSE after SE(3) Umeyama "
              "alignment (evo); KITTI t and r are the odometry benchmark's average translational (%) and rotational "
              "(deg/100 m) drift over 100–800 m segments. Every dataset is checked first (`vislam check`, as "
              "`vislam run --auto`): its runs use the check's suggestions — IMU noise per axis, gyro bias, "
              "IMU–camera rotation, velocity association, time offset, where the data asks for them — and the "
              "defaults otherwise. The dense datasets' velocities carry white noise of about 0.5 m/s and "
              "0.05 rad/s per axis and sample, which the check measures (earlier reports set 0.5 m/s and "
              "0.05 rad/s for files under dense/ by hand).")

    def datasets_section(self, usable: list[DatasetInput]) -> None:
        doc = self.doc
        smoother = "smoother" in self.dataset_methods
        doc.h(2, "1. Localization and mapping separately, and SLAM (Figs 1–6)" + (
            "; the smoother beside them" if smoother else ""))
        doc.p("For every dataset: IMU localization by EKF prediction, then landmark mapping by EKF update on that "
              "trajectory (\"separately\", Part A of the report), and visual-inertial SLAM (Part B)"
              + (", and beyond the report the sliding-window smoother on GTSAM over the same measurements "
                 "(`vislam run --mode smoother`) and its batch Levenberg–Marquardt refinement (`--refine`; one "
                 "smoother run serves both rows)" if smoother else "")
              + ". Each run's files are in the folder named in the table; time is estimation only (refined: "
              "smoother + refinement), ms/frame its median per frame.")
        for d in usable:
            directory = f"{RUNS_DIR}/{d.key}"
            comparison = self.compare(d, directory, None, None, " + ".join(METHOD_SHORT[k] for k in
                                                                            self.dataset_methods),
                                      methods=self.dataset_methods)
            if comparison is None:
                continue
            new = _comparison_rows("datasets", d.label, comparison, directory)
            self.rows += new
            doc.h(3, d.label)
            doc.p(f"Options from `vislam check`: {describe_suggestions(d.auto)}; filter noise "
                  f"{describe_filter_noise(d.options)}.")
            doc.table(["Method", "Frames", "Landmarks", "Camera ATE (m)", "Camera KITTI t (%)", "IMU ATE (m)",
                       "KITTI t (%)", "KITTI r (deg/100 m)", "Time (s)", "ms/frame", "RTF", "Folder"],
                      [[r.method, _frames(r), _landmarks(r), _n(r.cam_ate_m, ".2f"), _n(r.cam_kitti_t_pct, ".2f"),
                        _n(r.ate_m, ".2f"), _n(r.kitti_t_pct, ".2f"),
                        _n(r.kitti_r_deg_per_100m, ".3f"), _n(r.filter_seconds, ".2f"), _n(r.frame_ms_median, ".2f"),
                        _n(r.real_time_factor, ".2g"), f"`{r.directory}/`"] for r in new], "lrrrrrrrrrrl")
            self.add_figures(_method_figs(directory, comparison, d.label))
            self.add_figures([(f"{directory}/{COMPARISON_FIGURE}", f"{d.label}: every method"
                               + (" and the ground truth" if d.ground_truth is not None else ""))]
                             + _error_figs(directory, comparison, d.label))

    def noise_section(self, sparse: list[DatasetInput]) -> None:
        doc, settings = self.doc, self.settings
        doc.h(2, "2. Performance with artificially increased noise (Figs 7–9)")
        if not settings.noise_levels:
            doc.p("No noise levels requested: section skipped.")
            return
        if not sparse:
            doc.p("No sparse dataset: section skipped.")
            self.notes.append("noise comparison skipped: no sparse dataset")
            return
        levels = "; ".join(describe_noise(lv.spec(settings.noise_seed), seed=False) for lv in settings.noise_levels)
        doc.p(f"White Gaussian noise is added to every velocity sample of the sparse datasets ({levels}; per axis "
              f"and sample, seed {settings.noise_seed}). Each level runs twice: with the dataset's own noise "
              f"model (the check's suggestion for the clean file; the defaults, {describe_filter_noise(FilterOptions())}, "
              "where it suggests none), which trusts the now noisy IMU, and with the filter told the injected level "
              "(σ = √(σ_dataset² + σ_added²) per axis), so that SLAM can lean on the cameras. "
              "\"Separately\" is the same in both: dead reckoning does not depend on the noise model.")
        panels = []
        for d in sparse:
            table, figs = [], []
            baseline = {r.method: r for r in self.rows if r.section == "datasets" and r.dataset == d.label}
            sep0, slam0 = baseline.get(METHOD_SHORT["separate"]), baseline.get(METHOD_SHORT["slam"])
            bars = [("no added noise", sep0.ate_m, slam0.ate_m)] if sep0 and slam0 else []
            for level in settings.noise_levels:
                spec = level.spec(settings.noise_seed)
                added = describe_noise(spec, seed=False)
                for told in (False, True):
                    options = _dataset_options(d.auto, level if told else None)
                    tag = "told" if told else "default"
                    directory = _noise_directory(d, level, told)
                    comparison = self.compare(d, directory, level if told else None, spec,
                                              f"noise {level.slug}, filter {tag}")
                    if comparison is None:
                        continue
                    sep, slam = new = _comparison_rows("noise", d.label, comparison, directory)
                    self.rows += new
                    bars.append((added.replace(", ", "\n") + f"\nfilter {tag}", sep.ate_m, slam.ate_m))
                    table.append([added, f"{tag}: {describe_filter_noise(options)}", _n(sep.cam_ate_m, ".2f"),
                                  _n(slam.cam_ate_m, ".2f"), _n(sep.ate_m, ".2f"),
                                  _n(slam.ate_m, ".2f"), _n(sep.kitti_t_pct, ".2f"), _n(slam.kitti_t_pct, ".2f"),
                                  slam_beats_separately(sep, slam), _landmarks(sep), _landmarks(slam),
                                  f"`{directory}/`"])
                    figs.append((f"{directory}/{COMPARISON_FIGURE}", f"{d.label}, added noise {added}, filter "
                                 f"{'told the added noise' if told else 'at its defaults'}"))
            doc.h(3, d.label)
            if table:
                doc.table(["Added noise", "Filter noise", "Camera ATE separately (m)", "Camera ATE SLAM (m)",
                           "IMU ATE separately (m)", "IMU ATE SLAM (m)",
                           "KITTI t separately (%)", "KITTI t SLAM (%)", "SLAM better?", "Landmarks separately",
                           "Landmarks SLAM", "Folder"], table, "llrrrrrrlrrl")
            self.add_figures(figs)
            if d.ground_truth is not None and bars:
                panels.append((d.label, [b[0] for b in bars], {"separate": [b[1] for b in bars],
                                                              "slam": [b[2] for b in bars]}))
        if panels:
            from vislam.tools.plotting import plot_grouped_bars

            name = "noise_ate.png"
            plot_grouped_bars(self.root / FIGURES_DIR / name, panels,
                              series=[("separate", METHOD_LABELS["separate"], "tab:orange"),
                                      ("slam", METHOD_LABELS["slam"], "tab:blue")],
                              ylabel="ATE (m)", title="ATE with artificially increased IMU noise")
            doc.h(3, "ATE against the added noise")
            self.add_figures([(f"{FIGURES_DIR}/{name}", "ATE of both methods against the added noise (datasets "
                               "with ground truth), with the filter at its defaults and told the added noise")])

    def moving_section(self) -> None:
        self.doc.h(2, "3. Moving landmarks: the failure case and the proposed fix (Figs 10–11)")
        if not self.settings.simulation_frames:
            self.doc.p("Simulation not requested: section skipped.")
            return
        rows, blocks = _moving_landmarks(self.root, self.settings, self.start_time, self.step, self.engine,
                                         self.pending)
        self.rows += rows
        for block in blocks:
            self.doc.blocks.append(block)
            if block[0] == "figs":
                self.figures.extend(p for p, _ in block[1])

    def summary_section(self) -> None:
        doc = self.doc
        doc.h(2, "4. Summary")
        doc.p("Every run of this report. Camera ATE / IMU ATE: RMSE of the left-camera / IMU position after SE(3) "
              "alignment (m; see Data); Camera KITTI t: the KITTI metric of the camera poses; KITTI t/r (IMU frame): "
              "average translational (%) and rotational (deg/100 m) drift over 100–800 m segments; n/a without "
              "ground truth. Filter time: estimation only (\"separately\" includes the localization); RTF: filter "
              "time / recording duration (< 1 is faster than real time).")
        doc.table(SUMMARY_HEADER, [_summary_cells(r) for r in self.rows], "lllllrrrrrrrrr")
        if self.notes:
            doc.h(2, "Notes")
            doc.items(self.notes)


# ----------------------------------------------------------------------------- pieces


#: The SLAM variants of the moving-landmark section: (key, label, FilterOptions changes, colour).
MOVING_VARIANTS = (
    ("default", "SLAM, default options", {}, "tab:blue"),
    ("no-gating", "SLAM without gating", {"gating_probability": None, "drift_test_probability": None}, "tab:red"),
    ("robust", "SLAM, robust preset", dict(ROBUST_PRESET), "tab:green"),
    ("motion-model", "SLAM with landmark motion model", {"landmark_motion": True}, "tab:purple"),
)


def _moving_scenes(settings: ReportSettings) -> dict[str, tuple[str, Any]]:
    """scene -> (label, SimulationOptions) of the moving-landmark section."""
    from vislam.core.simulate import SimulationOptions

    n = settings.simulation_frames
    return {
        "static": ("static scene", SimulationOptions(seed=settings.simulation_seed, n_frames=n, **SIMULATION_NOISE)),
        "moving": ("10 % moving landmarks, 2 % outliers",
                   SimulationOptions(seed=settings.simulation_seed, n_frames=n, moving_fraction=0.1,
                                     outlier_fraction=0.02, **SIMULATION_NOISE)),
    }


def _moving_runs(base: FilterOptions) -> list[tuple[str, str, str, FilterOptions]]:
    """(key, label, mode, options) of the runs on each simulated drive."""
    return [("localization", "IMU localization", "localization", base)] + [
        (key, label, "slam", base.replace(**changes)) for key, label, changes, _ in MOVING_VARIANTS]


def _moving_dataset(scene: str, scene_label: str, drive, sim_options) -> dict[str, Any]:
    seq = drive.sequence
    return {"name": f"simulated-{scene}", "label": f"Simulated drive, {scene_label}", "path": None,
            "source": "simulator", "frames": seq.n_frames, "landmarks": seq.n_landmarks,
            "duration_s": seq.duration_s, "cam_T_imu": seq.cam_T_imu.tolist(),
            "simulation": sim_options.to_dict()}


def _simulate_task(sim_options):
    from vislam.core.simulate import simulate_drive

    return simulate_drive(sim_options)


def _moving_run_task(drive, scene: str, scene_label: str, sim_options, key: str, label: str, mode: str,
                     options: FilterOptions, directory: Path, start_time: float, figure: bool = True):
    """One run of the moving-landmark section on a simulated drive, graded against the
    truth and written into ``directory`` (a task), with its trajectory figure when
    ``figure`` (the report shows it) and no error figure. Returns (result, evaluation)."""
    from vislam.core.estimators import run as run_estimator

    seq = drive.sequence
    truth = TrajectoryFile(drive.world_T_imu, seq.timestamps_s, "tum", "simulator truth")
    truth_info = {"path": None, "format": "simulator", "frame": "imu"}
    dataset = _moving_dataset(scene, scene_label, drive, sim_options)
    result = run_estimator(seq, mode, options)
    evaluation = evaluate_run(result, truth, seq)
    with OutputStage(directory) as stage:
        extra = {"evaluation": stage_evaluation(stage.staging, evaluation, f"{dataset['label']} — {label} vs truth",
                                                ground_truth=truth_info, figure=False),
                 "variant": label}
        # short: the label is the figure's title (with the mode appended)
        short = f"Simulator, {'moving landmarks' if scene == 'moving' else 'static'}, {key.replace('-', ' ')}"
        write_run_outputs(stage, result, dataset={**dataset, "label": short},
                          duration_s=seq.duration_s, start_time=start_time, extra=extra, figure=figure)
    return result, evaluation


def _moving_variant_figures() -> dict[str, str]:
    """The run figures the moving-landmark section shows (the only ones its runs draw):
    path -> caption, the SLAM variants on the scene with moving landmarks."""
    return {f"{RUNS_DIR}/simulator-moving/{key}/{FIGURE}": f"Scene with moving landmarks: {label} (rejected "
            "landmarks as red crosses)" for key, label, _, _ in MOVING_VARIANTS}


def _submit_moving(engine, root: Path, settings: ReportSettings, start_time: float) -> dict[str, Any]:
    """Submit the simulations and runs of the moving-landmark section; returns
    ``{"simulator-<scene>": drive future, "<run directory>": (result, evaluation) future}``."""
    futures: dict[str, Any] = {}
    base = FilterOptions(**SIMULATION_NOISE)
    shown = _moving_variant_figures()
    for scene, (scene_label, sim_options) in _moving_scenes(settings).items():
        drive = futures[f"simulator-{scene}"] = engine.submit(_simulate_task, sim_options, priority=10)
        for key, label, mode, options in _moving_runs(base):
            directory = f"{RUNS_DIR}/simulator-{scene}/{key}"
            futures[directory] = engine.submit(_moving_run_task, drive, scene, scene_label, sim_options, key, label,
                                               mode, options, root / directory, start_time,
                                               f"{directory}/{FIGURE}" in shown, priority=5)
    return futures


def _moving_landmarks(root: Path, settings: ReportSettings, start_time: float, step, engine=None,
                      pending: dict[str, Any] | None = None) -> tuple[list, list]:
    """The moving-landmark section: simulated drives with and without moving landmarks,
    four SLAM variants on each, graded against the truth. Returns (rows, doc blocks).
    The runs are taken from ``pending`` (see :func:`_submit_moving`), submitted to
    ``engine`` (default: this process) when absent."""
    from vislam.tools.cluster import SequentialEngine

    doc = _Doc()
    rows: list[ReportRow] = []
    n = settings.simulation_frames
    scenes = _moving_scenes(settings)
    base = FilterOptions(**SIMULATION_NOISE)
    if pending is None or f"simulator-{next(iter(scenes))}" not in pending:
        pending = _submit_moving(engine or SequentialEngine(), Path(root).resolve(), settings, start_time)
    doc.p(f"The report blames its failures (Figs 10–11) on landmarks on moving vehicles, and proposes a prediction "
          f"step for the landmarks. The KITTI files have no ground truth for which points move, so this section "
          f"uses the simulator: a {n}-frame KITTI-like drive (seed {settings.simulation_seed}, IMU noise "
          f"{SIMULATION_NOISE['velocity_noise_mps']} m/s and {SIMULATION_NOISE['angular_noise_radps']} rad/s per "
          f"axis and sample, 0.5 px pixel noise) with 10 % of the landmarks on moving vehicles and 2 % gross "
          f"outlier observations, against the same drive with neither. SLAM runs with the filter told the IMU "
          f"noise ({describe_filter_noise(base)}) and: default options; no chi-square gating (the report's "
          f"filter); the robust preset ({', '.join(f'`{k}={v}`' for k, v in ROBUST_PRESET.items())}); and the "
          f"landmark motion model (`landmark_motion=True`, the report's proposed fix). A run that stops on a "
          f"numerical failure is shown as far as it got (partial).")
    results, drives, table = _moving_results(scenes, base, pending, rows, step)
    doc.table(["Scene", "Filter", "Frames", "Landmarks", "ATE (m)", "KITTI t (%)", "Filter time (s)", "Note",
               "Folder"], table, "llrrrrrll")
    doc.figures(_moving_figures(root / FIGURES_DIR, results, drives["moving"].world_T_imu, base, rows, step))
    doc.figures(list(_moving_variant_figures().items()))
    step("moving-landmark figures: the variants")
    return rows, doc.blocks


def _moving_results(scenes: dict, base: FilterOptions, pending: dict, rows: list, step):
    """The moving-landmark runs, taken from ``pending``: appends a row per run to
    ``rows``; returns (results by (scene, key), drives by scene, table rows)."""
    results: dict[tuple[str, str], RunResult] = {}
    drives = {}
    table = []
    for scene, (scene_label, sim_options) in scenes.items():
        drive = pending.pop(f"simulator-{scene}").result()
        drives[scene] = drive
        stats = drive.statistics()
        for key, label, mode, options in _moving_runs(base):
            directory = f"{RUNS_DIR}/simulator-{scene}/{key}"
            result, evaluation = pending.pop(directory).result()
            results[scene, key] = result
            row = _row("moving", f"simulator, {scene_label}", label, result, evaluation,
                       "none (simulated IMU noise 0.5 m/s, 0.05 rad/s)",
                       describe_filter_noise(options), directory)
            rows.append(row)
            table.append([scene_label, label, _frames(row), _landmarks(row), _n(row.ate_m, ".2f"),
                          _n(row.kitti_t_pct, ".2f"), _n(row.filter_seconds, ".2f"),
                          ("stopped: " + (result.error or "")) if result.partial else "", f"`{directory}/`"])
        step(f"simulator, {scene_label} ({stats.n_moving_landmarks} moving landmarks, {stats.n_outliers} outlier "
             f"observations): " + ", ".join(f"{r.method} ATE {_n(r.ate_m, '.2f')} m"
                                             + (" (partial)" if r.partial else "")
                                             for r in rows if r.dataset == f"simulator, {scene_label}"))
    return results, drives, table


def _moving_figures(figs_dir: Path, results: dict, truth: np.ndarray, base: FilterOptions, rows: list,
                    step) -> list:
    """The moving-landmark section's two comparison maps; returns their (path, caption)."""
    from vislam.tools.plotting import MapLayer, plot_comparison_map

    def label_of(scene, key, label):
        r = results[scene, key]
        return label + (f" (stopped at frame {r.stats.frames_processed})" if r.partial else "")

    # the failure (the report's Figs 10-11): the report's filter, without gating, on the
    # static and on the moving scene, with their maps
    path_a = figs_dir / "moving_failure.png"
    plot_comparison_map(path_a, [
        MapLayer(results["static", "no-gating"].world_T_imu, label_of("static", "no-gating", "static scene"),
                 "tab:blue", results["static", "no-gating"].landmarks, short="static scene"),
        MapLayer(results["moving", "no-gating"].world_T_imu,
                 label_of("moving", "no-gating", "scene with moving landmarks"), "tab:red",
                 results["moving", "no-gating"].landmarks, short="moving scene"),
    ], "Simulated drive: SLAM without gating (the report's filter)",
        f"filter {describe_filter_noise(base)}, no chi-square gate\nATE: static scene "
        f"{_ate(rows, 'static scene', 'SLAM without gating')}, with moving landmarks and outliers "
        f"{_ate(rows, 'moving', 'SLAM without gating')}",
        ground_truth=truth)
    step("moving-landmark figures: the failure")
    # every variant on the moving scene
    path_b = figs_dir / "moving_variants.png"
    layers = [MapLayer(results["moving", "localization"].world_T_imu, "IMU localization (dead reckoning)", "tab:orange",
                       linestyle="--", linewidth=1.3)]
    layers += [MapLayer(results["moving", key].world_T_imu, label_of("moving", key, label), color)
               for key, label, _, color in MOVING_VARIANTS]
    plot_comparison_map(path_b, layers, "Simulated drive with moving landmarks: SLAM variants",
                        "10 % moving landmarks, 2 % outlier observations\nATE: " + ", ".join(
                            f"{key} {_ate(rows, 'moving', label)}" for key, label, _, _ in MOVING_VARIANTS),
                        ground_truth=truth)
    return [(f"{FIGURES_DIR}/{path_a.name}", "SLAM without gating (the report's filter) on the static scene and on "
             "the scene with moving landmarks and outliers (landmarks of each in its colour)"),
            (f"{FIGURES_DIR}/{path_b.name}", "Every SLAM variant on the scene with moving landmarks, and IMU-only "
             "localization")]


def _ate(rows: list[ReportRow], scene: str, method: str) -> str:
    for r in rows:
        if scene in r.dataset and r.method == method:
            return "n/a" if r.ate_m is None else f"{r.ate_m:.2f} m"
    return "n/a"
