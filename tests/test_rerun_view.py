"""The Rerun recording of a run (vislam.tools.rerun_view, ``vislam run --rerun``): record a
simulated run, load the .rrd back with the SDK's reader and compare what is in it with
the run."""

from __future__ import annotations

import logging
import sys
from collections import defaultdict

import numpy as np
import pytest

rr = pytest.importorskip("rerun")

from rerun.chunk import RrdReader  # noqa: E402

from vislam.cli import main  # noqa: E402
from vislam.core.estimators import run  # noqa: E402
from vislam.core.options import FilterOptions  # noqa: E402
from vislam.core.simulate import SimulationOptions, simulate_drive  # noqa: E402
from vislam.errors import ConfigError, OutputError  # noqa: E402
from vislam.tools import rerun_view  # noqa: E402
from vislam.tools.dataset_io import save_sequence  # noqa: E402
from vislam.tools.rerun_view import SIGMA_SCALE, RerunRecorder  # noqa: E402

N_FRAMES = 150


@pytest.fixture(autouse=True)
def _strict_rerun():
    """Make the SDK raise on a bad log call instead of warning (a test must see it)."""
    previous = rr.strict_mode()
    rr.set_strict_mode(True)
    yield
    rr.set_strict_mode(previous)


@pytest.fixture(scope="module")
def drive():
    return simulate_drive(SimulationOptions(seed=0, n_frames=N_FRAMES, outlier_fraction=0.02))  # outliers: some landmarks get rejected (red)


@pytest.fixture(scope="module")
def slam(drive):
    return run(drive.sequence, "slam", FilterOptions())


@pytest.fixture(scope="module")
def slam_recording(tmp_path_factory, drive, slam):
    path = tmp_path_factory.mktemp("rrd") / "slam.rrd"
    with RerunRecorder(drive.sequence.camera, drive.sequence.cam_T_imu, path=path, recording_name="sim") as rec:
        rec.log_result(slam, drive.sequence)
    return load(path)


class Recording:
    """The rows of an .rrd, by entity: static components and time-indexed rows."""

    def __init__(self):
        self.static: dict[str, dict[str, list]] = defaultdict(dict)
        self.rows: dict[str, list[dict]] = defaultdict(list)

    def series(self, entity: str, component: str) -> tuple[np.ndarray, list]:
        """(frames, values) of the rows of ``entity`` that hold ``component``, by frame."""
        rows = sorted((r for r in self.rows[entity] if r.get(component) is not None), key=lambda r: r["frame"])
        return np.array([r["frame"] for r in rows]), [r[component] for r in rows]

    def latest(self, entity: str, component: str):
        frames, values = self.series(entity, component)
        return values[-1] if values else None


def load(path) -> Recording:
    out = Recording()
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch().to_pydict()
        entity = chunk.entity_path
        if chunk.is_static:
            for name, values in batch.items():
                if name != "rerun.controls.RowId":
                    out.static[entity][name] = values[-1]
            continue
        for i in range(chunk.num_rows):
            out.rows[entity].append({name: values[i] for name, values in batch.items()})
    return out


def test_imu_poses_and_timelines_round_trip(slam_recording, slam):
    frames, translations = slam_recording.series("/world/imu", "Transform3D:translation")
    n = slam.world_T_imu.shape[0]
    assert n == N_FRAMES
    np.testing.assert_array_equal(frames, np.arange(n))  # one pose per frame on the frame timeline
    # float32 storage: 1e-6 relative
    np.testing.assert_allclose(np.array([t[0] for t in translations]), slam.world_T_imu[:, :3, 3], rtol=1e-6,
                               atol=1e-6)
    _, mats = slam_recording.series("/world/imu", "Transform3D:mat3x3")
    R = np.array([np.reshape(m[0], (3, 3)).T for m in mats])  # Rerun stores 3x3 column-major
    np.testing.assert_allclose(R, slam.world_T_imu[:, :3, :3], atol=1e-6)
    times = np.array([r["time"] for r in sorted(slam_recording.rows["/world/imu"], key=lambda r: r["frame"])])
    seconds = np.array([t.value for t in times], dtype=np.float64) * 1e-9  # timestamp[ns]
    np.testing.assert_allclose(seconds, slam.timestamps_s, atol=1e-6, rtol=0)
    _, heights = slam_recording.series("/height/imu_z_m", "Scalars:scalars")
    np.testing.assert_allclose(np.ravel(heights), slam.world_T_imu[:, 2, 3], atol=1e-9)


