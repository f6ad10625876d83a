"""The output directory of a run: file contents, summary, atomicity, partial runs."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from vislam.core.estimators import run
from vislam.core.lie import se3_exp
from vislam.core.options import FilterOptions
from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.errors import EstimationError, OutputError
from vislam.tools import outputs
from vislam.tools.outputs import (
    FIGURE,
    LANDMARKS_NPZ,
    LANDMARKS_PLY,
    SUMMARY,
    TRAJECTORY_KITTI,
    TRAJECTORY_TUM,
    OutputStage,
    absolute_trajectory_error,
    json_safe,
    landmark_arrays,
    process_start_time,
    write_demo_outputs,
    write_run_outputs,
)
from vislam.tools.trajectory_io import read_kitti, read_tum

from conftest import HALF_SCENE

N_FRAMES = 120
ALL_FILES = {TRAJECTORY_TUM, TRAJECTORY_KITTI, LANDMARKS_PLY, LANDMARKS_NPZ, FIGURE, SUMMARY}

REQUIRED_KEYS = {
    "vislam_version", "dataset", "mode", "options", "frames", "frames_processed", "landmarks_initialized",
    "landmarks_in_map", "landmarks_rejected", "observations_used", "observations_gated", "observations_repeated",
    "filter_seconds", "total_seconds", "frame_ms_median", "frame_ms_p95", "duration_s", "real_time_factor",
    "partial", "error",
}


@pytest.fixture(scope="module")
def drive():
    # IMU noise so that SLAM has something to correct; outliers so that some landmarks get rejected
    return simulate_drive(SimulationOptions(n_frames=N_FRAMES, velocity_noise_mps=0.3, angular_noise_radps=0.02,
                                            outlier_fraction=0.02, **HALF_SCENE))


@pytest.fixture(scope="module")
def filter_options():
    return FilterOptions(velocity_noise_mps=0.3, angular_noise_radps=0.02)


@pytest.fixture(scope="module")
def results(drive, filter_options):
    return {mode: run(drive.sequence, mode, filter_options) for mode in ("localization", "mapping", "slam")}


def _dataset(seq):
    return {"name": seq.name, "path": None, "frames": seq.n_frames, "duration_s": seq.duration_s,
            "cam_T_imu": seq.cam_T_imu.tolist()}


def _write(stage_dir, result, seq, start_time=None):
    start_time = time.time() - 1.0 if start_time is None else start_time
    with OutputStage(stage_dir) as stage:
        return write_run_outputs(stage, result, dataset=_dataset(seq), duration_s=seq.duration_s,
                                 start_time=start_time)


def read_ply(path):
    """A minimal, independent PLY reader (ascii or binary little-endian vertices)."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    assert header[0] == "ply"
    fmt = header[1].split()[1]
    types = {"float": "<f4", "double": "<f8", "int": "<i4", "uint": "<u4", "uchar": "u1", "char": "i1",
             "short": "<i2", "ushort": "<u2"}
    count, props = None, []
    for line in header[2:]:
        words = line.split()
        if words[0] == "element":
            assert words[1] == "vertex", "only a vertex element is expected"
            count = int(words[2])
        elif words[0] == "property":
            props.append((words[2], types[words[1]]))
    dtype = np.dtype(props)
    if fmt == "binary_little_endian":
        assert len(data) - end == count * dtype.itemsize, "body size does not match the header"
        return np.frombuffer(data, dtype=dtype, count=count, offset=end)
    assert fmt == "ascii"
    rows = [tuple(line.split()) for line in data[end:].decode("ascii").splitlines() if line.strip()]
    return np.array([tuple(np.array(v).astype(t) for v, (_, t) in zip(r, props)) for r in rows], dtype=dtype)


def _lines(path):
    return [line for line in path.read_text().splitlines() if line.strip()]


@pytest.mark.parametrize("mode", ["localization", "mapping", "slam"])
def test_trajectory_files_reload_to_the_result(tmp_path, drive, results, mode):
    result = results[mode]
    summary = _write(tmp_path, result, drive.sequence)
    ts, poses = read_tum(tmp_path / TRAJECTORY_TUM)
    np.testing.assert_allclose(ts, drive.sequence.timestamps_s, atol=1e-9, rtol=0)
    np.testing.assert_allclose(poses, result.world_T_imu, atol=1e-6, rtol=0)
    np.testing.assert_allclose(read_kitti(tmp_path / TRAJECTORY_KITTI), result.world_T_imu, atol=1e-6, rtol=0)
    expected = ALL_FILES if mode != "localization" else ALL_FILES - {LANDMARKS_PLY, LANDMARKS_NPZ}
    assert {p.name for p in tmp_path.iterdir()} == expected
    assert set(summary["outputs"]) == expected


