"""``vislam simulate --images``: a simulated drive written as a KITTI raw date folder.

:func:`write_rendered_drive` renders the drive's rectified grey stereo pairs
(:mod:`vislam.core.render`) and writes, into ``out_dir`` (the *date folder*)::

    calib_cam_to_cam.txt, calib_velo_to_cam.txt, calib_imu_to_velo.txt
    sim_drive_SSSS_sync/image_00/data/0000000000.png ... , image_00/timestamps.txt
    sim_drive_SSSS_sync/image_01/...                        (SSSS: the seed)
    sim_drive_SSSS_sync/oxts/data/0000000000.txt ... , oxts/timestamps.txt
    groundtruth.kitti, groundtruth.tum, sequence.npz, landmarks_true.npz
    scene_planes.npz                                         (the rendered planes)

The calibration files hold the drive's camera exactly (``P_rect_00 = [K | 0]``,
``P_rect_01 = [K | -fx b]``, ``R_rect_00 = I``, ``T_velo→cam = cam_T_imu``,
``T_imu→velo = I``, printed with 13 significant digits), so reading them back with
:func:`vislam.tools.frontend_io.read_kitti_calibration` gives the drive's K, b and
cam_T_imu. The OXTS packets hold the recorded velocities (``vf vl vu`` = the sequence's
linear velocity, ``wf wl wu`` its angular velocity) and the true roll, pitch, yaw; the
other fields (GPS position, accelerations, accuracies) are 0. ``sequence.npz`` is the
simulator's own point-feature observations of the same drive, to compare with.

``scene_planes.npz``: ``origin``, ``e1``, ``e2``, ``normal`` (Q, 3), ``lengths`` (Q, 2):
rectangle ``origin + a e1 + b e2``, ``0 <= a <= lengths[:, 0]``, ``0 <= b <= lengths[:, 1]``
(world frame, m) — the true geometry every image pixel shows.

Everything appears at once or not at all (an :class:`~vislam.tools.outputs.OutputStage`).
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

import numpy as np

from vislam.core.render import RenderOptions, build_scene, camera_poses, render_pair
from vislam.core.simulate import SimulatedDrive
from vislam.tools.npz import write_npz

__all__ = ["write_rendered_drive", "drive_folder_name", "write_kitti_calibration", "kitti_timestamp_lines"]


def drive_folder_name(seed: int) -> str:
    return f"sim_drive_{int(seed):04d}_sync"


def _numbers(values) -> str:
    return " ".join(f"{float(v):.12e}" for v in np.ravel(values))


def write_kitti_calibration(date_dir, K, baseline_m: float, cam_T_imu, image_size_px) -> None:
    """The three KITTI calibration files for a rectified pair with ``R_rect_00 = I`` and
    ``T_imu→velo = I`` (so ``T_velo→cam = cam_T_imu``)."""
    from vislam.tools.atomic import write_text_atomic

    date_dir = Path(date_dir)
    K = np.asarray(K, dtype=np.float64)
    P0 = np.hstack([K, np.zeros((3, 1))])
    P1 = P0.copy()
    P1[0, 3] = -K[0, 0] * baseline_m
    size = _numbers(image_size_px)
    write_text_atomic(date_dir / "calib_cam_to_cam.txt", "\n".join([
        "calib_time: simulated by vislam",
        f"S_rect_00: {size}", f"R_rect_00: {_numbers(np.eye(3))}", f"P_rect_00: {_numbers(P0)}",
        f"S_rect_01: {size}", f"R_rect_01: {_numbers(np.eye(3))}", f"P_rect_01: {_numbers(P1)}", ""]))
    T = np.asarray(cam_T_imu, dtype=np.float64)
    write_text_atomic(date_dir / "calib_velo_to_cam.txt", "\n".join([
        "calib_time: simulated by vislam", f"R: {_numbers(T[:3, :3])}", f"T: {_numbers(T[:3, 3])}", ""]))
    write_text_atomic(date_dir / "calib_imu_to_velo.txt", "\n".join([
        "calib_time: simulated by vislam", f"R: {_numbers(np.eye(3))}", f"T: {_numbers(np.zeros(3))}", ""]))


def kitti_timestamp_lines(timestamps_s) -> str:
    """KITTI ``timestamps.txt`` text (UTC, nanoseconds) of UNIX times."""
    lines = []
    for t in np.asarray(timestamps_s, dtype=np.float64):
        whole = int(np.floor(t))
        ns = int(round((t - whole) * 1e9))
        if ns >= 1_000_000_000:
            whole, ns = whole + 1, ns - 1_000_000_000
        stamp = _dt.datetime.fromtimestamp(whole, tz=_dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S")
        lines.append(f"{stamp}.{ns:09d}")
    return "\n".join(lines) + "\n"


def _oxts_lines(drive: SimulatedDrive) -> list[str]:
    seq = drive.sequence
    R = drive.world_T_imu[:, :3, :3]
    yaw = np.arctan2(R[:, 1, 0], R[:, 0, 0])
    pitch = -np.arcsin(np.clip(R[:, 2, 0], -1, 1))
    roll = np.arctan2(R[:, 2, 1], R[:, 2, 2])
    out = []
    for k in range(seq.n_frames):
        packet = np.zeros(30)
        packet[3:6] = roll[k], pitch[k], yaw[k]
        packet[8:11] = seq.linear_velocity_in_imu_mps[k]  # vf vl vu
        packet[20:23] = seq.angular_velocity_in_imu_radps[k]  # wf wl wu
        out.append(" ".join(f"{v:.15g}" for v in packet) + "\n")
    return out


def write_rendered_drive(drive: SimulatedDrive, out_dir, options: RenderOptions | None = None,
                         progress=None) -> list[Path]:
    """Render and write ``drive`` into the date folder ``out_dir`` (see the module docstring);
    returns the top-level paths written. ``progress``: optional callable(frames done)."""
    import cv2

    from vislam.tools.outputs import OutputStage
    from vislam.tools.simulate_io import write_simulated_drive

    o = options or RenderOptions()
    seq = drive.sequence
    K, b = seq.camera.K, seq.camera.baseline_m
    scene = build_scene(drive.world_T_imu, drive.options.ground_below_imu_m, drive.options.seed, o)
    poses = camera_poses(drive.world_T_imu, seq.cam_T_imu)
    rng = np.random.default_rng([drive.options.seed, 2121])
    name = drive_folder_name(drive.options.seed)
    with OutputStage(out_dir) as stage:
        root = stage.staging
        write_kitti_calibration(root, K, b, seq.cam_T_imu, (o.width_px, o.height_px))
        drive_dir = root / name
        stamps = kitti_timestamp_lines(seq.timestamps_s)
        for cam in ("image_00", "image_01"):
            (drive_dir / cam / "data").mkdir(parents=True)
            (drive_dir / cam / "timestamps.txt").write_text(stamps)
        (drive_dir / "oxts" / "data").mkdir(parents=True)
        (drive_dir / "oxts" / "timestamps.txt").write_text(stamps)
        for k, line in enumerate(_oxts_lines(drive)):
            (drive_dir / "oxts" / "data" / f"{k:010d}.txt").write_text(line)
        for k in range(seq.n_frames):
            left, right = render_pair(scene, poses[k], K, b, o, rng)
            for cam, image in (("image_00", left), ("image_01", right)):
                cv2.imwrite(str(drive_dir / cam / "data" / f"{k:010d}.png"), image)
            if progress is not None:
                progress(k + 1)
        write_simulated_drive(drive, root)
        write_npz(root / "scene_planes.npz", {"origin": scene.origin, "e1": scene.e1, "e2": scene.e2,
                                              "normal": scene.normal, "lengths": scene.lengths})
        written = stage.commit(replace_directories=True)
    return sorted(written)
