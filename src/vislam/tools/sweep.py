"""Parameter sweeps: a grid of runs on a Dask cluster, one table of results.

A sweep SPEC (YAML or TOML) lists::

    datasets:                       # each: path, optional name, groundtruth, gt_format, gt_frame
      - path: ../shared/data/sparse/0020.npz
        groundtruth: ../shared/data/groundtruth/0020.txt
        gt_frame: auto                # the default: the format's convention (KITTI: left camera, TUM: IMU)
      - {path: ../shared/data/sparse/0042.npz}      # no ground truth: no ATE/KITTI columns
    modes: [slam, localization]     # default [slam]
    options:                        # named FilterOptions sets (default: {default: {}})
      default: {}
      loose: {velocity_noise_mps: 0.1, gating_probability: null}
      dense: dense.yaml             # or an options file (YAML/TOML), relative to the SPEC
      nested: {noise: {velocity_mps: 0.5}}   # groups of options, as in an options file
    noise:                          # named injected-noise settings (NoiseSpec fields, no seed)
      none: {}                      #   (default: {none: {}})
      imu: {velocity_noise_mps: 0.3, angular_noise_radps: 0.006}
    seeds: [0, 1]                   # seeds of the injected noise (default [0])

Relative paths are resolved against the SPEC's folder. Dataset names default to the
file stem (two datasets with the same stem need a ``name``). The grid is datasets x
modes x option sets x noise settings x seeds, one **cell** each (with ``none`` noise the
seed changes nothing: those cells repeat the same run). Every problem with the SPEC is a
one-line :class:`~vislam.errors.ConfigError` naming the SPEC file and the key.

One cell (:func:`run_cell`, engine-independent, no output files): load the dataset,
check the ground truth against it, inject the noise (:func:`vislam.core.noise.inject_noise`,
the ``--add-*`` flags of ``vislam run``), run the estimator, evaluate. A dataset's
``gt_format`` defaults to ``auto`` (the format the file's lines say: 12 values KITTI, 8 TUM),
``gt_frame`` to ``auto``, the format's convention as in ``vislam eval`` and
``vislam run --gt`` (KITTI: left-camera poses; TUM: IMU poses); the frame used is the
row's ``gt_frame``. Camera ground truth is converted with the ``cam_T_imu`` the cell's
filter used (an option set's ``cam_T_imu`` or rotation correction included), and also
evaluated in the camera frame (``cam_ate_m``, ``cam_kitti_*``). It returns a row
(a dict of :data:`COLUMNS`) and never raises for a problem of the cell: a bad path, a
mismatched ground truth, a filter failure or a bug become ``status = "error"`` with the
message in ``error``.

:func:`run_sweep` runs the cells on an engine (:mod:`vislam.tools.cluster`: a Dask
cluster, or in-process) and writes ``DIR/results.csv`` **incrementally**: the header
when the file is created (atomically), then one row per finished cell, appended and
flushed (``fsync``) as results arrive (``distributed.as_completed``). Resuming: a rerun
with the same ``--out`` reads ``results.csv`` and skips every cell whose key (dataset,
mode, options, noise, seed) already has a row with status ``ok`` or ``partial`` (a filter
that stops early does so again: a result, not an accident) computed from the same files
and settings (``dataset_path``, ``groundtruth_path``, ``options_values``,
``noise_values``: editing an option set in the SPEC reruns its cells); cells with status
``error`` are run again (their error may have been transient: a file not yet mounted on a worker, a
worker that died). A truncated last line (a sweep killed mid-write) is dropped. When every
cell has run, the file is rewritten once, atomically, with one row per cell in grid order
(the latest row of a cell wins; rows of cells not in this SPEC are kept after them), and
``DIR/summary.png`` shows the headline metric by option set and dataset with the spread
over seeds. Sweeps sharing an ``--out`` (at the same time, in several processes) merge:
every change of results.csv holds an ``flock`` on ``DIR/.results.csv.lock`` and opens
the file afresh, so no row of either is lost. The table is CSV only (plain, appendable, diffable; floats written with
``repr``, so they read back exactly); ``pandas.read_csv`` loads it in one line.

For clusters, see :mod:`vislam.tools.cluster`: workers must import the same vislam and
see the dataset paths (absolute, resolved by the client) under the same names.
"""

from __future__ import annotations

