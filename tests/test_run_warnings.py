"""Every estimator warns when its own statistics say it did not do its job (issue 22.7):
no observation ever used, a long stretch without a visual update, most observations
refused, a time gap beyond its model — in the result (run_warnings), on stderr and in
summary.json."""

from __future__ import annotations

import json

import numpy as np
import pytest

import vislam
from vislam.cli import main
from vislam.core.noise import NoiseSpec, inject_noise
from vislam.core.results import JOB_LIMITS, run_warnings
from vislam.core.sequence import StereoObservations
from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.tools.dataset_io import save_sequence

#: A light scene (about 50 observations per frame) to keep the file fast.
SCENE = dict(facade_density_per_m=0.5)


@pytest.fixture(scope="module")
def drive():
    return simulate_drive(SimulationOptions(n_frames=40, seed=7, **SCENE)).sequence


def _with_pixels(seq, pixels):
    obs = seq.observations
    return seq.replace(observations=StereoObservations(obs.frame_offsets, obs.landmark_ids, pixels, obs.n_landmarks))


def _modes():
    modes = ["mapping", "slam"]
    try:
        import gtsam  # noqa: F401

        modes.append("smoother")
    except ImportError:  # pragma: no cover - gtsam is a dependency
        pass
    return modes


@pytest.mark.parametrize("mode", _modes())
def test_clean_drive_gives_no_warning(drive, mode):
    assert run_warnings(vislam.run(drive, mode, vislam.FilterOptions())) == []


@pytest.mark.parametrize("mode", _modes())
@pytest.mark.parametrize("how", ["negative disparity", "zero disparity"])
def test_no_landmark_ever_used_warns(drive, mode, how):
    px = drive.observations.pixels.copy()
    if how == "negative disparity":
        px[:, [0, 2]] = px[:, [2, 0]]
    else:
        px[:, 2] = px[:, 0]
    r = vislam.run(_with_pixels(drive, px), mode, vislam.FilterOptions())
    assert not r.partial and r.stats.observations_used == 0
    warnings = run_warnings(r)
    assert len(warnings) == 1 and warnings[0].startswith("no observation was used")
    assert f"{drive.observations.n_observations} not initialized" in warnings[0]


@pytest.mark.parametrize("mode", _modes())
def test_most_observations_refused_warns(drive, mode):
    noisy, info = inject_noise(drive, NoiseSpec(outlier_fraction=0.99, seed=1))
    assert info["outliers_injected"] > 0.9 * drive.observations.n_observations
    warnings = run_warnings(vislam.run(noisy, mode, vislam.FilterOptions()))
    assert any("observations" in w and ("refused" in w or "failed the gate" in w) for w in warnings), warnings
    assert any("landmarks were rejected" in w for w in warnings), warnings


def test_long_stretch_without_a_visual_update_warns():
    seq = simulate_drive(SimulationOptions(n_frames=90, seed=7, **SCENE)).sequence
    obs = seq.observations
    keep = (obs.frame_index < 10) | (obs.frame_index >= 80)  # frames 10-79 (7 s) have no observation
    offsets = np.zeros(seq.n_frames + 1, dtype=np.int64)
    np.cumsum(np.bincount(obs.frame_index[keep], minlength=seq.n_frames), out=offsets[1:])
    blind = seq.replace(observations=StereoObservations(offsets, obs.landmark_ids[keep], obs.pixels[keep],
                                                        obs.n_landmarks))
    warnings = run_warnings(vislam.run(blind, "slam", vislam.FilterOptions()))
    seconds = blind.timestamps_s[79] - blind.timestamps_s[9]
    assert seconds > JOB_LIMITS["no_update_s"]
    assert warnings == [f"no visual update for {seconds:.1f} s (frames 10-79; expected at most "
                        f"{JOB_LIMITS['no_update_s']:g} s): the recording has no observations there; the trajectory "
                        f"there is dead reckoning"]


@pytest.mark.parametrize("mode", ["localization", "slam"])
def test_time_gap_beyond_the_model_warns(drive, mode):
    t = drive.timestamps_s.copy()
    t[20:] += 10.0
    r = vislam.run(drive.replace(timestamps_s=t), mode, vislam.FilterOptions())
    gap = [w for w in run_warnings(r) if "time gap" in w]
    assert len(gap) == 1 and "19 -> 20" in gap[0] and "beyond the motion model" in gap[0]


