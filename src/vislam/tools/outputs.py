"""The output directory of ``vislam run`` and ``vislam demo``.

Files (all in the output directory ``DIR``):

* ``trajectory.tum`` — ``timestamp tx ty tz qx qy qz qw`` of world_T_imu, one line per
  frame processed, the dataset's timestamps;
* ``trajectory.kitti`` — the 12 row-major values of world_T_imu's top 3x4 per frame;
* ``landmarks.ply`` (mapping and SLAM) — the map as a binary little-endian PLY point
  cloud (MeshLab, CloudCompare, Open3D open it): ``float x y z`` (world frame, m),
  ``uchar red green blue`` (green: ok, red: rejected), ``int id`` (dataset landmark id),
  ``int track``, ``int n_observations``, ``int n_gated``, ``uchar status`` (0 ok,
  1 rejected) and ``float sigma``: √trace of the 3x3 position covariance (m), the
  filter's RMS position uncertainty;
* ``landmarks.npz`` (mapping and SLAM) — every field of the
  :class:`~vislam.core.results.LandmarkMap` at full precision: ``ids``, ``track``,
  ``p_lm_in_world`` (K, 3), ``covariance`` (K, 3, 3), ``n_observations``, ``n_gated``,
  ``first_frame``, ``last_frame``, ``status``, ``v_lm_in_world`` (K, 3);
* ``trajectory.png`` — the report's xy-plane figure (:mod:`vislam.tools.plotting`);
* ``summary.json`` — what ran and how it went, see :func:`build_summary`;
* demo only: ``groundtruth.tum`` (the true IMU poses), ``groundtruth.kitti`` (the true
  left-camera poses, by the KITTI convention, as the shared data's ``groundtruth/*.txt``)
  and ``localization.tum`` (the dead-reckoning trajectory, for comparison).

``summary.json`` records under ``calibration`` the IMU-camera transform the filter used
(``calibration.cam_T_imu``, after every correction: a ``cam_T_imu`` override in the
options, ``--auto``'s rotation correction), the data file's (``calibration.file_cam_T_imu``)
and the corrections that made the one from the other (``calibration.corrections``: field,
value, effect, source), from the result's :attr:`~vislam.core.results.RunResult.calibration`.
``vislam eval`` takes ``calibration.cam_T_imu`` from there to convert camera ground truth.
``dataset.cam_T_imu`` (when the caller gives it in ``dataset``: ``vislam run``,
``compare``, ``demo`` and ``report`` do) is the data file's transform, as recorded.

Atomicity: an :class:`OutputStage` writes every file into a hidden staging directory
beside ``DIR`` and, once all are complete, swaps it in for ``DIR`` in one step (the
entries of ``DIR`` the run does not replace hard-linked into it first; Ctrl-C deferred):
a failure, Ctrl-C or kill at any moment leaves ``DIR`` as the previous complete folder or
the new complete one, and the next run deletes the staging directories of killed runs.
A failure or Ctrl-C before the commit leaves ``DIR`` as it was — no new file, no
temporary debris (a directory the stage created is removed again). After a successful commit ``DIR`` holds one run's outputs:
the landmark files of an earlier mapping/SLAM run are removed by a localization run.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import logging
import os
import re
import shutil
import signal
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from vislam.core.results import LandmarkMap, RunResult
from vislam.errors import OutputError
from vislam.tools.jsonio import json_safe, write_json  # noqa: F401 (re-exported)
from vislam.tools.atomic import write_bytes_atomic
from vislam.tools.npz import write_npz
from vislam.tools.trajectory_io import imu_to_camera_trajectory, write_kitti, write_tum

__all__ = [
    "TRAJECTORY_TUM",
    "TRAJECTORY_KITTI",
    "LANDMARKS_PLY",
    "LANDMARKS_NPZ",
    "FIGURE",
    "SUMMARY",
    "GROUNDTRUTH_TUM",
    "GROUNDTRUTH_KITTI",
    "LOCALIZATION_TUM",
    "MODE_TITLES",
    "display_name",
    "file_label",
    "method_title",
    "OutputStage",
    "landmark_arrays",
    "write_landmarks_ply",
    "json_safe",
    "write_json",
    "process_start_time",
    "command_start_time",
    "build_summary",
    "absolute_trajectory_error",
    "write_run_outputs",
    "write_demo_outputs",
]

logger = logging.getLogger(__name__)

TRAJECTORY_TUM = "trajectory.tum"
TRAJECTORY_KITTI = "trajectory.kitti"
LANDMARKS_PLY = "landmarks.ply"
LANDMARKS_NPZ = "landmarks.npz"
FIGURE = "trajectory.png"
SUMMARY = "summary.json"
GROUNDTRUTH_TUM = "groundtruth.tum"
GROUNDTRUTH_KITTI = "groundtruth.kitti"
LOCALIZATION_TUM = "localization.tum"
#: Smoother: its online estimates (each pose as estimated at its own frame).
ONLINE_TUM = "online.tum"
#: Smoother with refine: the smoother's final trajectory (trajectory.tum is the refined one).
SMOOTHER_TUM = "smoother.tum"
#: Files that belong to one mode only; a commit without them removes older copies.
_MODE_FILES = (LANDMARKS_PLY, LANDMARKS_NPZ, ONLINE_TUM, SMOOTHER_TUM)

#: Mode names in titles and summaries.
MODE_TITLES = {"localization": "IMU localization", "mapping": "Landmark mapping", "slam": "Visual-inertial SLAM",
               "smoother": "Sliding-window smoother"}

_STAGE_PREFIX = ".vislam-staging-"


def method_title(result: RunResult) -> str:
    """The method actually run, for titles: a ``--refine`` smoother run says so."""
    title = MODE_TITLES.get(result.mode, result.mode)
    if result.mode == "smoother" and getattr(result.options, "refine", False):
        title += " + batch refinement"
    return title


def _printable(text: str) -> str:
    """``text`` with undecodable bytes of a file name (surrogate escapes) shown as U+FFFD."""
    return text.encode("utf-8", "surrogateescape").decode("utf-8", "replace")


def file_label(path) -> str:
    """``dense/0027.npz``: the file's folder and name, which tell the shared files apart
    (``sparse/0027.npz`` and ``dense/0027.npz`` share the drive's name)."""
    p = Path(path)
    return _printable(f"{p.parent.name}/{p.name}" if p.parent.name else str(p.name))


def display_name(dataset: Mapping[str, Any], default: str = "") -> str:
    """The dataset's name in figure titles: its ``label`` (e.g. ``0027 + noise (...)``)
    with the drive's name replaced by the file it came from (:func:`file_label`)."""
    name = str(dataset.get("name") or default)
    label = str(dataset.get("label") or name)
    path = dataset.get("path")
    if path and name and (label == name or label.startswith(name + " ")):
        label = file_label(path) + label[len(name):]
    return _printable(label)


# ----------------------------------------------------------------------------- staging


@contextlib.contextmanager
def _sigint_deferred():
    """Hold back Ctrl-C (SIGINT) for the duration of the block, then deliver it."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: received.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if received and callable(previous):
            previous(signal.SIGINT, None)  # default handler: raises KeyboardInterrupt


def _host() -> str:
    return re.sub(r"[^A-Za-z0-9_]", "_", socket.gethostname()) or "host"


#: A staging directory's name: ``[.DIR.]vislam-staging-HOST-PID-XXXXXXXX`` (mkdtemp's suffix).
_STAGE_NAME = re.compile(r"vislam-staging-(?P<host>[A-Za-z0-9_]+)-(?P<pid>\d+)-[A-Za-z0-9_]{8}$")
#: Age after which a staging directory of the old name (no host and pid) counts as stale.
_OLD_STAGE_AGE_S = 600.0


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _stale(path: Path) -> bool:
    """Whether a staging directory belongs to no running process (a killed run's)."""
    m = _STAGE_NAME.search(path.name)
    if m is None:  # an old-style name: stale once old enough
        try:
            return time.time() - path.lstat().st_mtime > _OLD_STAGE_AGE_S
        except OSError:
            return False
    if m["host"] != _host():  # another machine's (a shared file system): not ours to judge
        return False
    return not _pid_alive(int(m["pid"]))


def clean_stale_staging(out_dir) -> list[Path]:
    """Delete the staging directories that killed runs left in ``out_dir`` and beside it
    (``.vislam-staging-*`` and ``.NAME.vislam-staging-*``). Returns what was removed."""
    out = Path(out_dir)
    found = []
    for where, prefix in ((out, _STAGE_PREFIX), (out.parent, f".{out.name}{_STAGE_PREFIX}")):
        try:
            entries = list(where.iterdir())
        except OSError:
            continue
        found += [p for p in entries if p.name.startswith(prefix) and p.is_dir() and not p.is_symlink()]
    removed = []
    for path in found:
        if _stale(path):
            shutil.rmtree(path, ignore_errors=True)
            if not path.exists():
                removed.append(path)
                logger.info("removed %s (the staging directory of a run that was killed)", path)
    return removed


_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Swap the directories ``a`` and ``b`` in one step (Linux ``renameat2`` with
    ``RENAME_EXCHANGE``); False where the system or file system cannot."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    renameat2.restype = ctypes.c_int
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EPERM):
        return False
    raise OSError(err, os.strerror(err), str(b))


class _CannotLink(Exception):
    """An entry of the output directory that cannot be hard-linked (a special file, another device)."""


def _link_tree(src: Path, dst: Path) -> None:
    """Recreate ``src`` at ``dst`` with hard links (directories recreated, symlinks copied)."""
    if src.is_symlink():
        os.symlink(os.readlink(src), dst)
    elif src.is_dir():
        if os.path.ismount(src):
            raise _CannotLink(src)
        os.mkdir(dst)
        shutil.copymode(src, dst)
        for child in src.iterdir():
            _link_tree(child, dst / child.name)
    elif src.is_file():
        try:
            os.link(src, dst, follow_symlinks=False)
        except OSError as exc:
            raise _CannotLink(src) from exc
    else:
        raise _CannotLink(src)


class OutputStage:
    """All-or-nothing output into a directory.

    Use as a context manager: entering cleans the staging directories of killed runs
    (:func:`clean_stale_staging`), creates ``out_dir`` if needed and a staging directory
    (so an unwritable destination fails *before* any work); files are written to
    :meth:`path` ``(name)``; :meth:`commit` puts them in place. Leaving the block without
    a commit (an exception, Ctrl-C) deletes the staging directory and any directory the
    stage created.

    The staging directory is beside ``out_dir`` (``.NAME.vislam-staging-HOST-PID-*``,
    when the parent is writable) and the commit swaps it in as a whole: the entries of
    ``out_dir`` the run does not replace are hard-linked into it, then one
    ``renameat2(RENAME_EXCHANGE)`` exchanges the two directories, and the old one is
    deleted. A kill at any moment leaves ``out_dir`` as the previous complete folder or
    the new complete one (and, at worst, a stale staging directory that the next run
    removes). Where that cannot be done (no ``renameat2``, an unwritable parent, an entry
    that cannot be hard-linked) the staged files are renamed into ``out_dir`` one by one,
    as before.
    """

    def __init__(self, out_dir):
        self.out_dir = Path(out_dir)
        self.staging: Path | None = None
        self.committed = False
        self.files: list[Path] = []  # final paths, after commit
        self._created: list[Path] = []
        self._beside = False  # the staging directory is beside out_dir (swappable)
        self._target = self.out_dir  # out_dir with symlinks resolved (what the swap exchanges)

    def __enter__(self) -> "OutputStage":
        out = self.out_dir
        if out.exists() and not out.is_dir():
            raise OutputError(f"{out}: exists and is not a directory (an output directory is expected)")
        missing = []
        parent = out
        while not parent.exists() and parent != parent.parent:
            missing.append(parent)
            parent = parent.parent
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"{out}: cannot create the output directory: {exc.strerror or exc}") from None
        self._created = missing  # deepest first
        if not os.access(out, os.W_OK | os.X_OK):
            self._remove_created()
            raise OutputError(f"{out}: cannot write in the output directory: permission denied")
        resolved = self._target = out.resolve()
        clean_stale_staging(resolved)
        tag = f"{_host()}-{os.getpid()}-"
        try:
            if resolved.parent == resolved or resolved.parent.stat().st_dev != resolved.stat().st_dev:
                raise OSError("a mount point: the staging directory goes inside it")
            self.staging = Path(tempfile.mkdtemp(prefix=f".{resolved.name}{_STAGE_PREFIX}{tag}", dir=resolved.parent))
            self._beside = True
        except OSError:
            try:
                self.staging = Path(tempfile.mkdtemp(prefix=f"{_STAGE_PREFIX}{tag}", dir=out))
            except OSError as exc:
                self._remove_created()
                raise OutputError(f"{out}: cannot write in the output directory: {exc.strerror or exc}") from None
        return self

    def path(self, name: str) -> Path:
        """Where to write the output ``name`` now (inside the staging directory)."""
        if self.staging is None:
            raise RuntimeError("OutputStage used outside its with-block")
        return self.staging / name

    def staged(self) -> list[str]:
        """Names of the complete files staged so far (temporary files excluded)."""
        if self.staging is None:
            return []
        return sorted(p.name for p in self.staging.iterdir() if not p.name.startswith("."))

    def commit(self, order: Iterable[str] = (), remove_stale: Iterable[str] = _MODE_FILES,
               replace_directories: bool = False) -> list[Path]:
        """Put the staged files in place and delete older copies of ``remove_stale``
        files this run did not produce; the other entries of the output directory stay.
        Ctrl-C is held back until the commit is done. In one step where the system
        allows it (see the class docstring), else by renames (``order`` first, the rest
        after, alphabetically).

        With ``replace_directories``, staged entries may be directories: an existing
        directory of the same name is replaced as a whole.
        """
        names = self.staged()
        out = self.out_dir
        if replace_directories:
            for name in names:
                target = out / name
                if self.path(name).is_dir() and (target.exists() or target.is_symlink()) and \
                        (not target.is_dir() or target.is_symlink()):
                    raise OutputError(f"{target}: exists and is not a directory; cannot replace it with the "
                                      f"output directory {name}/")
            remove_stale = ()
        with _sigint_deferred():
            if self._beside and self._swap(names, set(remove_stale)):
                self.committed = True
                self.files = [out / n for n in names]
                return self.files
            if replace_directories:
                return self._commit_replacing_directories(names, order)
            return self._commit_by_renames(names, order, remove_stale)

    def _swap(self, names: list[str], remove_stale: set[str]) -> bool:
        """The one-step commit; False (nothing changed in out_dir) when it cannot be done."""
        out, staging = self._target, self.staging
        keep = set(names) | remove_stale
        try:
            for entry in out.iterdir():
                if entry.name not in keep:
                    _link_tree(entry, staging / entry.name)
            shutil.copymode(out, staging)
            swapped = _exchange(staging, out)
        except _CannotLink as exc:
            logger.debug("%s: committing file by file (%s cannot be hard-linked)", out, exc)
            swapped = False
        except OSError as exc:
            raise OutputError(f"{out}: cannot move the outputs into place: {exc.strerror or exc}") from None
        if not swapped:
            for entry in list(staging.iterdir()):  # back to the staged files alone
                if entry.name not in names:
                    shutil.rmtree(entry) if entry.is_dir() and not entry.is_symlink() else entry.unlink()
            return False
        self._cleanup()  # the previous folder, now at the staging path
        return True

    def _commit_by_renames(self, names: list[str], order: Iterable[str], remove_stale: Iterable[str]) -> list[Path]:
        ordered = [n for n in order if n in names] + [n for n in names if n not in order]
        final: list[Path] = []
        try:
            for name in ordered:
                os.replace(self.path(name), self.out_dir / name)
                final.append(self.out_dir / name)
            for name in remove_stale:
                if name not in names:
                    with contextlib.suppress(FileNotFoundError):
                        (self.out_dir / name).unlink()
        except OSError as exc:
            raise OutputError(f"{self.out_dir}: cannot move the outputs into place: {exc.strerror or exc}") \
                from None
        self.committed = True
        self.files = final
        self._cleanup()
        return final

    def _commit_replacing_directories(self, names: list[str], order: Iterable[str]) -> list[Path]:
        """By renames, with ``replace_directories``: an existing directory of a staged
        one's name is moved into the staging area first (and deleted with it); on
        failure it is moved back."""
        out = self.out_dir
        moved: list[tuple[Path, Path]] = []
        try:
            for name in names:
                target = out / name
                if self.path(name).is_dir() and target.is_dir() and not target.is_symlink():
                    aside = self.path(f".replaced-{name}")
                    os.replace(target, aside)
                    moved.append((aside, target))
            return self._commit_by_renames(names, order, ())
        except (OSError, OutputError) as exc:
            for aside, target in reversed(moved):
                with contextlib.suppress(OSError):
                    if not target.exists():
                        os.replace(aside, target)
            if isinstance(exc, OutputError):
                raise
            raise OutputError(f"{out}: cannot move the outputs into place: {exc.strerror or exc}") from None

    def _cleanup(self) -> None:
        if self.staging is not None:
            shutil.rmtree(self.staging, ignore_errors=True)
            self.staging = None

    def _remove_created(self) -> None:
        for d in self._created:  # deepest first; only if still empty
            with contextlib.suppress(OSError):
                d.rmdir()
        self._created = []

    def __exit__(self, exc_type, exc, tb) -> None:
        if not self.committed:
            self._cleanup()
            self._remove_created()
        else:
            self._cleanup()