def test_camera_frustum_and_view_coordinates(slam_recording, drive):
    seq = drive.sequence
    static = slam_recording.static
    assert "ViewCoordinates:xyz" in static["/world"]  # z up
    cam = static["/world/imu/camera"]
    imu_T_cam = np.linalg.inv(seq.cam_T_imu)
    np.testing.assert_allclose(cam["Transform3D:translation"][0], imu_T_cam[:3, 3], atol=1e-6)
    np.testing.assert_allclose(np.reshape(cam["Transform3D:mat3x3"][0], (3, 3)).T, imu_T_cam[:3, :3], atol=1e-6)
    np.testing.assert_allclose(np.reshape(cam["Pinhole:image_from_camera"][0], (3, 3)).T, seq.camera.K, rtol=1e-6)


def test_covariance_ellipsoid_is_the_world_position_covariance(slam_recording, slam):
    frames, half = slam_recording.series("/world/position_covariance", "Ellipsoids3D:half_sizes")
    _, quats = slam_recording.series("/world/position_covariance", "Ellipsoids3D:quaternions")
    _, centers = slam_recording.series("/world/position_covariance", "Ellipsoids3D:centers")
    np.testing.assert_array_equal(frames, np.arange(N_FRAMES))
    expected = slam.position_covariance_in_world()
    from scipy.spatial.transform import Rotation

    for t in range(0, N_FRAMES, 7):
        axes = Rotation.from_quat(np.asarray(quats[t][0], dtype=np.float64)).as_matrix()
        sigma = np.asarray(half[t][0], dtype=np.float64) / SIGMA_SCALE
        cov = axes @ np.diag(sigma**2) @ axes.T
        scale = np.max(np.abs(expected[t]))
        np.testing.assert_allclose(cov, expected[t], atol=1e-5 * scale)
        np.testing.assert_allclose(centers[t][0], slam.world_T_imu[t, :3, 3], rtol=1e-6, atol=1e-6)


def test_live_landmarks_and_frozen_map(slam_recording, slam):
    lm = slam.landmarks
    assert len(lm) > 0 and lm.rejected.any() and (~lm.rejected).any()  # the drive exercises both colours
    frames, ids = slam_recording.series("/world/landmarks/live", "landmark_id")
    _, positions = slam_recording.series("/world/landmarks/live", "Points3D:positions")
    np.testing.assert_array_equal(frames, np.arange(N_FRAMES))
    for t in range(N_FRAMES):
        live = (lm.first_frame <= t) & (t <= lm.last_frame)
        assert sorted(ids[t] or []) == sorted(lm.ids[live].tolist())
        got = np.asarray(positions[t] or np.zeros((0, 3)), dtype=np.float64).reshape(-1, 3)
        np.testing.assert_allclose(got[np.argsort(ids[t] or [], kind="stable")] if len(got) else got,
                                   lm.p_lm_in_world[live][np.argsort(lm.ids[live], kind="stable")], rtol=1e-6,
                                   atol=1e-5)
    # At the last frame the frozen blocks (latest rows) plus the live points are the whole map.
    blocks = [e for e in slam_recording.rows if e.startswith("/world/landmarks/map/")]
    assert blocks
    map_ids, map_points, map_colors = [], [], []
    for entity in blocks:
        map_ids += slam_recording.latest(entity, "landmark_id")
        map_points += slam_recording.latest(entity, "Points3D:positions")
        map_colors += slam_recording.latest(entity, "Points3D:colors")
    live_last = lm.last_frame == N_FRAMES - 1
    frozen = ~live_last
    assert sorted(map_ids) == sorted(lm.ids[frozen].tolist())
    order = np.argsort(map_ids, kind="stable")
    want = np.argsort(lm.ids[frozen], kind="stable")
    np.testing.assert_allclose(np.asarray(map_points, dtype=np.float64)[order], lm.p_lm_in_world[frozen][want],
                               rtol=1e-6, atol=1e-5)
    red = (np.asarray(map_colors, dtype=np.uint32) >> 24) > 200  # RGBA packed, red channel in the top byte
    np.testing.assert_array_equal(red[order], lm.rejected[frozen][want])
    # a frozen point appears at the frame after its last observation, not before
    first_logged = {}
    for entity in blocks:
        for frame, frame_ids in zip(*slam_recording.series(entity, "landmark_id")):
            for i in frame_ids:
                first_logged.setdefault(i, frame)
    for i, last in zip(lm.ids[frozen], lm.last_frame[frozen]):
        assert first_logged[i] == last + 1


def test_stats_series(slam_recording, slam):
    frames, ms = slam_recording.series("/stats/frame_ms", "Scalars:scalars")
    np.testing.assert_array_equal(frames, np.arange(N_FRAMES))
    np.testing.assert_allclose(np.ravel(ms), slam.stats.frame_seconds * 1e3)
    _, live = slam_recording.series("/stats/live_landmarks", "Scalars:scalars")
    lm = slam.landmarks
    t = np.arange(N_FRAMES)[:, None]
    np.testing.assert_array_equal(np.ravel(live), ((lm.first_frame <= t) & (t <= lm.last_frame)).sum(axis=1))


