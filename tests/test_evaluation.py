"""Tests of evaluation against ground truth (vislam.tools.evaluation, vislam.cli.eval)."""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO_ROOT, drifting_estimate, in_process, shared_file
from vislam.core.lie import make_pose, se3_exp, se3_inverse, so3_exp
from vislam.errors import ConfigError, GroundTruthError
from vislam.tools.evaluation import (
    associate,
    camera_to_imu_trajectory,
    evaluate,
    evaluate_associated,
    evaluate_files,
    format_table,
    load_estimate,
    load_ground_truth,
    plot_error_over_distance,
    write_metrics_json,
)
from vislam.tools.trajectory_io import TrajectoryFile, read_kitti, write_kitti, write_tum

# ----------------------------------------------------------------------------- helpers


def drive(rng, n: int, speed_m: float = 1.2) -> np.ndarray:
    """A curvy 3-D ground-truth trajectory (world_T_imu, first pose identity)."""
    k = np.arange(n - 1)
    xi = np.zeros((n - 1, 6))
    xi[:, 0] = speed_m
    xi[:, 1] = 0.02 * np.sin(k / 17.0)
    xi[:, 2] = 0.01 * np.cos(k / 23.0)
    xi[:, 5] = 0.01 * np.sin(k / 40.0) + rng.normal(0, 0.002, n - 1)
    xi[:, 3:5] = rng.normal(0, 0.001, (n - 1, 2))
    steps = se3_exp(xi)
    poses = np.empty((n, 4, 4))
    poses[0] = np.eye(4)
    for i in range(n - 1):
        poses[i + 1] = poses[i] @ steps[i]
    return poses


def dead_reckoning(timestamps, linear_velocity, angular_velocity) -> np.ndarray:
    """world_T_imu[k+1] = world_T_imu[k] @ exp(tau_k u_{k+1}), tau_k = t[k+1] - t[k]."""
    u = np.concatenate([linear_velocity, angular_velocity], axis=1)
    steps = se3_exp(np.diff(timestamps)[:, None] * u[1:])
    poses = np.empty((len(timestamps), 4, 4))
    poses[0] = np.eye(4)
    for k in range(len(steps)):
        poses[k + 1] = poses[k] @ steps[k]
    return poses


def evo_tool(name: str) -> str:
    candidate = Path(sys.executable).parent / name
    if candidate.is_file():
        return str(candidate)
    found = shutil.which(name)
    if not found:
        pytest.skip(f"{name} is not installed")
    return found