@pytest.mark.parametrize("mode", ["mapping", "slam"])
def test_landmark_files(tmp_path, drive, results, mode):
    result = results[mode]
    lm = result.landmarks
    assert len(lm) > 50
    _write(tmp_path, result, drive.sequence)
    vertices = read_ply(tmp_path / LANDMARKS_PLY)
    assert vertices.shape == (len(lm),)
    xyz = np.column_stack([vertices["x"], vertices["y"], vertices["z"]])
    np.testing.assert_allclose(xyz, lm.p_lm_in_world, rtol=1e-6, atol=1e-4)  # float32
    np.testing.assert_array_equal(vertices["id"], lm.ids)
    np.testing.assert_array_equal(vertices["track"], lm.track)
    np.testing.assert_array_equal(vertices["n_observations"], lm.n_observations)
    np.testing.assert_array_equal(vertices["status"], lm.status)
    trace = np.trace(lm.covariance, axis1=1, axis2=2)
    np.testing.assert_allclose(vertices["sigma"], np.sqrt(trace), rtol=1e-5)
    # the map is a map of roadside points: a landmark's sigma is metres, not kilometres
    assert np.median(vertices["sigma"]) < 5.0
    with np.load(tmp_path / LANDMARKS_NPZ, allow_pickle=False) as npz:
        stored = {k: npz[k] for k in npz.files}
    expected = landmark_arrays(lm)
    assert set(stored) == set(expected) >= {"ids", "track", "p_lm_in_world", "covariance", "n_observations",
                                              "n_gated", "first_frame", "last_frame", "status"}
    for key, value in expected.items():
        np.testing.assert_array_equal(stored[key], value, err_msg=key)
    assert stored["covariance"].shape == (len(lm), 3, 3)


def test_landmark_positions_recover_the_simulated_truth(tmp_path, drive, results):
    """The PLY holds the SLAM map in the world frame: static, non-rejected landmarks lie
    near their true positions (the estimate starts from the true first pose)."""
    lm = results["slam"].landmarks
    _write(tmp_path, results["slam"], drive.sequence)
    v = read_ply(tmp_path / LANDMARKS_PLY)
    ok = v["status"] == 0
    true = drive.p_lm_in_world[v["id"][ok]]
    err = np.linalg.norm(np.column_stack([v["x"], v["y"], v["z"]])[ok] - true, axis=1)
    assert np.median(err) < 2.0, np.median(err)
    assert ok.sum() == np.count_nonzero(lm.status == 0)


@pytest.mark.parametrize("mode", ["localization", "slam"])
def test_summary_is_consistent_with_the_files(tmp_path, drive, results, mode):
    result = results[mode]
    start = time.time() - result.stats.filter_seconds - 0.5  # as if the process had started before the run
    _write(tmp_path, result, drive.sequence, start_time=start)
    text = (tmp_path / SUMMARY).read_text()
    summary = json.loads(text, parse_constant=lambda c: pytest.fail(f"non-strict JSON constant {c}"))
    assert REQUIRED_KEYS <= set(summary)
    assert summary["mode"] == mode
    assert summary["options"] == FilterOptions(velocity_noise_mps=0.3, angular_noise_radps=0.02).to_dict()
    assert summary["frames"] == summary["frames_processed"] == N_FRAMES
    assert len(_lines(tmp_path / TRAJECTORY_TUM)) == summary["frames"]
    assert len(_lines(tmp_path / TRAJECTORY_KITTI)) == summary["frames"]
    assert 0 < summary["filter_seconds"] <= summary["total_seconds"]
    assert summary["total_seconds"] >= 0.5
    assert summary["duration_s"] == pytest.approx(drive.sequence.duration_s)
    assert summary["real_time_factor"] == pytest.approx(summary["filter_seconds"] / summary["duration_s"])
    assert summary["frame_ms_median"] <= summary["frame_ms_p95"]
    assert summary["partial"] is False and summary["error"] is None
    assert summary["dataset"]["name"] == drive.sequence.name
    if mode == "slam":
        lm = result.landmarks
        assert summary["landmarks_in_map"] == len(lm) == len(read_ply(tmp_path / LANDMARKS_PLY))
        assert summary["landmarks_rejected"] == int(np.count_nonzero(lm.status))
        assert summary["landmarks_rejected"] > 0  # the drive has outliers
        assert summary["landmarks_initialized"] >= summary["landmarks_in_map"] - summary["landmarks_rejected"]
        assert 0 < summary["observations_used"] <= result.stats.observations_total
        assert summary["observations_gated"] > 0
    else:
        assert summary["landmarks_in_map"] == 0


