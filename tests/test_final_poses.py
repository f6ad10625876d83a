"""``pop_final_poses()`` / ``vislam.final_poses``: each frame's final pose in the output
convention (world_T_imu), the same as the batch run returns — also for a filter that runs
behind the newest frame (the stalled-track remap) and for the smoother."""

from __future__ import annotations

import numpy as np
import pytest

import vislam
from vislam.core.lie import se3_inverse
from vislam.core.simulate import SimulationOptions, simulate_drive

NOISY = dict(velocity_noise_mps=0.5, angular_noise_radps=0.05)


@pytest.fixture(scope="module")
def stalled_drive():
    # stalls every 10 frames: the remap holds frames, so the live pose runs ahead of the final one
    return simulate_drive(SimulationOptions(seed=4, n_frames=80, stall_period=10, **NOISY))


def _collect(poses):
    ts, Ts = zip(*poses)
    return np.array(ts), np.array(Ts)


@pytest.mark.parametrize("mode, cls", [("slam", vislam.SlamFilter), ("localization", vislam.LocalizationFilter)])
def test_final_poses_equal_the_batch_run(stalled_drive, mode, cls):
    seq = stalled_drive.sequence
    options = vislam.FilterOptions(**NOISY)
    batch = vislam.run(seq, mode, options)
    poses = vislam.final_poses(cls(seq.calibration, options), seq.frames())
    ts, world_T_imu = _collect(poses)
    np.testing.assert_array_equal(ts, np.arange(seq.n_frames))
    np.testing.assert_allclose(world_T_imu, batch.world_T_imu, atol=1e-9)
    if mode == "slam":
        assert poses.landmarks is not None and poses.landmarks.ids.size == batch.landmarks.ids.size


def test_pop_final_poses_is_pop_processed_inverted(stalled_drive):
    seq = stalled_drive.sequence
    remap = vislam.FilterOptions(**NOISY, repeated_observations="skip")  # the remap runs behind
    f = vislam.SlamFilter(seq.calibration, remap)
    g = vislam.SlamFilter(seq.calibration, remap)
    held = 0
    for frame in seq.frames():
        f.step(frame)
        g.step(frame)
        finals = f.pop_final_poses()
        processed = g.pop_processed()
        assert [t for t, _ in finals] == [p[0] for p in processed]
        for (_, world_T_imu), (_, imu_T_world, _, _) in zip(finals, processed):
            np.testing.assert_allclose(world_T_imu, se3_inverse(imu_T_world), atol=1e-12)
        held = max(held, frame.index + 1 - (finals[-1][0] + 1 if finals else 0))
    assert held > 1  # the remap really ran behind: the newest pose was not yet final
    f.drain()
    assert f.pop_final_poses()[-1][0] == seq.n_frames - 1


def test_smoother_final_poses_equal_its_final_trajectory():
    pytest.importorskip("gtsam")
    seq = simulate_drive(SimulationOptions(seed=2, n_frames=50, **NOISY)).sequence
    f = vislam.SmootherFilter(seq.calibration, vislam.FilterOptions(**NOISY, smoother_window_s=1.0))
    behind, got = [], []
    poses = vislam.final_poses(f, seq.frames())
    for t, world_T_imu in poses:
        behind.append(f.frame_index - t)  # how far behind the newest frame the pose became final
        got.append(world_T_imu)
    final, _ = f.final_trajectory()
    assert len(got) == seq.n_frames
    assert max(behind) > 5  # poses left the window while the drive went on
    np.testing.assert_array_equal(np.array(got), final)
    assert poses.landmarks is not None