def run_evo(tmp_path, tool: str, *args: str) -> dict:
    """Run an evo command-line tool with its own HOME (evo writes ~/.evo) and return the
    statistics it saves."""
    home = tmp_path / "evo_home"
    home.mkdir(exist_ok=True)
    zip_path = tmp_path / f"evo_{len(list(tmp_path.glob('evo_*.zip')))}.zip"
    env = {**os.environ, "HOME": str(home), "MPLBACKEND": "Agg"}
    proc = subprocess.run(
        [evo_tool(tool), *args, "--no_warnings", "--save_results", str(zip_path)],
        capture_output=True, text=True, env=env, timeout=300,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    with zipfile.ZipFile(zip_path) as zf:
        return json.loads(zf.read("stats.json"))


def small_dataset(path, timestamps, cam_T_imu) -> str:
    """A valid report-convention npz with no features (only timestamps and cam_T_imu matter)."""
    T = len(timestamps)
    np.savez(
        path,
        time_stamps=np.asarray(timestamps)[None, :],
        features=np.full((4, 1, T), -1.0),
        linear_velocity=np.zeros((3, T)),
        rotational_velocity=np.zeros((3, T)),
        K=np.array([[700.0, 0.0, 600.0], [0.0, 700.0, 180.0], [0.0, 0.0, 1.0]]),
        b=np.array(0.5),
        cam_T_imu=cam_T_imu,
    )
    return str(path)


CAM_T_IMU = make_pose(so3_exp([1.2, -1.2, 1.2]), [-0.3, 0.7, -1.1])


# ----------------------------------------------------------------------------- (a) evo agreement


def test_ape_and_rpe_agree_with_evo_command_line(tmp_path):
    rng = np.random.default_rng(0)
    gt = drive(rng, 400)
    est = make_pose(so3_exp([0.1, 0.2, -0.3]), [5.0, -2.0, 1.0]) @ drifting_estimate(rng, gt)
    gt_file, est_file = tmp_path / "gt.txt", tmp_path / "est.txt"
    write_kitti(gt_file, gt)
    write_kitti(est_file, est)
    result = evaluate(read_kitti(est_file), read_kitti(gt_file))
    assert result.ape.rmse > 0.1  # a real error, not a trivial zero

    aligned = run_evo(tmp_path, "evo_ape", "kitti", str(gt_file), str(est_file), "-a")
    assert abs(result.ape.rmse - aligned["rmse"]) < 1e-6
    assert abs(result.ape.max - aligned["max"]) < 1e-6
    unaligned = run_evo(tmp_path, "evo_ape", "kitti", str(gt_file), str(est_file))
    assert abs(result.ape_unaligned.rmse - unaligned["rmse"]) < 1e-6
    rpe_t = run_evo(tmp_path, "evo_rpe", "kitti", str(gt_file), str(est_file), "-r", "trans_part", "-d", "1")
    assert abs(result.rpe_trans.rmse - rpe_t["rmse"]) < 1e-9
    rpe_r100 = run_evo(tmp_path, "evo_rpe", "kitti", str(gt_file), str(est_file), "-r", "angle_deg",
                       "-d", "100", "-u", "m", "--pairs_from_reference")
    assert abs(result.rpe_rot_100m.rmse - rpe_r100["rmse"]) < 1e-9


@pytest.mark.parametrize("errors", ["drifting", "random rotations"])
def test_rpe_rotation_angles_equal_evos(errors):
    """The RPE rotation statistics (angles of evo's relative error poses, taken in one
    batch) equal evo's own rotation_angle_deg RPE, statistic by statistic, over one frame
    and over 100 m: on a drifting estimate (small angles) and on one with a random
    rotation per pose (angles over all of [0, 180] deg, near 180 too)."""
    from evo.core import metrics as evo_metrics
    from evo.core.trajectory import PosePath3D

    from vislam.tools.evaluation import _rpe_translation_rotation

    rng = np.random.default_rng(3)
    gt = drive(rng, 300)
    est = drifting_estimate(rng, gt)
    if errors == "random rotations":
        axes = rng.normal(size=(len(gt), 3))
        axes /= np.linalg.norm(axes, axis=1, keepdims=True)
        est[:, :3, :3] = so3_exp(axes * rng.uniform(0, np.pi, (len(gt), 1))) @ est[:, :3, :3]
    ref, path = PosePath3D(poses_se3=list(gt)), PosePath3D(poses_se3=list(est))
    for delta, unit in ((1, evo_metrics.Unit.frames), (100, evo_metrics.Unit.meters)):
        trans, rot = _rpe_translation_rotation(ref, path, delta, unit)
        expected = evo_metrics.RPE(evo_metrics.PoseRelation.rotation_angle_deg, delta=delta, delta_unit=unit,
                                   all_pairs=False, pairs_from_reference=True)
        expected.process_data((ref, path))
        stats = expected.get_all_statistics()
        assert rot.n == np.size(expected.error) == trans.n > 0
        for key in ("rmse", "mean", "median", "std", "min", "max"):
            assert getattr(rot, key) == pytest.approx(stats[key], rel=1e-9, abs=1e-9), (delta, key)
        if errors == "random rotations":
            assert stats["max"] > 170.0  # the near-π branch was exercised


# ----------------------------------------------------------------------------- (b) camera -> IMU


def test_camera_ground_truth_converts_back_to_imu(tmp_path):
    rng = np.random.default_rng(1)
    world_T_imu = drive(rng, 120)
    imu_T_cam = se3_inverse(CAM_T_IMU)
    world_T_cam = CAM_T_IMU @ world_T_imu @ imu_T_cam
    np.testing.assert_allclose(world_T_cam[0], np.eye(4), atol=1e-12)  # as in the KITTI files
    path = tmp_path / "gt_cam.txt"
    write_kitti(path, world_T_cam)
    gt = load_ground_truth(path, fmt="kitti", frame="cam", cam_T_imu=CAM_T_IMU)
    np.testing.assert_allclose(gt.world_T_body, world_T_imu, rtol=0, atol=1e-9)
    np.testing.assert_allclose(camera_to_imu_trajectory(world_T_cam, CAM_T_IMU), world_T_imu, atol=1e-9)
    # frame="imu" leaves the poses alone
    np.testing.assert_array_equal(load_ground_truth(path, frame="imu").world_T_body, world_T_cam)


def test_camera_ground_truth_needs_a_rigid_cam_T_imu(tmp_path):
    path = tmp_path / "gt.txt"
    write_kitti(path, drive(np.random.default_rng(2), 10))
    with pytest.raises(ConfigError, match="cam_T_imu"):
        load_ground_truth(path, frame="cam")
    with pytest.raises(ConfigError, match="rigid"):
        load_ground_truth(path, frame="cam", cam_T_imu=2 * np.eye(4))
    with pytest.raises(ConfigError, match="format"):
        load_ground_truth(path, fmt="csv")
    with pytest.raises(ConfigError, match="frame"):
        load_ground_truth(path, frame="gps")
    with pytest.raises(GroundTruthError, match="no such file"):
        load_ground_truth(tmp_path / "missing.txt")


# ----------------------------------------------------------------------------- (c) association


def test_kitti_association_by_index_truncates_to_shorter(tmp_path, caplog):
    rng = np.random.default_rng(3)
    gt_poses = drive(rng, 45)
    est_poses = drifting_estimate(rng, drive(rng, 50))
    est = TrajectoryFile(est_poses, None, "kitti", "est.txt")
    gt = TrajectoryFile(gt_poses, None, "kitti", "gt.txt")
    with caplog.at_level(logging.INFO, logger="vislam.tools.evaluation"):
        assoc = associate(est, gt)
    assert assoc.method == "index" and assoc.n_pairs == 45
    assert (assoc.n_estimate, assoc.n_ground_truth) == (50, 45)
    np.testing.assert_array_equal(assoc.est_world_T_imu, est_poses[:45])
    np.testing.assert_array_equal(assoc.gt_world_T_imu, gt_poses)
    assert "45 frames compared" in caplog.text
    # the other way round
    assoc = associate(TrajectoryFile(est_poses[:30], None, "kitti", "e"), gt)
    assert assoc.n_pairs == 30
    np.testing.assert_array_equal(assoc.gt_world_T_imu, gt_poses[:30])


def test_doubtful_pairings_are_named_in_the_notes(tmp_path, caplog):
    """An evaluation that can be computed but is doubtful says why: a ground truth covering
    few of the estimate's poses, or an estimate whose path is much longer or shorter than
    the ground truth's (another drive's ground truth, km/h read as m/s, a diverged run).
    The estimate of the same drive, with its small drift, gets no such note."""
    rng = np.random.default_rng(5)
    gt_poses = drive(rng, 200)  # 240 m
    est_poses = drifting_estimate(rng, gt_poses)
    write_kitti(tmp_path / "gt.txt", gt_poses)
    write_kitti(tmp_path / "est.txt", est_poses)
    fast = est_poses.copy()
    fast[:, :3, 3] *= 3.6  # speeds in km/h taken for m/s
    write_kitti(tmp_path / "fast.txt", fast)
    write_kitti(tmp_path / "short_gt.txt", gt_poses[:100])

    def notes(est, gt):
        return [n for n in evaluate_files(tmp_path / est, tmp_path / gt, gt_frame="imu").notes
                if "path" in n or "have a ground-truth pose" in n]

    assert notes("est.txt", "gt.txt") == []
    with caplog.at_level(logging.WARNING, logger="vislam.tools.evaluation"):
        (note,) = notes("fast.txt", "gt.txt")
    ratio = float(note.split("m, ")[1].split("x the ground truth's")[0])
    assert 3.5 < ratio < 3.7 and "gt.txt the ground truth of this drive" in note, note
    assert note in caplog.text
    (note,) = notes("est.txt", "short_gt.txt")
    assert note.startswith("only 100 of the estimate's 200 poses have a ground-truth pose"), note
    # a standing vehicle's noisy path is not judged: below 20 m of ground truth nothing is said
    still = np.broadcast_to(np.eye(4), (200, 4, 4)).copy()
    write_kitti(tmp_path / "still.txt", still)
    assert notes("est.txt", "still.txt") == []


def test_tum_association_by_timestamp():
    rng = np.random.default_rng(4)
    n = 200
    t = 1317000000.0 + 0.1036 * np.arange(n)
    gt_poses = drive(rng, n)
    gt = TrajectoryFile(gt_poses, t, "tum", "gt.tum")
    # the estimate covers frames 20..179, every other frame, with 5 ms of time jitter
    frames = np.arange(20, 180, 2)
    est_poses = gt_poses[frames] @ se3_exp(rng.normal(0, 0.01, (len(frames), 6)))
    est = TrajectoryFile(est_poses, t[frames] + rng.uniform(-0.005, 0.005, len(frames)), "tum", "est.tum")
    assoc = associate(est, gt)
    assert assoc.method == "timestamp" and assoc.n_pairs == len(frames)
    np.testing.assert_array_equal(assoc.gt_world_T_imu, gt_poses[frames])
    np.testing.assert_array_equal(assoc.est_world_T_imu, est_poses)

    # nothing within max_diff: a clear error
    late = TrajectoryFile(est_poses, est.timestamps_s + 1000.0, "tum", "late.tum")
    with pytest.raises(GroundTruthError, match="no timestamps match"):
        associate(late, gt)

    # a KITTI estimate has no times: needs the dataset's
    kitti_est = TrajectoryFile(gt_poses[:150], None, "kitti", "est.txt")
    with pytest.raises(ConfigError, match="--dataset"):
        associate(kitti_est, gt)
    assoc = associate(kitti_est, gt, dataset_timestamps=t)
    assert assoc.method == "timestamp" and assoc.n_pairs == 150
    np.testing.assert_array_equal(assoc.gt_world_T_imu, gt_poses[:150])
    with pytest.raises(GroundTruthError, match="only 100 frames"):
        associate(kitti_est, gt, dataset_timestamps=t[:100])

    # a TUM estimate against KITTI ground truth is matched by time when the dataset gives the times
    kitti_gt = TrajectoryFile(gt_poses, None, "kitti", "gt.txt")
    assoc = associate(est, kitti_gt, dataset_timestamps=t)
    assert assoc.method == "timestamp"
    np.testing.assert_array_equal(assoc.gt_world_T_imu, gt_poses[frames])

    with pytest.raises(ConfigError):
        associate(est, gt, max_diff_s=0.0)


# ----------------------------------------------------------------------------- evaluate()


def test_evaluate_known_errors_and_outputs(tmp_path):
    rng = np.random.default_rng(5)
    gt = drive(rng, 300)
    offset = np.array([0.3, -0.4, 1.2])
    est = gt.copy()
    est[:, :3, 3] += offset  # a constant offset: removed by alignment
    r = evaluate(est, gt)
    assert r.n_frames_compared == 300
    assert r.ape_unaligned.rmse == pytest.approx(np.linalg.norm(offset), rel=1e-12)
    assert r.ape.rmse < 1e-9
    assert r.rpe_trans.rmse < 1e-9 and r.rpe_rot.rmse < 1e-5
    assert r.path_length_m == pytest.approx(299 * np.linalg.norm([1.2, 0.02, 0.01]), rel=0.01)
    assert r.kitti.has_segments
    # the alignment maps the estimate onto the ground truth
    np.testing.assert_allclose(r.alignment[:3, 3], -offset, atol=1e-9)
    np.testing.assert_allclose(r.est_world_T_imu_aligned[:, :3, 3], gt[:, :3, 3], atol=1e-9)
    np.testing.assert_allclose(r.aligned_position_error_m, 0.0, atol=1e-9)

    d = r.to_dict()
    for key in ("ape_rmse_m", "ape_unaligned_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "kitti_t_pct",
                "kitti_r_deg_per_100m", "n_frames_compared", "path_length_m"):
        assert key in d
    path = tmp_path / "out" / "metrics.json"
    write_metrics_json(r, path)
    loaded = json.loads(path.read_text())
    assert loaded["ape_unaligned_rmse_m"] == pytest.approx(np.linalg.norm(offset), rel=1e-12)
    assert loaded["n_frames_compared"] == 300
    table = format_table(r)
    assert "APE translation, SE(3)-aligned (m)" in table and "KITTI odometry" in table

    png = tmp_path / "out" / "fig.png"
    plot_error_over_distance(r, png, title="test")
    import matplotlib.image

    assert matplotlib.image.imread(png).shape[:2] == (720, 1140)  # 9.5x6 in at 120 dpi (legends right of the axes)
    assert sorted(p.name for p in png.parent.iterdir()) == ["fig.png", "metrics.json"]  # no debris


def test_positions_that_overflow_give_nan_and_notes_not_a_crash(tmp_path):
    """An estimate with one position at 1e308 m (finite, but its square overflows; the
    file readers refuse it, a library caller may not): evo's alignment SVD fails; the
    evaluation says so in its notes, its aligned metrics are NaN (null in metrics.json),
    numpy prints no floating-point warning, and the error figure is drawn."""
    import warnings

    rng = np.random.default_rng(4)
    n = 150
    gt = make_pose(so3_exp(np.c_[np.zeros(n), np.zeros(n), np.linspace(0, 1.5, n)]),
                   np.c_[np.linspace(0, 150, n), 10 * np.sin(np.linspace(0, 3, n)), np.zeros(n)])
    est = drifting_estimate(rng, gt)
    est[40, :3, 3] = 1e308
    gt_file = TrajectoryFile(path=str(tmp_path / "gt.tum"), world_T_body=gt, timestamps_s=np.arange(n) * 0.1,
                             fmt="tum")
    est_file = TrajectoryFile(path=str(tmp_path / "est.tum"), world_T_body=est, timestamps_s=np.arange(n) * 0.1,
                              fmt="tum")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = evaluate_associated(est_file, gt_file)
    assert np.isnan(r.ape.rmse)
    assert any("alignment impossible" in note for note in r.notes)
    assert any("path over the compared frames is inf m" in note for note in r.notes)
    # the same position in the ground truth: the distance along it is inf from frame 40 on
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        swapped = evaluate(gt, est)
    assert np.isinf(swapped.distance_along_gt_m[-1])
    plot_error_over_distance(swapped, tmp_path / "fig.png")
    assert (tmp_path / "fig.png").read_bytes()[:4] == b"\x89PNG"
    path = tmp_path / "m.json"
    write_metrics_json(r, path)
    assert json.loads(path.read_text())["ape_rmse_m"] is None


def test_short_and_straight_trajectories_give_nan_not_crash(tmp_path):
    # 50 m straight line: alignment is degenerate, no 100 m RPE, no KITTI segment
    n = 51
    gt = make_pose(np.broadcast_to(np.eye(3), (n, 3, 3)), np.c_[np.arange(n), np.zeros(n), np.zeros(n)])
    est = gt.copy()
    est[:, :3, 3] *= 1.1
    r = evaluate(est, gt)
    assert np.isnan(r.ape.rmse) and not np.isnan(r.ape_unaligned.rmse)
    assert np.isnan(r.rpe_trans_100m.rmse) and np.isnan(r.kitti.t_pct)
    assert len(r.notes) == 3
    path = tmp_path / "m.json"
    write_metrics_json(r, path)
    loaded = json.loads(path.read_text())  # strict JSON: NaN became null
    assert loaded["ape_rmse_m"] is None and loaded["kitti_t_pct"] is None
    assert loaded["rpe_trans_rmse_m"] == pytest.approx(0.1)
    assert "n/a" in format_table(r)
    plot_error_over_distance(r, tmp_path / "f.png")
    assert (tmp_path / "f.png").stat().st_size > 10000


def test_evaluate_rejects_mismatched_input():
    gt = drive(np.random.default_rng(6), 20)
    with pytest.raises(ValueError, match="associate"):
        evaluate(gt[:10], gt)
    with pytest.raises(GroundTruthError):
        evaluate(gt[:1], gt[:1])


# ----------------------------------------------------------------------------- (d) CLI


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "vislam", "eval", *args],
        capture_output=True, text=True, cwd=REPO_ROOT, timeout=300,
        env={**os.environ, "MPLBACKEND": "Agg"},
    )


