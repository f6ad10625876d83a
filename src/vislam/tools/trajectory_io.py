"""Trajectory files: TUM and KITTI.

* TUM: ``timestamp tx ty tz qx qy qz qw`` per line (8 values, quaternion scalar-last).
* KITTI odometry: the 12 row-major values of the top 3x4 of each pose per line.

Both hold ``world_T_<body>`` poses, one per line. Values are separated by white space;
blank lines and ``#`` comments are ignored (as evo does). Text is UTF-8 (a byte-order
mark and CRLF line ends, as Windows editors write, are fine) or, failing that, read as
Latin-1 (the numbers are ASCII either way); a file with NUL bytes is not text.

Writers are atomic (see :mod:`vislam.tools.atomic`) and write every number with the
shortest representation that reads back to the same float, so a write -> read round
trip is exact.

Readers raise :class:`~vislam.errors.GroundTruthError` with a one-line message naming
the file (and the line) for a missing, unreadable or malformed file: wrong number of
values, non-numeric or non-finite values, an empty file, a rotation block that is not a
rotation, a zero quaternion, TUM timestamps that do not increase, or a position
coordinate beyond ±:data:`MAX_POSITION_M`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vislam.errors import GroundTruthError
from vislam.core.lie import quaternion_from_rotation, rotation_from_quaternion
from vislam.tools.atomic import write_text_atomic

#: Ground-truth formats and frames understood by the evaluation (vislam.tools.evaluation).
GT_FORMATS = ("kitti", "tum")
GT_FRAMES = ("imu", "cam")
#: Accepted values of a ground-truth frame option: a frame, or "auto" for the format's
#: convention (see :func:`default_gt_frame`).
GT_FRAME_CHOICES = ("auto",) + GT_FRAMES
#: Accepted values of a ground-truth format option: a format, or "auto" for the one the
#: file's values per line say (see :func:`resolve_gt_format`).
GT_FORMAT_CHOICES = ("auto",) + GT_FORMATS


def resolve_gt_format(path, fmt: str) -> str:
    """``fmt``, or for ``"auto"`` the format of the file at ``path`` from its values per
    line (:func:`detect_format`: 12 -> ``"kitti"``, 8 -> ``"tum"``; GroundTruthError,
    naming the file, for a missing, empty or malformed one)."""
    return detect_format(path) if fmt == "auto" else fmt


def default_gt_frame(fmt: str) -> str:
    """Body frame of ground-truth poses in format ``fmt`` when nothing else is said.

    KITTI odometry ground truth holds left-camera poses by that format's convention
    (``groundtruth/*.txt`` of the shared data, and vislam's own simulated
    ``groundtruth.kitti``): ``"cam"``. TUM has no body-frame convention; vislam's TUM
    files hold IMU poses: ``"imu"``.
    """
    if fmt not in GT_FORMATS:
        raise ValueError(f"unknown ground-truth format {fmt!r}; expected one of {', '.join(GT_FORMATS)}")
    return "cam" if fmt == "kitti" else "imu"


def camera_to_imu_trajectory(world_T_cam, cam_T_imu) -> np.ndarray:
    """Left-camera poses -> IMU poses: ``imu_T_cam @ world_T_cam(i) @ cam_T_imu``.

    The camera trajectory's world frame is the first camera frame; the result's world
    frame is the first IMU frame (``world_T_imu(0) = I`` when ``world_T_cam(0) = I``).
    """
    from vislam.core.lie import se3_inverse

    cam_T_imu = np.asarray(cam_T_imu, dtype=np.float64)
    return se3_inverse(cam_T_imu) @ np.asarray(world_T_cam, dtype=np.float64) @ cam_T_imu


def imu_to_camera_trajectory(world_T_imu, cam_T_imu) -> np.ndarray:
    """IMU poses -> left-camera poses, the inverse of :func:`camera_to_imu_trajectory`:
    ``cam_T_imu @ world_T_imu(i) @ imu_T_cam`` (world frame: the first camera frame when
    ``world_T_imu(0) = I``, as KITTI ground truth)."""
    from vislam.core.lie import se3_inverse

    cam_T_imu = np.asarray(cam_T_imu, dtype=np.float64)
    return cam_T_imu @ np.asarray(world_T_imu, dtype=np.float64) @ se3_inverse(cam_T_imu)


#: Largest time difference (s) of an associated estimate / ground-truth pair. Well below
#: half the frame interval of KITTI (0.1 s), so that no pose can match two others.
DEFAULT_MAX_DIFF_S = 0.02

__all__ = [
    "GT_FORMATS",
    "GT_FORMAT_CHOICES",
    "GT_FRAMES",
    "GT_FRAME_CHOICES",
    "DEFAULT_MAX_DIFF_S",
    "default_gt_frame",
    "resolve_gt_format",
    "camera_to_imu_trajectory",
    "imu_to_camera_trajectory",
    "TrajectoryFile",
    "format_tum",
    "format_kitti",
    "write_tum",
    "write_kitti",
    "read_kitti",
    "read_tum",
    "read_trajectory",
    "detect_format",
    "ROTATION_TOLERANCE",
    "QUATERNION_NORM_TOLERANCE",
]

#: Largest accepted deviation of RᵀR from I (and of det R from 1) in a KITTI file; the
#: KITTI ground truth is printed with ~7 significant digits.
ROTATION_TOLERANCE = 1e-3
#: Largest accepted deviation of a TUM quaternion's norm from 1 (it is normalized).
QUATERNION_NORM_TOLERANCE = 1e-2

_NCOLS = {"kitti": 12, "tum": 8}
_NAMES = {"kitti": "KITTI", "tum": "TUM"}


# ----------------------------------------------------------------------------- writing


def _as_poses(world_T_body) -> np.ndarray:
    poses = np.asarray(world_T_body, dtype=np.float64)
    if poses.shape == (4, 4):
        poses = poses[None]
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"poses must have shape (N, 4, 4), got {poses.shape}")
    if not np.all(np.isfinite(poses)):
        raise ValueError("poses contain non-finite values")
    return poses


def _format_rows(table: np.ndarray) -> str:
    # repr() of a Python float is the shortest string that reads back to the same value.
    return "".join(" ".join(map(repr, row)) + "\n" for row in table.tolist())


def format_tum(timestamps_s, world_T_body) -> str:
    """TUM text of ``world_T_body`` poses at ``timestamps_s`` (exact round trip)."""
    poses = _as_poses(world_T_body)
    ts = np.asarray(timestamps_s, dtype=np.float64).ravel()
    if ts.shape[0] != poses.shape[0]:
        raise ValueError("one timestamp per pose is required")
    if not np.all(np.isfinite(ts)):
        raise ValueError("timestamps contain non-finite values")
    quat_xyzw = quaternion_from_rotation(poses[:, :3, :3]) if len(poses) else np.zeros((0, 4))
    table = np.column_stack([ts, poses[:, :3, 3], quat_xyzw])
    return _format_rows(table)


def format_kitti(world_T_body) -> str:
    """KITTI text of ``world_T_body`` poses (exact round trip)."""
    poses = _as_poses(world_T_body)
    return _format_rows(poses[:, :3, :].reshape(-1, 12))


def write_tum(path, timestamps_s, world_T_body) -> None:
    write_text_atomic(path, format_tum(timestamps_s, world_T_body))


def write_kitti(path, world_T_body) -> None:
    write_text_atomic(path, format_kitti(world_T_body))


# ----------------------------------------------------------------------------- reading


@dataclass(frozen=True, eq=False)
class TrajectoryFile:
    """A trajectory read from a file.

    Attributes:
        world_T_body: (N, 4, 4) poses.
        timestamps_s: (N,) seconds for a TUM file, None for a KITTI file.
        fmt: ``"kitti"`` or ``"tum"``.
        path: the file.
    """

    world_T_body: np.ndarray
    timestamps_s: np.ndarray | None
    fmt: str
    path: str

    def __len__(self) -> int:
        return int(self.world_T_body.shape[0])


def _read_text(path: Path, what: str) -> str:
    if not path.exists():
        raise GroundTruthError(f"{path}: no such file ({what} trajectory expected)")
    if path.is_dir():
        raise GroundTruthError(f"{path}: is a directory ({what} trajectory file expected)")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise GroundTruthError(f"{path}: cannot be read: {exc.strerror or exc}") from None
    if b"\x00" in data:  # a binary file (an .npz, an image): no text has NUL bytes
        raise GroundTruthError(f"{path}: not a text file ({what} trajectory expected)")
    try:
        return data.decode("utf-8-sig")  # (a byte-order mark, as Windows editors write, is dropped)
    except UnicodeDecodeError:
        # a legacy 8-bit encoding (e.g. an accented comment): the numbers are ASCII in any of them
        return data.decode("latin-1")


def _data_lines(text: str):
    """(line number, fields) of every non-blank, non-comment line."""
    for lineno, line in enumerate(text.splitlines(), start=1):
        content = line.split("#", 1)[0].strip()
        if content:
            yield lineno, content.split()


#: Largest |coordinate| (m) of a position read: 1e9 m is 150 times an Earth radius, beyond
#: any ECEF or UTM coordinate, and far below where squares of positions overflow (1e154).
MAX_POSITION_M = 1e9


def _check_positions(path: Path, poses: np.ndarray, lines: np.ndarray) -> np.ndarray:
    far = np.abs(poses[:, :3, 3]).max(axis=1) > MAX_POSITION_M
    if far.any():
        i = int(np.argmax(far))
        raise GroundTruthError(
            f"{path}: line {lines[i]}: position coordinate {np.abs(poses[i, :3, 3]).max():.3g} m, beyond "
            f"±{MAX_POSITION_M:.0e} m; a trajectory in metres was expected"
        )
    return poses


def _values(fields: list[str]) -> str:
    return f"{len(fields)} value" + ("" if len(fields) == 1 else "s")


def _separator_hint(fields: list[str]) -> str:
    """A hint for values separated by something else than white space (a CSV export)."""
    for sep in (",", ";"):
        if any(sep in f for f in fields):
            return f" (separated by white space; this line has {sep!r} between values)"
    return ""


def _short(s: str, n: int = 40) -> str:
    return s if len(s) <= n else s[: n - 3] + "..."


def _parse_table(path: Path, text: str, ncols: int, what: str) -> tuple[np.ndarray, np.ndarray]:
    """(table (N, ncols), line numbers (N,)) of a whitespace-separated numeric file."""
    rows: list[list[float]] = []
    linenos: list[int] = []
    for lineno, fields in _data_lines(text):
        if len(fields) != ncols:
            raise GroundTruthError(
                f"{path}: line {lineno}: {_values(fields)}; a {what} trajectory has {ncols} per line"
                f"{_separator_hint(fields)}"
            )
        try:
            rows.append([float(f) for f in fields])
        except ValueError:
            bad = next(f for f in fields if not _is_float(f))
            raise GroundTruthError(
                f"{path}: line {lineno}: non-numeric value {_short(bad)!r} ({what} trajectory expected)"
            ) from None
        linenos.append(lineno)
    if not rows:
        raise GroundTruthError(f"{path}: empty file (no poses; {what} trajectory expected)")
    table = np.array(rows, dtype=np.float64)
    lines = np.array(linenos)
    finite = np.all(np.isfinite(table), axis=1)
    if not finite.all():
        i = int(np.argmin(finite))
        raise GroundTruthError(f"{path}: line {lines[i]}: non-finite value (nan or inf) in {what} trajectory")
    return table, lines


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def detect_format(path) -> str:
    """``"kitti"`` (12 values per line) or ``"tum"`` (8 values per line), from the first
    data line of the file; :class:`GroundTruthError` for anything else."""
    path = Path(path)
    text = _read_text(path, "TUM or KITTI")
    return _detect(path, text)


def _detect(path: Path, text: str) -> str:
    for lineno, fields in _data_lines(text):
        if len(fields) == 12:
            return "kitti"
        if len(fields) == 8:
            return "tum"
        raise GroundTruthError(
            f"{path}: line {lineno}: {_values(fields)}; expected 12 (KITTI) or 8 (TUM) per line{_separator_hint(fields)}"
        )
    raise GroundTruthError(f"{path}: empty file (no poses; TUM or KITTI trajectory expected)")


def _kitti_from_table(path: Path, table: np.ndarray, lines: np.ndarray) -> np.ndarray:
    n = table.shape[0]
    poses = np.zeros((n, 4, 4))
    poses[:, :3, :] = table.reshape(n, 3, 4)
    poses[:, 3, 3] = 1.0
    R = poses[:, :3, :3]
    ortho = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    bad = (ortho > ROTATION_TOLERANCE) | (np.abs(det - 1.0) > ROTATION_TOLERANCE)
    if bad.any():
        i = int(np.argmax(bad))
        raise GroundTruthError(
            f"{path}: line {lines[i]}: the 3x3 block is not a rotation (max |R^T R - I| = {ortho[i]:.3g}, "
            f"det = {det[i]:.6g}); KITTI lines hold the top 3x4 of a rigid transform"
        )
    return _check_positions(path, poses, lines)


def _tum_from_table(path: Path, table: np.ndarray, lines: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    q = table[:, 4:]
    norms = np.linalg.norm(q, axis=1)
    bad = np.abs(norms - 1.0) > QUATERNION_NORM_TOLERANCE
    if bad.any():
        i = int(np.argmax(bad))
        raise GroundTruthError(
            f"{path}: line {lines[i]}: quaternion (qx qy qz qw) has norm {norms[i]:.6g}; expected a unit quaternion"
        )
    ts = table[:, 0]
    steps = np.diff(ts)
    if np.any(steps <= 0):
        i = int(np.argmax(steps <= 0)) + 1
        raise GroundTruthError(
            f"{path}: line {lines[i]}: timestamp {float(ts[i])!r} does not increase (previous {float(ts[i - 1])!r}); "
            "TUM timestamps must be strictly increasing"
        )
    poses = np.zeros((table.shape[0], 4, 4))
    poses[:, :3, :3] = rotation_from_quaternion(q)  # (normalizes)
    poses[:, :3, 3] = table[:, 1:4]
    poses[:, 3, 3] = 1.0
    return ts, _check_positions(path, poses, lines)


def read_kitti(path) -> np.ndarray:
    """(N, 4, 4) poses from a KITTI odometry file."""
    path = Path(path)
    table, lines = _parse_table(path, _read_text(path, "KITTI"), 12, "KITTI")
    return _kitti_from_table(path, table, lines)


def read_tum(path) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps (N,), poses (N, 4, 4)) from a TUM file."""
    path = Path(path)
    table, lines = _parse_table(path, _read_text(path, "TUM"), 8, "TUM")
    return _tum_from_table(path, table, lines)


def read_trajectory(path, fmt: str | None = None) -> TrajectoryFile:
    """Read a TUM or KITTI file; ``fmt=None`` detects the format from the number of
    values per line (12 -> KITTI, 8 -> TUM)."""
    path = Path(path)
    if fmt is not None and fmt not in _NCOLS:
        raise ValueError(f"unknown trajectory format {fmt!r}; expected 'kitti' or 'tum'")
    text = _read_text(path, _NAMES[fmt] if fmt else "TUM or KITTI")
    if fmt is None:
        fmt = _detect(path, text)
    table, lines = _parse_table(path, text, _NCOLS[fmt], _NAMES[fmt])
    if fmt == "kitti":
        return TrajectoryFile(_kitti_from_table(path, table, lines), None, "kitti", str(path))
    ts, poses = _tum_from_table(path, table, lines)
    return TrajectoryFile(poses, ts, "tum", str(path))
