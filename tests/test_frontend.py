"""The visual front end: readers of the three folder layouts, the tracker, `vislam track`."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import SHARED_DATA, shared_file

cv2 = pytest.importorskip("cv2")

from vislam.cli import main  # noqa: E402
from vislam.core.tracking import StereoTracker, TrackerOptions  # noqa: E402
from vislam.errors import ConfigError, DatasetError  # noqa: E402
from vislam.tools.frontend_io import open_stereo_source, read_kitti_calibration  # noqa: E402

# --------------------------------------------------------------------------- KITTI calibration

# The published 2011_09_30 calibration (shared data README), in the KITTI files' own format.
_CAM_TO_CAM = """calib_time: 09-Jan-2012 14:00:15
corner_dist: 9.950000e-02
S_rect_00: 1.226000e+03 3.700000e+02
R_rect_00: 9.999280e-01 8.085985e-03 -8.866797e-03 -8.123205e-03 9.999583e-01 -4.169750e-03 8.832711e-03 4.241477e-03 9.999520e-01
P_rect_00: 7.070912e+02 0.000000e+00 6.018873e+02 0.000000e+00 0.000000e+00 7.070912e+02 1.831104e+02 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00
S_rect_01: 1.226000e+03 3.700000e+02
P_rect_01: 7.070912e+02 0.000000e+00 6.018873e+02 -3.798145e+02 0.000000e+00 7.070912e+02 1.831104e+02 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00
S_rect_02: 1.242000e+03 3.750000e+02
P_rect_02: 7.070912e+02 0.000000e+00 6.018873e+02 4.688783e+01 0.000000e+00 7.070912e+02 1.831104e+02 1.178601e-01 0.000000e+00 0.000000e+00 1.000000e+00 6.203223e-03
S_rect_03: 1.242000e+03 3.750000e+02
P_rect_03: 7.070912e+02 0.000000e+00 6.018873e+02 -3.334597e+02 0.000000e+00 7.070912e+02 1.831104e+02 1.930130e+00 0.000000e+00 0.000000e+00 1.000000e+00 3.318498e-03
"""
_VELO_TO_CAM = """calib_time: 15-Mar-2012 11:37:16
R: 7.027555e-03 -9.999753e-01 2.599616e-05 -2.254837e-03 -4.184312e-05 -9.999975e-01 9.999728e-01 7.027479e-03 -2.255075e-03
T: -7.137748e-03 -7.482656e-02 -3.336324e-01
delta_f: 0.000000e+00 0.000000e+00
delta_c: 0.000000e+00 0.000000e+00
"""
_IMU_TO_VELO = """calib_time: 25-May-2012 16:47:16
R: 9.999976e-01 7.553071e-04 -2.035826e-03 -7.854027e-04 9.998898e-01 -1.482298e-02 2.024406e-03 1.482454e-02 9.998881e-01
T: -8.086759e-01 3.195559e-01 -7.997231e-01
"""


def _write_kitti_calib(date_dir):
    date_dir.mkdir(parents=True, exist_ok=True)
    (date_dir / "calib_cam_to_cam.txt").write_text(_CAM_TO_CAM)
    (date_dir / "calib_velo_to_cam.txt").write_text(_VELO_TO_CAM)
    (date_dir / "calib_imu_to_velo.txt").write_text(_IMU_TO_VELO)
    return date_dir


def test_kitti_calibration_matches_the_shared_0027_file(tmp_path):
    from vislam.tools.dataset_io import load_sequence

    seq = load_sequence(shared_file("sparse/0027.npz"))
    cal = read_kitti_calibration(_write_kitti_calib(tmp_path / "2011_09_30"))
    np.testing.assert_allclose(cal["K"], seq.camera.K, atol=1e-6)
    assert abs(cal["baseline_m"] - seq.camera.baseline_m) < 1e-6
    np.testing.assert_allclose(cal["cam_T_imu"][:3, :3], seq.cam_T_imu[:3, :3], atol=1e-6)
    # the published translation (the shared files store -Rᵀ t instead; data README)
    np.testing.assert_allclose(cal["cam_T_imu"][:3, 3], [-0.316, 0.734, -1.138], atol=2e-3)
    np.testing.assert_allclose(-cal["cam_T_imu"][:3, :3].T @ cal["cam_T_imu"][:3, 3], seq.cam_T_imu[:3, 3],
                               atol=2e-3)
    assert cal["image_size_px"] == (1226, 370)


def test_kitti_colour_pair_is_the_grey_calibration_moved_by_p_rect(tmp_path):
    date = _write_kitti_calib(tmp_path / "2011_09_30")
    grey = read_kitti_calibration(date, "grey")
    colour = read_kitti_calibration(date, "colour")
    np.testing.assert_allclose(colour["cam_T_imu"][:3, :3], grey["cam_T_imu"][:3, :3], atol=1e-12)
    # a point's coordinates in rectified camera 2 = those in rectified camera 0 + P_rect_02[:, 3] / f
    offset = colour["cam_T_imu"][:3, 3] - grey["cam_T_imu"][:3, 3]
    np.testing.assert_allclose(offset, [4.688783e01 / 707.0912, 1.178601e-01 / 707.0912, 6.203223e-03], atol=1e-12)
    assert abs(colour["baseline_m"] - (4.688783e01 + 3.334597e02) / 707.0912) < 1e-12
    assert colour["image_size_px"] == (1242, 375)


def test_kitti_calibration_errors_name_the_file_and_key(tmp_path):
    date = _write_kitti_calib(tmp_path / "d")
    (date / "calib_imu_to_velo.txt").write_text("R: 1 0 0 0 1 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"calib_imu_to_velo.txt: key 'T' missing"):
        read_kitti_calibration(date)
    (date / "calib_imu_to_velo.txt").unlink()
    with pytest.raises(DatasetError, match=r"calib_imu_to_velo.txt: missing"):
        read_kitti_calibration(date)


# --------------------------------------------------------------------------- a plain folder of textured images


def _texture(rng, h, w):
    """A smooth random texture (blobs of many sizes) with strong corners."""
    img = np.zeros((h, w))
    for s in (3, 7, 15):
        small = rng.random((h // s + 2, w // s + 2))
        img += cv2.resize(small, (w + 2 * s, h + 2 * s), interpolation=cv2.INTER_CUBIC)[s:s + h, s:s + w]
    img = (img - img.min()) / np.ptp(img)
    return (40 + 180 * img).astype(np.uint8)


def _plain_folder(root, n=6, disparity=8.0, shift=(1.5, 0.5), size=(320, 200), seed=0, noise=0.0):
    """A plain-layout folder: a fronto-parallel textured plane, the right image the left
    shifted by ``disparity`` px, each frame the previous shifted by ``shift`` px. ``noise`` > 0:
    from the second frame on, both images get white pixel noise of that standard deviation
    (grey levels; the geometry stays the same)."""
    rng = np.random.default_rng(seed)
    w, h = size
    big = _texture(rng, h + 80, w + 80)
    (root / "left").mkdir(parents=True)
    (root / "right").mkdir()
    for k in range(n):
        dx, dy = 20 + k * shift[0], 20 + k * shift[1]
        for side, extra in (("left", 0.0), ("right", disparity)):
            M = np.array([[1.0, 0, -dx - extra], [0, 1.0, -dy]])  # dst(x) = src(x + dx + extra), inside src
            img = cv2.warpAffine(big, M, (w, h), flags=cv2.INTER_CUBIC)
            if noise > 0 and k > 0:
                img = np.clip(img + rng.normal(0.0, noise, img.shape), 0, 255).astype(np.uint8)
            cv2.imwrite(str(root / side / f"{k:06d}.png"), img)
    f = 300.0
    (root / "calibration.yaml").write_text(
        f"K: [[{f}, 0, {w / 2}], [0, {f}, {h / 2}], [0, 0, 1]]\nbaseline: 0.5\n"
        "cam_T_imu: [[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1]]\n")
    rows = ["t,vx,vy,vz,wx,wy,wz"] + [f"{100 + 0.1 * k},1,0,0,0,0,0.01" for k in range(n)]
    (root / "velocities.csv").write_text("\n".join(rows) + "\n")
    return root


def test_tracker_on_shifted_texture_recovers_disparity_and_motion(tmp_path):
    source = open_stereo_source(_plain_folder(tmp_path / "plain"))
    assert source.layout == "folder" and source.n_frames == 6
    tracker = StereoTracker(source.K, source.baseline_m, TrackerOptions(target_features=80, grid_cols=4,
                                                                        grid_rows=2))
    frames = [tracker.process(*source.read_pair(t)) for t in range(source.n_frames)]
    ids0, px0 = frames[0]
    assert ids0.size >= 40
    np.testing.assert_allclose(np.median(px0[:, 0] - px0[:, 2]), 8.0, atol=0.05)
    assert np.median(np.abs(px0[:, 1] - px0[:, 3])) < 0.05
    ids5, px5 = frames[5]
    common, i0, i5 = np.intersect1d(ids0, ids5, return_indices=True)
    assert common.size >= 0.8 * ids0.size  # stable ids
    moved = px5[i5, :2] - px0[i0, :2]
    np.testing.assert_allclose(np.median(moved, axis=0), [-7.5, -2.5], atol=0.05)  # 5 frames of -shift
    assert np.all(np.abs(moved - [-7.5, -2.5]) < 0.1)


def test_new_corner_stereo_search_is_opencv_ncc_and_refuses_repeated_texture(tmp_path):
    source = open_stereo_source(_plain_folder(tmp_path / "plain", disparity=13.0))
    left, right = source.read_pair(0)
    for level in (0, 1, 2):
        tracker = StereoTracker(source.K, source.baseline_m, TrackerOptions(stereo_search_level=level))
        tracker._shape = left.shape
        corners = cv2.goodFeaturesToTrack(left, 60, 0.01, 10).reshape(-1, 2).astype(float)
        corners = corners[(corners[:, 0] > 60) & (corners[:, 1] > 20) & (corners[:, 1] < 180)]
        stereo, ok = tracker._stereo_search({"left": left, "right": right}, corners)
        assert ok.mean() > 0.9
        # before the affine step: the search level's pixel, sub-pixel by the parabola
        np.testing.assert_allclose(np.median(stereo[ok, 0] - stereo[ok, 2]), 13.0, atol=0.3 * 2 ** level)
        # the vectorised score is OpenCV's TM_CCOEFF_NORMED
        L, R, _ = tracker._search_images({"left": left, "right": right})
        r, s = max(2, (21 >> level) // 2), 2 ** level
        u, v = np.round(corners[0] / s).astype(int)
        x0 = max(r, u - int(np.ceil(250 / s)))
        score = cv2.matchTemplate(R[v - r:v + r + 1, x0 - r:u + r + 1], L[v - r:v + r + 1, u - r:u + r + 1],
                                  cv2.TM_CCOEFF_NORMED).ravel()
        assert abs(u - (x0 + np.argmax(score)) - (corners[0, 0] - stereo[0, 2]) / s) < 1.0
    # stripes repeating every 16 px: every match is ambiguous, none is kept
    x = np.arange(320)
    stripes = np.tile((128 + 80 * np.sin(2 * np.pi * x / 16)).astype(np.uint8), (200, 1))
    stripes[:, ::37] = 30  # some corners
    tracker = StereoTracker(source.K, source.baseline_m)
    tracker._shape = stripes.shape
    pts = np.array([[150.0, 100.0], [200.0, 60.0], [250.0, 140.0]])
    _, ok = tracker._stereo_search({"left": stripes, "right": np.roll(stripes, -5, axis=1)}, pts)
    assert not ok.any()


def test_geometric_gate_allows_the_depth_uncertainty_of_far_points():
    K = np.array([[700.0, 0, 600], [0, 700, 180], [0, 0, 1]])
    tracker = StereoTracker(K, 0.5)
    tracker._shape = (375, 1242)
    X = np.array([[20.0, 1.0, 60.0], [0.5, 0.5, 20.0]])  # far at the side, nearer in the middle
    ahead = np.array([0.0, 0.0, 10.0])  # ten frames later, 10 m further forward
    for off_px, far_kept in ((0.2, True), (0.3, False)):
        birth = tracker._project(X)
        birth[:, 2] -= off_px  # the stereo match off by about stereo_sigma_px: the far depth 3-5 % off
        X_est, cov = tracker._triangulate(birth), tracker._point_covariance(birth)
        assert cov[0, 2, 2] > 50 * cov[1, 2, 2]  # the depth variance grows with z^4
        measured, predicted = tracker._project(X - ahead), tracker._project(X_est - ahead)
        err = np.abs(measured - predicted).max(axis=1)
        assert err[0] > 1.5 > err[1]  # the far point is beyond the plain 1.5 px bound
        kept = tracker._gate(predicted, measured, X_est - ahead, cov, 1.5)
        # ... and kept while within gate_max_factor (1.5) x 1.5 px in plain pixels
        assert kept[1] and kept[0] == far_kept == (err[0] <= 2.25)
    # a 3 px error across the flow (v) is refused for either point
    off = measured.copy()
    off[:, [1, 3]] += 3.0
    assert not tracker._gate(predicted, off, X_est - ahead, cov, 1.5).any()


def test_tracks_past_their_appearance_bound_are_kept_while_the_geometry_confirms_them(tmp_path):
    # from the second frame on both images are noisy (10 grey levels) while the plane slides as
    # before: the residual against the first template rises past its bound, the geometry does not
    source = open_stereo_source(_plain_folder(tmp_path / "plain", n=10, noise=10.0))
    true_moved = 9 * np.array([-1.5, -0.5, -1.5, -0.5])
    survivors, error = {}, {}
    # off; on (0.5 px); on with a bound (0.05 px) below the positions' own error, so none is confirmed
    for case, (factor, bound) in {"off": (0.0, 0.5), "on": (1.5, 0.5), "tight": (1.5, 0.05)}.items():
        tracker = StereoTracker(source.K, source.baseline_m, TrackerOptions(
            affine_confirm_factor=factor, affine_confirm_px=bound, target_features=80, grid_cols=4, grid_rows=2))
        frames = [tracker.process(*source.read_pair(t)) for t in range(source.n_frames)]
        (ids0, px0), (ids9, px9) = frames[0], frames[-1]
        common, i0, i9 = np.intersect1d(ids0, ids9, return_indices=True)
        survivors[case] = common.size / ids0.size
        error[case] = np.median(np.abs(px9[i9] - px0[i0] - true_moved).max(axis=1))
        stats = tracker.stats.to_dict()
        assert (stats["confirmed"] > 0) == (case == "on")
        assert stats["rejections"]["geometric"] == stats["rejections"]["drift"] == 0
        if case != "on":  # the appearance check ends many; unconfirmed suspects count under it
            assert stats["rejections"]["appearance"] >= 0.2 * ids0.size
    assert survivors["on"] > survivors["off"] + 0.2
    assert abs(survivors["tight"] - survivors["off"]) <= 0.05
    # the tracks the geometry kept are as close to the true motion as those the appearance check kept
    assert error["on"] <= 1.1 * error["off"] + 0.05


def test_tracker_counts_every_track_end_with_its_length(tmp_path):
    # the texture slides 9 px per frame to the left: corners leave through the left edge
    source = open_stereo_source(_plain_folder(tmp_path / "plain", n=10, shift=(9.0, 0.0)))
    tracker = StereoTracker(source.K, source.baseline_m, TrackerOptions(target_features=80, grid_cols=4,
                                                                        grid_rows=2, side_band_fraction=0.0))
    frames = [tracker.process(*source.read_pair(t)) for t in range(source.n_frames)]
    stats = tracker.stats.to_dict()
    ends = stats["track_ends"]
    assert sum(e["count"] for e in ends.values()) > 0
    # every track started either ended (counted under one reason) or is alive in the last frame
    assert sum(e["count"] for e in ends.values()) + frames[-1][0].size == tracker._next_id
    for reason, e in ends.items():
        assert e["count"] == stats["rejections"][reason]
    # lengths: an id seen in frames a..b that ended in frame b+1 lasted b-a+1 frames
    seen = {}
    for t, (ids, _) in enumerate(frames):
        for i in ids:
            seen.setdefault(int(i), []).append(t)
    assert all(v == list(range(v[0], v[-1] + 1)) for v in seen.values())  # no gaps
    ended = [len(v) for v in seen.values() if v[-1] < len(frames) - 1]
    hist = sum(np.asarray(h) for h in tracker.stats.end_lengths.values())
    np.testing.assert_array_equal(hist, np.bincount(ended, minlength=hist.size))


def test_vislam_track_writes_a_recording_and_statistics(tmp_path, capsys):
    from vislam.tools.dataset_io import load_sequence

    src = _plain_folder(tmp_path / "plain")
    out = tmp_path / "o" / "tracks.npz"
    assert main(["track", str(src), "--out", str(out), "--quiet", "--features", "60"]) == 0
    seq = load_sequence(out)
    assert seq.n_frames == 6
    np.testing.assert_allclose(seq.linear_velocity_in_imu_mps[:, 0], 1.0)
    np.testing.assert_allclose(seq.timestamps_s, 100 + 0.1 * np.arange(6))
    assert seq.observations.track_lengths().min() >= 2
    stats = json.loads((tmp_path / "o" / "tracks.tracking.json").read_text())
    assert stats["frames"] == 6 and stats["tracks"] == seq.n_landmarks
    assert stats["tracks_per_frame_output"]["mean"] == pytest.approx(seq.observations.counts_per_frame().mean())


def test_tracker_options_from_file_and_errors(tmp_path):
    from vislam.cli.track import tracker_options_from_args

    cfg = tmp_path / "t.yaml"
    cfg.write_text("target_features: 123\nfb_threshold_px: 0.8\n")
    opts = tracker_options_from_args(cfg, {"min_track_length": 4})
    assert (opts.target_features, opts.fb_threshold_px, opts.min_track_length) == (123, 0.8, 4)
    cfg.write_text("target_feature: 1\n")
    with pytest.raises(ConfigError, match="t.yaml: unknown tracker option.*target_feature"):
        tracker_options_from_args(cfg)
    with pytest.raises(ConfigError, match="--features must be >= 1"):
        tracker_options_from_args(None, {"target_features": 0})
    with pytest.raises(ConfigError, match="stereo_window_px must be odd"):
        TrackerOptions(stereo_window_px=20)


def test_tracker_options_beyond_any_image_are_refused_and_a_patch_too_big_matches_nothing(tmp_path):
    """Values far beyond an image (grid_cols 1e9 asked numpy for 30 GB, min_distance_px
    1e300 crashed OpenCV's corner detector) are ConfigErrors naming the field; a stereo
    patch larger than the (downscaled) image gives no match and the few-tracks warning,
    not an IndexError."""
    from vislam.tools.frontend_io import track_source

    for field, value, words in (("grid_cols", 10 ** 9, "grid_cols must be at most 200"),
                                ("klt_levels", 10 ** 9, "klt_levels must be at most 8"),
                                ("min_distance_px", 1e300, "min_distance_px must be at most 100000")):
        with pytest.raises(ConfigError, match=words):
            TrackerOptions(**{field: value})
    source = open_stereo_source(_plain_folder(tmp_path / "f"))  # 320 x 200 px
    for options in (TrackerOptions(stereo_window_px=201), TrackerOptions(stereo_search_level=8)):
        _, stats = track_source(source, options)
        assert stats["tracks"] == 0 and "only 0.0 tracked landmarks" in stats["warnings"][0]


#: A complete EuRoC camera sensor.yaml (cam0 of V1_01).
_EUROC_SENSOR = """T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]
resolution: [752, 480]
intrinsics: [458.654, 457.296, 367.215, 248.375]
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""


