"""Defaults of the ground-truth frame that cannot mislead (``vislam eval``, ``vislam run --gt``).

KITTI ground truth holds left-camera poses by the format's convention, so ``--gt-frame
auto`` (the default) reads it as the camera; ``cam_T_imu`` comes from ``--dataset``, else
from the ``summary.json`` of the run folder the estimate sits in, else the command
refuses with one line. TUM ground truth defaults to the IMU.

The ground truth here is a simulated drive's: IMU poses ``world_T_imu`` and the same
poses as left-camera poses in KITTI form, ``world_T_cam = cam_T_imu @ world_T_imu @
imu_T_cam`` (world = first camera frame, as the KITTI files; the inverse of
:func:`vislam.tools.evaluation.camera_to_imu_trajectory`).
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from conftest import shared_file
from vislam.cli import main
from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.errors import ConfigError
from vislam.tools.evaluation import evaluate, load_ground_truth
from vislam.tools.simulate_io import write_simulated_drive
from vislam.tools.trajectory_io import read_kitti, read_tum, write_kitti


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """A simulated drive on disk, a localization run of it, and its ground truth as
    camera poses (KITTI) and IMU poses (KITTI and TUM)."""
    root = tmp_path_factory.mktemp("evaldefaults")
    drive = simulate_drive(SimulationOptions(n_frames=150, seed=4, velocity_noise_mps=0.3, angular_noise_radps=0.01))
    write_simulated_drive(drive, root / "sim")
    data = root / "sim" / "sequence.npz"
    run_dir = root / "run"
    assert main(["run", str(data), "--mode", "localization", "--out", str(run_dir), "--quiet"]) == 0
    cam_T_imu = drive.sequence.cam_T_imu
    assert not np.allclose(cam_T_imu[:3, :3], np.eye(3))  # the conversion matters
    world_T_cam = cam_T_imu @ drive.world_T_imu @ np.linalg.inv(cam_T_imu)
    gt_cam = root / "gt_cam.kitti"
    write_kitti(gt_cam, world_T_cam)
    gt_imu = root / "gt_imu.kitti"
    write_kitti(gt_imu, drive.world_T_imu)
    est = read_kitti(run_dir / "trajectory.kitti")
    return {
        "root": root, "data": data, "run": run_dir, "drive": drive, "gt_cam": gt_cam, "gt_imu": gt_imu,
        "gt_tum": root / "sim" / "groundtruth.tum",
        # the true answer, computed directly from the poses
        "ate": evaluate(est, drive.world_T_imu).ape.rmse,
    }


def _eval(capsys, *args):
    code = main(["eval", *map(str, args)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _metrics(out_dir):
    return json.loads((out_dir / "metrics.json").read_text())


def _assert_refused(code, err, out_dir, *fragments):
    assert code != 0
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("vislam eval: error:"), err
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    assert not out_dir.exists()  # nothing written


def test_simulated_kitti_ground_truth_holds_camera_poses(sim):
    # vislam simulate follows the KITTI convention too, so its files work with the defaults
    np.testing.assert_allclose(read_kitti(sim["root"] / "sim" / "groundtruth.kitti"), read_kitti(sim["gt_cam"]),
                               rtol=0, atol=1e-9)
    summary = json.loads((sim["run"] / "summary.json").read_text())
    np.testing.assert_array_equal(summary["dataset"]["cam_T_imu"], sim["drive"].sequence.cam_T_imu)
    assert summary["dataset"]["path"] == str(sim["data"].resolve())


def test_eval_kitti_default_is_camera_with_cam_T_imu_from_the_run_summary(sim, tmp_path, capsys):
    est = sim["run"] / "trajectory.kitti"
    code, printed, err = _eval(capsys, est, sim["gt_cam"], "--out", tmp_path / "default")
    assert code == 0, err
    default = _metrics(tmp_path / "default")
    code, _, err = _eval(capsys, est, sim["gt_cam"], "--gt-frame", "cam", "--dataset", sim["data"],
                         "--out", tmp_path / "explicit")
    assert code == 0, err
    explicit = _metrics(tmp_path / "explicit")
    assert default["ape_rmse_m"] == pytest.approx(explicit["ape_rmse_m"], rel=0, abs=1e-9)
    assert default["ape_rmse_m"] == pytest.approx(sim["ate"], rel=0, abs=1e-9)
    assert default["kitti_t_pct"] == pytest.approx(explicit["kitti_t_pct"], rel=1e-9, nan_ok=True)
    # recorded and printed: which frame, why, and where cam_T_imu came from
    summary_path = str(sim["run"].resolve() / "summary.json")
    assert default["ground_truth_frame"] == "cam" and default["ground_truth_frame_requested"] == "auto"
    # the transform the filter used, recorded by the run (no correction here: the file's)
    assert default["cam_T_imu_source"] == f"{summary_path} (calibration.cam_T_imu, the transform the filter used)"
    np.testing.assert_array_equal(default["cam_T_imu"], sim["drive"].sequence.cam_T_imu)
    assert explicit["ground_truth_frame_requested"] == "cam"
    # --dataset of the same data file: the run's calibration still wins (it is what the filter used)
    assert explicit["cam_T_imu_source"] == default["cam_T_imu_source"]
    header = next(line for line in printed.splitlines() if line.startswith("ground truth:"))
    assert "left-camera poses (default for KITTI ground truth)" in header and summary_path in header


def test_eval_refuses_camera_ground_truth_without_cam_T_imu(sim, tmp_path, capsys):
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    est = outside / "trajectory.kitti"
    shutil.copy(sim["run"] / "trajectory.kitti", est)
    code, _, err = _eval(capsys, est, sim["gt_cam"], "--out", tmp_path / "e")
    _assert_refused(code, err, tmp_path / "e", str(sim["gt_cam"]), "--dataset DATA", "--gt-frame imu",
                    str(outside / "summary.json"))
    code, _, err = _eval(capsys, est, sim["gt_cam"], "--gt-frame", "cam", "--out", tmp_path / "e")
    _assert_refused(code, err, tmp_path / "e", "--dataset DATA")
    # with the dataset it works, and gives the right answer
    code, _, err = _eval(capsys, est, sim["gt_cam"], "--dataset", sim["data"], "--out", tmp_path / "e")
    assert code == 0, err
    assert _metrics(tmp_path / "e")["ape_rmse_m"] == pytest.approx(sim["ate"], rel=0, abs=1e-9)


def test_eval_explicit_imu_frame_reads_the_poses_as_they_are(sim, tmp_path, capsys):
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    est = outside / "est.kitti"
    shutil.copy(sim["run"] / "trajectory.kitti", est)
    code, printed, err = _eval(capsys, est, sim["gt_imu"], "--gt-frame", "imu", "--out", tmp_path / "e")
    assert code == 0, err
    metrics = _metrics(tmp_path / "e")
    assert metrics["ape_rmse_m"] == pytest.approx(sim["ate"], rel=0, abs=1e-9)
    assert metrics["ground_truth_frame"] == "imu" and metrics["cam_T_imu_source"] is None
    assert "ground truth: IMU poses (as requested)" in printed
    # inside the run folder, --gt-frame imu still wins over the KITTI default
    code, _, err = _eval(capsys, sim["run"] / "trajectory.kitti", sim["gt_imu"], "--gt-frame", "imu",
                         "--out", tmp_path / "e2")
    assert code == 0, err
    assert _metrics(tmp_path / "e2")["ape_rmse_m"] == pytest.approx(sim["ate"], rel=0, abs=1e-9)


def test_eval_tum_default_is_imu(sim, tmp_path, capsys):
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    est = outside / "est.tum"  # no summary.json needed: nothing to convert
    shutil.copy(sim["run"] / "trajectory.tum", est)
    code, printed, err = _eval(capsys, est, sim["gt_tum"], "--gt-format", "tum", "--out", tmp_path / "e")
    assert code == 0, err
    metrics = _metrics(tmp_path / "e")
    assert metrics["ground_truth_frame"] == "imu" and metrics["ground_truth_frame_requested"] == "auto"
    assert metrics["association"]["method"] == "timestamp"
    assert metrics["ape_rmse_m"] == pytest.approx(sim["ate"], rel=0, abs=1e-9)
    assert "ground truth: IMU poses (default for TUM ground truth)" in printed


def test_run_gt_kitti_default_is_camera(sim, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", str(sim["data"]), "--mode", "localization", "--out", str(out), "--quiet",
                 "--gt", str(sim["gt_cam"])]) == 0
    ev = json.loads((out / "summary.json").read_text())["evaluation"]
    assert ev["ground_truth"]["frame"] == "cam" and ev["ground_truth"]["frame_requested"] == "auto"
    assert ev["ground_truth"]["cam_T_imu_source"] == "calibration.cam_T_imu of this run (the transform the filter used)"
    assert ev["ape_rmse_m"] == pytest.approx(sim["ate"], rel=0, abs=1e-9)
    assert _metrics(out)["ground_truth_frame"] == "cam"
    # TUM: IMU by default
    out_tum = tmp_path / "run_tum"
    assert main(["run", str(sim["data"]), "--mode", "localization", "--out", str(out_tum), "--quiet",
                 "--gt", str(sim["gt_tum"]), "--gt-format", "tum"]) == 0
    ev_tum = json.loads((out_tum / "summary.json").read_text())["evaluation"]
    assert ev_tum["ground_truth"]["frame"] == "imu"
    assert ev_tum["ape_rmse_m"] == pytest.approx(sim["ate"], rel=0, abs=1e-9)


def test_gt_format_is_read_from_the_file_unless_given(sim, tmp_path, capsys):
    """--gt-format auto (the default) takes a TUM ground truth (8 values per line) as TUM,
    matched by time and held as IMU poses, in eval and in run; a format given is obeyed,
    and a file that does not have it is refused in one line naming it."""
    est = sim["run"] / "trajectory.tum"
    code, _, err = _eval(capsys, est, sim["gt_tum"], "--out", tmp_path / "e")
    assert code == 0, err
    metrics = _metrics(tmp_path / "e")
    assert metrics["ground_truth_format"] == "tum" and metrics["ground_truth_frame"] == "imu"
    assert metrics["association"]["method"] == "timestamp"
    assert metrics["ape_rmse_m"] == pytest.approx(sim["ate"], rel=0, abs=1e-9)
    out = tmp_path / "run"
    assert main(["run", str(sim["data"]), "--mode", "localization", "--out", str(out), "--quiet",
                 "--gt", str(sim["gt_tum"])]) == 0
    ev = json.loads((out / "summary.json").read_text())["evaluation"]
    assert ev["ground_truth"]["format"] == "tum" and ev["ground_truth"]["frame"] == "imu"
    assert ev["ape_rmse_m"] == pytest.approx(sim["ate"], rel=0, abs=1e-9)
    code = main(["run", str(sim["data"]), "--mode", "localization", "--out", str(tmp_path / "x"), "--quiet",
                 "--gt", str(sim["gt_tum"]), "--gt-format", "kitti"])
    err = capsys.readouterr().err
    assert code == 2 and not (tmp_path / "x").exists()
    assert len(err.strip().splitlines()) == 1 and str(sim["gt_tum"]) in err and "12 per line" in err


@pytest.mark.parametrize("damage, fragments", [
    (lambda s: (s["dataset"].pop("cam_T_imu"), s.pop("calibration")),
     ("calibration.cam_T_imu", "dataset.cam_T_imu", "--dataset ", "sequence.npz")),
    (lambda s: s["calibration"].__setitem__("cam_T_imu", [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
     ("calibration.cam_T_imu", "4x4 rigid")),
    (lambda s: s["dataset"].__setitem__("cam_T_imu", [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
     ("dataset.cam_T_imu", "4x4 rigid")),
    (lambda s: s["dataset"].__setitem__("cam_T_imu", [[1, 0, 0], [0, 1, 0], [0, 0, 1]]),
     ("dataset.cam_T_imu", "4x4 rigid")),
    (lambda s: s["dataset"].__setitem__("cam_T_imu", "identity"), ("dataset.cam_T_imu", "4x4 rigid")),
    (None, ("not valid JSON",)),
])
def test_eval_validates_the_run_summary(sim, tmp_path, capsys, damage, fragments):
    run_dir = tmp_path / "run"
    shutil.copytree(sim["run"], run_dir)
    summary_path = run_dir / "summary.json"
    if damage is None:
        summary_path.write_text("{ not json")
    else:
        summary = json.loads(summary_path.read_text())
        damage(summary)
        summary_path.write_text(json.dumps(summary))
    code, _, err = _eval(capsys, run_dir / "trajectory.kitti", sim["gt_cam"], "--out", tmp_path / "e")
    _assert_refused(code, err, tmp_path / "e", str(summary_path), *fragments)


def test_eval_of_an_older_run_summary_uses_the_file_transform_and_says_so(sim, tmp_path, capsys):
    run_dir = tmp_path / "run"
    shutil.copytree(sim["run"], run_dir)
    summary = json.loads((run_dir / "summary.json").read_text())
    del summary["calibration"]  # as written before the calibration was recorded
    (run_dir / "summary.json").write_text(json.dumps(summary))
    code, printed, err = _eval(capsys, run_dir / "trajectory.kitti", sim["gt_cam"], "--out", tmp_path / "e")
    assert code == 0, err
    metrics = _metrics(tmp_path / "e")
    assert metrics["ape_rmse_m"] == pytest.approx(sim["ate"], rel=0, abs=1e-9)
    assert "dataset.cam_T_imu, the data file's transform" in metrics["cam_T_imu_source"]
    assert "the data file's transform" in printed


def test_load_ground_truth_defaults_follow_the_format(sim):
    cam_T_imu = sim["drive"].sequence.cam_T_imu
    with pytest.raises(ConfigError, match="left-camera poses"):
        load_ground_truth(sim["gt_cam"])  # KITTI: camera, and no cam_T_imu given
    gt = load_ground_truth(sim["gt_cam"], cam_T_imu=cam_T_imu)
    np.testing.assert_allclose(gt.world_T_body, sim["drive"].world_T_imu, rtol=0, atol=1e-9)
    tum = load_ground_truth(sim["gt_tum"], fmt="tum")  # TUM: IMU, cam_T_imu not needed
    np.testing.assert_array_equal(tum.world_T_body, read_tum(sim["gt_tum"])[1])


# ----------------------------------------------------------------------------- shared data


@pytest.mark.shared
def test_eval_0027_defaults_match_the_explicit_flags(tmp_path, capsys):
    """The issue's case: `vislam eval RUN/trajectory.kitti groundtruth/0027.txt --out e` with no
    frame flags gives the ATE of `--gt-frame cam --dataset sparse/0027.npz`."""
    data = shared_file("sparse/0027.npz")
    gt = shared_file("groundtruth/0027.txt")
    run_dir = tmp_path / "run"
    assert main(["run", str(data), "--mode", "localization", "--out", str(run_dir), "--quiet"]) == 0
    est = run_dir / "trajectory.kitti"
    code, _, err = _eval(capsys, est, gt, "--out", tmp_path / "default")
    assert code == 0, err
    code, _, err = _eval(capsys, est, gt, "--gt-frame", "cam", "--dataset", data, "--out", tmp_path / "explicit")
    assert code == 0, err
    default, explicit = _metrics(tmp_path / "default"), _metrics(tmp_path / "explicit")
    assert default["n_frames_compared"] == explicit["n_frames_compared"] == 1101
    assert default["ape_rmse_m"] == pytest.approx(explicit["ape_rmse_m"], rel=0, abs=1e-9)
    assert 1.0 < default["ape_rmse_m"] < 4.0  # dead reckoning on sparse 0027: about 2 m
    assert default["kitti_t_pct"] == pytest.approx(explicit["kitti_t_pct"], rel=1e-9)
    assert default["ground_truth_frame"] == "cam"