import contextlib
import csv
import datetime as _dt
import io
import json
import logging
import math
import os
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: no lock
    fcntl = None

from vislam.core.noise import NoiseSpec
from vislam.core.options import MODES, FilterOptions, flatten_options
from vislam.core.suggest import unknown_names_message
from vislam.errors import ConfigError, GroundTruthError, OutputError, VislamError
from vislam.tools.config import _one_line, read_config_document
from vislam.tools.trajectory_io import GT_FORMAT_CHOICES, GT_FRAME_CHOICES, default_gt_frame, resolve_gt_format

__all__ = ["SweepSpec", "DatasetEntry", "Cell", "COLUMNS", "KEY_COLUMNS", "RESULTS_FILE", "SUMMARY_FIGURE",
           "SweepResult", "load_spec", "parse_spec", "run_cell", "run_sweep", "read_results", "cell_key",
           "plot_summary", "rows_equal", "spec_summary", "RUN_INFO_COLUMNS", "DONE_STATUSES"]

logger = logging.getLogger(__name__)

RESULTS_FILE = "results.csv"
#: The lock file beside results.csv (see :func:`_locked`).
LOCK_FILE = ".results.csv.lock"
SUMMARY_FIGURE = "summary.png"

#: The key of a cell: a cell is done when results.csv has a row with this key and a done status.
KEY_COLUMNS = ("dataset", "mode", "options", "noise", "seed")
#: Statuses of a finished cell that a resumed sweep does not run again.
DONE_STATUSES = ("ok", "partial")
#: Columns of results.csv, in order.
COLUMNS = KEY_COLUMNS + (
    "status",                 # ok | partial (the filter stopped early; metrics on its frames) | error
    "error",                  # one-line message (error, or why a run is partial)
    "frames", "frames_processed",
    "gt_frame",               # body frame the ground truth was read as: cam (left camera) | imu; empty without
    "cam_ate_m",              # camera ground truth: SE(3)-aligned RMSE of the left-camera position (m), the
    "cam_kitti_t_pct", "cam_kitti_r_deg_per_100m",  # estimate as world_T_imu @ imu_T_cam (calibration used)
    "ate_m",                  # IMU frame: SE(3)-aligned position RMSE vs ground truth (m); empty without it
    "ape_unaligned_rmse_m",
    "kitti_t_pct", "kitti_r_deg_per_100m", "kitti_segments",
    "n_frames_compared",
    "nis_mean",               # mean normalized innovation squared, when the result carries it (else empty)
    "observations_used", "observations_gated",
    "landmarks_initialized", "landmarks_rejected", "landmarks_in_map",
    "filter_seconds",         # estimation only
    "cell_seconds",           # the whole cell on its worker: load, noise, run, evaluation
    "finished_at",            # UTC time the cell finished (ISO 8601)
    "worker",                 # host:pid of the process that ran the cell
    "dataset_path", "groundtruth_path",
    "options_values",         # the option set's fields (JSON), as given in the SPEC
    "noise_values",           # the noise setting's fields (JSON), as given in the SPEC
)
#: Columns that describe how/where/when a cell ran rather than what it computed.
RUN_INFO_COLUMNS = ("filter_seconds", "cell_seconds", "finished_at", "worker")

_SPEC_KEYS = ("datasets", "modes", "options", "noise", "seeds")
_DATASET_KEYS = ("path", "name", "groundtruth", "gt_format", "gt_frame")
_NOISE_FIELDS = tuple(f for f in NoiseSpec.__dataclass_fields__ if f != "seed")


# ----------------------------------------------------------------------------- the SPEC


@dataclass(frozen=True)
class DatasetEntry:
    name: str
    path: str
    groundtruth: str | None = None
    #: "auto" (from the file's values per line: 12 -> kitti, 8 -> tum), "kitti" or "tum".
    gt_format: str = "auto"
    #: "auto" (the format's convention: KITTI -> cam, TUM -> imu), "cam" or "imu".
    gt_frame: str = "auto"

    @property
    def resolved_gt_format(self) -> str:
        """The ground truth's format: ``gt_format``, or the file's for "auto"."""
        return resolve_gt_format(self.groundtruth, self.gt_format)

    @property
    def resolved_gt_frame(self) -> str:
        """The ground truth's body frame: ``gt_frame``, or the format's convention for "auto"."""
        return default_gt_frame(self.resolved_gt_format) if self.gt_frame == "auto" else self.gt_frame