def _bad_folders(tmp_path):
    cases = {}
    empty = tmp_path / "nolayout"
    (empty / "images").mkdir(parents=True)
    cases["no layout"] = (empty, "matches no image layout")
    p = _plain_folder(tmp_path / "nocal")
    (p / "calibration.yaml").unlink()
    cases["missing calibration"] = (p, "calibration.yaml: missing")
    p = _plain_folder(tmp_path / "badcal")
    (p / "calibration.yaml").write_text("K: [[300, 0, 160], [0, 300, 100]]\nbaseline: 0.5\n")
    cases["malformed calibration"] = (p, "calibration.yaml: key 'K'")
    p = _plain_folder(tmp_path / "lever")
    cal = p / "calibration.yaml"
    cal.write_text(cal.read_text().replace("[[0, -1, 0, 0]", "[[0, -1, 0, 1e300]"))
    cases["lever arm of 1e300 m"] = (p, "calibration.yaml: the IMU-camera translation is [1e+300")
    p = _plain_folder(tmp_path / "farcx")
    cal = p / "calibration.yaml"
    cal.write_text(cal.read_text().replace("K: [[300.0, 0, ", "K: [[300.0, 0, 1e200], [0, 300.0, 1e200], [0, 0, 1]]\nX: [[0, 0, ", 1))
    cases["principal point of 1e200 px"] = (p, "calibration.yaml: key 'K' has principal point (1e+200, 1e+200) px")
    p = _plain_folder(tmp_path / "badimg")
    (p / "right" / "000003.png").write_bytes(b"not a png")
    cases["unreadable image"] = (p, "000003.png: cannot be read as an image")
    p = _plain_folder(tmp_path / "count")
    (p / "right" / "000005.png").unlink()
    cases["counts disagree"] = (p, "holds 5 images")
    p = _plain_folder(tmp_path / "vcount")
    (p / "velocities.csv").write_text("t,vx,vy,vz,wx,wy,wz\n0,1,0,0,0,0,0\n0.1,1,0,0,0,0,0\n")
    cases["velocity rows disagree"] = (p, "velocities.csv: has 2 rows; expected one per image pair")
    p = _plain_folder(tmp_path / "vfar")
    csv = p / "velocities.csv"
    csv.write_text(csv.read_text().replace(",1,0,0,0,0,0.01\n", ",1,0,0,1e200,0,0.01\n", 1))
    cases["velocity of 1e200"] = (p, "velocities.csv: line 2 ('100.0,1,0,0,1e200,0,0.01') has a velocity beyond")
    # KITTI: left/right time stamps disagree
    date = _write_kitti_calib(tmp_path / "k" / "2011_09_30")
    drive = date / "2011_09_30_drive_0001_sync"
    for cam, offset in (("image_00", 0.0), ("image_01", 0.02)):
        (drive / cam / "data").mkdir(parents=True)
        for k in range(3):
            cv2.imwrite(str(drive / cam / "data" / f"{k:010d}.png"), np.zeros((370, 1226), np.uint8))
        (drive / cam / "timestamps.txt").write_text(
            "".join(f"2011-09-30 12:00:0{k}.{int((0.1 + offset) * 1e9):09d}\n" for k in range(3)))
    cases["timestamps disagree"] = (drive, "image_01/timestamps.txt: time stamp of frame 0 differs")
    # EuRoC: a sensor.yaml that is not a mapping, one without its intrinsics, with a date, a negative focal
    # length, and one sensor.yaml for both cameras
    for name, text, needle in (("euroc list", "- 1\n", "sensor.yaml: holds list [1], not a mapping"),
                               ("euroc no intrinsics", "resolution: [752, 480]\n",
                                "sensor.yaml: key 'intrinsics' is missing; expected 4 finite numbers"),
                               ("euroc bad date", "date: 2013-13-01\n", "sensor.yaml: invalid YAML (month"),
                               ("euroc negative focal", _EUROC_SENSOR.replace("[458.654", "[-458.654"),
                                "focal lengths fu = -458.654"),
                               # one sensor.yaml for both cameras: no baseline (was an OpenCV traceback)
                               ("euroc one place", _EUROC_SENSOR, "puts both cameras at the same place")):
        root = tmp_path / name.replace(" ", "_")
        for cam in ("cam0", "cam1"):
            (root / "mav0" / cam / "data").mkdir(parents=True)
            (root / "mav0" / cam / "sensor.yaml").write_text(text)
            (root / "mav0" / cam / "data.csv").write_text("#timestamp [ns],filename\n1403715273262142976,a.png\n")
        cases[name] = (root, needle)
    return cases