def test_slam_goes_on_after_an_hour_without_frames():
    """Two recordings in one file, an hour apart: the SLAM prior is then so wide (72 m,
    1 rad) that some innovation covariances are singular in floating point. Those
    observations are gated (NIS = inf) and the run completes, with the gap's warning;
    it stopped with "numerical failure at frame 72: Singular matrix" before."""
    from vislam.core.updaters import innovation_nis

    S = np.tile(np.eye(4), (3, 1, 1))
    S[1] = np.ones((4, 4))  # singular
    nis = innovation_nis(np.ones((3, 4)), S)
    assert nis[1] == np.inf and nis[0] == nis[2] == 4.0
    seq = simulate_drive(SimulationOptions(n_frames=120, seed=0)).sequence
    t = seq.timestamps_s.copy()
    t[70:] += 3600.0
    r = vislam.run(seq.replace(timestamps_s=t), "slam", vislam.FilterOptions())
    assert not r.partial, r.error
    assert any("time gap" in w and "69 -> 70" in w for w in run_warnings(r))


@pytest.mark.parametrize("unit, scale, fix", [("milliseconds", 1e3, "timestamp_scale 0.001"),
                                               ("microseconds", 1e6, "timestamp_scale 1e-06"),
                                               ("none", 30.0, "not a frame clock")])
def test_time_stamps_not_in_seconds_warn_and_the_fix_silences_it(drive, unit, scale, fix):
    """Time stamps in ms (µs, or no clock at all: frames 3 s apart). The run warns and
    names the fix; with it (timestamp_scale, as `vislam check` suggests) no warning."""
    t = drive.timestamps_s * scale
    r = vislam.run(drive.replace(timestamps_s=t), "localization", vislam.FilterOptions())
    (warning,) = [w for w in run_warnings(r) if "apart (median)" in w]
    assert fix in warning and (unit in warning or unit == "none")
    if unit != "none":
        fixed = vislam.run(drive.replace(timestamps_s=t), "localization",
                           vislam.FilterOptions(timestamp_scale=1 / scale))
        assert run_warnings(fixed) == []


