"""The stepwise filters of the public API (vislam.SlamFilter etc.): fed frame by frame,
they reproduce the batch runs; the frames of a file can be streamed; the README's Python
example runs as written."""

from __future__ import annotations

import re

import numpy as np
import pytest

import vislam
from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.tools.dataset_io import iter_frames, save_sequence

from conftest import REPO_ROOT

NOISY = dict(velocity_noise_mps=0.5, angular_noise_radps=0.05)


@pytest.fixture(scope="module")
def drive():
    return simulate_drive(SimulationOptions(seed=3, n_frames=120, moving_fraction=0.1, outlier_fraction=0.02))


def _stepwise(seq, mode, options):
    """Drive a filter through the public API with separate predict/update calls."""
    cls = {"localization": vislam.LocalizationFilter, "mapping": vislam.MappingFilter, "slam": vislam.SlamFilter}[mode]
    f = cls(seq.calibration, options)
    poses, covs, nis = [], [], []
    for k, frame in enumerate(seq.frames()):
        if k:
            f.predict(frame.dt_s, frame.linear_velocity_mps, frame.angular_velocity_radps)
        stats = f.update(frame.landmark_ids, frame.pixels)
        assert stats.frame == k and stats.observations == frame.n_observations
        poses.append(f.world_T_imu)
        covs.append(f.pose_covariance)
        nis.append(stats.nis_mean)
        if mode == "slam":
            assert f.live_landmark_ids.shape == (stats.live_landmarks,)
            assert f.live_p_lm_in_world.shape == (stats.live_landmarks, 3)
    return np.array(poses), np.array(covs), np.array(nis), f.finish()


@pytest.mark.parametrize("mode", ["localization", "mapping", "slam"])
@pytest.mark.parametrize("options", [vislam.FilterOptions(), vislam.FilterOptions(**NOISY, init_frames=3),
                                     vislam.FilterOptions(probation_frames=2, repeated_observations="split")],
                         ids=["default", "noisy-delayed-init", "probation-split"])
def test_stepwise_equals_batch(drive, mode, options):
    seq = drive.sequence
    batch = vislam.run(seq, mode, options)
    poses, covs, nis, landmarks = _stepwise(seq, mode, options)
    assert not batch.partial
    np.testing.assert_allclose(poses, batch.world_T_imu, rtol=0, atol=1e-9)
    np.testing.assert_allclose(covs, batch.pose_covariance, rtol=0, atol=1e-12)
    np.testing.assert_allclose(nis, batch.frame_stats["nis_mean"], rtol=1e-8)  # BLAS threads may differ
    if mode != "localization":
        assert len(landmarks) == len(batch.landmarks) > 0
        np.testing.assert_array_equal(landmarks.ids, batch.landmarks.ids)
        np.testing.assert_allclose(landmarks.p_lm_in_world, batch.landmarks.p_lm_in_world, rtol=0, atol=1e-9)


def test_frame_stats_add_up_to_run_stats(drive):
    r = vislam.run(drive.sequence, "slam", vislam.FilterOptions())
    fs = r.frame_stats
    assert fs["observations"].sum() == drive.sequence.observations.n_observations
    assert fs["used"].sum() == r.stats.observations_used
    assert fs["gated"].sum() == r.stats.observations_gated
    assert fs["initialized"].sum() == r.stats.landmarks_initialized
    assert fs["rejected"].sum() == r.stats.landmarks_rejected
    assert fs["live_landmarks"].max() == r.stats.max_state_landmarks


@pytest.mark.parametrize("pixel_noise_px", [0.5, 2.0])
def test_frame_nis_follows_the_pixel_noise_ratio(pixel_noise_px):
    """The 4-D stereo NIS averages 4 (σ_true/σ_filter)² when the pixel noise dominates:
    4 when the filter is told the simulator's 0.5 px (a little less: the gate cuts the
    tail), 0.25 with the default 2 px."""
    sim = simulate_drive(SimulationOptions(seed=5, n_frames=120))
    r = vislam.run(sim.sequence, "slam", vislam.FilterOptions(pixel_noise_px=pixel_noise_px))
    fs = r.frame_stats
    ok = fs["nis_count"] > 0
    mean = np.average(fs["nis_mean"][ok], weights=fs["nis_count"][ok])
    expected = 4 * (sim.options.pixel_noise_px / pixel_noise_px) ** 2
    assert 0.6 * expected < mean < 1.6 * expected


def test_frozen_map_grows_and_last_frozen_reported(drive):
    f = vislam.SlamFilter(drive.sequence.calibration, vislam.FilterOptions())
    sizes, frozen = [], 0
    for frame in drive.sequence.frames():
        f.step(frame)
        frozen += f.last_frozen[0].size
        sizes.append(len(f.frozen_map()))
    assert sizes == sorted(sizes) and sizes[-1] == frozen > 0
    live_at_end = f.live_landmark_ids.size
    assert len(f.finish()) == frozen + live_at_end


