"""Hostile and unusual image folders given to the visual front end (`vislam track`, and
`run` / `check` on a folder): each is one clear error line naming the file and the key or
field, exit code 2 and nothing written — or, for a recording that can be tracked but whose
pairs look wrong, a warning naming the cause. Every folder is built here, small
(160x120 px), so the tests need no shared data."""

from __future__ import annotations

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from test_frontend import _texture  # noqa: E402  (the textured plane of test_frontend's folders)
from vislam.cli import main  # noqa: E402
from vislam.errors import DatasetError  # noqa: E402
from vislam.tools.frontend_io import open_stereo_source, track_source  # noqa: E402

W, H = 160, 120
F = 150.0
T0_NS = 1_403_715_273_262_142_976


def _pairs(n, disparity=6.0, seed=0):
    """n rectified pairs of a fronto-parallel textured plane, the right image the left moved
    ``disparity`` px to the left, each frame the previous moved by (1, 0.5) px."""
    big = _texture(np.random.default_rng(seed), H + 60, W + 60)
    for k in range(n):
        out = []
        for extra in (0.0, disparity):
            M = np.array([[1.0, 0, -(20 + k) - extra], [0, 1.0, -(20 + 0.5 * k)]])
            out.append(cv2.warpAffine(big, M, (W, H), flags=cv2.INTER_CUBIC))
        yield out


def _plain(root, n=5, names=None):
    (root / "left").mkdir(parents=True)
    (root / "right").mkdir()
    for k, (left, right) in enumerate(_pairs(n)):
        name = names[k] if names else f"{k:06d}.png"
        cv2.imwrite(str(root / "left" / name), left)
        cv2.imwrite(str(root / "right" / name), right)
    (root / "calibration.yaml").write_text(f"K: [[{F}, 0, {W / 2}], [0, {F}, {H / 2}], [0, 0, 1]]\nbaseline: 0.5\n"
                                           "cam_T_imu: [[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1]]\n")
    (root / "velocities.csv").write_text("t,vx,vy,vz,wx,wy,wz\n"
                                         + "".join(f"{100 + 0.1 * k:.1f},1,0,0,0,0,0\n" for k in range(n)))
    return root


def _sensor_yaml(tx=0.0, ty=0.0, intrinsics=f"[{F}, {F}, {W / 2}, {H / 2}]", distortion="[0.0, 0.0, 0.0, 0.0]",
                 resolution=f"[{W}, {H}]"):
    return (f"%YAML:1.0\nT_BS:\n  cols: 4\n  rows: 4\n  data: [1.0, 0.0, 0.0, {tx}, 0.0, 1.0, 0.0, {ty}, 0.0, 0.0, 1.0, "
            f"0.0, 0.0, 0.0, 0.0, 1.0]\nresolution: {resolution}\ncamera_model: pinhole\nintrinsics: {intrinsics}\n"
            f"distortion_model: radial-tangential\ndistortion_coefficients: {distortion}\n")


def _euroc(root, n=4):
    """An EuRoC/ASL folder: cam1 0.1 m to the right of cam0 (the body frame is cam0's), no
    distortion, 20 Hz."""
    mav0 = root / "mav0"
    for cam, tx in (("cam0", 0.0), ("cam1", 0.1)):
        (mav0 / cam / "data").mkdir(parents=True)
        (mav0 / cam / "sensor.yaml").write_text(_sensor_yaml(tx=tx))
    rows = []
    for k, (left, right) in enumerate(_pairs(n)):
        stamp = T0_NS + k * 50_000_000
        cv2.imwrite(str(mav0 / "cam0" / "data" / f"{stamp}.png"), left)
        cv2.imwrite(str(mav0 / "cam1" / "data" / f"{stamp}.png"), right)
        rows.append(f"{stamp},{stamp}.png\n")
    for cam in ("cam0", "cam1"):
        (mav0 / cam / "data.csv").write_text("#timestamp [ns],filename\n" + "".join(rows))
    return root


