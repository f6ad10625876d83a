"""Per-landmark bookkeeping bounded by what is in view (vislam.core.bookkeeping).

The tables are checked against plain Python models under random operation sequences,
and the estimators are checked to need no memory per dataset id: a drive whose
landmark ids are spread over a range of 2⁴⁰ gives the same result as the original.
"""

from __future__ import annotations

import numpy as np
import pytest

from vislam.core import estimators
from vislam.core.bookkeeping import IdTable, MapBuilder, RepeatDetector, TrackTable
from vislam.core.options import FilterOptions
from vislam.core.results import LANDMARK_OK, LANDMARK_REJECTED, RunStats
from vislam.core.sequence import StereoObservations
from vislam.core.simulate import SimulationOptions, simulate_drive

from conftest import HALF_SCENE

NOISY_IMU = dict(velocity_noise_mps=0.5, angular_noise_radps=0.05)


@pytest.mark.parametrize("seed", range(5))
def test_id_table_matches_a_dict_model(seed):
    rng = np.random.default_rng(seed)
    table = IdTable({"a": ((), np.int64, -7), "b": ((2,), np.float64, 0.5)}, capacity=4)
    model: dict[int, tuple[int, np.ndarray]] = {}
    max_live = 0
    for _ in range(300):
        live = np.array(sorted(model), dtype=np.int64)
        if rng.random() < 0.55 or not model:
            candidates = rng.choice(10**12, size=rng.integers(1, 30), replace=False)
            new = np.setdiff1d(candidates, live)
            rng.shuffle(new)
            rows = table.add(new)
            # new rows start at the initial values, then get a value of their own
            assert np.all(table["a"][rows] == -7) and np.all(table["b"][rows] == 0.5)
            vals = rng.integers(0, 1000, new.size)
            table["a"][rows] = vals
            table["b"][rows] = vals[:, None] * np.array([1.0, -1.0])
            model.update({int(i): (int(v), v * np.array([1.0, -1.0])) for i, v in zip(new, vals)})
        else:
            gone = rng.choice(live, size=rng.integers(1, live.size + 1), replace=False)
            table.remove(np.concatenate([gone, [10**13]]))  # ids not live are ignored
            for i in gone:
                del model[int(i)]
        max_live = max(max_live, len(model))
        assert len(table) == len(model)
        np.testing.assert_array_equal(table.ids, sorted(model))
        probe = np.concatenate([np.array(sorted(model), dtype=np.int64), rng.integers(0, 10**12, 20)])
        rows = table.rows(probe)
        for i, row in zip(probe, rows):
            if int(i) in model:
                assert table["a"][row] == model[int(i)][0]
                np.testing.assert_array_equal(table["b"][row], model[int(i)][1])
            else:
                assert row == -1
        live_rows = table.rows(table.ids)
        assert np.unique(live_rows).size == live_rows.size  # one row per live id
    # capacity follows the most ids ever live at once, not the ids ever seen
    assert table.capacity <= max(4, int(np.ceil(IdTable.GROWTH * max_live)) + 30)


def _rejected(tracks: TrackTable, ids) -> np.ndarray:
    rows = tracks.rows(np.asarray(ids))
    return (rows >= 0) & tracks["rejected"][np.maximum(rows, 0)]


def test_track_table_counts_rejects_and_forgets_rejections_out_of_view():
    stats = RunStats(frames=3)
    tracks = TrackTable()
    ids = np.array([3, 9, 40])
    tracks.started(ids, 0)
    for t, ok in ((1, [True, False, False]), (2, [True, False, True])):
        bad = tracks.updated(ids, np.array(ok), t, stats, max_consecutive=2)
    np.testing.assert_array_equal(bad, [9])
    nobs, ngated, first, last = tracks.entry(ids)
    np.testing.assert_array_equal(nobs, [3, 1, 2])
    np.testing.assert_array_equal(ngated, [0, 2, 1])
    np.testing.assert_array_equal(first, [0, 0, 0])
    np.testing.assert_array_equal(last, [2, 0, 2])
    np.testing.assert_array_equal(_rejected(tracks, [3, 9, 40, 41]), [False, True, False, False])
    assert (stats.observations_used, stats.observations_gated, stats.landmarks_rejected) == (3, 3, 1)
    tracks.end_unseen_rejections(np.array([3, 9]))  # 9 still in view: stays rejected
    assert _rejected(tracks, [9])[0]
    tracks.end_unseen_rejections(np.array([3]))  # out of view: forgotten; 40 is not rejected
    np.testing.assert_array_equal(tracks.ids, [3, 40])