def test_frame_stats_attribute_is_recorded(tmp_path, drive, slam):
    class WithStats:  # the per-frame stats the stepwise filter will attach
        def __getattr__(self, name):
            return getattr(slam, name)

    result = WithStats()
    result.frame_stats = {"innovations": np.arange(N_FRAMES) * 2.0}
    path = tmp_path / "s.rrd"
    with RerunRecorder(drive.sequence.camera, drive.sequence.cam_T_imu, path=path) as rec:
        rec.log_result(result)
    frames, values = load(path).series("/stats/innovations", "Scalars:scalars")
    np.testing.assert_array_equal(frames, np.arange(N_FRAMES))
    np.testing.assert_allclose(np.ravel(values), np.arange(N_FRAMES) * 2.0)


def test_blocks_keep_the_whole_trajectory_and_map(tmp_path, drive, monkeypatch):
    """log_frame directly, with small blocks: the latest rows of the blocks hold every
    trajectory point in order (consecutive blocks share an end point) and every frozen point."""
    monkeypatch.setattr(rerun_view, "BLOCK_POINTS", 7)
    rng = np.random.default_rng(1)
    n = 30
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    frozen = [rng.normal(size=(int(k), 3)) for k in rng.integers(0, 4, n)]
    path = tmp_path / "b.rrd"
    with RerunRecorder(drive.sequence.camera, drive.sequence.cam_T_imu, path=path) as rec:
        next_id = 0
        for t in range(n):
            k = len(frozen[t])
            rec.log_frame(t, 0.1 * t, poses[t], None, [], np.zeros((0, 3)), np.arange(next_id, next_id + k), frozen[t],
                          np.arange(k) % 2 == 0)
            next_id += k
    rec_ = load(path)
    strips = sorted((e for e in rec_.rows if e.startswith("/world/trajectory/")),
                    key=lambda e: int(e.rsplit("/", 1)[1]))
    assert len(strips) > 1
    points = []
    for i, entity in enumerate(strips):
        strip = np.asarray(rec_.latest(entity, "LineStrips3D:strips")[0], dtype=np.float64)
        assert len(strip) <= 7
        if i:
            np.testing.assert_allclose(strip[0], points[-1], rtol=1e-6)  # connected
            strip = strip[1:]
        points += list(strip)
    np.testing.assert_allclose(np.array(points), poses[:, :3, 3], rtol=1e-6, atol=1e-6)
    ids, pts = [], []
    for entity in (e for e in rec_.rows if e.startswith("/world/landmarks/map/")):
        ids += rec_.latest(entity, "landmark_id")
        pts += rec_.latest(entity, "Points3D:positions")
    order = np.argsort(ids)
    np.testing.assert_array_equal(np.array(ids)[order], np.arange(next_id))
    np.testing.assert_allclose(np.array(pts, dtype=np.float64)[order], np.concatenate(frozen), rtol=1e-6, atol=1e-6)
    assert "/world/position_covariance" not in rec_.rows  # no covariance given


@pytest.mark.parametrize("mode", ["localization", "mapping"])
def test_other_modes(tmp_path, mode):
    drive = simulate_drive(SimulationOptions(seed=2, n_frames=40))
    result = run(drive.sequence, mode, FilterOptions())
    path = tmp_path / f"{mode}.rrd"
    with RerunRecorder(drive.sequence.camera, drive.sequence.cam_T_imu, path=path) as rec:
        rec.log_result(result, drive.sequence)
    recording = load(path)
    frames, translations = recording.series("/world/imu", "Transform3D:translation")
    np.testing.assert_array_equal(frames, np.arange(40))
    np.testing.assert_allclose(np.array([t[0] for t in translations]), result.world_T_imu[:, :3, 3], rtol=1e-6,
                               atol=1e-6)
    live_ids = [i for _, ids in zip(*recording.series("/world/landmarks/live", "landmark_id")) for i in ids or []]
    if mode == "localization":
        assert live_ids == []
    else:
        assert set(live_ids) == set(result.landmarks.ids.tolist())


def test_abort_leaves_no_file(tmp_path, drive):
    path = tmp_path / "a.rrd"
    path.write_bytes(b"old")
    with pytest.raises(RuntimeError, match="boom"):
        with RerunRecorder(drive.sequence.camera, drive.sequence.cam_T_imu, path=path) as rec:
            rec.log_frame(0, 0.0, np.eye(4), None, [], np.zeros((0, 3)))
            raise RuntimeError("boom")
    assert path.read_bytes() == b"old"  # the previous file, untouched
    assert [p.name for p in tmp_path.iterdir()] == ["a.rrd"]  # no temporary debris