def test_bad_folders_give_one_line_exit_2_and_no_output(tmp_path, capsys):
    for name, (src, needle) in _bad_folders(tmp_path).items():
        out = tmp_path / "out" / f"{name.replace(' ', '_')}.npz"
        capsys.readouterr()
        code = main(["track", str(src), "--out", str(out), "--quiet"])
        err = capsys.readouterr().err
        assert code == 2, (name, err)
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("vislam track: error: "), (name, err)
        assert needle in lines[0], (name, lines[0])
        assert not out.exists() and not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir()), name


# --------------------------------------------------------------------------- EuRoC real images

EUROC = SHARED_DATA / "images" / "euroc_v1_01_first95"


@pytest.fixture(scope="module")
def euroc_tracks():
    if not (EUROC / "mav0" / "cam0" / "data.csv").is_file():
        pytest.skip(f"shared data not available: {EUROC}")
    from vislam.tools.frontend_io import track_source

    source = open_stereo_source(EUROC)
    sequence, stats = track_source(source)
    return source, sequence, stats


@pytest.mark.shared
def test_euroc_rectified_calibration_agrees_with_sensor_yaml(euroc_tracks):
    from vislam.core.lie import se3_inverse

    source, _, _ = euroc_tracks
    extra = source.extra
    t_cam1_in_cam0 = se3_inverse(extra["cam1_T_cam0"])[:3, 3]
    assert abs(source.baseline_m - np.linalg.norm(t_cam1_in_cam0)) < 1e-9  # 0.110 m
    # the rectified left camera is the raw cam0 turned by R_rect: undo it and get sensor.yaml's T_BS back
    R_rect = extra["rect_R_cam0"]
    cam0_T_imu = np.eye(4)
    cam0_T_imu[:3, :3] = R_rect.T @ source.cam_T_imu[:3, :3]
    cam0_T_imu[:3, 3] = R_rect.T @ source.cam_T_imu[:3, 3]
    np.testing.assert_allclose(se3_inverse(cam0_T_imu), extra["body_T_cam0"], atol=1e-9)
    # the rectified x axis points along the baseline (the right camera straight to the right)
    np.testing.assert_allclose(R_rect @ t_cam1_in_cam0, [source.baseline_m, 0, 0], atol=1e-9)
    assert np.degrees(np.arccos((np.trace(R_rect) - 1) / 2)) < 3  # a small turn