@dataclass(frozen=True)
class Cell:
    """One run of the grid (everything a worker needs; plain, picklable values)."""

    dataset: DatasetEntry
    mode: str
    options_name: str
    options: dict[str, Any]
    noise_name: str
    noise: dict[str, Any]
    seed: int

    @property
    def key(self) -> tuple[str, str, str, str, str]:
        return (self.dataset.name, self.mode, self.options_name, self.noise_name, str(self.seed))

    def settings(self) -> dict[str, str]:
        """What a row must match besides the key to count as this cell's result."""
        gt_frame = ""
        if self.dataset.groundtruth:
            try:
                gt_frame = self.dataset.resolved_gt_frame
            except GroundTruthError:  # an unreadable file: the cell fails with that error when it runs
                gt_frame = self.dataset.gt_frame
        return {"dataset_path": self.dataset.path, "groundtruth_path": self.dataset.groundtruth or "",
                "gt_frame": gt_frame,
                "options_values": _json(self.options), "noise_values": _json(self.noise)}


def _json(values: Mapping[str, Any]) -> str:
    return json.dumps(values, sort_keys=True, separators=(",", ":"))


@dataclass
class SweepSpec:
    source: str
    datasets: list[DatasetEntry]
    modes: list[str]
    options: dict[str, dict[str, Any]]
    noise: dict[str, dict[str, Any]]
    seeds: list[int]

    def cells(self) -> list[Cell]:
        """The grid, in order: datasets, modes, option sets, noise settings, seeds."""
        return [Cell(d, m, on, ov, nn, nv, s) for d in self.datasets for m in self.modes
                for on, ov in self.options.items() for nn, nv in self.noise.items() for s in self.seeds]


def cell_key(row: Mapping[str, Any]) -> tuple[str, ...]:
    return tuple(str(row[k]) for k in KEY_COLUMNS)


def load_spec(path) -> SweepSpec:
    """Read and validate a SPEC file (YAML or TOML by suffix)."""
    path = Path(path)
    return parse_spec(_read_spec_file(path), source=str(path), base_dir=path.resolve().parent)


def _read_spec_file(path: Path) -> Any:
    return read_config_document(path, "SPEC file")


def _name(value, where: str) -> str:
    if isinstance(value, bool) or not isinstance(value, (str, int)) or not str(value).strip():
        raise ConfigError(f"{where}: expected a non-empty name, got {value!r}")
    text = str(value).strip()
    if any(c in text for c in "\n\r,\""):
        raise ConfigError(f"{where}: a name may not contain commas, quotes or line breaks, got {text!r}")
    return text


def _path(value, where: str, base_dir: Path) -> str:
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(f"{where}: expected a file path, got {value!r}")
    p = Path(value.strip()).expanduser()
    return str(p if p.is_absolute() else (base_dir / p).resolve())


def _named_sets(raw, key: str, source: str, default: dict, parse) -> dict[str, dict[str, Any]]:
    if raw is None:
        return default
    if not isinstance(raw, Mapping) or not raw:
        raise ConfigError(f"{source}: {key}: expected a non-empty mapping of names to settings, got "
                          f"{type(raw).__name__ if raw else raw!r}")
    out = {}
    for name, value in raw.items():
        name = _name(name, f"{source}: {key}")
        out[name] = parse(value, f"{source}: {key}.{name}")
    return out


def parse_spec(raw: Any, source: str = "spec", base_dir=None) -> SweepSpec:
    """Validate a SPEC mapping (see the module docstring); ``source`` names it in errors,
    relative paths are resolved against ``base_dir`` (default: the current directory)."""
    base_dir = Path(base_dir) if base_dir is not None else Path.cwd()
    if not isinstance(raw, Mapping):
        raise ConfigError(f"{source}: expected a mapping with keys {', '.join(_SPEC_KEYS)}, got {type(raw).__name__}")
    unknown = [k for k in raw if k not in _SPEC_KEYS]
    if unknown:
        raise ConfigError(f"{source}: {unknown_names_message('key', unknown[:1], _SPEC_KEYS)}")
    datasets = _parse_datasets(raw.get("datasets"), source, base_dir)
    modes = _parse_modes(raw.get("modes", ["slam"]), source)
    options = _named_sets(raw.get("options"), "options", source, {"default": {}},
                          lambda value, where: _parse_option_set(value, where, base_dir))
    noise = _named_sets(raw.get("noise"), "noise", source, {"none": {}}, _parse_noise_setting)
    seeds = _parse_seeds(raw.get("seeds", [0]), source)
    return SweepSpec(source, datasets, modes, options, noise, seeds)