def test_missing_rerun_sdk_is_a_config_error(monkeypatch, drive):
    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun -> ImportError
    with pytest.raises(ConfigError, match=r"pip install 'vislam\[viewer\]'"):
        RerunRecorder(drive.sequence.camera, drive.sequence.cam_T_imu, path="x.rrd")


def test_spawn_without_a_viewer_warns_and_records(tmp_path, drive, monkeypatch, caplog):
    monkeypatch.setattr(rerun_view, "_has_display", lambda: False)
    path = tmp_path / "s.rrd"
    with caplog.at_level(logging.WARNING, logger="vislam.tools.rerun_view"):
        with RerunRecorder(drive.sequence.camera, drive.sequence.cam_T_imu, path=path, spawn=True) as rec:
            rec.log_frame(0, 0.0, np.eye(4), np.eye(6), [], np.zeros((0, 3)))
    assert not rec.spawned
    assert "not opening a live viewer" in caplog.text
    assert load(path).series("/world/imu", "Transform3D:translation")[0].tolist() == [0]


def test_spawn_only_without_a_viewer_records_nothing(drive, monkeypatch, caplog):
    monkeypatch.setattr(rerun_view, "_viewer_executable", lambda: None)
    monkeypatch.setattr(rerun_view, "_has_display", lambda: True)
    with caplog.at_level(logging.WARNING, logger="vislam.tools.rerun_view"):
        with RerunRecorder(drive.sequence.camera, drive.sequence.cam_T_imu, spawn=True) as rec:
            rec.log_frame(0, 0.0, np.eye(4), None, [], np.zeros((0, 3)))
    assert not rec.spawned and not rec.enabled and rec.frames_logged == 1
    assert "no 'rerun' viewer executable" in caplog.text


def test_unwritable_path_is_an_output_error(tmp_path, drive):
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(OutputError, match="cannot create directory"):
        RerunRecorder(drive.sequence.camera, drive.sequence.cam_T_imu, path=blocker / "x.rrd")
    with pytest.raises(OutputError, match="is a directory"):
        RerunRecorder(drive.sequence.camera, drive.sequence.cam_T_imu, path=tmp_path)


# ----------------------------------------------------------------------------- CLI


@pytest.fixture(scope="module")
def sim_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "sim.npz"
    save_sequence(simulate_drive(SimulationOptions(seed=3, n_frames=60)).sequence, path)
    return path


def test_cli_run_writes_a_loadable_recording(tmp_path, sim_file, capsys):
    rrd = tmp_path / "rec" / "x.rrd"  # a missing directory is created, like --out
    code = main(["run", str(sim_file), "--mode", "slam", "--out", str(tmp_path / "out"), "--rerun", str(rrd)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert f"rerun:         {rrd}" in captured.out
    recording = load(rrd)
    frames, translations = recording.series("/world/imu", "Transform3D:translation")
    np.testing.assert_array_equal(frames, np.arange(60))
    from vislam.tools.trajectory_io import read_tum

    _, poses = read_tum(tmp_path / "out" / "trajectory.tum")  # the same run as the other outputs
    np.testing.assert_allclose(np.array([t[0] for t in translations]), poses[:, :3, 3], rtol=1e-6, atol=1e-5)
    assert any(e.startswith("/world/landmarks/") for e in recording.rows)
    assert sorted(p.name for p in rrd.parent.iterdir()) == ["x.rrd"]


def test_cli_unwritable_rerun_path_fails_before_any_output(tmp_path, sim_file, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    out = tmp_path / "out"
    code = main(["run", str(sim_file), "--out", str(out), "--rerun", str(blocker / "x.rrd"), "--quiet"])
    captured = capsys.readouterr()
    assert code != 0
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("vislam run: error:") and str(blocker) in lines[0]
    assert not out.exists()  # the output directory the run would have created is not left behind


@pytest.mark.parametrize("where", ["estimator", "outputs"])
def test_cli_interrupted_or_failed_run_leaves_no_recording(tmp_path, sim_file, monkeypatch, capsys, where):
    """Ctrl-C during the run, or a failure writing the other outputs: no .rrd, no temporary file."""
    from vislam.core import estimators
    from vislam.tools import outputs

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    def failing(*args, **kwargs):
        raise OutputError("disk full (simulated)")

    if where == "estimator":
        monkeypatch.setattr(estimators, "run_slam", interrupted)
    else:
        monkeypatch.setattr(outputs, "write_run_outputs", failing)
    rrd_dir = tmp_path / "rrd"
    rrd_dir.mkdir()
    code = main(["run", str(sim_file), "--out", str(tmp_path / "out"), "--rerun", str(rrd_dir / "x.rrd"), "--quiet"])
    capsys.readouterr()
    assert code == (130 if where == "estimator" else OutputError.exit_code)
    assert list(rrd_dir.iterdir()) == []