# ----------------------------------------------------------------------------- landmarks


def landmark_arrays(landmarks: LandmarkMap) -> dict[str, np.ndarray]:
    """The arrays of ``landmarks.npz`` (every LandmarkMap field, numeric)."""
    return {
        "ids": np.asarray(landmarks.ids, dtype=np.int64),
        "track": np.asarray(landmarks.track, dtype=np.int64),
        "p_lm_in_world": np.asarray(landmarks.p_lm_in_world, dtype=np.float64).reshape(-1, 3),
        "covariance": np.asarray(landmarks.covariance, dtype=np.float64).reshape(-1, 3, 3),
        "n_observations": np.asarray(landmarks.n_observations, dtype=np.int64),
        "n_gated": np.asarray(landmarks.n_gated, dtype=np.int64),
        "first_frame": np.asarray(landmarks.first_frame, dtype=np.int64),
        "last_frame": np.asarray(landmarks.last_frame, dtype=np.int64),
        "status": np.asarray(landmarks.status, dtype=np.uint8),
        "v_lm_in_world": np.asarray(landmarks.v_lm_in_world, dtype=np.float64).reshape(-1, 3),
    }


_PLY_DTYPE = np.dtype([
    ("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
    ("red", "u1"), ("green", "u1"), ("blue", "u1"),
    ("id", "<i4"), ("track", "<i4"), ("n_observations", "<i4"), ("n_gated", "<i4"),
    ("status", "u1"), ("sigma", "<f4"),
])
_PLY_TYPES = {"<f4": "float", "|u1": "uchar", "<i4": "int"}
_COLOR_OK = (46, 160, 67)
_COLOR_REJECTED = (220, 30, 30)


def write_landmarks_ply(path, landmarks: LandmarkMap, comments: Iterable[str] = ()) -> None:
    """Write the map as a binary little-endian PLY point cloud (atomically); see the
    module docstring for the vertex properties."""
    n = len(landmarks)
    v = np.zeros(n, dtype=_PLY_DTYPE)
    p = np.asarray(landmarks.p_lm_in_world, dtype=np.float64).reshape(-1, 3)
    v["x"], v["y"], v["z"] = p[:, 0], p[:, 1], p[:, 2]
    status = np.asarray(landmarks.status, dtype=np.uint8)
    colors = np.where((status != 0)[:, None], _COLOR_REJECTED, _COLOR_OK)
    v["red"], v["green"], v["blue"] = colors[:, 0], colors[:, 1], colors[:, 2]
    v["id"] = landmarks.ids
    v["track"] = landmarks.track
    v["n_observations"] = landmarks.n_observations
    v["n_gated"] = landmarks.n_gated
    v["status"] = status
    trace = np.trace(np.asarray(landmarks.covariance, dtype=np.float64).reshape(-1, 3, 3), axis1=1, axis2=2)
    with np.errstate(invalid="ignore"):
        v["sigma"] = np.sqrt(trace)
    header = ["ply", "format binary_little_endian 1.0"]
    # PLY headers are ASCII: other characters of a comment (a dataset name, a label)
    # are written as \uXXXX escapes rather than failing the whole run
    header += ["comment " + " ".join(str(c).split()).encode("ascii", "backslashreplace").decode("ascii")
               for c in comments]
    header += ["comment world frame = first IMU pose (x forward, y left, z up), metres",
               "comment status: 0 ok, 1 rejected; sigma: sqrt(trace of the position covariance) in m",
               f"element vertex {n}"]
    header += [f"property {_PLY_TYPES[_PLY_DTYPE[name].str]} {name}" for name in _PLY_DTYPE.names]
    header.append("end_header")
    data = ("\n".join(header) + "\n").encode("ascii") + v.tobytes()
    write_bytes_atomic(path, data)


# ----------------------------------------------------------------------------- summary


#: Longest plausible time from a process's start to the first line of vislam's launcher
#: (the interpreter's own start-up, a cold disk included).
MAX_INTERPRETER_START_S = 3.0


def command_start_time() -> float | None:
    """The epoch time at which this ``vislam`` command started, for ``total_seconds``:
    the process start (:func:`process_start_time`, so the interpreter's start-up and the
    imports count), unless the process existed long before vislam's launcher ran — a
    shell that executed the command in its own process (``bash -c 'pip install ... &&
    vislam demo'`` reported the installation's time as the demo's) — then the launcher's
    start. None outside the command line (a notebook, a test): the caller's own clock."""
    launcher = sys.modules.get("vislam._launcher")
    launched = getattr(launcher, "STARTED", None)
    if launched is None:
        return None
    started = process_start_time()
    if started is None or launched - started > MAX_INTERPRETER_START_S:
        return launched
    return started


def process_start_time() -> float | None:
    """The epoch time at which this process started (Linux ``/proc``), or None."""
    try:
        stat = Path("/proc/self/stat").read_text()
        start_ticks = int(stat[stat.rindex(")") + 2:].split()[19])  # field 22: starttime
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        elapsed = uptime - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None
    if not 0.0 <= elapsed < 30 * 86400:
        return None
    return time.time() - elapsed


def build_summary(result: RunResult, *, dataset: Mapping[str, Any], duration_s: float, start_time: float | None,
                  outputs: Iterable[str] = (), extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The content of ``summary.json``.

    Keys: ``vislam_version``, ``dataset`` (name, path, …), ``mode``, ``options``
    (FilterOptions.to_dict()), ``frames``, ``frames_processed``, ``landmarks_initialized``,
    ``landmarks_in_map``, ``landmarks_rejected`` (map entries flagged rejected),
    ``observations_total/used/gated/repeated/not_initialized``, ``filter_seconds`` (time
    in estimation only), ``frame_ms_median``, ``frame_ms_p95``, ``total_seconds`` (from
    ``start_time``, an epoch time — the process start when known — to now),
    ``duration_s`` (of the recording), ``real_time_factor`` (filter_seconds / duration of
    the frames processed; < 1 is faster than real time), ``partial``, ``error``,
    ``outputs``, ``filter_arithmetic`` (SLAM: "compiled" kernels or "numpy", see
    :mod:`vislam.core.kernels`), ``imu_bias`` (mean, RMS and final b̂ of the SLAM filter's IMU-error state,
    when on), ``calibration`` (the cam_T_imu the filter used, the file's, the corrections;
    see the module docstring) and the entries of ``extra``. Non-finite numbers become null on writing.
    """
    from vislam import __version__

    stats = result.stats
    s: dict[str, Any] = {"vislam_version": __version__, "dataset": dict(dataset), "mode": result.mode,
                         "options": result.options.to_dict()}
    s.update(stats.to_dict())
    lm = result.landmarks
    s["landmarks_in_map"] = len(lm) if lm is not None else 0
    s["landmarks_rejected"] = int(np.count_nonzero(lm.status)) if lm is not None else stats.landmarks_rejected
    ts = np.asarray(result.timestamps_s, dtype=np.float64)
    processed_s = float(ts[-1] - ts[0]) if ts.size > 1 else 0.0
    s["duration_s"] = float(duration_s)
    s["real_time_factor"] = stats.filter_seconds / processed_s if processed_s > 0 else None
    s["total_seconds"] = (time.time() - start_time) if start_time is not None else None
    s["partial"] = bool(result.partial)
    s["error"] = result.error
    s["outputs"] = list(outputs)
    if result.extra.get("arithmetic"):
        s["filter_arithmetic"] = result.extra["arithmetic"]
    if result.calibration is not None:
        s["calibration"] = _calibration_record(result, (extra or {}).get("auto"))
    bias = result.extra.get("imu_bias") if result.extra else None
    if bias is not None and len(bias):  # the SLAM filter's IMU-error state (b_v m/s, b_ω rad/s)
        b = np.asarray(bias)
        s["imu_bias"] = {"mean": b.mean(axis=0).tolist(), "rms": np.sqrt((b * b).mean(axis=0)).tolist(),
                         "final": b[-1].tolist()}
    if extra:
        s.update(extra)
    return s


def _calibration_record(result: RunResult, auto: Mapping[str, Any] | None) -> dict[str, Any]:
    """summary.json's ``calibration``: :meth:`CalibrationUsed.to_dict` with the source of
    each correction (``vislam check``'s suggestion under ``--auto`` when it suggested that
    very value, else the filter options: an options file)."""
    record = result.calibration.to_dict()
    suggested = (auto or {}).get("suggested") or {}
    for c in record["corrections"]:
        value = suggested.get(c["field"])
        same = value is not None and np.allclose(np.asarray(value, dtype=np.float64),
                                                 np.asarray(c["value"], dtype=np.float64), rtol=0, atol=1e-12)
        c["source"] = "vislam check's suggestion (--auto)" if same else "the filter options (options file)"
    return record


def absolute_trajectory_error(est_world_T_imu: np.ndarray, gt_world_T_imu: np.ndarray) -> float | None:
    """ATE (m): RMSE of the position after SE(3) Umeyama alignment of the estimate onto
    the ground truth (evo, via :func:`vislam.tools.evaluation.evaluate`), over the
    frames both have; None when fewer than 2 frames can be compared."""
    from vislam.tools.evaluation import evaluate

    n = min(len(est_world_T_imu), len(gt_world_T_imu))
    if n < 2:
        return None
    return float(evaluate(est_world_T_imu[:n], gt_world_T_imu[:n]).ape.rmse)


# ----------------------------------------------------------------------------- writing


def _figure_subtitle(result: RunResult, extra: str | None = None) -> str:
    st = result.stats
    parts = [f"{st.frames_processed} frames"]
    if st.frames_processed != st.frames:
        parts[0] += f" of {st.frames} (stopped early)"
    if result.landmarks is not None:
        n_rej = int(np.count_nonzero(result.landmarks.status))
        parts.append(f"{len(result.landmarks)} landmarks" + (f", {n_rej} rejected" if n_rej else ""))
    if extra:
        parts.append(extra)
    return " · ".join(parts)


def _write_common(stage: OutputStage, result: RunResult, dataset_name: str, curves, subtitle_extra: str | None,
                  ply_comments: Iterable[str], plot=None, figure: bool = True) -> dict | None:
    """Write the trajectories and the map into ``stage``, and the figure unless ``figure``
    is False; returns the figure's view (:func:`~vislam.tools.plotting.plot_trajectory_map`)
    or None without it."""
    if plot is None:
        from vislam.tools.plotting import plot_trajectory_map as plot

    write_tum(stage.path(TRAJECTORY_TUM), result.timestamps_s, result.world_T_imu)
    write_kitti(stage.path(TRAJECTORY_KITTI), result.world_T_imu)
    if result.landmarks is not None:
        write_npz(stage.path(LANDMARKS_NPZ), landmark_arrays(result.landmarks))
        write_landmarks_ply(stage.path(LANDMARKS_PLY), result.landmarks, comments=ply_comments)
    if not figure:
        return None
    title = f"{dataset_name} — {method_title(result)}"
    if result.partial:
        title += " (partial)"
    return plot(stage.path(FIGURE), curves, result.landmarks, title=title,
                subtitle=_figure_subtitle(result, subtitle_extra))


_COMMIT_ORDER = (TRAJECTORY_TUM, TRAJECTORY_KITTI, ONLINE_TUM, SMOOTHER_TUM, LANDMARKS_NPZ, LANDMARKS_PLY, FIGURE,
                 GROUNDTRUTH_TUM, GROUNDTRUTH_KITTI, LOCALIZATION_TUM, SUMMARY)


def write_run_outputs(stage: OutputStage, result: RunResult, *, dataset: Mapping[str, Any], duration_s: float,
                      start_time: float | None, extra: Mapping[str, Any] | None = None,
                      ground_truth: np.ndarray | None = None, plot=None, figure: bool = True) -> dict[str, Any]:
    """Write the outputs of ``vislam run`` for ``result`` into ``stage`` and commit them.

    ``dataset`` (``name`` and ``path`` at least) goes into summary.json and the figure's
    title. ``ground_truth`` ((n, 4, 4) world_T_imu, e.g. the evaluation's) is drawn in
    the figure. ``plot`` draws the figure (default
    :func:`vislam.tools.plotting.plot_trajectory_map`; the CLI passes a
    :class:`~vislam.tools.figure_process.FigureProcess`'s); ``figure=False`` writes every
    other output but no figure (``vislam report`` draws only the figures it shows).
    Returns the summary written.
    """
    from vislam.tools.plotting import TrajectoryCurve

    name = display_name(dataset, result.sequence_name)
    label = "trajectory (localization poses)" if result.mode == "mapping" else "trajectory"
    if result.mode == "mapping" and dataset.get("poses") not in (None, "localization"):
        label = "trajectory (given poses)"
    curves = [TrajectoryCurve(result.world_T_imu, label)]
    # the smoother's other trajectories (online estimates; before refinement)
    for key, fname, curve_label, color in (("online_world_T_imu", ONLINE_TUM, "online estimate", "tab:orange"),
                                           ("smoother_world_T_imu", SMOOTHER_TUM, "smoother (before refine)",
                                            "tab:green")):
        poses = result.extra.get(key)
        if poses is not None:
            write_tum(stage.path(fname), result.timestamps_s, poses)
            curves.insert(0, TrajectoryCurve(poses, curve_label, color=color, linestyle="--", linewidth=1.2,
                                             zorder=2, mark_ends=False))
    if len(curves) > 1:
        curves[-1] = TrajectoryCurve(result.world_T_imu, "refined" if result.options.refine else "final (smoothed)")
    if ground_truth is not None and len(ground_truth):
        curves.insert(0, TrajectoryCurve(np.asarray(ground_truth), "ground truth", color="0.25", linewidth=3.2,
                                         zorder=2, mark_ends=False, ground_truth=True))
    view = _write_common(stage, result, name, curves, None,
                         [f"vislam landmarks of {name} ({result.mode})"], plot, figure)
    extra = {**(extra or {}), "landmarks_outside_figure": None if view is None else view["landmarks_outside_view"]}
    summary = build_summary(result, dataset=dataset, duration_s=duration_s, start_time=start_time,
                            outputs=stage.staged() + [SUMMARY], extra=extra)
    write_json(stage.path(SUMMARY), summary)
    stage.commit(order=_COMMIT_ORDER)
    return summary


def write_demo_outputs(stage: OutputStage, slam: RunResult, localization: RunResult, true_world_T_imu: np.ndarray,
                       *, dataset: Mapping[str, Any], duration_s: float, start_time: float | None,
                       extra: Mapping[str, Any] | None = None, plot=None) -> dict[str, Any]:
    """Write the outputs of ``vislam demo`` into ``stage`` and commit them: those of a
    SLAM run, plus the ground truth, the localization trajectory, and in summary.json
    the ATE of SLAM and of localization against the truth. Returns the summary.
    ``plot``: as for :func:`write_run_outputs`.

    ``dataset["cam_T_imu"]`` (4x4) is required: ``groundtruth.kitti`` holds camera poses.
    """
    if dataset.get("cam_T_imu") is None:
        raise ValueError("dataset must give cam_T_imu (groundtruth.kitti holds left-camera poses)")
    from vislam.tools.plotting import TrajectoryCurve

    ate_slam = absolute_trajectory_error(slam.world_T_imu, true_world_T_imu)
    ate_loc = absolute_trajectory_error(localization.world_T_imu, true_world_T_imu)
    name = str(dataset.get("label") or dataset.get("name") or slam.sequence_name)
    curves = [
        TrajectoryCurve(true_world_T_imu, "ground truth", color="0.25", linestyle="-", linewidth=3.2, zorder=2,
                        mark_ends=False, ground_truth=True),  # the simulator's: from the filters' start pose
        TrajectoryCurve(localization.world_T_imu, "IMU localization (dead reckoning)", color="tab:orange",
                        linestyle="--", linewidth=1.4, zorder=3, mark_ends=False),
        TrajectoryCurve(slam.world_T_imu, "SLAM estimate", color="tab:blue", linewidth=1.6, zorder=4),
    ]

    def fmt(x):
        return "n/a" if x is None else f"{x:.2f} m"

    view = _write_common(stage, slam, name, curves, f"ATE: SLAM {fmt(ate_slam)}, localization {fmt(ate_loc)}",
                         [f"vislam demo landmarks of {name} (slam)"], plot)
    timestamps = localization.timestamps_s  # every frame (SLAM's may stop early)
    write_tum(stage.path(GROUNDTRUTH_TUM), timestamps, true_world_T_imu)
    write_kitti(stage.path(GROUNDTRUTH_KITTI), imu_to_camera_trajectory(true_world_T_imu, dataset["cam_T_imu"]))
    write_tum(stage.path(LOCALIZATION_TUM), timestamps, localization.world_T_imu)
    ground_truth = {
        "ate_m": {"slam": ate_slam, "localization": ate_loc},
        "ate_method": "RMSE of the IMU position after SE(3) Umeyama alignment (evo APE, translation part, "
                      "via vislam.tools.evaluation.evaluate)",
        "localization_filter_seconds": localization.stats.filter_seconds,
    }
    extra = {**(extra or {}), "ground_truth": ground_truth, "landmarks_outside_figure": view["landmarks_outside_view"]}
    summary = build_summary(slam, dataset=dataset, duration_s=duration_s, start_time=start_time,
                            outputs=stage.staged() + [SUMMARY], extra=extra)
    write_json(stage.path(SUMMARY), summary)
    stage.commit(order=_COMMIT_ORDER)
    return summary