def _parse_datasets(items, source: str, base_dir: Path) -> list[DatasetEntry]:
    """The spec's ``datasets``: a non-empty list of paths or mappings with 'path', distinct names."""
    if not isinstance(items, list) or not items:
        raise ConfigError(f"{source}: datasets: expected a non-empty list of datasets (each a mapping with a "
                          f"'path'), got {items!r}")
    datasets: list[DatasetEntry] = []
    for i, item in enumerate(items):
        where = f"{source}: datasets[{i}]"
        entry = _parse_dataset(item, where, base_dir)
        if any(d.name == entry.name for d in datasets):
            raise ConfigError(f"{where}: dataset name {entry.name!r} is used twice; give the datasets distinct "
                              f"'name's")
        datasets.append(entry)
    return datasets


def _parse_dataset(item, where: str, base_dir: Path) -> DatasetEntry:
    """One entry of ``datasets``: a path, or a mapping of path, name, groundtruth, gt_format, gt_frame."""
    if isinstance(item, str):
        item = {"path": item}
    if not isinstance(item, Mapping):
        raise ConfigError(f"{where}: expected a mapping with 'path' (and optionally {', '.join(_DATASET_KEYS[1:])})"
                          f", got {type(item).__name__}")
    bad = [k for k in item if k not in _DATASET_KEYS]
    if bad:
        raise ConfigError(f"{where}: {unknown_names_message('key', bad[:1], _DATASET_KEYS)}")
    if "path" not in item:
        raise ConfigError(f"{where}: missing 'path' (the dataset file)")
    path = _path(item["path"], f"{where}.path", base_dir)
    name = _name(item["name"], f"{where}.name") if "name" in item else Path(path).stem
    gt = _path(item["groundtruth"], f"{where}.groundtruth", base_dir) if item.get("groundtruth") is not None \
        else None
    fmt = item.get("gt_format", "auto")
    if fmt not in GT_FORMAT_CHOICES:
        raise ConfigError(f"{where}.gt_format: expected one of {', '.join(GT_FORMAT_CHOICES)}, got {fmt!r}")
    frame = item.get("gt_frame", "auto")
    if frame not in GT_FRAME_CHOICES:
        raise ConfigError(f"{where}.gt_frame: expected one of {', '.join(GT_FRAME_CHOICES)}, got {frame!r}")
    if gt is None and ("gt_format" in item or "gt_frame" in item):
        raise ConfigError(f"{where}: gt_format/gt_frame given without a groundtruth file")
    return DatasetEntry(name, path, gt, fmt, frame)


def _parse_modes(modes, source: str) -> list[str]:
    """The spec's ``modes``: a mode or a non-empty list of distinct modes."""
    if isinstance(modes, str):
        modes = [modes]
    if not isinstance(modes, list) or not modes:
        raise ConfigError(f"{source}: modes: expected a non-empty list of {', '.join(MODES)}, got {modes!r}")
    for m in modes:
        if m not in MODES:
            raise ConfigError(f"{source}: modes: unknown mode {m!r}; expected {', '.join(MODES)}")
    if len(set(modes)) != len(modes):
        raise ConfigError(f"{source}: modes: a mode is listed twice: {modes!r}")
    return list(modes)


def _parse_option_set(value, where: str, base_dir: Path) -> dict[str, Any]:
    """One named option set: a mapping of FilterOptions fields or an options file; the
    fields it gives, validated."""
    from vislam.tools.config import OPTIONAL_FIELDS, load_options_file

    if isinstance(value, str):  # an options file
        file = _path(value, where, base_dir)
        try:
            values = load_options_file(file)
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}") from None
    elif value is None:
        values = {}
    elif isinstance(value, Mapping):
        values = flatten_options(value, where)  # groups of options -> flat names
    else:
        raise ConfigError(f"{where}: expected a mapping of FilterOptions fields or an options file, got "
                          f"{type(value).__name__}")
    for k in OPTIONAL_FIELDS:  # the off-words of options files
        v = values.get(k)
        if v is False or (isinstance(v, str) and v.strip().lower() in ("none", "null", "off")):
            values[k] = None
    options = FilterOptions.from_dict(values, source=where)
    return {k: v for k, v in options.to_dict().items() if k in values}


