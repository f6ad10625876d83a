"""Hostile and unusual inputs found by probing (/tmp/hostile_inputs/probe.py): each ends in
one clear error of the package's own (naming the file or the argument and what was
expected) or in a run without numpy warnings — never a traceback, a silent wrong result
or a half-written output folder.

In-memory recordings (vislam.Sequence, its observations and calibration) hold the
loader's rules; the stepwise filters refuse complex pixels and ids beyond int64; ground
truth files written by Windows editors or in another unit are read or named; a recording
stamped in nanoseconds is matched with a ground truth in seconds once ``timestamp_scale``
says so; ``vislam eval`` writes its two files together or not at all.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from conftest import HALF_SCENE, in_process

import vislam
from vislam.core.contract import checked_frame, checked_world_T_imu
from vislam.core.sequence import Calibration, SequenceError, StereoObservations
from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.core.smoother import SmootherFilter
from vislam.errors import ConfigError, DatasetError, GroundTruthError, OutputError
from vislam.tools.dataset_io import load_sequence, save_sequence
from vislam.tools.evaluation import associate
from vislam.tools.trajectory_io import (
    TrajectoryFile,
    format_kitti,
    read_trajectory,
    write_tum,
)

N_FRAMES = 30


@pytest.fixture(scope="module")
def drive():
    return simulate_drive(SimulationOptions(n_frames=N_FRAMES, seed=2, **HALF_SCENE))


# ----------------------------------------------------------------------------- in-memory recordings


@pytest.mark.parametrize("case, needle", [
    ("nan", "timestamps_s has nan at frame 5; expected finite seconds"),
    ("inf", "timestamps_s has inf at frame 5"),
    ("reversed", "timestamps_s is not strictly increasing at frame 1"),
    ("equal", "timestamps_s is not strictly increasing at frame 1"),
    ("gap", "timestamps_s has a frame interval of 1e+12 s at frame 6; expected at most 1e+09 s"),
])
def test_a_sequence_refuses_time_stamps_the_filters_cannot_step(drive, case, needle):
    """A NaN, a step back or a repeated time reached the filters as "predict: dt_s must be
    ..." (an argument the user never passed; equal times ran with dt = 0 silently). The
    Sequence refuses them itself: a DatasetError (one CLI line) that is still a ValueError."""
    seq = drive.sequence
    t = seq.timestamps_s.copy()
    t = {"nan": np.where(np.arange(t.size) == 5, np.nan, t), "inf": np.where(np.arange(t.size) == 5, np.inf, t),
         "reversed": t[::-1].copy(), "equal": np.full_like(t, t[0]),
         "gap": np.where(np.arange(t.size) > 5, t + 1e12, t)}[case]
    with pytest.raises(SequenceError) as info:
        seq.replace(timestamps_s=t)
    assert isinstance(info.value, DatasetError) and isinstance(info.value, ValueError)
    message = str(info.value)
    assert needle in message and message.startswith("simulator: ") and "\n" not in message


def test_a_sequence_without_frames_is_refused(drive):
    """Zero frames ended in an IndexError inside vislam.run."""
    empty = StereoObservations(np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros((0, 4)), 0)
    with pytest.raises(SequenceError, match="timestamps_s is empty; a recording needs at least one frame"):
        drive.sequence.replace(timestamps_s=np.zeros(0), linear_velocity_in_imu_mps=np.zeros((0, 3)),
                               angular_velocity_in_imu_radps=np.zeros((0, 3)), observations=empty)


@pytest.mark.parametrize("make, needle", [
    (lambda T: np.full((4, 4), np.nan), "must be a finite 4x4 rigid transform"),
    (lambda T: np.diag([2.0, 2.0, 2.0, 1.0]) @ T, "is not a rigid transform (max |RᵀR - I| = 3, det R = 8"),
    (lambda T: T @ np.diag([1.0, 1.0, 1.0, 1.0]) + np.diag([0, 0, 0, 1.0]), "last row [0.0, 0.0, 0.0, 2.0]"),
    (lambda T: np.block([[T[:3, :3], np.array([[0.0], [1e4], [0.0]])], [T[3:]]]), "lever arm within ±1000 m"),
])
def test_sequence_and_calibration_refuse_a_cam_T_imu_that_is_not_rigid(drive, make, needle):
    """A NaN or scaled cam_T_imu ran "ok" through vislam.run and the filters, every
    observation silently lost; the loader refused it, an in-memory recording did not."""
    seq = drive.sequence
    bad = make(np.array(seq.cam_T_imu))
    with pytest.raises(SequenceError) as info:
        seq.replace(cam_T_imu=bad)
    assert needle in str(info.value)
    with pytest.raises(SequenceError, match="^Calibration: "):
        vislam.SlamFilter(Calibration(seq.camera, bad))


def test_from_dense_refuses_an_entry_missing_in_some_coordinates(drive):
    """The dataset marks an unobserved cell with -1 in all four coordinates; from_dense
    took a cell with one -1 as an observation at pixel -1 (the loader refuses it)."""
    dense = drive.sequence.observations.dense()
    j, t = (int(i) for i in np.argwhere(dense[0] != -1)[0])
    dense[3, j, t] = -1.0
    with pytest.raises(SequenceError, match=rf"landmark {j} at frame {t} has \[uL, vL, uR, vR\] = .*-1\.0\]; "
                                            r"expected four pixels or -1 in all four"):
        StereoObservations.from_dense(dense)


def test_save_sequence_names_a_directory_or_an_unwritable_path(drive, tmp_path):
    before = sorted(tmp_path.iterdir())
    with pytest.raises(OutputError, match=f"^{tmp_path}: is a directory; expected the path of the .npz file"):
        save_sequence(drive.sequence, tmp_path)
    assert sorted(tmp_path.iterdir()) == before  # no temporary file left
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError):
        save_sequence(drive.sequence, tmp_path / "file" / "drive.npz")


def test_iter_frames_refuses_the_pixels_load_sequence_refuses(drive, tmp_path):
    """A Fortran-ordered file (streamed frame by frame) with a pixel at 1e300: load_sequence
    refused it, iter_frames handed it to the filters."""
    path = tmp_path / "drive.npz"
    save_sequence(drive.sequence, path, fortran_order=True)
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    features = np.asfortranarray(arrays["features"])
    j, t = (int(i) for i in np.argwhere(features[0] != -1)[0])
    features[0, j, t] = 1e300
    np.savez(path, **{**arrays, "features": features})
    needle = rf"key 'features' landmark {j} at frame {t}: has \[uL, vL, uR, vR\] = \[1e\+300, .*within ±1e\+06"
    with pytest.raises(DatasetError, match=needle):
        load_sequence(path)
    with pytest.raises(DatasetError, match=needle):
        list(vislam.iter_frames(path))


# ----------------------------------------------------------------------------- stepwise filters


@pytest.mark.parametrize("cls", [vislam.MappingFilter, vislam.SlamFilter, SmootherFilter])
def test_update_refuses_complex_pixels_and_ids_beyond_int64_without_warnings(drive, cls):
    """Complex pixels lost their imaginary part with a ComplexWarning and were used; a
    uint64 id beyond int64 wrapped around to a negative id."""
    frames = list(drive.sequence.frames(0, 2))
    f = cls(drive.sequence.calibration, vislam.FilterOptions())
    f.step(frames[0])
    ids, pixels = np.array(frames[1].landmark_ids), np.array(frames[1].pixels)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a ComplexWarning (or any other) fails the test
        with pytest.raises(ConfigError, match=r"pixels must be real numbers.*got complex values"):
            f.update(ids, pixels.astype(np.complex128))
        huge = ids[-1:].astype(np.uint64) + np.uint64(2**63)
        with pytest.raises(ConfigError, match="landmark ids must be within the int64 range, got 9223372036854"):
            f.update(huge, pixels[-1:])
    assert f.diagnostics.failed is None
    f.step(frames[1])  # still usable
    assert np.isfinite(f.world_T_imu).all()


def test_pose_and_frame_checks_of_the_contract():
    """The checks a filter's update(world_T_imu=) and step(frame) need (see the report:
    MappingFilter took a scaled pose as it was, and a NaN one failed in the camera model;
    step('x') was an AttributeError)."""
    T = np.eye(4)
    T[:3, 3] = (1.0, 2.0, 3.0)
    np.testing.assert_array_equal(checked_world_T_imu(T.tolist()), T)
    for bad, needle in ((np.full((4, 4), np.nan), "must be a finite 4x4 rigid transform"),
                        (2 * T, "must be a finite 4x4 rigid transform"), (np.eye(3), "must be 4x4, got (3, 3)"),
                        ("pose", "must be a 4x4 rigid transform, got 'pose'")):
        with pytest.raises(ConfigError, match=f"^update: world_T_imu {needle}".replace("(", r"\(").replace(")", r"\)")):
            checked_world_T_imu(bad)
    with pytest.raises(ConfigError, match="step: expected a vislam Frame .* got str without dt_s, "):
        checked_frame("frame")


def test_a_pose_rounded_to_four_decimals_is_made_rigid():
    """A pose file printed with four decimals is rigid only to ~1e-4: the pose is used with
    the nearest rotation (mapping with such --poses was refused at first by the check)."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zyx", [0.7, 0.1, -0.2]).as_matrix()
    T[:3, 3] = (3.1, 0.69, -0.006)
    rounded = np.round(T, 4)
    out = checked_world_T_imu(rounded)
    np.testing.assert_allclose(out[:3, :3].T @ out[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(out, T, atol=1e-4)
    assert np.linalg.det(out[:3, :3]) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("cls", [vislam.LocalizationFilter, vislam.MappingFilter, vislam.SlamFilter, SmootherFilter])
def test_every_filter_checks_what_step_and_update_are_given(drive, cls):
    """step('x') was an AttributeError inside every filter; the localization filter counted
    float ids and NaN pixels without a look; the mapping filter used a scaled pose."""
    f = cls(drive.sequence.calibration)
    with pytest.raises(ConfigError, match="^step: expected a vislam Frame"):
        f.step("frame")
    with pytest.raises(ConfigError, match="^step: expected a vislam Frame"):
        list(vislam.final_poses(cls(drive.sequence.calibration), [1, 2]))
    with pytest.raises(ConfigError, match="^update: landmark ids must be integers"):
        f.update([1.5], [[1.0, 2.0, 3.0, 4.0]])
    with pytest.raises(ConfigError, match="^update: pixels must be finite"):
        f.update([1], [[np.nan, 2.0, 3.0, 4.0]])
    assert f.frame_index == -1  # nothing was counted
    if cls is vislam.MappingFilter:
        frame = next(iter(drive.sequence.frames()))
        with pytest.raises(ConfigError, match="^update: world_T_imu must be a finite 4x4 rigid transform"):
            f.update(frame.landmark_ids, frame.pixels, world_T_imu=2.0 * np.eye(4))
        assert f.frame_index == -1
        f.update(frame.landmark_ids, frame.pixels, world_T_imu=np.eye(4))
        assert f.frame_index == 0


def test_run_names_the_arguments_it_was_given(drive):
    """vislam.run with a file name or an options dict was an AttributeError."""
    with pytest.raises(ConfigError, match="^run: expected a vislam Sequence .* got str"):
        vislam.run("drive.npz", "slam")
    with pytest.raises(ConfigError, match="^run: options must be a FilterOptions .* got dict"):
        vislam.run(drive.sequence, "slam", {"velocity_noise_mps": 0.5})
    with pytest.raises(ConfigError, match="^unknown mode"):
        vislam.run(drive.sequence, ["slam"])


# ----------------------------------------------------------------------------- trajectory files


def test_ground_truth_written_by_windows_editors_is_read(drive, tmp_path):
    """A UTF-8 byte-order mark (Notepad) was "non-numeric value '\\ufeff1.0'", a Latin-1
    comment "not a text file"; CRLF line ends were read already."""
    text = format_kitti(drive.world_T_imu)
    expected = read_trajectory(_write(tmp_path / "plain.txt", text.encode())).world_T_body
    for name, data in (("bom.txt", b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode()),
                       ("latin1.txt", "# café, données\n".encode("latin-1") + text.encode())):
        got = read_trajectory(_write(tmp_path / name, data))
        assert got.fmt == "kitti"
        np.testing.assert_array_equal(got.world_T_body, expected)


def test_binary_and_comma_separated_files_are_named(tmp_path, drive):
    binary = _write(tmp_path / "gt.npz", b"PK\x03\x04\x00\x00" + bytes(range(256)))
    with pytest.raises(GroundTruthError, match=f"^{binary}: not a text file"):
        read_trajectory(binary)
    csv = _write(tmp_path / "gt.csv", format_kitti(drive.world_T_imu).replace(" ", ",").encode())
    with pytest.raises(GroundTruthError, match=r"line 1: 1 value; expected 12 \(KITTI\) or 8 \(TUM\) per line "
                                               r"\(separated by white space; this line has ',' between values\)"):
        read_trajectory(csv)


def _write(path, data: bytes):
    path.write_bytes(data)
    return path


@pytest.mark.parametrize("scale, where, needle", [
    (1e9, "gt", "the frame interval of gt.tum is 1e+09 times the other's: are its time stamps in nanoseconds?"),
    (1e-3, "est", "the frame interval of est.tum is 1e+03 times the other's: are its time stamps in milliseconds?"),
    (1.0, "shift", "the two time ranges do not overlap (1000 s apart): is gt.tum the ground truth"),
])
def test_time_stamps_that_never_match_say_why(drive, scale, where, needle):
    ts = drive.sequence.timestamps_s - drive.sequence.timestamps_s[0]
    poses = np.asarray(drive.world_T_imu)
    est = TrajectoryFile(poses, ts + 100.0, "tum", "est.tum")
    gt_ts = (ts + 100.0) * scale if where != "shift" else ts + 100.0 + ts[-1] + 1000.0
    gt = TrajectoryFile(poses, gt_ts, "tum", "gt.tum")
    with pytest.raises(GroundTruthError) as info:
        associate(est, gt)
    assert "no timestamps match within 0.02 s" in str(info.value) and needle in str(info.value)


# ----------------------------------------------------------------------------- the commands


@pytest.fixture(scope="module")
def ns_drive(drive, tmp_path_factory):
    """The drive stamped in nanoseconds since the epoch, and its TUM ground truth in seconds."""
    d = tmp_path_factory.mktemp("ns")
    seq = drive.sequence
    save_sequence(seq.replace(timestamps_s=seq.timestamps_s * 1e9), d / "ns.npz")
    write_tum(d / "gt.tum", seq.timestamps_s, drive.world_T_imu)
    (d / "ns.yaml").write_text("timestamp_scale: 1.0e-9\n")
    return d


def test_ground_truth_in_seconds_matches_a_recording_in_ns_with_timestamp_scale(ns_drive, tmp_path, capsys):
    """The fix the run suggests for time stamps in ns (timestamp_scale 1e-9) made a TUM
    ground truth (and --poses) fail: they were matched with the frame times as stored,
    before the scale."""
    out = tmp_path / "out"
    proc = in_process(capsys, "run", ns_drive / "ns.npz", "--mode", "mapping", "--poses", ns_drive / "gt.tum",
                      "--config", ns_drive / "ns.yaml", "--gt", ns_drive / "gt.tum", "--out", out, "--quiet")
    assert proc.returncode == 0, proc.stderr
    evaluation = json.loads((out / "summary.json").read_text())["evaluation"]
    assert evaluation["n_frames_compared"] == N_FRAMES
    assert evaluation["ape_rmse_m"] < 1e-6  # mapping with the true poses given: the trajectory is the truth


@pytest.mark.parametrize("flag", ["--gt", "--poses"])
def test_ground_truth_of_a_recording_in_ns_without_the_scale_names_the_fix(ns_drive, tmp_path, capsys, flag):
    out = tmp_path / "out"
    proc = in_process(capsys, "run", ns_drive / "ns.npz", "--mode", "mapping", flag, ns_drive / "gt.tum",
                      "--out", out)
    assert proc.returncode == 2
    (line,) = proc.stderr.splitlines()
    assert line.startswith("vislam run: error: ") and str(ns_drive / "gt.tum") in line
    assert "with time stamps in nanoseconds, run with --auto or with timestamp_scale 1e-09 in a --config file" in line
    assert not out.exists()


def test_eval_writes_its_two_files_together_or_not_at_all(drive, tmp_path, capsys, monkeypatch):
    """A failing figure left a new metrics.json beside the previous run's figure."""
    est, gt = tmp_path / "est.tum", tmp_path / "gt.tum"
    ts = drive.sequence.timestamps_s
    write_tum(gt, ts, drive.world_T_imu)
    poses = np.array(drive.world_T_imu)
    poses[:, 0, 3] += np.linspace(0, 0.5, len(poses))
    write_tum(est, ts, poses)
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("kept")
    (out / "error_over_distance.png").write_bytes(b"old figure")

    from vislam.tools import evaluation

    def broken(*args, **kwargs):
        raise OutputError("figure: cannot draw")

    monkeypatch.setattr(evaluation, "plot_error_over_distance", broken)
    proc = in_process(capsys, "eval", est, gt, "--out", out)
    assert proc.returncode == 2 and proc.stderr.strip() == "vislam eval: error: figure: cannot draw"
    assert sorted(p.name for p in out.iterdir()) == ["error_over_distance.png", "keep.txt"]
    assert (out / "error_over_distance.png").read_bytes() == b"old figure"
    monkeypatch.undo()
    proc = in_process(capsys, "eval", est, gt, "--out", out)
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in out.iterdir()) == ["error_over_distance.png", "keep.txt", "metrics.json"]
    assert (out / "error_over_distance.png").read_bytes()[:4] == b"\x89PNG"


@pytest.fixture(scope="module")
def degenerate_files(drive, tmp_path_factory):
    """Legal but degenerate recordings: two frames; no observation at all; the vehicle
    standing still with every frame's pixels the first frame's."""
    d = tmp_path_factory.mktemp("degenerate")
    seq = drive.sequence
    obs = seq.observations
    dense = obs.dense()
    two = seq.replace(timestamps_s=seq.timestamps_s[:2], linear_velocity_in_imu_mps=seq.linear_velocity_in_imu_mps[:2],
                      angular_velocity_in_imu_radps=seq.angular_velocity_in_imu_radps[:2],
                      observations=StereoObservations.from_dense(dense[:, :, :2]))
    none = seq.replace(observations=StereoObservations.from_dense(np.full_like(dense, -1.0)))
    still = seq.replace(linear_velocity_in_imu_mps=np.zeros((N_FRAMES, 3)),
                        angular_velocity_in_imu_radps=np.zeros((N_FRAMES, 3)),
                        observations=StereoObservations.from_dense(np.repeat(dense[:, :, :1], N_FRAMES, axis=2)))
    paths = {}
    for name, s in (("two_frames", two), ("no_observations", none), ("standing_still", still)):
        paths[name] = d / f"{name}.npz"
        save_sequence(s, paths[name])
    return paths


@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize("name", ["two_frames", "no_observations", "standing_still"])
def test_degenerate_recordings_run_in_every_mode_without_warnings(degenerate_files, tmp_path, capsys, name):
    path = degenerate_files[name]
    assert load_sequence(path).n_frames in (2, N_FRAMES)
    for mode in ("localization", "mapping", "slam", "smoother"):
        out = tmp_path / mode
        proc = in_process(capsys, "run", path, "--mode", mode, "--out", out)
        assert proc.returncode == 0, (mode, proc.stderr)
        assert "Traceback" not in proc.stderr and "Warning" not in proc.stderr
        summary = json.loads((out / "summary.json").read_text())
        assert summary["frames_processed"] == summary["frames"] and not summary["partial"]
        if name == "no_observations" and mode != "localization":  # said, not silent
            assert any("no observation was used" in w for w in summary["warnings"])


def test_check_suggests_only_what_a_run_can_take(drive, tmp_path, capsys):
    """Frames 1 µs apart made check suggest velocity_scale 99590, beyond the option's range:
    `--auto` then stopped on a legal file with an options error. The suggestion is dropped
    (its finding says why), and the run goes on with the rest."""
    from vislam.core.check import check_sequence

    seq = drive.sequence
    fast = seq.replace(timestamps_s=seq.timestamps_s * 1e-5)
    result = check_sequence(fast)
    vislam.FilterOptions.from_dict(result.suggested)  # every suggestion is a valid option
    assert "velocity_scale" not in result.suggested
    scale = next(f for f in result.findings if f.code == "velocity-scale")
    assert "is not suggested (suggested: velocity_scale must be in (0, 1000]" in scale.message
    assert any(n.startswith("velocity_scale ") and "not suggested" in n for n in result.notes)
    path = tmp_path / "fast.npz"
    save_sequence(fast, path)
    proc = in_process(capsys, "run", path, "--auto", "--out", tmp_path / "out", "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "out" / "summary.json").is_file()