def _kitti(root, n=4, s_rect=True):
    """A KITTI raw date folder with one drive (identity extrinsics, baseline 0.5 m); the drive."""
    date = root / "2011_09_30"
    drive = date / "2011_09_30_drive_0001_sync"
    p0 = f"{F} 0 {W / 2} 0 0 {F} {H / 2} 0 0 0 1 0"
    p1 = f"{F} 0 {W / 2} {-0.5 * F} 0 {F} {H / 2} 0 0 0 1 0"
    size = f"S_rect_00: {W} {H}\nS_rect_01: {W} {H}\n" if s_rect else ""
    date.mkdir(parents=True)
    (date / "calib_cam_to_cam.txt").write_text(f"{size}R_rect_00: 1 0 0 0 1 0 0 0 1\nP_rect_00: {p0}\nP_rect_01: {p1}\n")
    for name in ("calib_velo_to_cam.txt", "calib_imu_to_velo.txt"):
        (date / name).write_text("R: 1 0 0 0 1 0 0 0 1\nT: 0 0 0\n")
    stamps = "".join(f"2011-09-30 12:00:00.{100_000_000 * k:09d}\n" for k in range(n))
    for sub in ("image_00", "image_01", "oxts"):
        (drive / sub / "data").mkdir(parents=True)
        (drive / sub / "timestamps.txt").write_text(stamps)
    for k, (left, right) in enumerate(_pairs(n, disparity=6.0)):
        cv2.imwrite(str(drive / "image_00" / "data" / f"{k:010d}.png"), left)
        cv2.imwrite(str(drive / "image_01" / "data" / f"{k:010d}.png"), right)
        (drive / "oxts" / "data" / f"{k:010d}.txt").write_text(" ".join(["0"] * 8 + ["1"] + ["0"] * 21) + "\n")
    return drive


def _refused(capsys, tmp_path, source, *needles, command="track", extra=()):
    """Run `vislam COMMAND SOURCE`; assert exit 2, one error line holding every needle, and
    nothing written. Returns the line."""
    out = tmp_path / f"out-{command}"
    target = ["--out", str(out / "t.npz")] if command == "track" else ["--out", str(out)]
    capsys.readouterr()
    code = main([command, str(source), *target, *extra] + (["--quiet"] if command != "check" else []))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith(f"vislam {command}: error: "), err
    for needle in needles:
        assert needle in err[0], (needle, err[0])
    assert not out.exists() or not any(out.rglob("*")), sorted(out.rglob("*"))
    return err[0]


# --------------------------------------------------------------------------- EuRoC data.csv and sensor.yaml


def test_the_synthetic_euroc_folder_is_tracked(tmp_path):
    """The base of the EuRoC cases below is a good recording: rectified to itself, tracked."""
    source = open_stereo_source(_euroc(tmp_path / "e"))
    assert abs(source.baseline_m - 0.1) < 1e-9
    _, stats = track_source(source)
    assert stats["tracks_per_frame_output"]["mean"] >= 10 and stats["warnings"] == []


@pytest.mark.parametrize("stamp, why", [("9" * 30, "30 digits (an OverflowError)"),
                                        ("14037152732621429\u00b2", "a superscript digit (isdigit, not int)"),
                                        ("1403715273.262", "seconds")])
def test_euroc_data_csv_time_stamps_that_are_not_int64_nanoseconds(tmp_path, capsys, stamp, why):
    root = _euroc(tmp_path / "e")
    csv = root / "mav0" / "cam0" / "data.csv"
    lines = csv.read_text().splitlines()
    lines[-1] = f"{stamp},{lines[-1].split(',')[1]}"
    csv.write_text("\n".join(lines) + "\n")
    _refused(capsys, tmp_path, root, "cam0/data.csv: line 5", "integer time stamp in nanoseconds")