def test_bad_calls_raise_clear_errors(drive):
    f = vislam.SlamFilter(drive.sequence.calibration)
    with pytest.raises(vislam.ConfigError, match="strictly increasing"):
        f.update(np.array([3, 2]), np.zeros((2, 4)))
    with pytest.raises(vislam.ConfigError, match=r"\(n, 4\)"):
        f.update(np.array([1]), np.zeros((1, 3)))
    with pytest.raises(vislam.ConfigError, match="dt_s"):
        f.predict(-0.1, np.zeros(3), np.zeros(3))


def test_failure_stops_the_filter_and_batch_is_partial(drive, monkeypatch):
    from conftest import poison_state_at

    bad = drive.sequence
    poison_state_at(monkeypatch, 40)  # a non-finite covariance: the health check must catch it
    r = vislam.run(bad, "slam", vislam.FilterOptions())
    assert r.partial and r.stats.frames_processed == 40 and "frame 40" in r.error
    f = vislam.SlamFilter(bad.calibration)
    with pytest.raises(vislam.EstimationError):
        for frame in bad.frames():
            f.step(frame)
    with pytest.raises(vislam.EstimationError, match="stopped earlier"):
        f.update(np.zeros(0, dtype=np.int64), np.zeros((0, 4)))


@pytest.mark.parametrize("fortran", [True, False])
def test_iter_frames_streams_the_file(drive, tmp_path, fortran):
    path = tmp_path / "drive.npz"
    save_sequence(drive.sequence, path, fortran_order=fortran)
    stream = iter_frames(path)
    assert stream.streams is fortran and len(stream) == drive.sequence.n_frames
    n = 0
    for frame, ref in zip(stream, drive.sequence.frames(), strict=True):
        assert frame.index == ref.index and frame.dt_s == ref.dt_s
        np.testing.assert_array_equal(frame.landmark_ids, ref.landmark_ids)
        np.testing.assert_array_equal(frame.pixels, ref.pixels)
        np.testing.assert_array_equal(frame.linear_velocity_mps, ref.linear_velocity_mps)
        n += 1
    assert n == drive.sequence.n_frames
    np.testing.assert_array_equal(stream.calibration.cam_T_imu, drive.sequence.cam_T_imu)


def test_iter_frames_reports_a_bad_frame_in_one_line(drive, tmp_path):
    dense = drive.sequence.observations.dense()
    j = int(drive.sequence.observations.frame(5)[0][0])
    dense[1, j, 5] = np.nan
    from vislam.tools.npz import write_npz

    s = drive.sequence
    path = tmp_path / "bad.npz"
    write_npz(path, {"time_stamps": s.timestamps_s[None], "features": np.asfortranarray(dense),
                     "linear_velocity": s.linear_velocity_in_imu_mps.T,
                     "rotational_velocity": s.angular_velocity_in_imu_radps.T, "K": s.camera.K,
                     "b": np.array(s.camera.baseline_m), "cam_T_imu": s.cam_T_imu})
    with pytest.raises(vislam.DatasetError, match=rf"bad.npz: key 'features' landmark {j} at frame 5"):
        list(iter_frames(path))


def _readme_example() -> str:
    text = (REPO_ROOT / "README.md").read_text(encoding="utf-8")
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    example = [b for b in blocks if "vislam.SlamFilter" in b]
    assert example, "the README has no Python example with vislam.SlamFilter"
    return example[0]


def test_readme_example_runs_as_written():
    """The README's example (on the simulator, as written): the final poses it streams
    equal the batch run's (its own assert) and follow the simulated truth."""
    scope: dict = {}
    exec(compile(_readme_example(), "README.md", "exec"), scope)
    pose = scope["world_T_imu"]
    assert pose.shape == (4, 4) and np.all(np.isfinite(pose))
    assert scope["t"] + 1 == scope["seq"].n_frames
    assert scope["error_m"] < 1.0  # SLAM with a noisy IMU stays near the truth


