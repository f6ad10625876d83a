"""Trajectory files: TUM (``timestamp tx ty tz qx qy qz qw``) and KITTI (12 row-major
values of the top 3x4 of each pose). Both hold ``world_T_<body>`` poses, one per line.
Writers are atomic (see :mod:`vislam.tools.atomic`).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from vislam.errors import GroundTruthError
from vislam.tools.atomic import write_text_atomic

__all__ = ["format_tum", "format_kitti", "write_tum", "write_kitti", "read_kitti", "read_tum"]


def format_tum(timestamps_s, world_T_body) -> str:
    poses = np.asarray(world_T_body, dtype=np.float64).reshape(-1, 4, 4)
    ts = np.asarray(timestamps_s, dtype=np.float64).ravel()
    if ts.shape[0] != poses.shape[0]:
        raise ValueError("one timestamp per pose is required")
    quat_xyzw = Rotation.from_matrix(poses[:, :3, :3]).as_quat()
    table = np.column_stack([ts, poses[:, :3, 3], quat_xyzw])
    buf = io.StringIO()
    np.savetxt(buf, table, fmt=["%.9f"] + ["%.9f"] * 7)
    return buf.getvalue()


def format_kitti(world_T_body) -> str:
    poses = np.asarray(world_T_body, dtype=np.float64).reshape(-1, 4, 4)
    buf = io.StringIO()
    np.savetxt(buf, poses[:, :3, :].reshape(-1, 12), fmt="%.9e")
    return buf.getvalue()


def write_tum(path, timestamps_s, world_T_body) -> None:
    write_text_atomic(path, format_tum(timestamps_s, world_T_body))


def write_kitti(path, world_T_body) -> None:
    write_text_atomic(path, format_kitti(world_T_body))


def _read_table(path, ncols: int, what: str) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise GroundTruthError(f"{path}: no such file ({what} trajectory expected)")
    try:
        with np.errstate(all="ignore"):
            table = np.loadtxt(path, dtype=np.float64, comments="#", ndmin=2)
    except (ValueError, UnicodeDecodeError) as exc:
        raise GroundTruthError(f"{path}: not a {what} trajectory ({ncols} numbers per line expected): {exc}") from None
    if table.shape[0] == 0:
        raise GroundTruthError(f"{path}: empty {what} trajectory")
    if table.shape[1] != ncols:
        raise GroundTruthError(f"{path}: {table.shape[1]} columns, a {what} trajectory has {ncols} per line")
    if not np.all(np.isfinite(table)):
        raise GroundTruthError(f"{path}: non-finite values in {what} trajectory")
    return table


def read_kitti(path) -> np.ndarray:
    """(N, 4, 4) poses from a KITTI odometry file."""
    table = _read_table(path, 12, "KITTI")
    poses = np.tile(np.eye(4), (table.shape[0], 1, 1))
    poses[:, :3, :] = table.reshape(-1, 3, 4)
    return poses


def read_tum(path) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps (N,), poses (N, 4, 4)) from a TUM file."""
    table = _read_table(path, 8, "TUM")
    norms = np.linalg.norm(table[:, 4:], axis=1)
    if np.any(norms < 1e-6):
        raise GroundTruthError(f"{path}: zero quaternion in TUM trajectory")
    poses = np.tile(np.eye(4), (table.shape[0], 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(table[:, 4:] / norms[:, None]).as_matrix()
    poses[:, :3, 3] = table[:, 1:4]
    return table[:, 0], poses