@pytest.mark.parametrize("bad", ["../../cam1/data/{}", "{cam1}/{}"])
def test_euroc_data_csv_file_names_outside_the_data_folder_are_refused(tmp_path, capsys, bad):
    """A listed name may not leave cam0/data (it read the right camera's image as the left one)."""
    root = _euroc(tmp_path / "e")
    csv = root / "mav0" / "cam0" / "data.csv"
    lines = csv.read_text().splitlines()
    stamp, name = lines[2].split(",")
    lines[2] = f"{stamp},{bad.format(name, cam1=root / 'mav0' / 'cam1' / 'data')}"
    csv.write_text("\n".join(lines) + "\n")
    _refused(capsys, tmp_path, root, "cam0/data.csv: line 3 names file", "expected a file name inside")


@pytest.mark.parametrize("camera, old, new, needles", [
    ("cam0", "resolution: [160, 120]", "resolution: [2000000, 2000000]",
     ("cam0/sensor.yaml: key 'resolution' is [2000000.0, 2000000.0]", "1 to 100000")),
    ("both", "resolution: [160, 120]", "resolution: [200, 100]",
     (".png: is 160x120 px; expected 200x100 px", "key 'resolution'")),
    ("cam0", f"intrinsics: [{F}, {F}, {W / 2}, {H / 2}]", f"intrinsics: [{F}, {F}, 5000.0, {H / 2}]",
     ("cam0/sensor.yaml: key 'intrinsics' has principal point (cu, cv) = (5000, 60) px",)),
    ("cam0", f"intrinsics: [{F},", "intrinsics: [true,", ("cam0/sensor.yaml: key 'intrinsics' is [True",)),
    ("cam1", "distortion_coefficients: [0.0,", "distortion_coefficients: [-1e30,",
     ("cam1/sensor.yaml: keys 'intrinsics' and 'distortion_coefficients' rectify to an image of which 0 %",)),
    ("cam1", "data: [1.0, 0.0, 0.0, 0.1,", "data: [1.0, 0.0, 0.0, -0.1,",
     ("key 'T_BS' puts cam1 0.1 m to the left of cam0", "sensor.yaml files swapped")),
    ("cam1", "data: [1.0, 0.0, 0.0, 0.1, 0.0, 1.0, 0.0, 0.0,", "data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.1,",
     ("key 'T_BS' puts cam1 above or below cam0",)),
])
def test_euroc_sensor_yaml_values_no_image_can_be_rectified_with(tmp_path, capsys, camera, old, new, needles):
    """Before: an OpenCV MemoryError traceback (resolution 2e6 px), a recording of zero tracks
    with the blank-images warning (principal point off the sensor, k1 = -1e30, cameras
    swapped or stacked: a negative or zero baseline given to the tracker), fu = 1.0 px (true)."""
    root = _euroc(tmp_path / "e")
    for cam in (("cam0", "cam1") if camera == "both" else (camera,)):
        yaml_file = root / "mav0" / cam / "sensor.yaml"
        text = yaml_file.read_text()
        assert old in text
        yaml_file.write_text(text.replace(old, new))
    _refused(capsys, tmp_path, root, *needles)


def test_euroc_frames_listed_but_missing_at_the_end_are_tracked_with_a_warning(tmp_path):
    """An excerpt's data.csv may list images it does not hold; the frames dropped are said."""
    root = _euroc(tmp_path / "e", n=5)
    max((root / "mav0" / "cam0" / "data").glob("*.png")).unlink()
    sequence, stats = track_source(open_stereo_source(root))
    assert sequence.n_frames == 4
    assert any("cam0/data.csv: lists 1 images that are not in" in w and "tracked the 4 frames present" in w
               for w in stats["warnings"]), stats["warnings"]


