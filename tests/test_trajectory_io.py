"""Tests of TUM / KITTI trajectory files (vislam.tools.trajectory_io)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vislam.core.lie import make_pose
from vislam.errors import GroundTruthError
from vislam.tools.trajectory_io import (
    detect_format,
    format_kitti,
    read_kitti,
    read_trajectory,
    read_tum,
    write_kitti,
    write_tum,
)


def random_poses(rng, n: int, scale: float = 1e3) -> np.ndarray:
    R = Rotation.random(n, random_state=rng).as_matrix()
    return make_pose(R, rng.normal(0, scale, (n, 3)))


def test_kitti_round_trip(tmp_path):
    poses = random_poses(np.random.default_rng(0), 50)
    path = tmp_path / "traj.txt"
    write_kitti(path, poses)
    back = read_kitti(path)
    np.testing.assert_allclose(back, poses, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(back, poses)  # shortest-repr floats: exact
    assert len(path.read_text().splitlines()) == 50
    assert all(len(line.split()) == 12 for line in path.read_text().splitlines())


def test_tum_round_trip_sign_agnostic_quaternion(tmp_path):
    rng = np.random.default_rng(1)
    poses = random_poses(rng, 40)
    ts = 1317384506.0 + 0.1037 * np.arange(40)
    path = tmp_path / "traj.tum"
    write_tum(path, ts, poses)
    ts_back, back = read_tum(path)
    np.testing.assert_array_equal(ts_back, ts)
    np.testing.assert_allclose(back, poses, rtol=0, atol=1e-9)

    # q and -q are the same rotation: flip the sign of every quaternion
    lines = []
    for line in path.read_text().splitlines():
        v = [float(x) for x in line.split()]
        v[4:] = [-q for q in v[4:]]
        lines.append(" ".join(repr(x) for x in v))
    flipped = tmp_path / "flipped.tum"
    flipped.write_text("\n".join(lines) + "\n")
    _, back2 = read_tum(flipped)
    np.testing.assert_allclose(back2, poses, rtol=0, atol=1e-9)


def test_read_trajectory_detects_format_and_skips_comments(tmp_path):
    rng = np.random.default_rng(2)
    poses = random_poses(rng, 5, scale=10.0)
    kitti = tmp_path / "a.txt"
    kitti.write_text("# a comment\n\n" + format_kitti(poses) + "   \n# end\n")
    traj = read_trajectory(kitti)
    assert traj.fmt == "kitti" and traj.timestamps_s is None and len(traj) == 5
    np.testing.assert_array_equal(traj.world_T_body, poses)
    assert detect_format(kitti) == "kitti"

    tum = tmp_path / "b.txt"
    write_tum(tum, np.arange(5.0), poses)
    traj = read_trajectory(tum)
    assert traj.fmt == "tum" and detect_format(tum) == "tum"
    np.testing.assert_array_equal(traj.timestamps_s, np.arange(5.0))
    np.testing.assert_allclose(traj.world_T_body, poses, atol=1e-12)


def test_files_are_readable_by_evo(tmp_path):
    file_interface = pytest.importorskip("evo.tools.file_interface")
    rng = np.random.default_rng(3)
    poses = random_poses(rng, 10)
    write_kitti(tmp_path / "k.txt", poses)
    evo_path = file_interface.read_kitti_poses_file(str(tmp_path / "k.txt"))
    np.testing.assert_array_equal(np.array(evo_path.poses_se3), poses)
    ts = 100.0 + np.arange(10)
    write_tum(tmp_path / "t.txt", ts, poses)
    evo_traj = file_interface.read_tum_trajectory_file(str(tmp_path / "t.txt"))
    np.testing.assert_array_equal(evo_traj.timestamps, ts)
    np.testing.assert_allclose(np.array(evo_traj.poses_se3), poses, atol=1e-9)


IDENTITY_KITTI = "1 0 0 0 0 1 0 0 0 0 1 0"
IDENTITY_TUM = "0 0 0 0 0 0 0 1"


@pytest.mark.parametrize(
    "reader, content, expected",
    [
        (read_kitti, f"{IDENTITY_KITTI}\n1 0 0 0 0 1 0 0 0 0 1\n", "line 2: 11 values"),
        (read_kitti, f"{IDENTITY_KITTI}\n1 0 0 x 0 1 0 0 0 0 1 0\n", "line 2: non-numeric value 'x'"),
        (read_kitti, f"{IDENTITY_KITTI}\n1 0 0 nan 0 1 0 0 0 0 1 0\n", "line 2: non-finite"),
        (read_kitti, f"{IDENTITY_KITTI}\n1 0 0 inf 0 1 0 0 0 0 1 0\n", "line 2: non-finite"),
        (read_kitti, "", "empty"),
        (read_kitti, "# only a comment\n\n", "empty"),
        (read_kitti, "2 0 0 0 0 1 0 0 0 0 1 0\n", "line 1: the 3x3 block is not a rotation"),
        (read_kitti, "-1 0 0 0 0 1 0 0 0 0 1 0\n", "not a rotation"),  # a reflection
        (read_kitti, f"{IDENTITY_TUM}\n", "line 1: 8 values; a KITTI trajectory has 12"),
        (read_tum, f"{IDENTITY_KITTI}\n", "line 1: 12 values; a TUM trajectory has 8"),
        (read_tum, "0 1 2 3 0 0 0 0\n", "line 1: quaternion"),
        (read_tum, "1 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n", "line 2: timestamp"),
        (read_tum, "0 0 0 0 0 0 0 1\n1 0 0 NaN 0 0 0 1\n", "line 2: non-finite"),
        (read_tum, "0 0 0 0 0 0 0 1\n1 0 -1e308 0 0 0 0 1\n", "line 2: position coordinate 1e+308 m, beyond"),
        (read_kitti, f"{IDENTITY_KITTI}\n1 0 0 0 0 1 0 2e9 0 0 1 0\n", "line 2: position coordinate 2e+09 m"),
        (read_trajectory, "1 2 3\n", "line 1: 3 values; expected 12 (KITTI) or 8 (TUM)"),
        (read_trajectory, "\n", "empty"),
    ],
)
def test_malformed_files_raise_ground_truth_error_naming_the_file(tmp_path, reader, content, expected):
    path = tmp_path / "bad.txt"
    path.write_text(content)
    with pytest.raises(GroundTruthError) as info:
        reader(path)
    message = str(info.value)
    assert str(path) in message
    assert expected in message
    assert "\n" not in message


@pytest.mark.parametrize("reader", [read_kitti, read_tum, read_trajectory])
def test_missing_directory_and_binary_files(tmp_path, reader):
    with pytest.raises(GroundTruthError, match="no such file") as info:
        reader(tmp_path / "missing.txt")
    assert str(tmp_path / "missing.txt") in str(info.value)
    with pytest.raises(GroundTruthError, match="is a directory"):
        reader(tmp_path)
    binary = tmp_path / "bin.txt"
    binary.write_bytes(b"\x93NUMPY\xff\xfe\x00\x01" * 10)
    with pytest.raises(GroundTruthError, match="not a text file"):
        reader(binary)


def test_writers_reject_bad_input(tmp_path):
    poses = random_poses(np.random.default_rng(4), 3)
    with pytest.raises(ValueError):
        write_tum(tmp_path / "t.txt", [0.0, 1.0], poses)
    bad = poses.copy()
    bad[0, 0, 3] = np.nan
    with pytest.raises(ValueError):
        write_kitti(tmp_path / "k.txt", bad)
    assert not (tmp_path / "k.txt").exists()
    assert list(tmp_path.iterdir()) == []  # no temporary debris either