def _parse_noise_setting(value, where: str) -> dict[str, Any]:
    """One named injected-noise setting: a mapping of NoiseSpec fields (no seed)."""
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise ConfigError(f"{where}: expected a mapping of noise fields ({', '.join(_NOISE_FIELDS)}), got "
                          f"{type(value).__name__}")
    if "seed" in value:
        raise ConfigError(f"{where}: 'seed' is not a noise setting here; list the seeds under 'seeds'")
    bad = [k for k in value if k not in _NOISE_FIELDS]
    if bad:
        raise ConfigError(f"{where}: {unknown_names_message('noise field', bad[:1], _NOISE_FIELDS)}")
    try:
        spec = NoiseSpec(**value)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    except TypeError as exc:  # pragma: no cover - guarded by the key check
        raise ConfigError(f"{where}: {exc}") from None
    return {k: v for k, v in spec.to_dict().items() if k in value}


def _parse_seeds(seeds, source: str) -> list[int]:
    """The spec's ``seeds``: an integer or a non-empty list of distinct integers >= 0."""
    if isinstance(seeds, int) and not isinstance(seeds, bool):
        seeds = [seeds]
    if not isinstance(seeds, list) or not seeds or any(isinstance(s, bool) or not isinstance(s, int) or s < 0
                                                       for s in seeds):
        raise ConfigError(f"{source}: seeds: expected a non-empty list of integers >= 0, got {seeds!r}")
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"{source}: seeds: a seed is listed twice: {seeds!r}")
    return list(seeds)


# ----------------------------------------------------------------------------- one cell


def _finite(x) -> float | None:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def run_cell(cell: Cell) -> dict[str, Any]:
    """Run one cell and return its row (see :data:`COLUMNS`); never raises for a problem
    of the cell (it becomes ``status="error"``). Runs with single-threaded BLAS."""
    from threadpoolctl import threadpool_limits

    t0 = time.perf_counter()
    row: dict[str, Any] = dict(zip(KEY_COLUMNS, cell.key))
    row.update(cell.settings())
    try:
        with threadpool_limits(limits=1, user_api="blas"):
            row.update(_compute_cell(cell))
    except VislamError as exc:
        row.update(status="error", error=_one_line(exc))
    except Exception as exc:  # a bug must not end the sweep: record it
        logger.exception("cell %s failed", cell.key)
        row.update(status="error", error=_one_line(f"{type(exc).__name__}: {exc}"))
    row["cell_seconds"] = time.perf_counter() - t0
    row["finished_at"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="microseconds")
    row["worker"] = f"{socket.gethostname()}:{os.getpid()}"
    return {c: row.get(c) for c in COLUMNS}


def _compute_cell(cell: Cell) -> dict[str, Any]:
    import numpy as np

    from vislam.core.estimators import run as run_estimator
    from vislam.core.noise import inject_noise
    from vislam.tools.comparison import evaluate_run, load_run_ground_truth
    from vislam.tools.dataset_io import load_sequence

    d = cell.dataset
    sequence = load_sequence(d.path)
    gt_frame = d.resolved_gt_frame if d.groundtruth else None
    gt = load_run_ground_truth(d.groundtruth, sequence, d.gt_format, gt_frame) if d.groundtruth else None
    noise = NoiseSpec(**cell.noise, seed=cell.seed)
    if not noise.is_zero:
        sequence, _ = inject_noise(sequence, noise)
    options = FilterOptions.from_dict(cell.options, source=f"options {cell.options_name}")
    result = run_estimator(sequence, cell.mode, options)
    st = result.stats
    lm = result.landmarks
    out: dict[str, Any] = {
        "status": "partial" if result.partial else "ok",
        "error": _one_line(result.error) if result.partial and result.error else "",
        "frames": st.frames, "frames_processed": st.frames_processed,
        "nis_mean": _finite(getattr(st, "nis_mean", None)),
        "observations_used": st.observations_used, "observations_gated": st.observations_gated,
        "landmarks_initialized": st.landmarks_initialized,
        "landmarks_rejected": int(np.count_nonzero(lm.status)) if lm is not None else None,
        "landmarks_in_map": len(lm) if lm is not None else None,
        "filter_seconds": st.filter_seconds,
    }
    if gt is not None:
        ev = evaluate_run(result, gt, sequence).to_dict()
        out.update({k: _finite(ev.get(k)) for k in ("ape_unaligned_rmse_m", "kitti_t_pct", "kitti_r_deg_per_100m")})
        out["ate_m"] = _finite(ev.get("ape_rmse_m"))
        out["gt_frame"] = gt_frame
        out["cam_ate_m"] = _finite(ev.get("cam_ape_rmse_m"))
        out["cam_kitti_t_pct"] = _finite(ev.get("cam_kitti_t_pct"))
        out["cam_kitti_r_deg_per_100m"] = _finite(ev.get("cam_kitti_r_deg_per_100m"))
        out["kitti_segments"] = ev.get("kitti_segments")
        out["n_frames_compared"] = ev.get("n_frames_compared")
    return out