def test_without_the_figure_every_other_output_is_written_and_the_summary_says_so(tmp_path, drive, results):
    result = results["slam"]
    seq = drive.sequence
    with OutputStage(tmp_path) as stage:
        summary = write_run_outputs(stage, result, dataset=_dataset(seq), duration_s=seq.duration_s,
                                    start_time=time.time() - 1.0, figure=False)
    assert {p.name for p in tmp_path.iterdir()} == ALL_FILES - {FIGURE}
    assert FIGURE not in summary["outputs"] and set(summary["outputs"]) == ALL_FILES - {FIGURE}
    assert summary["landmarks_outside_figure"] is None
    assert json.loads((tmp_path / SUMMARY).read_text()) == summary


def test_json_safe_replaces_non_finite_numbers():
    data = {"a": float("nan"), "b": [np.float32(np.inf), np.int64(3), np.bool_(True)], "c": np.array([1.0, -np.inf])}
    assert json_safe(data) == {"a": None, "b": [None, 3, True], "c": [1.0, None]}
    json.dumps(json_safe(data), allow_nan=False)


def test_process_start_time_is_in_the_past():
    t = process_start_time()
    if t is None:
        pytest.skip("no /proc on this platform")
    assert time.time() - 3600 < t <= time.time()


def _snapshot(directory):
    return {p.name: p.read_bytes() for p in sorted(directory.iterdir())}


@pytest.mark.parametrize("victim", ["write_landmarks_ply", "write_json", "plot_trajectory_map"])
@pytest.mark.parametrize("exception", [RuntimeError, KeyboardInterrupt])
def test_a_failure_while_writing_leaves_no_file(tmp_path, drive, results, monkeypatch, victim, exception):
    def boom(*args, **kwargs):
        raise exception("simulated failure")

    if victim == "plot_trajectory_map":
        monkeypatch.setattr("vislam.tools.plotting.plot_trajectory_map", boom)
    else:
        monkeypatch.setattr(outputs, victim, boom)
    # a new directory: removed again
    fresh = tmp_path / "new" / "out"
    with pytest.raises(exception):
        _write(fresh, results["slam"], drive.sequence)
    assert not fresh.exists() and not (tmp_path / "new").exists()
    # an existing directory with an earlier run's outputs: left exactly as it was
    monkeypatch.undo()
    old = tmp_path / "old"
    _write(old, results["localization"], drive.sequence)
    (old / "notes.txt").write_text("mine")
    before = _snapshot(old)
    if victim == "plot_trajectory_map":
        monkeypatch.setattr("vislam.tools.plotting.plot_trajectory_map", boom)
    else:
        monkeypatch.setattr(outputs, victim, boom)
    with pytest.raises(exception):
        _write(old, results["slam"], drive.sequence)
    assert _snapshot(old) == before  # no new file, no temporary file, nothing changed


def test_failure_during_the_run_leaves_no_file(tmp_path, drive):
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        with OutputStage(out) as stage:
            (stage.path("trajectory.tum")).write_text("half")
            raise KeyboardInterrupt
    assert not out.exists()


def test_a_second_run_replaces_the_first(tmp_path, drive, results):
    _write(tmp_path, results["slam"], drive.sequence)
    assert (tmp_path / LANDMARKS_PLY).exists()
    _write(tmp_path, results["localization"], drive.sequence)
    assert {p.name for p in tmp_path.iterdir()} == ALL_FILES - {LANDMARKS_PLY, LANDMARKS_NPZ}
    assert json.loads((tmp_path / SUMMARY).read_text())["mode"] == "localization"


def test_unwritable_destination_is_an_output_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    for out in (blocker, blocker / "sub"):
        with pytest.raises(OutputError) as info:
            with OutputStage(out):
                pass
        assert str(out) in str(info.value)
    assert [p.name for p in tmp_path.iterdir()] == ["file"]