def test_a_byte_order_mark_is_not_part_of_the_first_row(tmp_path):
    """Spreadsheets write a UTF-8 BOM: a data.csv without header was refused at line 1, and a
    velocity CSV without header lost its first row (read as a header)."""
    root = _euroc(tmp_path / "e")
    for cam in ("cam0", "cam1"):
        csv = root / "mav0" / cam / "data.csv"
        csv.write_bytes(b"\xef\xbb\xbf" + "".join(csv.read_text().splitlines(True)[1:]).encode())
    source = open_stereo_source(root)
    assert source.n_frames == 4
    plain = _plain(tmp_path / "p")
    csv = plain / "velocities.csv"
    csv.write_bytes(b"\xef\xbb\xbf" + "".join(csv.read_text().splitlines(True)[1:]).encode())
    source = open_stereo_source(plain)
    np.testing.assert_allclose(source.timestamps_s, 100 + 0.1 * np.arange(5))


# --------------------------------------------------------------------------- pixels: bit depth, size, pairs


def test_twelve_bit_images_in_16_bit_pngs_keep_their_grey_levels(tmp_path):
    """12-bit data in 16-bit PNGs was decoded to 8 bits by dropping the low byte (12 grey levels
    left: 7 tracks a frame instead of 200); it is scaled by one factor, 255/4095, for the whole
    recording. A 16-bit image among 8-bit ones is refused."""
    folder = _plain(tmp_path / "p")
    eight = open_stereo_source(folder).read_pair(2)
    for image in folder.rglob("*.png"):
        cv2.imwrite(str(image), cv2.imread(str(image), cv2.IMREAD_UNCHANGED).astype(np.uint16) * 16)
    twelve = open_stereo_source(folder).read_pair(2)
    for a, b in zip(eight, twelve):
        assert a.dtype == b.dtype == np.uint8
        assert np.abs(a.astype(int) - b.astype(int)).max() <= 1 and np.ptp(b) > 150
    mixed = _plain(tmp_path / "m")
    image = mixed / "right" / "000003.png"
    cv2.imwrite(str(image), cv2.imread(str(image), cv2.IMREAD_UNCHANGED).astype(np.uint16) * 256)
    with pytest.raises(DatasetError, match=r"right/000003.png: has uint16 pixels, .*000000.png uint8; expected one "
                                           r"bit depth"):
        track_source(open_stereo_source(mixed))


def test_floating_point_images_are_refused_naming_their_type(tmp_path, capsys):
    folder = _plain(tmp_path / "p")
    for image in folder.rglob("*.png"):
        cv2.imwrite(str(image.with_suffix(".tiff")), cv2.imread(str(image), 0).astype(np.float32) / 255)
        image.unlink()
    _refused(capsys, tmp_path, folder, "left/000000.tiff: has float32 pixels; expected an 8- or 16-bit")


def test_image_files_are_paired_in_numeric_order(tmp_path):
    """1.png, 2.png, ..., 10.png: plain sorting put 10 before 2 — frames out of time order
    beside velocities in order."""
    folder = _plain(tmp_path / "p", n=12, names=[f"{k}.png" for k in range(12)])
    source = open_stereo_source(folder)
    assert [p.name for p in source.left_files] == [f"{k}.png" for k in range(12)]


def test_identical_left_and_right_images_are_refused(tmp_path, capsys):
    """A right folder that is a copy of the left one: zero disparity everywhere (EuRoC's
    rectification made chance matches of them: 23 tracks a frame and no warning)."""
    folder = _plain(tmp_path / "p")
    for image in (folder / "right").glob("*.png"):
        image.write_bytes((folder / "left" / image.name).read_bytes())
    _refused(capsys, tmp_path, folder, "right/000000.png: is the same image as", "left/000000.png",
             "zero disparity")
    root = _euroc(tmp_path / "e")
    for image in (root / "mav0" / "cam1" / "data").glob("*.png"):
        image.write_bytes((root / "mav0" / "cam0" / "data" / image.name).read_bytes())
    _refused(capsys, tmp_path / "e", root, "cam1/data/", "is the same image as", command="run",
             extra=("--velocities", str(_velocity_csv(tmp_path))))