@pytest.mark.shared
def test_euroc_stereo_rows_drift_and_depths(euroc_tracks):
    source, seq, stats = euroc_tracks
    obs = seq.observations
    px = obs.pixels
    assert seq.n_frames == 95 and obs.counts_per_frame().min() >= 30
    assert np.median(np.abs(px[:, 1] - px[:, 3])) <= 0.5  # epipolar rows after rectification
    depth = source.K[0, 0] * source.baseline_m / (px[:, 0] - px[:, 2])
    assert np.all((depth > 0.5) & (depth < 15.0))  # a room
    # drift of the static camera's tracks over the 95 frames: the MAV on the floor still moves the image by up
    # to ~1.5 px in all (motors; every track shifts alike), so the drift is the departure of each track from
    # the common image motion — a homography from frame 0 fitted to all full-length tracks
    full = np.flatnonzero(obs.track_lengths() == seq.n_frames)
    assert full.size >= 30
    first = obs.frame(0)
    last = obs.frame(seq.n_frames - 1)
    p0 = first[1][np.searchsorted(first[0], full), :2]
    p1 = last[1][np.searchsorted(last[0], full), :2]
    H, _ = cv2.findHomography(p0, p1, 0)
    pred = cv2.perspectiveTransform(p0.reshape(-1, 1, 2), H).reshape(-1, 2)
    assert np.median(np.linalg.norm(p1 - pred, axis=1)) <= 0.3