def test_online_stall_remap_equals_the_remapped_sequence():
    """SLAM with ``stalled_tracks: remap`` (online, through the stall buffer) gives the
    same trajectory and map as the plain filter on the sequence remapped as a whole
    (:func:`vislam.core.stalls.remap_sequence`), when the delay covers every lag."""
    from vislam.core.stalls import remap_sequence, track_lags

    sim = simulate_drive(SimulationOptions(seed=4, n_frames=150, stall_period=10, velocity_noise_mps=0.5,
                                           angular_noise_radps=0.05))
    seq = sim.sequence
    max_lag = int(track_lags(seq.observations).max())
    assert max_lag >= 2  # the drive has stalled tracks
    base = vislam.FilterOptions(**NOISY, repeated_observations="skip")  # the remap runs with skip
    online = vislam.run(seq, "slam", base.replace(stalled_tracks="remap", stall_max_delay_frames=max_lag))
    offline = vislam.run(remap_sequence(seq), "slam", base.replace(stalled_tracks="keep"))
    np.testing.assert_allclose(online.world_T_imu, offline.world_T_imu, rtol=0, atol=1e-9)
    np.testing.assert_allclose(online.landmarks.p_lm_in_world, offline.landmarks.p_lm_in_world, rtol=0, atol=1e-9)
    assert online.stats.observations_repeated == int(seq.observations.repeated_mask().sum())
    assert online.stats.observations_lag_dropped == 0
    # a shorter delay drops exactly the observations lagging more
    short = vislam.run(seq, "slam", base.replace(stall_max_delay_frames=1))
    lags = track_lags(seq.observations)
    assert short.stats.observations_lag_dropped == int(((lags > 1) & ~seq.observations.repeated_mask()).sum())


def test_online_pose_is_predicted_to_the_newest_frame():
    """Behind by the stall delay, the filter still reports the newest frame's pose: the
    last updated pose predicted with the IMU samples received since."""
    sim = simulate_drive(SimulationOptions(seed=6, n_frames=60, stall_period=10))
    f = vislam.SlamFilter(sim.sequence.calibration, vislam.FilterOptions(stall_max_delay_frames=5, repeated_observations="skip"))
    for frame in sim.sequence.frames():
        f.step(frame)
        assert f.frame_index == frame.index
        if frame.index >= 5:
            assert f.last_frame_stats.frame == frame.index - 5
        # dead reckoning over ≤ 5 frames of a clean IMU stays within centimetres of the truth
        assert np.linalg.norm(f.world_T_imu[:3, 3] - sim.world_T_imu[frame.index, :3, 3]) < 0.5
    f.drain()
    assert f.last_frame_stats.frame == sim.sequence.n_frames - 1


def test_a_full_state_lets_the_lowest_ids_in_bounds_its_size_and_says_so():
    """``max_landmarks_in_state`` bounds the SLAM state: the landmarks beyond it wait (the
    lowest ids enter first), are counted, and the run warns. A bound at the drive's peak
    changes nothing."""
    from vislam.core.results import run_warnings

    drive = simulate_drive(SimulationOptions(seed=3, n_frames=120, **NOISY))
    seq = drive.sequence
    options = vislam.FilterOptions(**NOISY)
    free = vislam.run(seq, "slam", options)
    peak = free.stats.max_state_landmarks
    assert peak > 12 and free.stats.observations_state_full == free.stats.frames_state_full == 0
    assert not any("state was full" in w for w in run_warnings(free))
    same = vislam.run(seq, "slam", options.replace(max_landmarks_in_state=peak))
    np.testing.assert_array_equal(same.world_T_imu, free.world_T_imu)
    assert same.stats.observations_state_full == 0

    cap = peak // 3
    f = vislam.SlamFilter(seq.calibration, options.replace(max_landmarks_in_state=cap))
    first = next(iter(seq.frames()))
    f.step(first)
    assert first.n_observations > cap  # the first frame alone overfills the state
    np.testing.assert_array_equal(f.live_landmark_ids, np.sort(first.landmark_ids)[:cap])
    capped = vislam.run(seq, "slam", options.replace(max_landmarks_in_state=cap))
    assert not capped.partial and capped.stats.max_state_landmarks == cap
    assert capped.stats.observations_state_full > 0 and capped.stats.frames_state_full > 0
    assert capped.stats.to_dict()["observations_state_full"] == capped.stats.observations_state_full
    warning = [w for w in run_warnings(capped) if "state was full" in w]
    assert len(warning) == 1 and f"max_landmarks_in_state {cap}" in warning[0]
    assert f"{capped.stats.observations_state_full} observations" in warning[0]
    # still SLAM: far from dead reckoning's drift under this IMU noise
    truth = drive.world_T_imu[:, :3, 3]
    dead = vislam.run(seq, "localization", options)
    ate = {name: float(np.sqrt(np.mean(np.sum((r.world_T_imu[:, :3, 3] - truth) ** 2, axis=1))))
           for name, r in (("capped", capped), ("dead", dead))}
    assert ate["capped"] < 0.5 * ate["dead"], ate
    # with delayed initialization, a landmark that passed its static test waits in its window
    delayed = vislam.run(seq, "slam", options.replace(max_landmarks_in_state=cap, init_frames=3))
    assert not delayed.partial and delayed.stats.max_state_landmarks == cap
    assert delayed.stats.observations_state_full > 0