def _velocity_csv(tmp_path):
    path = tmp_path / "v.csv"
    t0 = T0_NS * 1e-9
    path.write_text("".join(f"{t0 + 0.1 * k - 1:.6f},1,0,0,0,0,0\n" for k in range(30)))
    return path


def test_swapped_left_and_right_folders_give_a_warning(tmp_path, capsys):
    """Left and right exchanged: every disparity negative, only chance matches (1 track a
    frame, with a warning that blamed blank or blurred images). The warning now says the
    pair matches as exchanged; `vislam track` prints it and still writes the file. (A pair
    as given gets no such warning: test_the_synthetic_euroc_folder_is_tracked and
    test_frontend's textured folder assert no warnings at all.)"""
    folder = _plain(tmp_path / "p")
    (folder / "left").rename(folder / "x")
    (folder / "right").rename(folder / "left")
    (folder / "x").rename(folder / "right")
    _, stats = track_source(open_stereo_source(folder))
    swapped = [w for w in stats["warnings"] if "left and right images swapped" in w]
    assert len(swapped) == 1 and "left/000000.png and" in swapped[0], stats["warnings"]
    n_exchanged, n_given = (int(swapped[0].split(": ")[1].split()[0]),
                            int(swapped[0].split("exchanged, ")[1].split()[0]))
    assert n_exchanged >= 3 * max(n_given, 1) and n_exchanged >= 10
    out = tmp_path / "t.npz"
    assert main(["track", str(folder), "--out", str(out)]) == 0 and out.is_file()
    assert "vislam track: warning: " in capsys.readouterr().err
    # EuRoC: the exchanged files are rectified each as the other camera (the raw images of the
    # shared V1_01 excerpt swapped: 23 tracks a frame and no warning before)
    root = _euroc(tmp_path / "e")
    data0, data1 = root / "mav0" / "cam0" / "data", root / "mav0" / "cam1" / "data"
    data0.rename(root / "x")
    data1.rename(data0)
    (root / "x").rename(data1)
    _, stats = track_source(open_stereo_source(root))
    assert any("cam0/data/" in w and "left and right images swapped" in w for w in stats["warnings"]), stats


@pytest.mark.parametrize("n", [1, 2])
def test_fewer_pairs_than_a_track_needs_are_refused(tmp_path, capsys, n):
    """1 or 2 pairs with min_track_length 3 wrote an empty recording with the blank-images
    warning; with --min-track-length 1 one pair is a recording."""
    folder = _plain(tmp_path / "p", n=n)
    _refused(capsys, tmp_path, folder, f"left: holds {n} image pair", "expected at least 3 (min_track_length")
    _refused(capsys, tmp_path, folder, f"left: holds {n} image pair", command="check")
    assert main(["track", str(folder), "--out", str(tmp_path / "one.npz"), "--quiet", "--min-track-length", "1"]) == 0


@pytest.mark.parametrize("size", [(8, 8), (400, 12)])
def test_images_too_small_to_hold_a_corner_are_refused(tmp_path, capsys, size):
    folder = _plain(tmp_path / "p")
    for image in folder.rglob("*.png"):
        cv2.imwrite(str(image), cv2.resize(cv2.imread(str(image), 0), size))
    _refused(capsys, tmp_path, folder, f"left/000000.png: is {size[0]}x{size[1]} px; expected at least 33x33 px",
             "border_px")


def test_a_boolean_baseline_is_not_one_metre(tmp_path, capsys):
    folder = _plain(tmp_path / "p")
    cal = folder / "calibration.yaml"
    cal.write_text(cal.read_text().replace("baseline: 0.5", "baseline: true"))
    _refused(capsys, tmp_path, folder, "calibration.yaml: key 'baseline' is True; expected 1 finite number")