@pytest.fixture
def cli_files(tmp_path):
    rng = np.random.default_rng(7)
    gt = drive(rng, 260)
    # the estimate has 5 more frames than the ground truth (as the shared data: 1106 vs 1101)
    est = drifting_estimate(rng, np.concatenate([gt, gt[-1] @ drive(rng, 6)[1:]]))
    gt_file, est_file = tmp_path / "gt.txt", tmp_path / "est.txt"
    write_kitti(gt_file, gt)
    write_kitti(est_file, est)
    return gt_file, est_file, gt, est


def test_cli_end_to_end(tmp_path, cli_files):
    gt_file, est_file, gt, est = cli_files
    out = tmp_path / "out"
    proc = run_cli(str(est_file), str(gt_file), "--out", str(out), "--gt-frame", "imu")
    assert proc.returncode == 0, proc.stderr
    assert "APE translation, SE(3)-aligned (m)" in proc.stdout
    metrics = json.loads((out / "metrics.json").read_text())
    expected = evaluate(est[: len(gt)], gt)
    assert metrics["n_frames_compared"] == len(gt) == 260
    for key, value in (
        ("ape_rmse_m", expected.ape.rmse),
        ("ape_unaligned_rmse_m", expected.ape_unaligned.rmse),
        ("rpe_trans_rmse_m", expected.rpe_trans.rmse),
        ("rpe_rot_rmse_deg", expected.rpe_rot.rmse),
        ("kitti_t_pct", expected.kitti.t_pct),
        ("kitti_r_deg_per_100m", expected.kitti.r_deg_per_100m),
        ("path_length_m", expected.path_length_m),
    ):
        assert metrics[key] == pytest.approx(value, rel=1e-12), key
    assert metrics["association"]["n_estimate"] == 265
    assert (out / "error_over_distance.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_camera_ground_truth_with_dataset(tmp_path):
    rng = np.random.default_rng(8)
    world_T_imu = drive(rng, 150)
    est = drifting_estimate(rng, world_T_imu)
    gt_file, est_file = tmp_path / "gt_cam.txt", tmp_path / "est.tum"
    write_kitti(gt_file, CAM_T_IMU @ world_T_imu @ se3_inverse(CAM_T_IMU))
    t = 1000.0 + 0.1 * np.arange(150)
    write_tum(est_file, t, est)
    data = small_dataset(tmp_path / "d.npz", t, CAM_T_IMU)
    out = tmp_path / "out"
    proc = run_cli(str(est_file), str(gt_file), "--out", str(out), "--gt-frame", "cam", "--dataset", data)
    assert proc.returncode == 0, proc.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["ape_rmse_m"] == pytest.approx(evaluate(est, world_T_imu).ape.rmse, rel=1e-9)
    assert metrics["association"]["method"] == "timestamp"


def _assert_one_line_error(proc, *fragments):
    assert proc.returncode != 0
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    for fragment in fragments:
        assert fragment in lines[0]


def test_cli_bad_inputs(tmp_path, cli_files, capsys):
    """The first case in a process of its own, the others by the entry point in this
    process (the exit code it returns is the process's, see __main__)."""
    def in_process_eval(*args):
        return in_process(capsys, "eval", *args)

    gt_file, est_file, _, _ = cli_files
    out = tmp_path / "out"
    missing = tmp_path / "missing.txt"
    _assert_one_line_error(run_cli(str(est_file), str(missing), "--out", str(out)), str(missing))
    _assert_one_line_error(in_process_eval(str(missing), str(gt_file), "--out", str(out)), str(missing))
    bad = tmp_path / "bad.txt"
    bad.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 zero 0 0 1 0\n")
    _assert_one_line_error(in_process_eval(str(est_file), str(bad), "--out", str(out)), str(bad), "line 2")
    _assert_one_line_error(in_process_eval(str(est_file), str(gt_file), "--out", str(out), "--gt-frame", "cam"),
                           "--dataset")
    _assert_one_line_error(in_process_eval(str(est_file), str(gt_file), "--out", str(out), "--dataset",
                                      str(tmp_path / "nope.npz")), "nope.npz")
    _assert_one_line_error(in_process_eval(str(est_file), str(gt_file), "--out", str(out), "--gt-format", "tum"),
                           str(gt_file))
    assert not out.exists()  # nothing half-written
    blocker = tmp_path / "file"
    blocker.write_text("x")
    _assert_one_line_error(in_process_eval(str(est_file), str(gt_file), "--out", str(blocker)), str(blocker))


# ----------------------------------------------------------------------------- (e) shared data


@pytest.mark.shared
def test_dead_reckoning_0027_against_ground_truth(tmp_path):
    data = shared_file("sparse/0027.npz")
    gt_cam = shared_file("groundtruth/0027.txt")
    from vislam.tools.dataset_io import load_sequence

    seq = load_sequence(data)
    est = dead_reckoning(seq.timestamps_s, seq.linear_velocity_in_imu_mps, seq.angular_velocity_in_imu_radps)
    est_file = tmp_path / "dr_0027.txt"
    write_kitti(est_file, est)
    result = evaluate_files(est_file, gt_cam, gt_format="kitti", gt_frame="cam", sequence=seq)
    assert result.n_frames_compared == 1101
    assert 1.0 < result.ape.rmse < 4.0  # measured: 2.03 m
    assert 0.5 < result.kitti.t_pct < 5.0

    # the same number from evo_ape on the converted, truncated files
    gt_imu = load_ground_truth(gt_cam, frame="cam", cam_T_imu=seq.cam_T_imu)
    gt_file, est_trunc = tmp_path / "gt_imu.txt", tmp_path / "est_1101.txt"
    write_kitti(gt_file, gt_imu.world_T_body)
    write_kitti(est_trunc, est[:1101])
    stats = run_evo(tmp_path, "evo_ape", "kitti", str(gt_file), str(est_trunc), "-a")
    assert abs(result.ape.rmse - stats["rmse"]) < 1e-6
    assert load_estimate(est_file).fmt == "kitti"
