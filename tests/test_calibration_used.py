"""One calibration, recorded and used everywhere (issue 24, items 3 and 4).

* Every run's :class:`~vislam.core.results.RunResult` carries the ``cam_T_imu`` its filter
  used (``calibration``) and summary.json records it (``calibration.cam_T_imu``) beside the
  data file's; ``vislam eval RUN/trajectory.kitti GT`` without flags converts camera
  ground truth with it, and so do ``run --gt``, ``compare`` and ``sweep``
  (:func:`vislam.tools.comparison.evaluate_run`).
* ``vislam sweep`` reads KITTI ground truth as camera poses by default, and says so.
* Where the ground truth holds camera poses, the camera-frame ATE and KITTI metric: the
  estimate as ``world_T_imu @ imu_T_cam`` against the ground truth as it is.

The drive is the simulator's, its ground truth written as KITTI left-camera poses
(``groundtruth.kitti``, as the shared data's ``groundtruth/*.txt``). Direct computations
here use numpy only (an SVD Umeyama alignment), not evo, which the tool uses.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from conftest import drifting_estimate, shared_file
from vislam.cli import main
from vislam.core.corrections import apply_corrections, calibration_used, rotate_cam_T_imu
from vislam.core.estimators import run as run_estimator
from vislam.core.lie import se3_exp, se3_inverse
from vislam.core.metrics import kitti_odometry_errors
from vislam.core.options import FilterOptions
from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.tools.comparison import evaluate_run, load_run_ground_truth
from vislam.tools.evaluation import evaluate
from vislam.tools.simulate_io import write_simulated_drive
from vislam.tools.sweep import parse_spec, run_cell
from vislam.tools.trajectory_io import camera_to_imu_trajectory, read_kitti

N_FRAMES = 150
N_SHORT = 50


def umeyama_rmse(est_xyz: np.ndarray, gt_xyz: np.ndarray) -> float:
    """RMSE of the positions after the rigid (SE(3), no scale) least-squares alignment of
    ``est_xyz`` onto ``gt_xyz`` (Umeyama 1991), by hand."""
    mu_e, mu_g = est_xyz.mean(0), gt_xyz.mean(0)
    cov = (gt_xyz - mu_g).T @ (est_xyz - mu_e) / len(est_xyz)
    U, _, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    S[2, 2] = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    R = U @ S @ Vt
    t = mu_g - R @ mu_e
    return float(np.sqrt(np.mean(np.sum((est_xyz @ R.T + t - gt_xyz) ** 2, axis=1))))


def _simulated(root, n_frames: int) -> dict:
    drive = simulate_drive(SimulationOptions(n_frames=n_frames, seed=4, velocity_noise_mps=0.3,
                                             angular_noise_radps=0.01))
    write_simulated_drive(drive, root / "sim")
    return {"root": root, "drive": drive, "data": root / "sim" / "sequence.npz",
            "gt": root / "sim" / "groundtruth.kitti", "file_cam_T_imu": drive.sequence.cam_T_imu}


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """A simulated drive (long enough for KITTI segments) on disk: sequence.npz (cam_T_imu
    = the shared files') and groundtruth.kitti (left-camera poses)."""
    return _simulated(tmp_path_factory.mktemp("calib"), N_FRAMES)


@pytest.fixture(scope="module")
def short(tmp_path_factory):
    """A short simulated drive, for the command-line runs."""
    return _simulated(tmp_path_factory.mktemp("calib_short"), N_SHORT)


def corrected_cam_T_imu(file_cam_T_imu: np.ndarray) -> np.ndarray:
    """Another calibration than the file's: translation moved by (0.3, -0.5, 0.8) m and the
    rotation turned by 2 degrees (the kind of correction issue 24 is about)."""
    out = rotate_cam_T_imu(file_cam_T_imu, (0.0, 2.0, 0.0))
    out[:3, 3] += (0.3, -0.5, 0.8)
    return out


def _main(capsys, *args):
    code = main([str(a) for a in args])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


# ----------------------------------------------------------------------------- item 3


def test_run_result_carries_the_calibration_after_corrections(sim):
    seq = sim["drive"].sequence
    override = corrected_cam_T_imu(seq.cam_T_imu)
    options = FilterOptions(cam_T_imu=tuple(map(tuple, override)), imu_camera_rotation_correction_deg=(0.5, 0, 0))
    result = run_estimator(seq, "localization", options)
    expected = rotate_cam_T_imu(override, (0.5, 0, 0))  # the override first, then the rotation (step 4)
    np.testing.assert_allclose(result.calibration.cam_T_imu, expected, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(result.calibration.recorded_cam_T_imu, seq.cam_T_imu)
    assert [c["field"] for c in result.calibration.corrections] == ["cam_T_imu", "imu_camera_rotation_correction_deg"]
    assert result.calibration.corrected
    # the same when the caller corrected the sequence first (as vislam run does)
    corrected = apply_corrections(seq, options)
    np.testing.assert_array_equal(corrected.recorded_cam_T_imu, seq.cam_T_imu)
    again = run_estimator(corrected, "localization", options)
    np.testing.assert_array_equal(again.calibration.cam_T_imu, result.calibration.cam_T_imu)
    np.testing.assert_array_equal(again.calibration.recorded_cam_T_imu, seq.cam_T_imu)
    # without corrections: the file's, nothing listed
    plain = calibration_used(seq)
    assert not plain.corrected and plain.corrections == ()


def test_summary_names_where_each_correction_came_from(sim):
    from vislam.tools.outputs import build_summary

    seq = sim["drive"].sequence
    result = run_estimator(seq, "localization", FilterOptions(imu_camera_rotation_correction_deg=(0.0, 1.5, 0.0)))
    dataset = {"name": seq.name, "cam_T_imu": seq.cam_T_imu.tolist()}

    def source(suggested):
        summary = build_summary(result, dataset=dataset, duration_s=seq.duration_s, start_time=None,
                                extra={"auto": {"suggested": suggested}} if suggested is not None else None)
        (correction,) = summary["calibration"]["corrections"]
        assert correction["field"] == "imu_camera_rotation_correction_deg" and correction["value"] == [0, 1.5, 0]
        return correction["source"]

    assert source({"imu_camera_rotation_correction_deg": [0.0, 1.5, 0.0]}) == "vislam check's suggestion (--auto)"
    # an options file that overrides --auto's suggestion, or no --auto at all: the options
    assert source({"imu_camera_rotation_correction_deg": [0.0, 1.0, 0.0]}) == "the filter options (options file)"
    assert source(None) == "the filter options (options file)"


def test_eval_without_flags_uses_the_calibration_the_filter_used(sim, tmp_path, capsys):
    file_cam_T_imu = sim["file_cam_T_imu"]
    override = corrected_cam_T_imu(file_cam_T_imu)
    config = tmp_path / "options.yaml"
    config.write_text(yaml.safe_dump({"cam_T_imu": override.tolist()}))
    run_dir = tmp_path / "run"
    code, _, err = _main(capsys, "run", sim["data"], "--mode", "localization", "--config", config, "--out", run_dir,
                         "--quiet", "--gt", sim["gt"])
    assert code == 0, err
    summary = json.loads((run_dir / "summary.json").read_text())
    cal = summary["calibration"]
    np.testing.assert_allclose(cal["cam_T_imu"], override, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(cal["file_cam_T_imu"], file_cam_T_imu)
    np.testing.assert_array_equal(summary["dataset"]["cam_T_imu"], file_cam_T_imu)  # the file's, as recorded
    assert cal["corrected"] and [c["field"] for c in cal["corrections"]] == ["cam_T_imu"]
    assert cal["corrections"][0]["source"] == "the filter options (options file)"

    # the truth: the ground truth's camera poses converted with the transform the filter used
    est = read_kitti(run_dir / "trajectory.kitti")
    gt_cam = read_kitti(sim["gt"])[: len(est)]
    direct = evaluate(est, camera_to_imu_trajectory(gt_cam, override)).ape.rmse
    with_file = evaluate(est, camera_to_imu_trajectory(gt_cam, file_cam_T_imu)).ape.rmse
    assert abs(direct - with_file) > 1e-3  # the two transforms give different answers: the test can fail

    code, printed, err = _main(capsys, "eval", run_dir / "trajectory.kitti", sim["gt"], "--out", tmp_path / "e")
    assert code == 0, err
    metrics = json.loads((tmp_path / "e" / "metrics.json").read_text())
    assert metrics["ape_rmse_m"] == pytest.approx(direct, rel=0, abs=1e-9)
    np.testing.assert_allclose(metrics["cam_T_imu"], override, rtol=0, atol=1e-15)
    assert "calibration.cam_T_imu, the transform the filter used, corrected from the data file's" in \
        metrics["cam_T_imu_source"]
    assert "the transform the filter used" in printed  # and it says which it used
    # run --gt evaluated the same way in the same run
    assert summary["evaluation"]["ape_rmse_m"] == pytest.approx(direct, rel=0, abs=1e-9)
    # --dataset of the same file: still the filter's (the summary belongs to that file)
    code, _, err = _main(capsys, "eval", run_dir / "trajectory.kitti", sim["gt"], "--dataset", sim["data"],
                         "--out", tmp_path / "e2")
    assert code == 0, err
    assert json.loads((tmp_path / "e2" / "metrics.json").read_text())["ape_rmse_m"] == pytest.approx(
        direct, rel=0, abs=1e-9)


def test_evaluate_run_converts_with_the_run_calibration_whatever_the_ground_truth_was_loaded_with(sim):
    seq = sim["drive"].sequence
    override = corrected_cam_T_imu(seq.cam_T_imu)
    gt = load_run_ground_truth(sim["gt"], seq)  # converted with the file's transform
    result = run_estimator(seq, "localization", FilterOptions(cam_T_imu=tuple(map(tuple, override))))
    ev = evaluate_run(result, gt, seq)
    direct = evaluate(result.world_T_imu, camera_to_imu_trajectory(read_kitti(sim["gt"]), override)).ape.rmse
    assert ev.ape.rmse == pytest.approx(direct, rel=0, abs=1e-9)
    np.testing.assert_allclose(ev.cam_T_imu, override, rtol=0, atol=1e-15)


def test_compare_with_auto_style_rotation_correction_records_and_uses_it(short, tmp_path, capsys):
    config = tmp_path / "options.yaml"
    config.write_text("imu_camera_rotation_correction_deg: [0.0, 1.5, 0.0]\n")
    out = tmp_path / "cmp"
    code, printed, err = _main(capsys, "compare", short["data"], "--methods", "slam", "--config", config,
                               "--out", out, "--gt", short["gt"])
    assert code == 0, err
    summary = json.loads((out / "slam" / "summary.json").read_text())
    used = rotate_cam_T_imu(short["file_cam_T_imu"], (0.0, 1.5, 0.0))
    np.testing.assert_allclose(summary["calibration"]["cam_T_imu"], used, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(summary["dataset"]["cam_T_imu"], short["file_cam_T_imu"])
    est = read_kitti(out / "slam" / "trajectory.kitti")
    gt_cam = read_kitti(short["gt"])
    direct = evaluate(est, camera_to_imu_trajectory(gt_cam, used)).ape.rmse
    assert summary["evaluation"]["ape_rmse_m"] == pytest.approx(direct, rel=0, abs=1e-9)
    direct_cam = umeyama_rmse((est @ se3_inverse(used))[:, :3, 3], gt_cam[:, :3, 3])
    assert summary["evaluation"]["cam_ape_rmse_m"] == pytest.approx(direct_cam, rel=0, abs=1e-9)
    assert "cam ATE m" in printed and "IMU ATE m" in printed


def _spec(sim, tmp_path, gt_frame: str | None, options: dict | None = None):
    entry = {"path": str(sim["data"]), "groundtruth": str(sim["gt"])}
    if gt_frame is not None:
        entry["gt_frame"] = gt_frame
    return parse_spec({"datasets": [entry], "modes": ["localization"], "options": {"o": options or {}}},
                      source=str(tmp_path / "spec.yaml"), base_dir=tmp_path)


def test_sweep_reads_kitti_ground_truth_as_camera_poses_by_default(sim, tmp_path):
    seq = sim["drive"].sequence
    (cell,) = _spec(sim, tmp_path, None).cells()
    row = run_cell(cell)
    assert row["status"] == "ok", row["error"]
    assert row["gt_frame"] == "cam"
    est = run_estimator(seq, "localization").world_T_imu
    gt_cam = read_kitti(sim["gt"])
    as_camera = evaluate(est, camera_to_imu_trajectory(gt_cam, seq.cam_T_imu)).ape.rmse
    as_imu = evaluate(est, gt_cam).ape.rmse  # the old default: KITTI camera poses read as IMU poses
    assert abs(as_camera - as_imu) > 1e-3
    assert row["ate_m"] == pytest.approx(as_camera, rel=0, abs=1e-9)
    assert row["cam_ate_m"] == pytest.approx(umeyama_rmse((est @ seq.imu_T_cam)[:, :3, 3], gt_cam[:, :3, 3]),
                                             rel=0, abs=1e-9)
    # asked for explicitly, the IMU reading is still there, and says so
    (cell_imu,) = _spec(sim, tmp_path, "imu").cells()
    row_imu = run_cell(cell_imu)
    assert row_imu["gt_frame"] == "imu" and row_imu["cam_ate_m"] is None
    assert row_imu["ate_m"] == pytest.approx(as_imu, rel=0, abs=1e-9)
    # an option set's cam_T_imu is the transform the cell's ground truth is converted with
    override = corrected_cam_T_imu(seq.cam_T_imu)
    (cell_o,) = _spec(sim, tmp_path, None, {"cam_T_imu": override.tolist()}).cells()
    row_o = run_cell(cell_o)
    assert row_o["ate_m"] == pytest.approx(evaluate(est, camera_to_imu_trajectory(gt_cam, override)).ape.rmse,
                                           rel=0, abs=1e-9)


# ----------------------------------------------------------------------------- item 4


def test_camera_frame_metrics_equal_a_direct_computation(sim):
    drive = sim["drive"]
    cam_T_imu = drive.sequence.cam_T_imu
    gt_imu = drive.world_T_imu
    gt_cam = cam_T_imu @ gt_imu @ se3_inverse(cam_T_imu)  # the KITTI convention: world = first camera
    est = drifting_estimate(np.random.default_rng(3), gt_imu, sigma_t=0.05, sigma_r=0.003)
    ev = evaluate(est, camera_to_imu_trajectory(gt_cam, cam_T_imu), gt_world_T_cam=gt_cam, cam_T_imu=cam_T_imu)
    est_cam = est @ se3_inverse(cam_T_imu)  # world_T_cam = world_T_imu @ imu_T_cam
    assert ev.camera.ape.rmse == pytest.approx(umeyama_rmse(est_cam[:, :3, 3], gt_cam[:, :3, 3]), rel=1e-9)
    assert ev.ape.rmse == pytest.approx(umeyama_rmse(est[:, :3, 3], gt_imu[:, :3, 3]), rel=1e-9)
    kitti_cam = kitti_odometry_errors(est_cam, gt_cam)
    assert kitti_cam.has_segments
    assert ev.camera.kitti.t_pct == pytest.approx(kitti_cam.t_pct, rel=1e-9)
    # (rel. 1e-9: evaluate projects the rotation blocks onto SO(3) first)
    assert ev.camera.kitti.r_deg_per_100m == pytest.approx(kitti_cam.r_deg_per_100m, rel=1e-9)
    d = ev.to_dict()
    assert d["cam_ape_rmse_m"] == ev.camera.ape.rmse and d["cam_kitti_t_pct"] == ev.camera.kitti.t_pct
    assert d["ape_rmse_m"] == ev.ape.rmse  # the IMU-frame numbers keep their keys
    # no camera ground truth: no camera numbers, and the keys say so
    imu_only = evaluate(est, gt_imu).to_dict()
    assert imu_only["cam_ape_rmse_m"] is None and "no camera-frame metrics" in imu_only["metrics_frames"]


def test_a_pure_lever_arm_error_shows_in_one_frame_only(sim):
    """With the correct calibration, the position error a rotation error causes through the
    lever arm: an estimate with the IMU positions exact and the orientations wrong has no
    IMU-frame ATE but a camera-frame ATE (the camera sits at the end of the lever arm), and
    one with the camera positions exact and the same orientations wrong the other way round.
    Umeyama alignment never increases the error, so the aligned camera-frame ATE is at most
    the RMS of |(R_err - I) t| and (for these small, varying errors) most of it."""
    drive = sim["drive"]
    cam_T_imu = drive.sequence.cam_T_imu
    imu_T_cam = se3_inverse(cam_T_imu)
    lever = np.linalg.norm(imu_T_cam[:3, 3])  # 1.4 m: the camera's position in the IMU frame
    gt_imu = drive.world_T_imu
    gt_cam = cam_T_imu @ gt_imu @ imu_T_cam
    n = len(gt_imu)
    rng = np.random.default_rng(7)
    angles = np.zeros((n, 6))
    angles[:, 3:] = rng.normal(0, np.radians(2.0), (n, 3))  # rotation error only, about the body origin
    err = se3_exp(angles)

    def metrics(est_imu):
        ev = evaluate(est_imu, camera_to_imu_trajectory(gt_cam, cam_T_imu), gt_world_T_cam=gt_cam,
                      cam_T_imu=cam_T_imu)
        return ev.ape.rmse, ev.camera.ape.rmse

    # orientation error about the IMU: IMU positions exact
    est_a = gt_imu @ err
    imu_ate, cam_ate = metrics(est_a)
    offsets = (est_a @ imu_T_cam)[:, :3, 3] - (gt_imu @ imu_T_cam)[:, :3, 3]
    unaligned = float(np.sqrt(np.mean(np.sum(offsets ** 2, axis=1))))
    assert imu_ate < 1e-6
    assert 0.5 * unaligned < cam_ate <= unaligned + 1e-12
    assert unaligned < lever * np.radians(2.0) * np.sqrt(3) * 1.5  # the size a lever arm gives it

    # the same orientation error about the camera: camera positions exact
    # world_T_imu = world_T_cam @ cam_T_imu, in the IMU world frame (world = first IMU) as estimates are
    est_b = imu_T_cam @ (gt_cam @ err) @ cam_T_imu
    imu_ate_b, cam_ate_b = metrics(est_b)
    assert cam_ate_b < 1e-6
    assert imu_ate_b > 0.5 * lever * np.radians(2.0)


# ----------------------------------------------------------------------------- the shared data


@pytest.mark.slow
def test_eval_of_a_corrected_run_on_the_shared_ground_truth(tmp_path, capsys):
    """Issue 24's "Done when": a run of sparse 0027 with a corrected cam_T_imu (the
    published translation, see the data README), evaluated by ``vislam eval
    RUN/trajectory.kitti groundtruth/0027.txt`` without flags, gives the ATE of the ground
    truth converted with the transform the filter used."""
    data = shared_file("sparse/0027.npz")
    gt_path = shared_file("groundtruth/0027.txt")
    from vislam.tools.dataset_io import load_sequence

    file_cam_T_imu = load_sequence(data).cam_T_imu
    published = file_cam_T_imu.copy()
    published[:3, 3] = (-0.316, 0.734, -1.138)  # KITTI's published cam_T_imu translation, 2011_09_30
    config = tmp_path / "published.yaml"
    config.write_text(yaml.safe_dump({"cam_T_imu": published.tolist()}))
    run_dir = tmp_path / "run"
    code, _, err = _main(capsys, "run", data, "--mode", "localization", "--config", config, "--out", run_dir,
                         "--quiet")
    assert code == 0, err
    code, _, err = _main(capsys, "eval", run_dir / "trajectory.kitti", gt_path, "--out", tmp_path / "e")
    assert code == 0, err
    metrics = json.loads((tmp_path / "e" / "metrics.json").read_text())
    est = read_kitti(run_dir / "trajectory.kitti")
    gt_cam = read_kitti(gt_path)
    n = len(gt_cam)
    direct = evaluate(est[:n], camera_to_imu_trajectory(gt_cam, published)).ape.rmse
    with_file = evaluate(est[:n], camera_to_imu_trajectory(gt_cam, file_cam_T_imu)).ape.rmse
    assert abs(direct - with_file) > 0.1
    assert metrics["ape_rmse_m"] == pytest.approx(direct, rel=0, abs=1e-9)
    direct_cam = umeyama_rmse((est[:n] @ se3_inverse(published))[:, :3, 3], gt_cam[:, :3, 3])
    assert metrics["cam_ape_rmse_m"] == pytest.approx(direct_cam, rel=0, abs=1e-9)