# --------------------------------------------------------------------------- KITTI raw


def test_kitti_without_s_rect_takes_the_size_of_any_readable_image(tmp_path, capsys):
    """Without S_rect the size came from a PNG header: JPEG images or an unreadable first PNG
    were a TypeError traceback."""
    drive = _kitti(tmp_path / "jpg", s_rect=False)
    for image in drive.rglob("*.png"):
        cv2.imwrite(str(image.with_suffix(".jpg")), cv2.imread(str(image), 0))
        image.unlink()
    assert open_stereo_source(drive).image_size_px == (W, H)
    drive = _kitti(tmp_path / "bad", s_rect=False)
    (drive / "image_00" / "data" / "0000000000.png").write_bytes(b"\x89PNG")
    _refused(capsys, tmp_path, drive, "image_00/data/0000000000.png: cannot be read as an image")


@pytest.mark.parametrize("s_rect", ["0.5 0.5", "-160 -120", "1e30 1e30"])
def test_kitti_s_rect_that_is_no_image_size_names_the_key(tmp_path, capsys, s_rect):
    drive = _kitti(tmp_path / "k")
    c2c = drive.parent / "calib_cam_to_cam.txt"
    c2c.write_text(c2c.read_text().replace(f"S_rect_00: {W} {H}", f"S_rect_00: {s_rect}"))
    _refused(capsys, tmp_path, drive, "calib_cam_to_cam.txt: key 'S_rect_00' is", "whole pixels, 1 to 100000")


def test_kitti_without_oxts_packets_names_the_folder(tmp_path, capsys):
    """An empty oxts/data was an IndexError traceback."""
    drive = _kitti(tmp_path / "k")
    for packet in (drive / "oxts" / "data").glob("*.txt"):
        packet.unlink()
    (drive / "oxts" / "timestamps.txt").write_text("")
    _refused(capsys, tmp_path, drive, "oxts/data: holds no OXTS packets; expected one .txt per frame")
    _refused(capsys, tmp_path, drive, "oxts/data: holds no OXTS packets", command="run")


# --------------------------------------------------------------------------- velocities and the output


def test_velocity_times_in_nanoseconds_are_named_as_such(tmp_path, capsys):
    root = _euroc(tmp_path / "e")
    csv = tmp_path / "ns.csv"
    csv.write_text("t,vx,vy,vz,wx,wy,wz\n" + "".join(f"{T0_NS + k * 100_000_000 - 10**9},1,0,0,0,0,0\n"
                                                      for k in range(30)))
    _refused(capsys, tmp_path, root, "ns.csv: covers", "its times look like nanoseconds, expected seconds",
             extra=("--velocities", str(csv)))


def test_an_output_below_a_file_is_refused_before_tracking(tmp_path, capsys):
    """--out FILE/t.npz with FILE a file: refused at once (it failed after the whole tracking)."""
    folder = _plain(tmp_path / "p")
    (tmp_path / "afile").write_text("x")
    capsys.readouterr()
    code = main(["track", str(folder), "--out", str(tmp_path / "afile" / "sub" / "t.npz"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "afile is a file; expected a directory to write t.npz into" in err[0]
    assert (tmp_path / "afile").read_text() == "x"


def test_left_and_right_folders_with_one_frame_missing_each_are_refused(tmp_path, capsys):
    """left/ without 000001.png, right/ without 000003.png: the same count, so every pair
    between them was silently a left image with its neighbour's right image."""
    folder = _plain(tmp_path / "p")
    (folder / "left" / "000001.png").unlink()
    (folder / "right" / "000003.png").unlink()
    csv = folder / "velocities.csv"
    csv.write_text("".join(csv.read_text().splitlines(True)[:-1]))
    _refused(capsys, tmp_path, folder, "right/000001.png: would be paired with", "left/000002.png (frame 1",
             "expected the same file names")