def test_imu_samples_beyond_a_vehicle_s_motion_warn(drive, tmp_path, capsys):
    """One corrupt sample (a speed of 1e8 m/s, a turn of 1e6 rad/s) is named with its
    frame; a drive's own samples give no such warning."""
    from vislam.core.sequence import imu_sample_warnings

    v, w = drive.linear_velocity_in_imu_mps.copy(), drive.angular_velocity_in_imu_radps.copy()
    assert imu_sample_warnings(v, w) == []
    v[12, 0], w[30, 2] = 1e8, -1e6
    speed, turn = imu_sample_warnings(v, w)
    assert "speed beyond 343 m/s" in speed and "1e+08 m/s, frame 12" in speed
    assert "turn rate beyond 35 rad/s" in turn and "1e+06 rad/s, frame 30" in turn
    data = tmp_path / "corrupt.npz"
    save_sequence(drive.replace(linear_velocity_in_imu_mps=v, angular_velocity_in_imu_radps=w), data)
    assert main(["run", str(data), "--mode", "localization", "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert speed in summary["warnings"] and turn in summary["warnings"] and speed in err
    # compare: in comparison.json, in every method's summary.json, and on stderr once
    assert main(["compare", str(data), "--methods", "separate", "--out", str(tmp_path / "cmp")]) == 0
    err = capsys.readouterr().err
    content = json.loads((tmp_path / "cmp" / "comparison.json").read_text())
    assert content["warnings"] == [speed, turn] and err.count(speed) == 1
    assert speed in json.loads((tmp_path / "cmp" / "separate" / "summary.json").read_text())["warnings"]


def test_run_prints_and_records_them(drive, tmp_path, capsys):
    px = drive.observations.pixels.copy()
    px[:, [0, 2]] = px[:, [2, 0]]
    data = tmp_path / "negative.npz"
    save_sequence(_with_pixels(drive, px), data)
    assert main(["run", str(data), "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert len(summary["warnings"]) == 1 and "no observation was used" in summary["warnings"][0]
    assert err.count("vislam: warning:") == 1 and summary["warnings"][0] in err


def _frozen(seq, first: int, last: int):
    """``seq`` whose frames first..last repeat frame first − 1's observations exactly (a
    camera or tracker that froze while the vehicle drove on)."""
    obs = seq.observations
    rows = [np.arange(obs.frame_offsets[k], obs.frame_offsets[k + 1]) for k in range(seq.n_frames)]
    for k in range(first, last + 1):
        rows[k] = rows[first - 1]
    take = np.concatenate(rows)
    offsets = np.r_[0, np.cumsum([r.size for r in rows])]
    return seq.replace(observations=StereoObservations(offsets, obs.landmark_ids[take], obs.pixels[take],
                                                       obs.n_landmarks))


@pytest.mark.parametrize("mode", _modes())
def test_frozen_images_warn_in_the_run_and_in_check(drive, mode):
    """Frames whose observations all repeat the previous frame's pixels while the IMU moves
    (a camera frozen for 20 s on sparse 0027: ATE 0.47 -> 1.92 m) gave no warning at all:
    the repeats were split into new landmarks, counted as used."""
    from vislam.core.check import check_sequence

    frozen = _frozen(drive, 15, 34)  # 2 s
    warnings = run_warnings(vislam.run(frozen, mode, vislam.FilterOptions()))
    line = next((w for w in warnings if "repeat the previous frame's pixels exactly" in w), None)
    assert line is not None, warnings
    assert line.startswith("frames 15-34 (")
    assert "did the images or the tracker freeze" in line
    # one frame of repeats (as the shared files' tracker makes them) is not a freeze
    assert not any("freeze" in w for w in run_warnings(vislam.run(_frozen(drive, 15, 15), mode,
                                                                  vislam.FilterOptions())))
    if mode == "slam":
        found = {f.code: f for f in check_sequence(frozen).findings}["repeated-observations"]
        assert found.severity == "WARN" and "in frames 15-34" in found.message
        assert {f.code: f for f in check_sequence(drive).findings}["repeated-observations"].severity == "OK"


@pytest.mark.parametrize("fault", ["zeros", "held"])
def test_an_imu_dropout_is_said_by_run_and_check(drive, fault):
    """IMU samples exactly 0 in all six channels (a dropout filled with zeros), or exactly
    the sample before them (a held value), for 1 s or more: no sensor reads that. Sparse 0027
    with 10 s of either ran without a word (ATE 0.47 -> 59.5 m and 38.8 m)."""
    from vislam.core.check import check_sequence
    from vislam.core.sequence import imu_sample_warnings

    v, w = drive.linear_velocity_in_imu_mps.copy(), drive.angular_velocity_in_imu_radps.copy()
    if fault == "zeros":
        v[10:22], w[10:22] = 0.0, 0.0
        first = 10
    else:
        v[10:22], w[10:22] = v[9], w[9]
        first = 10  # sample 10 is the first that repeats sample 9
    faulty = drive.replace(linear_velocity_in_imu_mps=v, angular_velocity_in_imu_radps=w)
    warnings = imu_sample_warnings(v, w)
    assert len(warnings) == 1 and f"frames {first}-21" in warnings[0]
    assert ("exactly 0 in all six channels" if fault == "zeros" else "exactly the sample before them") in warnings[0]
    found = {f.code: f for f in check_sequence(faulty).findings}["imu-samples"]
    assert found.severity == "WARN" and f"frames {first}-21" in found.message
    # fewer than 10 such samples (a short stop with an exact zero) and the clean drive say nothing
    v2, w2 = drive.linear_velocity_in_imu_mps.copy(), drive.angular_velocity_in_imu_radps.copy()
    v2[10:19], w2[10:19] = 0.0, 0.0
    assert imu_sample_warnings(v2, w2) == []
    assert imu_sample_warnings(drive.linear_velocity_in_imu_mps, drive.angular_velocity_in_imu_radps) == []


def test_isolated_imu_spikes_are_said_and_do_not_make_the_noise():
    """Eight 50 m/s spikes in sparse 0027's forward velocity ran without a word, and check
    took them for white noise (3.84 m/s suggested, which --auto applied: ATE 6.2 m against
    5.2 m without). They are now a warning, and check suggests no noise from them. White
    noise of 0.5 m/s and 0.05 rad/s, or 2 m/s and 0.2 rad/s, is not a spike."""
    from vislam.core.check import check_sequence
    from vislam.core.sequence import imu_sample_warnings, imu_spikes

    for vn, an, seed in ((0.5, 0.05, 1), (2.0, 0.2, 2)):
        noisy = simulate_drive(SimulationOptions(n_frames=300, seed=seed, velocity_noise_mps=vn, angular_noise_radps=an,
                                                 **SCENE)).sequence
        assert imu_spikes(noisy.linear_velocity_in_imu_mps, noisy.angular_velocity_in_imu_radps) == []
    seq = simulate_drive(SimulationOptions(n_frames=300, seed=3, **SCENE)).sequence
    v = seq.linear_velocity_in_imu_mps.copy()
    v[[40, 120, 200], 0] = 50.0
    spiky = seq.replace(linear_velocity_in_imu_mps=v)
    warnings = imu_sample_warnings(v, seq.angular_velocity_in_imu_radps)
    assert len(warnings) == 1 and "3 isolated IMU sample(s)" in warnings[0] and "frames 40, 120, 200" in warnings[0]
    result = check_sequence(spiky)
    assert "velocity_noise_mps" not in result.suggested
    noise = {f.code: f for f in result.findings}["noise"]
    assert noise.severity == "WARN" and "3 isolated IMU sample(s)" in noise.message