def test_partial_results_are_written_and_flagged(tmp_path, drive, filter_options, monkeypatch):
    fail_at = 70
    from vislam.core import kernels, updaters

    calls = {"n": 0}

    def failing(real_update):
        def failing_update(*args, **kwargs):
            calls["n"] += 1
            if calls["n"] >= fail_at:
                raise EstimationError(f"simulated divergence at update {calls['n']}")
            return real_update(*args, **kwargs)
        return failing_update

    # the update of either arithmetic (compiled kernels or the numpy reference)
    monkeypatch.setattr(kernels.KernelOps, "update", failing(kernels.KernelOps.update))
    monkeypatch.setattr(updaters, "slam_update", failing(updaters.slam_update))
    result = run(drive.sequence, "slam", filter_options)
    assert result.partial and "simulated divergence" in result.error
    done = result.stats.frames_processed
    assert 0 < done < N_FRAMES
    summary = _write(tmp_path, result, drive.sequence)
    on_disk = json.loads((tmp_path / SUMMARY).read_text())
    assert on_disk == json.loads(json.dumps(json_safe(summary)))
    assert on_disk["partial"] is True and "simulated divergence" in on_disk["error"]
    assert on_disk["frames"] == N_FRAMES and on_disk["frames_processed"] == done
    assert len(_lines(tmp_path / TRAJECTORY_TUM)) == done
    assert len(_lines(tmp_path / TRAJECTORY_KITTI)) == done
    ts, poses = read_tum(tmp_path / TRAJECTORY_TUM)
    np.testing.assert_allclose(ts, drive.sequence.timestamps_s[:done], atol=1e-9)
    assert len(read_ply(tmp_path / LANDMARKS_PLY)) == len(result.landmarks) > 0
    assert (tmp_path / FIGURE).stat().st_size > 10_000


def test_absolute_trajectory_error_is_alignment_invariant(drive):
    gt = np.asarray(drive.world_T_imu)
    rigid = se3_exp(np.array([3.0, -2.0, 0.5, 0.01, -0.02, 0.3]))
    assert absolute_trajectory_error(rigid @ gt, gt) < 1e-6
    rng = np.random.default_rng(1)
    noisy = gt.copy()
    offsets = rng.normal(scale=0.5, size=(len(gt), 3))
    offsets -= offsets.mean(axis=0)
    noisy[:, :3, 3] += offsets
    ate = absolute_trajectory_error(noisy, gt)
    rmse = float(np.sqrt(np.mean(np.sum(offsets**2, axis=1))))
    assert 0.9 * rmse < ate <= rmse + 1e-9  # alignment can only reduce the error
    assert absolute_trajectory_error(gt[:1], gt[:1]) is None


def test_demo_outputs_include_truth_and_ate(tmp_path, drive, results):
    slam, loc = results["slam"], results["localization"]
    with OutputStage(tmp_path) as stage:
        summary = write_demo_outputs(stage, slam, loc, drive.world_T_imu, dataset=_dataset(drive.sequence),
                                     duration_s=drive.sequence.duration_s, start_time=time.time() - 1)
    assert (tmp_path / "groundtruth.tum").exists() and (tmp_path / "localization.tum").exists()
    _, gt = read_tum(tmp_path / "groundtruth.tum")
    np.testing.assert_allclose(gt, drive.world_T_imu, atol=1e-6)
    # groundtruth.kitti: left-camera poses (KITTI convention), cam_T_imu recorded in summary.json
    cam_T_imu = np.array(json.loads((tmp_path / SUMMARY).read_text())["dataset"]["cam_T_imu"])
    np.testing.assert_array_equal(cam_T_imu, drive.sequence.cam_T_imu)
    world_T_cam = read_kitti(tmp_path / "groundtruth.kitti")
    np.testing.assert_allclose(np.linalg.inv(cam_T_imu) @ world_T_cam @ cam_T_imu, drive.world_T_imu, atol=1e-6)
    ate = json.loads((tmp_path / SUMMARY).read_text())["ground_truth"]["ate_m"]
    assert ate == summary["ground_truth"]["ate_m"]
    assert ate["slam"] == pytest.approx(absolute_trajectory_error(slam.world_T_imu, drive.world_T_imu))
    assert ate["localization"] == pytest.approx(absolute_trajectory_error(loc.world_T_imu, drive.world_T_imu))
    assert ate["slam"] < ate["localization"]


def test_ply_header_stays_ascii_with_non_ascii_labels(tmp_path):
    from vislam.core.results import LandmarkMap
    from vislam.tools.outputs import write_landmarks_ply

    path = tmp_path / "lm.ply"
    write_landmarks_ply(path, LandmarkMap.empty(), comments=["Dataset 27 — SLAM σ"])
    header = path.read_bytes().split(b"end_header\n")[0]
    header.decode("ascii")  # raises if not ASCII
    assert b"Dataset 27 \\u2014 SLAM \\u03c3" in header