# ----------------------------------------------------------------------------- results.csv


def _cell_text(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else ""
    return str(value)


def _csv_line(row: Mapping[str, Any]) -> str:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow([_cell_text(row.get(c)) for c in COLUMNS])
    return buf.getvalue()


def read_results(path) -> list[dict[str, str]]:
    """The rows of a results.csv (strings; empty = no value), in file order. A truncated
    last line (no newline: a sweep killed while writing) is ignored. Raises OutputError
    when the file is not a results table of this version."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return []
    except (OSError, UnicodeDecodeError) as exc:
        raise OutputError(f"{path}: cannot be read: {getattr(exc, 'strerror', None) or exc}") from None
    if text and not text.endswith("\n"):
        text = text[: text.rfind("\n") + 1]
    reader = csv.reader(io.StringIO(text))
    header = next(reader, None)
    if header is None:
        return []
    if tuple(header) != COLUMNS:
        raise OutputError(f"{path}: not a results table of this vislam version (columns {','.join(header[:6])}...; "
                          f"expected {','.join(COLUMNS[:6])}...); use another --out or move the file away")
    return [dict(zip(COLUMNS, r)) for r in reader if len(r) == len(COLUMNS)]


@contextlib.contextmanager
def _locked(path: Path):
    """Hold the exclusive lock of results.csv ``path`` (``flock`` on a lock file beside it,
    :data:`LOCK_FILE`: results.csv itself is replaced by the compaction, its lock would
    go with the old file). Every change of results.csv happens under it, so sweeps that
    share an ``--out`` (concurrently, in several processes) merge their rows instead of
    replacing each other's. The kernel releases it when a process dies."""
    lock_path = path.with_name(LOCK_FILE)
    try:
        fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError as exc:
        raise OutputError(f"{lock_path}: cannot be created: {exc.strerror or exc}") from None
    try:
        if fcntl is not None:
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


class _ResultsLog:
    """results.csv for appending: the header is created atomically, then each row is
    appended, flushed and fsynced — each step under :func:`_locked`, with the file opened
    by name every time (another sweep on the same ``--out`` may have rewritten it)."""

    def __init__(self, path: Path):
        from vislam.tools.atomic import write_text_atomic

        self.path = path
        with _locked(path):
            if not path.exists() or path.stat().st_size == 0:
                write_text_atomic(path, _csv_line(dict(zip(COLUMNS, COLUMNS))))
            else:  # drop a truncated last line before appending
                try:
                    with open(path, "rb+") as fp:
                        data = fp.read()
                        if not data.endswith(b"\n"):
                            fp.truncate(data.rfind(b"\n") + 1)
                except OSError as exc:
                    raise OutputError(f"{path}: cannot be written: {exc.strerror or exc}") from None

    def append(self, row: Mapping[str, Any]) -> None:
        with _locked(self.path):
            try:
                with open(self.path, "a", encoding="utf-8", newline="") as fp:
                    fp.write(_csv_line(row))
                    fp.flush()
                    os.fsync(fp.fileno())
            except OSError as exc:
                raise OutputError(f"{self.path}: cannot be written: {exc.strerror or exc}") from None

    def close(self) -> None:
        pass


def _compact(path: Path, cells: list[Cell]) -> list[dict[str, str]]:
    """Rewrite results.csv atomically (under :func:`_locked`): one row per cell in grid
    order (the latest wins), then rows of other cells (not in this SPEC, e.g. those of
    another sweep on the same ``--out``) in file order. Returns the grid's rows."""
    from vislam.tools.atomic import write_text_atomic

    with _locked(path):
        latest: dict[tuple, dict[str, str]] = {}
        for r in read_results(path):
            latest.pop(cell_key(r), None)  # keep file order of the latest rows
            latest[cell_key(r)] = r
        grid = [latest.pop(c.key) for c in cells if c.key in latest]
        rows = grid + list(latest.values())
        write_text_atomic(path, "".join(_csv_line(r) for r in [dict(zip(COLUMNS, COLUMNS))] + rows))
    return grid


# ----------------------------------------------------------------------------- the sweep


def _is_done(row: Mapping[str, str] | None, cell: Cell) -> bool:
    """Whether ``row`` (the latest of the cell's key) is a finished result of ``cell``:
    a done status and the same files and settings (a set renamed or edited in the SPEC
    since is run again)."""
    return (row is not None and row["status"] in DONE_STATUSES
            and all(row[k] == v for k, v in cell.settings().items()))


@dataclass
class SweepResult:
    """What :func:`run_sweep` did."""

    out_dir: Path
    results_path: Path
    figure_path: Path | None
    rows: list[dict[str, str]]          # one per cell of the grid, as in results.csv
    n_cells: int
    n_skipped: int                      # done before this call (resumed)
    n_run: int                          # computed now
    n_errors: int                       # rows with status error (of the grid)
    seconds: float
    engine: str
    notes: list[str] = field(default_factory=list)


def run_sweep(spec: SweepSpec, out_dir, engine=None, on_row: Callable[[dict, int, int], None] | None = None,
              on_start: Callable[[int, int], None] | None = None, figure: bool = True) -> SweepResult:
    """Run every cell of ``spec`` not yet done in ``out_dir/results.csv`` on ``engine``
    (:mod:`vislam.tools.cluster`; default: in this process), appending a row per finished
    cell; then compact the table and draw the summary figure (see the module docstring).

    ``on_start(n_todo, n_done)`` is called once before any cell runs, ``on_row(row,
    done, total)`` after each row is written. On an interrupt (Ctrl-C) the rows written so
    far stay, and a rerun resumes."""
    from vislam.tools.cluster import SequentialEngine

    engine = engine or SequentialEngine()
    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputError(f"{out_dir}: exists and is not a directory (an output directory is expected)")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{out_dir}: cannot create the output directory: {exc.strerror or exc}") from None
    path = out_dir / RESULTS_FILE
    cells = spec.cells()
    latest = {cell_key(r): r for r in read_results(path)}
    todo = [c for c in cells if not _is_done(latest.get(c.key), c)]
    n_skipped = len(cells) - len(todo)
    if on_start:
        on_start(len(todo), n_skipped)
    log = _ResultsLog(path)
    futures = {}
    try:
        by_future = {}
        for c in todo:
            f = engine.submit(run_cell, c)
            by_future[f] = c
        futures = by_future
        for i, f in enumerate(engine.as_completed(list(by_future)), 1):
            c = by_future[f]
            try:
                row = f.result()
            except Exception as exc:  # the task itself failed (e.g. a worker died): an error row
                row = {**dict(zip(KEY_COLUMNS, c.key)), **c.settings(), "status": "error",
                       "error": _one_line(f"{type(exc).__name__}: {exc}"),
                       "finished_at": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="microseconds")}
            log.append(row)
            if on_row:
                on_row(row, i, len(todo))
    except BaseException:
        engine.cancel(list(futures))
        raise
    finally:
        log.close()
    rows = _compact(path, cells)
    figure_path = None
    notes = []
    if figure:
        try:
            figure_path = plot_summary(rows, out_dir / SUMMARY_FIGURE, spec)
        except VislamError as exc:
            notes.append(f"summary figure not drawn: {exc}")
    n_errors = sum(r["status"] == "error" for r in rows)
    return SweepResult(out_dir, path, figure_path, rows, len(cells), n_skipped, len(todo), n_errors,
                       time.perf_counter() - t0, engine.name, notes)