@pytest.mark.shared
def test_euroc_without_velocities_is_refused_by_the_filters(euroc_tracks, tmp_path, capsys):
    from vislam.tools.frontend_io import write_tracks

    _, seq, stats = euroc_tracks
    path = write_tracks(seq, stats, tmp_path / "euroc.npz")[0]
    code = main(["run", str(path), "--out", str(tmp_path / "run"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "holds no velocities" in err and "--velocities" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "run").exists() or not any((tmp_path / "run").iterdir())


def test_run_and_check_on_bad_folders_give_one_line_and_write_nothing(tmp_path, capsys):
    cases = _bad_folders(tmp_path)
    for command in ("run", "check", "compare"):
        for name in ("no layout", "unreadable image", "counts disagree"):
            src, needle = cases[name]
            out = tmp_path / f"{command}-{name.replace(' ', '_')}"
            capsys.readouterr()
            code = main([command, str(src), "--out", str(out)] + (["--quiet"] if command != "check" else []))
            err = capsys.readouterr().err.strip().splitlines()
            assert code == 2 and len(err) == 1 and needle in err[0], (command, name, err)
            assert err[0].startswith(f"vislam {command}: error: ")
            assert not out.exists(), (command, name)


def test_run_refuses_an_euroc_folder_without_velocities_before_any_work(tmp_path, capsys):
    if not (EUROC / "mav0").is_dir():
        pytest.skip(f"shared data not available: {EUROC}")
    code = main(["run", str(EUROC), "--out", str(tmp_path / "o"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "no IMU velocities" in err[0] and "--velocities" in err[0]
    assert not (tmp_path / "o").exists()


def test_report_takes_an_image_folder(tmp_path, capsys):
    src = _plain_folder(tmp_path / "plain", n=8)
    out = tmp_path / "report"
    code = main(["report", "--data", str(src), "--out", str(out), "--sim-frames", "0", "--no-smoother",
                 "--noise-levels", "none", "--sequential", "--quiet"])
    assert code == 0, capsys.readouterr().err
    text = (out / "report.md").read_text()
    assert "images/plain" in text
    assert (out / "tracks" / "plain" / "tracks.npz").is_file()


def test_euroc_velocity_csv_is_interpolated_at_the_image_times(tmp_path):
    if not (EUROC / "mav0").is_dir():
        pytest.skip(f"shared data not available: {EUROC}")
    bare = open_stereo_source(EUROC)
    t = bare.timestamps_s
    grid = np.linspace(t[0] - 1, t[-1] + 1, 37)
    rows = ["t,vx,vy,vz,wx,wy,wz"] + [f"{g:.9f},{g - t[0]:.9f},1,2,0,0,{2 * (g - t[0]):.9f}" for g in grid]
    csv = tmp_path / "v.csv"
    csv.write_text("\n".join(rows) + "\n")
    source = open_stereo_source(EUROC, velocities=csv)
    np.testing.assert_allclose(source.velocities[:, 0], t - t[0], atol=1e-6)
    np.testing.assert_allclose(source.velocities[:, 5], 2 * (t - t[0]), atol=1e-6)
    csv.write_text("t,vx,vy,vz,wx,wy,wz\n" + f"{t[0]:.9f},0,0,0,0,0,0\n{t[10]:.9f},0,0,0,0,0,0\n")
    with pytest.raises(DatasetError, match=r"v.csv: covers .*; expected it to cover the image times"):
        open_stereo_source(EUROC, velocities=csv)


def test_a_baseline_in_millimetres_is_tracked_with_a_warning_naming_the_factor(tmp_path):
    """calibration.yaml with the baseline in millimetres: the tracks are what the images
    hold, but every triangulated point is kilometres away, beyond the filter's depth
    guards; the statistics warn of it and name x 0.001, and the textured folder with the
    baseline in metres gets no such warning."""
    from vislam.tools.frontend_io import track_source

    folder = _plain_folder(tmp_path / "mm")
    cal = folder / "calibration.yaml"
    cal.write_text(cal.read_text().replace("baseline: 0.5\n", "baseline: 500\n"))
    sequence, stats = track_source(open_stereo_source(folder))
    assert sequence.camera.baseline_m == 500.0 and stats["tracks"] > 0
    [warning] = stats["warnings"]
    assert "0 % are within the filter's depth guards" in warning and "0.5 m (the file's x 0.001" in warning
    # a baseline of 1e300 m overflows the points' covariances: the same warning, no floating-point one
    import warnings

    cal.write_text(cal.read_text().replace("baseline: 500\n", "baseline: 1e300\n"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, stats = track_source(open_stereo_source(folder))
    assert len(stats["warnings"]) == 1 and "no landmark can start" in stats["warnings"][0]


def test_a_folder_without_texture_is_tracked_with_a_warning_that_run_repeats(tmp_path):
    """Blank images give no corners: the tracks file is written (it is what the images
    hold), with a warning that names the likely causes, in the statistics, on `vislam
    track`'s stderr, among `vislam run`'s warnings and on the stderr of `check` and `compare`;
    textured pairs give none."""
    from vislam.tools.frontend_io import track_source

    _, stats = track_source(open_stereo_source(_plain_folder(tmp_path / "textured")))
    assert stats["tracks_per_frame_output"]["mean"] >= 10 and stats["warnings"] == []
    blank = _plain_folder(tmp_path / "blank")
    for image in list((blank / "left").glob("*.png")) + list((blank / "right").glob("*.png")):
        cv2.imwrite(str(image), np.full((200, 320), 128, np.uint8))
    _, stats = track_source(open_stereo_source(blank))
    assert stats["tracks"] == 0 and len(stats["warnings"]) == 1 and "blank" in stats["warnings"][0]
    track = subprocess.run([sys.executable, "-m", "vislam", "track", str(blank), "--out", str(tmp_path / "t.npz")],
                           capture_output=True, text=True, timeout=300)
    assert track.returncode == 0 and (tmp_path / "t.npz").is_file()
    assert track.stderr.count("vislam track: warning: only 0.0 tracked landmarks per frame") == 1, track.stderr
    out = tmp_path / "run"
    run = subprocess.run([sys.executable, "-m", "vislam", "run", str(blank), "--out", str(out), "--quiet"],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    warnings = json.loads((out / "summary.json").read_text())["warnings"]
    assert warnings[0].startswith("only 0.0 tracked landmarks per frame")
    for command, prefix in (("check", "vislam check: warning: tracking: "), ("compare", "vislam: warning: tracking: ")):
        done = subprocess.run([sys.executable, "-m", "vislam", command, str(blank), "--out", str(tmp_path / command)],
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        assert done.stderr.count(prefix + "only 0.0 tracked landmarks per frame") == 1, (command, done.stderr)