def test_repeat_detector_equals_whole_sequence_test():
    rng = np.random.default_rng(0)
    M, T = 60, 40
    dense = np.full((4, M, T), -1.0)
    seen = rng.random((M, T)) < 0.6
    dense[:, seen] = rng.uniform(10, 500, (4, int(seen.sum())))
    for t in range(1, T):  # repeat some of the previous frame's pixels bit for bit
        both = seen[:, t] & seen[:, t - 1] & (rng.random(M) < 0.3)
        dense[:, both, t] = dense[:, both, t - 1]
    obs = StereoObservations.from_dense(dense)
    expected = obs.repeated_mask()
    assert 0 < expected.sum() < expected.size
    stats = RunStats(frames=T)
    detect = RepeatDetector(True, stats)
    got = np.concatenate([detect(t, *obs.frame(t)) for t in range(T)])
    np.testing.assert_array_equal(got, expected)
    assert stats.observations_repeated == expected.sum()
    off = RepeatDetector(False, RunStats(frames=T))
    assert not any(off(t, *obs.frame(t)).any() for t in range(T))


def test_map_builder_numbers_tracks_by_first_frame_across_chunks(monkeypatch):
    monkeypatch.setattr(MapBuilder, "CHUNK", 3)
    b = MapBuilder()
    # (id, first frame) added out of order; id 5 has three tracks, id 2 has two
    entries = [(5, 30), (2, 7), (5, 4), (9, 0), (2, 1), (5, 12), (1, 3)]
    for i, first in entries:
        b.add(np.array([i]), np.full((1, 3), i + first / 100), np.eye(3)[None] * first, np.array([first + 1]),
              np.array([0]), np.array([first]), np.array([first + 2]), LANDMARK_REJECTED if i == 9 else LANDMARK_OK)
    m = b.build()
    np.testing.assert_array_equal(m.ids, [1, 2, 2, 5, 5, 5, 9])
    np.testing.assert_array_equal(m.first_frame, [3, 1, 7, 4, 12, 30, 0])
    np.testing.assert_array_equal(m.track, [0, 0, 1, 0, 1, 2, 0])
    np.testing.assert_allclose(m.p_lm_in_world[:, 0], m.ids + m.first_frame / 100)
    np.testing.assert_array_equal(m.covariance[:, 0, 0], m.first_frame)
    np.testing.assert_array_equal(m.n_observations, m.first_frame + 1)
    np.testing.assert_array_equal(m.last_frame, m.first_frame + 2)
    np.testing.assert_array_equal(m.status, [LANDMARK_OK] * 6 + [LANDMARK_REJECTED])
    assert MapBuilder().build().ids.size == 0


@pytest.fixture(scope="module")
def drive():
    return simulate_drive(SimulationOptions(seed=1, n_frames=120, moving_fraction=0.1, outlier_fraction=0.02,
                                            **NOISY_IMU, **HALF_SCENE))


@pytest.mark.parametrize("mode,extra", [
    ("mapping", {}),
    ("slam", {}),
    ("slam", {"init_frames": 3, "probation_frames": 2, "drift_test_probability": 0.9}),
    ("slam", {"repeated_observations": "split"}),
])
def test_estimators_need_no_memory_per_dataset_id(drive, mode, extra):
    """The same drive with its ids spread over [0, 2⁴⁰): an array per dataset id would
    need terabytes. The result must be the original's, ids mapped."""
    seq = drive.sequence
    obs = seq.observations
    spread = np.int64(2**40 // obs.n_landmarks)  # strictly increasing map keeps the per-frame order
    huge = StereoObservations(obs.frame_offsets, obs.landmark_ids * spread + 11, obs.pixels, 2**40)
    opts = FilterOptions(**NOISY_IMU, **extra)
    a = estimators.run(seq, mode, opts)
    b = estimators.run(seq.replace(observations=huge), mode, opts)
    np.testing.assert_array_equal(a.world_T_imu, b.world_T_imu)
    la, lb = a.landmarks, b.landmarks
    np.testing.assert_array_equal(la.ids * spread + 11, lb.ids)
    for key in ("track", "p_lm_in_world", "covariance", "n_observations", "n_gated", "first_frame", "last_frame",
                "status"):
        np.testing.assert_array_equal(getattr(la, key), getattr(lb, key), err_msg=key)
    assert a.stats.to_dict()["landmarks_rejected"] == b.stats.to_dict()["landmarks_rejected"]
    assert la.ids.size > 100 and np.any(la.status == LANDMARK_REJECTED)


@pytest.mark.parametrize("mode", ["mapping", "slam"])
def test_a_landmark_seen_again_after_a_gap_starts_a_new_track(drive, mode):
    """Mapping and SLAM end a track when its landmark is not observed in a frame."""
    dense = drive.sequence.observations.dense()
    observed = dense[0] != -1
    # a static landmark observed for 20+ frames; hide it in one frame in the middle
    lengths = observed.sum(axis=1)
    j = int(np.flatnonzero((lengths >= 20) & np.all(observed[:, 40:61], axis=1))[0])
    dense[:, j, 50] = -1.0
    seq = drive.sequence.replace(observations=StereoObservations.from_dense(dense))
    lm = estimators.run(seq, mode, FilterOptions(**NOISY_IMU)).landmarks
    mine = lm.ids == j
    assert mine.sum() == 2
    np.testing.assert_array_equal(lm.track[mine], [0, 1])
    first, last = lm.first_frame[mine], lm.last_frame[mine]
    assert last[0] <= 49 and first[1] >= 51