# ----------------------------------------------------------------------------- the figure


def plot_summary(rows: list[Mapping[str, str]], path, spec: SweepSpec) -> Path | None:
    """The summary figure: one panel per (mode, noise setting), the datasets along x, one
    marker per option set: the mean over seeds (bar) and every seed (dots), i.e. the
    spread. The metric is ATE where any cell has it, else the filter time. Returns the
    path, or None when no cell has a value to draw."""
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from vislam.tools.atomic import atomic_path

    ok = [r for r in rows if r["status"] in DONE_STATUSES]
    has_ate = any(_finite(r["ate_m"]) is not None for r in ok)
    metric, label = ("ate_m", "ATE, SE(3)-aligned RMSE (m)") if has_ate else ("filter_seconds", "filter time (s)")
    values: dict[tuple, list[float]] = {}
    for r in ok:
        x = _finite(r[metric])
        if x is not None:
            values.setdefault((r["mode"], r["noise"], r["dataset"], r["options"]), []).append(x)
    if not values:
        return None
    datasets = [d.name for d in spec.datasets]
    if has_ate:
        datasets = [n for n in datasets if any(k[2] == n for k in values)]
    panels = [(m, n) for m in spec.modes for n in spec.noise if any(k[:2] == (m, n) for k in values)]
    opt_names = list(spec.options)
    ncols = min(len(panels), 3)
    nrows = math.ceil(len(panels) / ncols)
    fig = Figure(figsize=(max(5.0, 1.3 * len(datasets) * max(1, len(opt_names)) ** 0.5 + 2.5) * ncols,
                      3.8 * nrows + 0.6), constrained_layout=True)
    FigureCanvasAgg(fig)
    axes = np.atleast_1d(fig.subplots(nrows, ncols, squeeze=False)).ravel()
    colors = [f"C{i % 10}" for i in range(len(opt_names))]
    width = 0.8 / max(1, len(opt_names))
    for ax, (mode, noise) in zip(axes, panels):
        for j, on in enumerate(opt_names):
            xs, means = [], []
            for i, dn in enumerate(datasets):
                v = values.get((mode, noise, dn, on))
                if not v:
                    continue
                x = i + (j - (len(opt_names) - 1) / 2) * width
                xs.append(x)
                means.append(float(np.mean(v)))
                ax.plot(np.full(len(v), x), v, "o", color="k", ms=3.5, zorder=3)
                if len(v) > 1:
                    ax.vlines(x, min(v), max(v), color="k", lw=1.0, zorder=3)
            ax.bar(xs, means, width=width * 0.9, color=colors[j], alpha=0.8, label=f"options {on!s}")
        ax.set_xticks(range(len(datasets)), datasets, rotation=20 if len(datasets) > 4 else 0)
        ax.set_xlabel("dataset")
        ax.set_ylabel(label)
        ax.set_title(f"mode {mode}, noise {noise}")
        ax.grid(axis="y", alpha=0.3)
        ax.legend(fontsize="small", title=f"bar: mean of {len(spec.seeds)} seed(s); dots: each seed",
                  title_fontsize="x-small")
    for ax in axes[len(panels):]:
        ax.set_visible(False)
    fig.suptitle(f"Sweep {Path(spec.source).name}: {label.split(',')[0].split(' (')[0]} by option set and dataset")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    return Path(path)


def spec_summary(spec: SweepSpec) -> str:
    return (f"{len(spec.datasets)} dataset(s) x {len(spec.modes)} mode(s) x {len(spec.options)} option set(s) x "
            f"{len(spec.noise)} noise setting(s) x {len(spec.seeds)} seed(s) = {len(spec.cells())} cells")


def rows_equal(a: Iterable[Mapping[str, str]], b: Iterable[Mapping[str, str]],
               ignore: Iterable[str] = RUN_INFO_COLUMNS) -> list[str]:
    """Differences between two tables, cell by cell (ignoring the run-info columns);
    empty when they agree exactly."""
    ignore = set(ignore)
    ia = {cell_key(r): r for r in a}
    ib = {cell_key(r): r for r in b}
    diffs = []
    for k in sorted(set(ia) | set(ib)):
        if k not in ia or k not in ib:
            diffs.append(f"{'/'.join(k)}: only in {'first' if k in ia else 'second'} table")
            continue
        for c in COLUMNS:
            if c not in ignore and ia[k][c] != ib[k][c]:
                diffs.append(f"{'/'.join(k)}: {c} {ia[k][c]!r} != {ib[k][c]!r}")
    return diffs

