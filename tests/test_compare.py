"""``vislam compare`` end to end, and ``vislam run --gt`` (evaluation in the same run)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from vislam.cli import main
from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.tools import comparison as comparison_module
from vislam.tools.evaluation import evaluate_files
from vislam.tools.simulate_io import write_simulated_drive
from vislam.tools.trajectory_io import write_kitti

from conftest import HALF_SCENE

RUN_FILES = {"trajectory.tum", "trajectory.kitti", "trajectory.png", "summary.json", "landmarks.ply",
             "landmarks.npz"}
EVAL_FILES = {"metrics.json", "error_over_distance.png"}
#: The report's two EKF methods only (the smoother has its own tests below; it costs ~4x SLAM).
EKF = ["--methods", "separate,slam"]
NOISE = ["--add-velocity-noise", "0.5", "--add-angular-noise", "0.05", "--velocity-noise", "0.5",
         "--angular-noise", "0.05"]


def _drive(tmp_path_factory, n_frames, **scene):
    directory = tmp_path_factory.mktemp(f"drive{n_frames}")
    drive = simulate_drive(SimulationOptions(n_frames=n_frames, seed=1, **scene))
    write_simulated_drive(drive, directory)
    return directory, drive


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    return _drive(tmp_path_factory, 120, **HALF_SCENE)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return _drive(tmp_path_factory, 60)


@pytest.fixture(scope="module")
def long(tmp_path_factory):
    return _drive(tmp_path_factory, 300)


def names(path):
    return {p.name for p in path.iterdir()}


def test_compare_writes_both_runs_the_figure_and_the_json(tmp_path, small, capsys):
    data, drive = small
    out = tmp_path / "cmp"
    assert main(["compare", str(data / "sequence.npz"), "--out", str(out), *EKF]) == 0
    printed = capsys.readouterr().out
    assert "separately" in printed and "SLAM" in printed and str(out) in printed
    assert names(out) == {"separate", "slam", "comparison.png", "comparison.json"}
    assert names(out / "separate") == RUN_FILES and names(out / "slam") == RUN_FILES
    assert (out / "comparison.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    content = json.loads((out / "comparison.json").read_text())
    assert content["injected_noise"] is None and content["ground_truth"] is None
    for key, mode in (("separate", "mapping"), ("slam", "slam")):
        m = content["methods"][key]
        summary = json.loads((out / key / "summary.json").read_text())
        assert summary["mode"] == mode and m["mode"] == mode
        # what vislam eval needs to convert KITTI (camera) ground truth for a trajectory of this folder
        np.testing.assert_array_equal(summary["dataset"]["cam_T_imu"], drive.sequence.cam_T_imu)
        assert m["frames"] == m["frames_processed"] == 120
        assert m["landmarks_in_map"] == summary["landmarks_in_map"] > 0
        assert m["filter_seconds"] == pytest.approx(summary["filter_seconds"])
        assert m["evaluation"] is None
    # "separately" maps on the localization trajectory: its trajectory is dead reckoning
    loc = tmp_path / "loc"
    assert main(["run", str(data / "sequence.npz"), "--mode", "localization", "--out", str(loc), "--quiet"]) == 0
    assert (loc / "trajectory.tum").read_text() == (out / "separate" / "trajectory.tum").read_text()


def test_compare_with_ground_truth_slam_beats_localization_under_imu_noise(tmp_path, long):
    data, drive = long
    out = tmp_path / "cmp"
    code = main(["compare", str(data / "sequence.npz"), "--out", str(out), "--quiet", *NOISE, *EKF,
                 "--gt", str(data / "groundtruth.tum"), "--gt-format", "tum"])
    assert code == 0
    content = json.loads((out / "comparison.json").read_text())
    ate = content["ate_m"]
    assert ate["separate"] is not None and ate["slam"] is not None
    assert ate["slam"] < 0.5 * ate["separate"], ate
    assert content["injected_noise"]["velocity_noise_mps"] == 0.5
    assert content["ground_truth"]["format"] == "tum"
    for key in ("separate", "slam"):
        assert names(out / key) == RUN_FILES | EVAL_FILES
        summary = json.loads((out / key / "summary.json").read_text())
        metrics = json.loads((out / key / "metrics.json").read_text())
        assert summary["injected_noise"]["angular_noise_radps"] == 0.05
        assert summary["options"]["velocity_noise_mps"] == 0.5
        assert summary["evaluation"]["ape_rmse_m"] == pytest.approx(ate[key])
        assert metrics["ape_rmse_m"] == pytest.approx(ate[key])
        assert content["methods"][key]["evaluation"]["kitti_t_pct"] == pytest.approx(metrics["kitti_t_pct"],
                                                                                      nan_ok=True)
        # the same number as evaluating the written trajectory afterwards
        independent = evaluate_files(out / key / "trajectory.tum", data / "groundtruth.tum", gt_format="tum")
        assert independent.ape.rmse == pytest.approx(ate[key], rel=1e-9)


def test_compare_replaces_an_earlier_output_as_a_whole(tmp_path, tiny):
    data, _ = tiny
    out = tmp_path / "cmp"
    assert main(["compare", str(data / "sequence.npz"), "--out", str(out), "--quiet", *EKF]) == 0
    (out / "slam" / "stale.txt").write_text("from an older run")
    (out / "unrelated.txt").write_text("keep me")
    assert main(["compare", str(data / "sequence.npz"), "--out", str(out), "--quiet", "--add-pixel-noise", "1",
                 *EKF]) == 0
    assert names(out / "slam") == RUN_FILES
    assert (out / "unrelated.txt").read_text() == "keep me"
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no staging debris
    assert json.loads((out / "comparison.json").read_text())["injected_noise"]["pixel_noise_px"] == 1.0


def test_compare_interrupted_while_writing_leaves_nothing(tmp_path, tiny, monkeypatch, capsys):
    data, _ = tiny

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(comparison_module, "plot_comparison", interrupted)  # after separate/ and slam/ are staged
    out = tmp_path / "deep" / "cmp"
    assert main(["compare", str(data / "sequence.npz"), "--out", str(out), *EKF]) == 130
    assert "no output written" in capsys.readouterr().err
    assert not (tmp_path / "deep").exists()


def test_compare_bad_inputs_one_line_nonzero_nothing_written(tmp_path, small, capsys):
    data, drive = small
    seq = str(data / "sequence.npz")
    garbage = tmp_path / "garbage.txt"
    garbage.write_text("1 2 3\n")
    too_long = tmp_path / "too_long.kitti"
    write_kitti(too_long, np.concatenate([drive.world_T_imu, drive.world_T_imu]))
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    cases = [
        [str(tmp_path / "missing.npz")],
        [seq, "--gt", str(tmp_path / "missing.txt")],
        [seq, "--gt", str(garbage)],
        [seq, "--gt", str(too_long)],
        [seq, "--add-angular-noise", "-0.1"],
        [seq, "--add-velocity-bias", "0.1"],
        [seq, "--velocity-noise", "-1"],
        [seq, "--methods", "slam,kalman"],
        [seq, "--methods", ","],
    ]
    for i, args in enumerate(cases):
        out = tmp_path / f"out{i}"
        code = main(["compare", *args, "--out", str(out)])
        err = capsys.readouterr().err
        assert code != 0, args
        assert len(err.strip().splitlines()) == 1 and err.startswith("vislam compare: error:"), (args, err)
        assert not out.exists(), args
    code = main(["compare", seq, "--out", str(a_file)])
    assert code != 0 and "not a directory" in capsys.readouterr().err
    assert a_file.read_text() == "x"


def test_compare_shows_the_smoother_and_its_refinement_beside_the_ekf(tmp_path, tiny, capsys):
    data, drive = tiny
    out = tmp_path / "cmp"
    # the default methods: separately, SLAM, the smoother and the refined smoother
    assert main(["compare", str(data / "sequence.npz"), "--out", str(out), "--add-velocity-noise", "0.3",
                 "--add-angular-noise", "0.006", "--velocity-noise", "0.3", "--angular-noise", "0.006",
                 "--gt", str(data / "groundtruth.tum"), "--gt-format", "tum"]) == 0
    printed = capsys.readouterr().out
    assert "smoother" in printed and "refined" in printed and "ms/frame" in printed
    assert names(out) == {"separate", "slam", "smoother", "refine", "comparison.png", "comparison.json"}
    content = json.loads((out / "comparison.json").read_text())
    assert list(content["methods"]) == ["separate", "slam", "smoother", "refine"]
    smoother, refined = content["methods"]["smoother"], content["methods"]["refine"]
    assert smoother["mode"] == refined["mode"] == "smoother"
    s_summary = json.loads((out / "smoother" / "summary.json").read_text())
    r_summary = json.loads((out / "refine" / "summary.json").read_text())
    assert s_summary["options"]["refine"] is False and r_summary["options"]["refine"] is True
    assert "refine_seconds" in r_summary["timing"] and "refine_seconds" not in s_summary["timing"]
    # one smoother run serves both: the refined folder's smoother.tum is the smoother's trajectory
    assert (out / "refine" / "smoother.tum").read_text() == (out / "smoother" / "trajectory.tum").read_text()
    assert refined["filter_seconds"] == pytest.approx(smoother["filter_seconds"])
    assert refined["estimation_seconds"] == pytest.approx(smoother["filter_seconds"] + refined["refine_seconds"])
    for key in ("smoother", "refine"):
        m = content["methods"][key]
        assert m["frames_processed"] == 60 and m["frame_ms_median"] > 0
        independent = evaluate_files(out / key / "trajectory.tum", data / "groundtruth.tum", gt_format="tum")
        assert independent.ape.rmse == pytest.approx(content["ate_m"][key], rel=1e-9)
        # on the noisy IMU the visual estimators beat dead reckoning by far
        assert content["ate_m"][key] < 0.5 * content["ate_m"]["separate"], content["ate_m"]


def test_compare_auto_checks_first_records_and_applies_the_suggestions(tmp_path, capsys):
    """A clean IMU whose gyro has a roll/pitch-rate bias: without --auto the estimators
    trust the gyro and tilt; --auto finds the bias, subtracts it, and says so."""
    bias = (0.01, 0.01, 0.0)
    drive = simulate_drive(SimulationOptions(n_frames=150, seed=1, gyro_bias_radps=bias))
    write_simulated_drive(drive, tmp_path / "data")
    seq, gt = str(tmp_path / "data" / "sequence.npz"), str(tmp_path / "data" / "groundtruth.tum")
    common = ["--methods", "slam", "--gt", gt, "--gt-format", "tum"]
    assert main(["compare", seq, "--out", str(tmp_path / "plain"), "--quiet", *common]) == 0
    assert main(["compare", seq, "--out", str(tmp_path / "auto"), "--auto", *common]) == 0
    captured = capsys.readouterr()
    assert "vislam check: WARN imu-bias" in captured.err and "auto (check): gyro_bias_radps" in captured.out
    plain = json.loads((tmp_path / "plain" / "comparison.json").read_text())
    auto = json.loads((tmp_path / "auto" / "comparison.json").read_text())
    assert plain["auto"] is None
    suggested = auto["auto"]["suggested"]["gyro_bias_radps"]
    # roll/pitch (a yaw bias is not observable this way), within half the bias on a 15 s drive
    assert np.linalg.norm(np.subtract(suggested[:2], bias[:2])) < 0.5 * np.linalg.norm(bias[:2]), suggested
    assert "imu-bias" in {f["code"] for f in auto["auto"]["findings"]}
    assert auto["options"]["gyro_bias_radps"] == suggested  # applied ...
    summary = json.loads((tmp_path / "auto" / "slam" / "summary.json").read_text())
    assert summary["auto"] == auto["auto"] and summary["options"]["gyro_bias_radps"] == suggested
    # ... and the result improves
    assert auto["ate_m"]["slam"] < 0.5 * plain["ate_m"]["slam"], (auto["ate_m"], plain["ate_m"])


# ----------------------------------------------------------------------------- vislam run --gt


def test_run_with_ground_truth_writes_metrics_and_prints_ate(tmp_path, small, capsys):
    data, drive = small
    out = tmp_path / "run"
    # the simulator's groundtruth.kitti holds left-camera poses (KITTI convention): the default converts them
    assert main(["run", str(data / "sequence.npz"), "--out", str(out), *NOISE,
                 "--gt", str(data / "groundtruth.kitti")]) == 0
    printed = capsys.readouterr().out
    assert "ATE:" in printed
    assert names(out) == RUN_FILES | EVAL_FILES
    summary = json.loads((out / "summary.json").read_text())
    ev = summary["evaluation"]
    for key in ("ape_rmse_m", "kitti_t_pct", "kitti_r_deg_per_100m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg"):
        assert key in ev
    assert ev["n_frames_compared"] == 120 and ev["ground_truth"]["frame"] == "cam"
    assert ev["ground_truth"]["frame_requested"] == "auto"
    assert ev["ground_truth"]["cam_T_imu_source"] == "calibration.cam_T_imu of this run (the transform the filter used)"
    assert f"IMU {ev['ape_rmse_m']:.3f} m" in printed and f"camera {ev['cam_ape_rmse_m']:.3f} m" in printed
    assert "metrics.json" in summary["outputs"] and "error_over_distance.png" in summary["outputs"]
    assert json.loads((out / "metrics.json").read_text())["ape_rmse_m"] == pytest.approx(ev["ape_rmse_m"])

    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["ground_truth_frame"] == "cam" and metrics["ground_truth_frame_requested"] == "auto"

    # the same truth as IMU poses in a KITTI file, with --gt-frame imu: the same answer
    imu_gt = tmp_path / "imu.kitti"
    write_kitti(imu_gt, drive.world_T_imu)
    out_imu = tmp_path / "run_imu"
    assert main(["run", str(data / "sequence.npz"), "--out", str(out_imu), "--quiet", *NOISE,
                 "--gt", str(imu_gt), "--gt-frame", "imu"]) == 0
    ev_imu = json.loads((out_imu / "summary.json").read_text())["evaluation"]
    assert ev_imu["ground_truth"]["frame"] == "imu" and ev_imu["ground_truth"]["cam_T_imu_source"] is None
    assert ev_imu["ape_rmse_m"] == pytest.approx(ev["ape_rmse_m"], rel=1e-6)
    # ... and the camera poses read as IMU poses by mistake give a different (worse) answer
    out_wrong = tmp_path / "run_wrong"
    assert main(["run", str(data / "sequence.npz"), "--out", str(out_wrong), "--quiet", *NOISE,
                 "--gt", str(data / "groundtruth.kitti"), "--gt-frame", "imu"]) == 0
    assert json.loads((out_wrong / "summary.json").read_text())["evaluation"]["ape_rmse_m"] > ev["ape_rmse_m"]
