"""Accuracy on the shared KITTI datasets against their ground truth (skipped without
``../shared/data``). The numbers in the comments were measured with the defaults."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import shared_file
from vislam.core import estimators
from vislam.core.noise import NoiseSpec, inject_noise
from vislam.core.options import FilterOptions
from vislam.tools.dataset_io import load_sequence
from vislam.tools.evaluation import evaluate, load_ground_truth

DENSE_IMU = dict(velocity_noise_mps=0.5, angular_noise_radps=0.05)


def _ate(result, gt) -> float:
    n = min(len(result.world_T_imu), len(gt.world_T_body))
    return evaluate(result.world_T_imu[:n], gt.world_T_body[:n]).ape.rmse


def _load(kind: str, stem: str):
    seq = load_sequence(shared_file(f"{kind}/{stem}.npz"))
    gt = load_ground_truth(shared_file(f"groundtruth/{stem}.txt"), fmt="kitti", frame="cam", cam_T_imu=seq.cam_T_imu)
    return seq, gt


@pytest.fixture(scope="module")
def dense27():
    return _load("dense", "0027")


@pytest.fixture(scope="module")
def dense27_slam_ate(dense27):
    """ATE of SLAM on dense 0027 as shared (files' lever arm, IMU frame: 7.19 m, the
    worst of this drive's noise-draw variants under the split stalled tracks)."""
    seq, gt = dense27
    return _ate(estimators.run(seq, "slam", FilterOptions(**DENSE_IMU)), gt)



def test_dense_0027_slam_far_better_than_localization():
    """With the published lever arm, SLAM's camera-frame ATE over the file and two fresh
    noise draws of the same drive (sparse 0027's clean velocities plus the dense files'
    white noise, as benchmarks/noise_draws.py draws 0 and 1) is a third of dead
    reckoning's on the file, or less. One file's ATE moves a lot: the file alone is the
    worst of seven variants (6.79 m; draws 0, 1: 2.19, 3.36 m; dead reckoning 14.2 m)."""
    from vislam.core.lie import se3_inverse
    from vislam.core.rigs import swapped_translation

    seq = load_sequence(shared_file("dense/0027.npz"))
    sparse = load_sequence(shared_file("sparse/0027.npz"))
    from vislam.tools.trajectory_io import read_trajectory

    gt_cam = read_trajectory(shared_file("groundtruth/0027.txt"), "kitti").world_T_body  # left-camera poses
    C = np.array(seq.cam_T_imu)
    C[:3, 3] = swapped_translation(seq.cam_T_imu)  # the files store imu_T_cam's translation
    opts = FilterOptions(**DENSE_IMU, cam_T_imu=C.tolist())

    def cam_ate(s, mode):
        r = estimators.run(s, mode, opts)
        cam = r.world_T_imu @ se3_inverse(C)
        n = min(len(cam), len(gt_cam))
        return evaluate(cam[:n], gt_cam[:n]).ape.rmse

    runs = [seq]
    for n in (0, 1):
        rng = np.random.default_rng(100 + n)
        v = sparse.linear_velocity_in_imu_mps + rng.normal(0, 0.5, sparse.linear_velocity_in_imu_mps.shape)
        w = sparse.angular_velocity_in_imu_radps + rng.normal(0, 0.05, sparse.angular_velocity_in_imu_radps.shape)
        runs.append(seq.replace(linear_velocity_in_imu_mps=v, angular_velocity_in_imu_radps=w))
    slam = np.mean([cam_ate(s, "slam") for s in runs])  # 4.11 m
    loc = cam_ate(seq, "localization")  # 14.2 m
    assert slam < 5.0
    assert 3 * slam < loc


@pytest.mark.parametrize("stem", ["0020", "0027"])
def test_sparse_slam_matches_localization(stem):
    seq, gt = _load("sparse", stem)
    slam = _ate(estimators.run(seq, "slam"), gt)  # 0020: 3.54 m, 0027: 2.04 m
    loc = _ate(estimators.run(seq, "localization"), gt)  # 0020: 3.52 m, 0027: 2.03 m
    assert slam <= 1.01 * loc


def test_dense_0027_gross_outliers(dense27, dense27_slam_ate):
    seq, gt = dense27
    opts = FilterOptions(**DENSE_IMU)
    clean = dense27_slam_ate
    noisy, info = inject_noise(seq, NoiseSpec(outlier_fraction=0.05, seed=1))
    assert info["outliers_injected"] == round(0.05 * seq.observations.n_observations)
    result = estimators.run(noisy, "slam", opts)
    with_outliers = _ate(result, gt)  # 3.19 m (seed 2: 1.93 m; clean 7.19 m)
    # 5 % gross outliers keep SLAM within the spread of clean runs over fresh IMU noise
    # draws of this drive (1.6-7.2 m) plus a margin, far from dead reckoning (15-16 m)
    assert with_outliers < max(6.0, 1.3 * clean)


def test_sparse_0020_with_five_times_the_velocity_noise():
    seq, gt = _load("sparse", "0020")
    noisy, _ = inject_noise(seq, NoiseSpec(velocity_noise_mps=0.1, angular_noise_radps=0.0015, seed=0))
    slam = estimators.run(noisy, "slam")
    loc = estimators.run(noisy, "localization")
    assert not slam.partial
    assert _ate(slam, gt) < 1.2 * _ate(loc, gt)  # 3.74 vs 3.73 m


def test_all_datasets_all_modes_run_without_subsampling():
    for kind, stem in [("sparse", "0042"), ("dense", "0022"), ("dense", "0034")]:
        seq = load_sequence(shared_file(f"{kind}/{stem}.npz"))
        opts = FilterOptions(**DENSE_IMU) if kind == "dense" else FilterOptions()
        r = estimators.run(seq, "slam", opts)
        assert not r.partial
        assert r.stats.frames_processed == seq.n_frames
        assert np.all(np.isfinite(r.world_T_imu))
        # every landmark that passed the guards is in the map (nothing subsampled)
        assert len(r.landmarks) == r.stats.landmarks_initialized


def test_iterated_update_stops_when_it_stops_contracting():
    """Sparse 0020 with the IMU-error state (0.3 m/s, 0.003 rad/s, 20 s): at frame 675, two
    landmarks in view, Gauss-Newton re-linearizations used to grow instead of shrink and
    drove b̂_v to 4.2 m/s (14 σ_b) and the ATE to 27 m; the iterated update now keeps the
    last iterate when a step would be larger than the one before (measured: |b̂_v| at most
    1.06 m/s, ATE 7.49 m; the defaults are unchanged, byte-equal on the shared files)."""
    seq, gt = _load("sparse", "0020")
    # the scenario as it was found: stalled tracks remapped (the default before 2026-12-02)
    r = estimators.run(seq, "slam", FilterOptions(imu_bias_sigma_mps=0.3, imu_bias_sigma_radps=0.003,
                                                 imu_bias_time_constant_s=20.0, repeated_observations="skip"))
    assert not r.partial
    assert np.abs(r.extra["imu_bias"][:, :3]).max() < 5 * 0.3
    assert _ate(r, gt) < 10.0
