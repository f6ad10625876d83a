"""Tests of the dataset loader/writer (vislam.tools.dataset_io)."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest

from conftest import shared_file
from vislam.core.lie import make_pose, se3_inverse, so3_exp
from vislam.core.sequence import StereoObservations
from vislam.errors import DatasetError
from vislam.tools import dataset_io
from vislam.tools.dataset_io import load_dataset, load_sequence, save_sequence, summarize_sequence

LATER = {"time_stamps": "t", "rotational_velocity": "angular_velocity"}


# ----------------------------------------------------------------------------- helpers


def valid_arrays(T: int = 12, M: int = 7, seed: int = 0) -> dict[str, np.ndarray]:
    """A small valid dataset in the report convention (contiguous tracks, some unobserved cells)."""
    rng = np.random.default_rng(seed)
    t = 1.3e9 + np.cumsum(rng.uniform(0.09, 0.11, T))
    features = np.full((4, M, T), -1.0)
    for j in range(M):
        start = int(rng.integers(0, T - 1))
        n = int(rng.integers(1, T - start + 1))
        uL = rng.uniform(10, 1200, n)
        v = rng.uniform(5, 370, n)
        d = rng.uniform(0.5, 80, n)
        features[:, j, start : start + n] = [uL, v, uL - d, v + rng.uniform(-1, 1, n)]
    features[:, 0, 0] = [300.0, 100.0, 302.5, 100.2]  # negative disparity: valid input
    cam_T_imu = make_pose(so3_exp(rng.normal(size=3)), rng.normal(size=3))
    return {
        "time_stamps": t[None, :],
        "features": features,
        "linear_velocity": rng.normal(0, 5, (3, T)),
        "rotational_velocity": rng.normal(0, 0.1, (3, T)),
        "K": np.array([[707.0912, 0.0, 601.8873], [0.0, 707.0912, 183.1104], [0.0, 0.0, 1.0]]),
        "b": np.array(0.5371506532679237),
        "cam_T_imu": cam_T_imu,
    }


def later_arrays(arrays: dict) -> dict:
    out = {LATER.get(k, k): v for k, v in arrays.items() if k != "cam_T_imu"}
    out["imu_T_cam"] = se3_inverse(arrays["cam_T_imu"])
    return out


def write(path, arrays: dict) -> str:
    np.savez(path, **arrays)  # object arrays get pickled: exactly what the loader must refuse
    return str(path)


def npy_bytes(header: dict, payload: bytes) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    buf.write(payload)
    return buf.getvalue()


def array_npy(array) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.asanyarray(array), allow_pickle=False)
    return buf.getvalue()


def write_zip(path, members: dict[str, bytes], compression=zipfile.ZIP_STORED) -> str:
    with zipfile.ZipFile(path, "w", compression=compression) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return str(path)


def assert_refused(path, key: str | None = None, *fragments: str) -> str:
    with pytest.raises(DatasetError) as info:
        load_sequence(path)
    message = str(info.value)
    assert str(path) in message
    assert "\n" not in message
    assert "np.float" not in message and "np.int" not in message, message  # numbers as a user writes them
    if key is not None:
        assert f"'{key}'" in message, message
    for fragment in fragments:
        assert fragment in message, message
    return message


def assert_same_sequence(a, b) -> None:
    oa, ob = a.observations, b.observations
    assert oa.n_landmarks == ob.n_landmarks
    np.testing.assert_array_equal(oa.frame_offsets, ob.frame_offsets)
    np.testing.assert_array_equal(oa.landmark_ids, ob.landmark_ids)
    np.testing.assert_array_equal(oa.pixels, ob.pixels)
    np.testing.assert_array_equal(oa.observed_mask, ob.observed_mask)
    np.testing.assert_array_equal(a.timestamps_s, b.timestamps_s)
    np.testing.assert_array_equal(a.linear_velocity_in_imu_mps, b.linear_velocity_in_imu_mps)
    np.testing.assert_array_equal(a.angular_velocity_in_imu_radps, b.angular_velocity_in_imu_radps)
    np.testing.assert_array_equal(a.camera.K, b.camera.K)
    assert a.camera.baseline_m == b.camera.baseline_m
    np.testing.assert_allclose(a.cam_T_imu, b.cam_T_imu, rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------- valid input


def test_loads_report_convention_exactly(tmp_path):
    arrays = valid_arrays()
    seq = load_sequence(write(tmp_path / "0027.npz", arrays))
    assert seq.name == "0027" and seq.source == str(tmp_path / "0027.npz")
    np.testing.assert_array_equal(seq.observations.dense(), arrays["features"])
    np.testing.assert_array_equal(seq.timestamps_s, arrays["time_stamps"][0])
    np.testing.assert_array_equal(seq.linear_velocity_in_imu_mps, arrays["linear_velocity"].T)
    np.testing.assert_array_equal(seq.angular_velocity_in_imu_radps, arrays["rotational_velocity"].T)
    np.testing.assert_array_equal(seq.cam_T_imu, arrays["cam_T_imu"])
    assert seq.camera.baseline_m == float(arrays["b"])
    ref = StereoObservations.from_dense(arrays["features"])
    np.testing.assert_array_equal(seq.observations.landmark_ids, ref.landmark_ids)
    np.testing.assert_array_equal(seq.observations.frame_offsets, ref.frame_offsets)
    assert load_sequence(tmp_path / "0027.npz", name="drive").name == "drive"


@pytest.mark.parametrize("compress", [True, False])
def test_save_load_round_trip(tmp_path, compress):
    original = load_sequence(write(tmp_path / "a.npz", valid_arrays(T=20, M=9, seed=3)))
    save_sequence(original, tmp_path / "b.npz", compress=compress)
    assert_same_sequence(load_sequence(tmp_path / "b.npz"), original)


def test_save_is_deterministic(tmp_path):
    seq = load_sequence(write(tmp_path / "a.npz", valid_arrays(seed=4)))
    save_sequence(seq, tmp_path / "b.npz")
    save_sequence(seq, tmp_path / "c.npz")
    assert (tmp_path / "b.npz").read_bytes() == (tmp_path / "c.npz").read_bytes()


def test_later_convention_equals_report_convention(tmp_path):
    arrays = valid_arrays(seed=5)
    report = load_dataset(write(tmp_path / "r.npz", arrays))
    later = load_dataset(write(tmp_path / "l.npz", later_arrays(arrays)))
    assert report.convention == "report" and later.convention == "later"
    assert later.keys["timestamps"] == "t" and later.keys["transform"] == "imu_T_cam"
    assert_same_sequence(later.sequence, report.sequence)
    np.testing.assert_allclose(later.sequence.cam_T_imu @ later_arrays(arrays)["imu_T_cam"], np.eye(4), atol=1e-12)
    # save_sequence can write the later convention too
    save_sequence(report.sequence, tmp_path / "l2.npz", convention="later")
    with np.load(tmp_path / "l2.npz", allow_pickle=False) as z:
        assert {"t", "angular_velocity", "imu_T_cam"} <= set(z.files)
        assert not {"time_stamps", "rotational_velocity", "cam_T_imu"} & set(z.files)
    assert_same_sequence(load_sequence(tmp_path / "l2.npz"), report.sequence)


def test_mixed_conventions_load_when_unambiguous(tmp_path):
    arrays = valid_arrays(seed=6)
    mixed = dict(arrays)
    mixed["t"] = mixed.pop("time_stamps")
    ds = load_dataset(write(tmp_path / "m.npz", mixed))
    assert ds.convention == "mixed"
    assert_same_sequence(ds.sequence, load_sequence(write(tmp_path / "r.npz", arrays)))


def test_fortran_ordered_features(tmp_path):
    arrays = valid_arrays(T=15, M=8, seed=7)
    fortran = dict(arrays, features=np.asfortranarray(arrays["features"]))
    ds = load_dataset(write(tmp_path / "f.npz", fortran))
    assert ds.features_fortran_order
    assert_same_sequence(ds.sequence, load_sequence(write(tmp_path / "c.npz", arrays)))


@pytest.mark.parametrize("dtype", [np.int16, np.int32, np.int64, np.float32])
@pytest.mark.parametrize("order", ["C", "F"])
def test_integer_and_float32_features(tmp_path, dtype, order):
    arrays = valid_arrays(seed=8)
    feats = np.round(arrays["features"]).astype(dtype)
    feats = np.asfortranarray(feats) if order == "F" else feats
    seq = load_sequence(write(tmp_path / "i.npz", dict(arrays, features=feats)))
    assert seq.observations.pixels.dtype == np.float64
    np.testing.assert_array_equal(seq.observations.dense(), feats.astype(np.float64))


def test_integer_dtypes_for_small_arrays_and_shape_variants(tmp_path):
    arrays = valid_arrays(seed=9)
    arrays["time_stamps"] = np.arange(100, 100 + arrays["features"].shape[2], dtype=np.int64)  # (T,)
    arrays["b"] = np.array([1], dtype=np.int32)  # size-1 array
    arrays["linear_velocity"] = np.round(arrays["linear_velocity"]).astype(np.int16)
    seq = load_sequence(write(tmp_path / "x.npz", arrays))
    np.testing.assert_array_equal(seq.timestamps_s, arrays["time_stamps"].astype(float))
    assert seq.camera.baseline_m == 1.0
    np.testing.assert_array_equal(seq.linear_velocity_in_imu_mps, arrays["linear_velocity"].T)


def test_extra_keys_are_ignored(tmp_path):
    arrays = valid_arrays(seed=10)
    ds = load_dataset(write(tmp_path / "e.npz", dict(arrays, notes=np.array(["hello"]), extra=np.zeros(3))))
    assert ds.extra_keys == ("extra", "notes")
    assert_same_sequence(ds.sequence, load_sequence(write(tmp_path / "r.npz", arrays)))


def test_zero_landmarks_is_a_valid_sequence(tmp_path):
    arrays = valid_arrays(seed=11)
    T = arrays["features"].shape[2]
    seq = load_sequence(write(tmp_path / "z.npz", dict(arrays, features=np.zeros((4, 0, T)))))
    assert seq.n_landmarks == 0 and seq.observations.n_observations == 0 and seq.n_frames == T


@pytest.mark.parametrize("order", ["C", "F"])
@pytest.mark.parametrize("chunk_bytes", [8, 40, 96, 1000])
def test_streaming_is_independent_of_chunk_size(tmp_path, monkeypatch, order, chunk_bytes):
    arrays = valid_arrays(T=23, M=11, seed=12)
    feats = arrays["features"] if order == "C" else np.asfortranarray(arrays["features"])
    path = write(tmp_path / "s.npz", dict(arrays, features=feats))
    monkeypatch.setattr(dataset_io, "CHUNK_BYTES", chunk_bytes)
    seq = load_sequence(path)
    np.testing.assert_array_equal(seq.observations.dense(), arrays["features"])


@pytest.mark.parametrize("order", ["C", "F"])
def test_bad_entry_in_a_late_chunk_is_located(tmp_path, monkeypatch, order):
    arrays = valid_arrays(T=23, M=11, seed=13)
    feats = np.full_like(arrays["features"], -1.0)
    feats[:, 9, 17] = [1.0, 2.0, 3.0, 4.0]
    feats[:, 8, 20] = [1.0, 2.0, 3.0, 4.0]
    feats[3, 9, 17] = np.nan  # vR of landmark 9 at frame 17
    feats = feats if order == "C" else np.asfortranarray(feats)
    path = write(tmp_path / "s.npz", dict(arrays, features=feats))
    monkeypatch.setattr(dataset_io, "CHUNK_BYTES", 64)
    assert_refused(path, "features", "landmark 9 at frame 17", "nan")


# ----------------------------------------------------------------------------- invalid files


def test_missing_file(tmp_path):
    assert_refused(tmp_path / "nope.npz", None, "not found")


def test_directory(tmp_path):
    (tmp_path / "d.npz").mkdir()
    assert_refused(tmp_path / "d.npz", None, "directory")


def test_empty_file(tmp_path):
    (tmp_path / "e.npz").write_bytes(b"")
    assert_refused(tmp_path / "e.npz", None, "empty")


@pytest.mark.parametrize("fraction", [0.1, 0.5, 0.9, 0.999])
def test_truncated_file(tmp_path, fraction):
    data = open(write(tmp_path / "ok.npz", valid_arrays()), "rb").read()
    (tmp_path / "t.npz").write_bytes(data[: int(len(data) * fraction)])
    assert_refused(tmp_path / "t.npz")


def test_truncated_member_names_the_key(tmp_path):
    arrays = valid_arrays()
    members = {f"{k}.npy": array_npy(v) for k, v in arrays.items()}
    members["features.npy"] = members["features.npy"][:-100]
    path = write_zip(tmp_path / "t.npz", members)
    assert_refused(path, "features", "bytes")


def test_text_file(tmp_path):
    (tmp_path / "t.npz").write_text("time_stamps,features\n1,2\n")
    assert_refused(tmp_path / "t.npz", None, "not an .npz")


def test_plain_npy(tmp_path):
    np.save(tmp_path / "a.npy", np.zeros((4, 3, 2)))
    assert_refused(tmp_path / "a.npy", None, ".npy")


def test_zip_without_npy_members(tmp_path):
    path = write_zip(tmp_path / "z.npz", {"readme.txt": b"hello", "data.csv": b"1,2"})
    assert_refused(path, None, "no .npy")


@pytest.mark.parametrize("key", ["features", "K", "time_stamps", "cam_T_imu"])
def test_object_array_is_refused_without_unpickling(tmp_path, key):
    arrays = valid_arrays()
    obj = np.empty(arrays[key].shape, dtype=object)
    obj[...] = 1.0
    assert_refused(write(tmp_path / "o.npz", dict(arrays, **{key: obj})), key, "object")


@pytest.mark.parametrize(
    "key, make",
    [
        ("features", lambda a: a.astype(np.complex128)),
        ("K", lambda a: a.astype(str)),
        ("linear_velocity", lambda a: a > 0),
        ("b", lambda a: np.array([(1.0, 2)], dtype=[("x", "f8"), ("y", "i4")])),
        ("time_stamps", lambda a: a.astype("datetime64[s]")),
    ],
)
def test_non_numeric_dtypes_are_refused(tmp_path, key, make):
    arrays = valid_arrays()
    assert_refused(write(tmp_path / "d.npz", dict(arrays, **{key: make(arrays[key])})), key, "dtype")


@pytest.mark.parametrize(
    "key", ["time_stamps", "features", "linear_velocity", "rotational_velocity", "K", "b", "cam_T_imu"]
)
def test_missing_key(tmp_path, key):
    arrays = valid_arrays()
    del arrays[key]
    assert_refused(write(tmp_path / "m.npz", arrays), key, "missing", "report convention", "later")


def test_missing_key_later_convention(tmp_path):
    arrays = later_arrays(valid_arrays())
    del arrays["imu_T_cam"]
    assert_refused(write(tmp_path / "m.npz", arrays), "cam_T_imu", "'imu_T_cam'", "missing")


@pytest.mark.parametrize(
    "report_key, later_key", [("time_stamps", "t"), ("rotational_velocity", "angular_velocity"), ("cam_T_imu", "imu_T_cam")]
)
def test_both_conventions_for_one_quantity_is_ambiguous(tmp_path, report_key, later_key):
    arrays = valid_arrays()
    later = later_arrays(arrays)
    both = dict(arrays, **{later_key: later[later_key]})
    assert_refused(write(tmp_path / "a.npz", both), report_key, f"'{later_key}'", "ambiguous")


T0, M0 = 12, 7  # shape of valid_arrays()


@pytest.mark.parametrize(
    "key, bad",
    [
        ("time_stamps", np.arange(2 * T0, dtype=float).reshape(2, T0)),
        ("time_stamps", np.arange(T0, dtype=float).reshape(1, 1, T0)),
        ("features", -np.ones((3, M0, T0))),
        ("features", -np.ones((4, M0, T0 - 1))),
        ("features", -np.ones((4, M0 * T0))),
        ("linear_velocity", np.zeros((T0, 3))),
        ("linear_velocity", np.zeros((3, T0 + 1))),
        ("rotational_velocity", np.zeros((4, T0))),
        ("rotational_velocity", np.zeros(3 * T0)),
        ("K", np.eye(4)),
        ("K", np.eye(3)[:2]),
        ("b", np.array([0.5, 0.5])),
        ("cam_T_imu", np.eye(4)[:3]),
        ("cam_T_imu", np.eye(3)),
    ],
)
def test_wrong_shapes(tmp_path, key, bad):
    arrays = valid_arrays()
    assert_refused(write(tmp_path / "s.npz", dict(arrays, **{key: bad})), key, "shape", "expected")


def test_wrong_features_shape_names_T_source(tmp_path):
    arrays = valid_arrays()
    path = write(tmp_path / "s.npz", dict(arrays, features=-np.ones((4, 10, 99))))
    assert_refused(path, "features", "(4, 10, 99)", "T = 12 from 'time_stamps'")


@pytest.mark.parametrize("key", ["linear_velocity", "rotational_velocity", "K", "b", "cam_T_imu"])
@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_non_finite_values(tmp_path, key, value):
    arrays = valid_arrays()
    bad = np.array(arrays[key], dtype=float)
    bad.flat[min(2, bad.size - 1)] = value
    assert_refused(write(tmp_path / "n.npz", dict(arrays, **{key: bad})), key)


@pytest.mark.parametrize("key", ["linear_velocity", "rotational_velocity"])
@pytest.mark.parametrize("value", [1e200, -2e9])
def test_velocities_beyond_any_unit_are_refused(tmp_path, key, value):
    """Finite, but beyond MAX_IMU_SAMPLE: a 1e200 sample overflowed the filters' squares
    (a traceback in SLAM and localization)."""
    arrays = valid_arrays()
    bad = np.array(arrays[key], dtype=float)
    bad[1, 4] = value
    assert_refused(write(tmp_path / "far.npz", dict(arrays, **{key: bad})), key, "row 1, frame 4", "within ±1e+09")
    bad[1, 4] = 1e9  # the bound itself loads
    load_sequence(write(tmp_path / "edge.npz", dict(arrays, **{key: bad})))


@pytest.mark.parametrize("entry, value, needle", [((0, 0), 1e200, "focal lengths 1e+200, 707.091 px"),
                                                  ((1, 2), -3e6, "principal point (601.887, -3e+06) px")])
def test_intrinsics_beyond_any_camera_are_refused(tmp_path, entry, value, needle):
    """Finite, but a focal length or principal point beyond 1e6 px (1e200 overflowed the
    filters: a traceback or numpy warnings in every mode)."""
    arrays = valid_arrays()
    K = arrays["K"].copy()
    K[entry] = value
    assert_refused(write(tmp_path / "k.npz", dict(arrays, K=K)), "K", needle, "1e+06")


@pytest.mark.parametrize("order", ["C", "F"])
def test_pixels_beyond_any_image_are_refused(tmp_path, order):
    arrays = valid_arrays()
    feats = arrays["features"].copy()
    feats[2, 0, 0] = 1e300  # uR of landmark 0 at frame 0 (overflowed the products of pixels)
    path = write(tmp_path / "p.npz", dict(arrays, features=np.asfortranarray(feats) if order == "F" else feats))
    assert_refused(path, "features", "landmark 0 at frame 0", "within ±1e+06")


def test_a_frame_interval_beyond_any_unit_is_refused_and_nanoseconds_load(tmp_path):
    arrays = valid_arrays()
    t = arrays["time_stamps"].copy()
    t[0, 6:] += 5e9  # 160 years: a 1e290 s interval overflowed the prediction's τ·u
    assert_refused(write(tmp_path / "t.npz", dict(arrays, time_stamps=t)), "time_stamps",
                   "frame interval of 5e+09 s at index 6")
    ns = arrays["time_stamps"] * 1e9  # Unix time in ns: 1e8 per frame, loads (vislam check names the unit)
    assert load_sequence(write(tmp_path / "ns.npz", dict(arrays, time_stamps=ns))).n_frames == 12


@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_non_finite_timestamps(tmp_path, value):
    arrays = valid_arrays()
    arrays["time_stamps"] = arrays["time_stamps"].copy()
    arrays["time_stamps"][0, 5] = value
    assert_refused(write(tmp_path / "n.npz", arrays), "time_stamps", "index 5")


def test_float32_unix_timestamps_are_refused_with_the_reason(tmp_path):
    """Unix seconds stored as float32 are 128 s apart: frames collide, and the error says why."""
    arrays = valid_arrays()
    arrays["time_stamps"] = arrays["time_stamps"].astype(np.float32)
    assert_refused(write(tmp_path / "f.npz", arrays), "time_stamps", "not strictly increasing", "float32",
                   "128 apart", "float64")


@pytest.mark.parametrize("delta", [0.0, -0.05])
def test_timestamps_not_strictly_increasing(tmp_path, delta):
    arrays = valid_arrays()
    t = arrays["time_stamps"].copy()
    t[0, 7] = t[0, 6] + delta
    arrays["time_stamps"] = t
    assert_refused(write(tmp_path / "n.npz", arrays), "time_stamps", "index 7", "strictly increasing")


@pytest.mark.parametrize("order", ["C", "F"])
@pytest.mark.parametrize(
    "entry, fragment",
    [
        ([np.nan, 1.0, 2.0, 3.0], "nan"),
        ([-1.0, -1.0, -1.0, np.inf], "inf"),
        ([300.0, -1.0, 290.0, 100.0], "-1"),
        ([-1.0, -1.0, -1.0, 5.0], "-1"),
    ],
)
def test_bad_feature_entries(tmp_path, order, entry, fragment):
    arrays = valid_arrays()
    feats = arrays["features"].copy()
    feats[:, 4, 9] = entry
    feats[:, 2, 11] = [np.nan] * 4  # a later frame (lower landmark): frame 9 is reported first
    feats = feats if order == "C" else np.asfortranarray(feats)
    assert_refused(write(tmp_path / "f.npz", dict(arrays, features=feats)), "features", "landmark 4 at frame 9", fragment)


@pytest.mark.parametrize("b", [0.0, -0.5])
def test_non_positive_baseline(tmp_path, b):
    assert_refused(write(tmp_path / "b.npz", dict(valid_arrays(), b=np.array(b))), "b", "positive")


def test_baseline_overflowing_the_stereo_matrix(tmp_path):
    assert_refused(write(tmp_path / "b.npz", dict(valid_arrays(), b=np.array(1e307))), "b", "overflow")


def test_timestamps_spanning_an_overflow(tmp_path):
    """-1e308 … 1e308: its span overflows; refused by its first frame interval."""
    arrays = valid_arrays()
    t = arrays["time_stamps"].copy()
    t[0, 0], t[0, -1] = -1e308, 1e308
    arrays["time_stamps"] = t
    assert_refused(write(tmp_path / "t.npz", arrays), "time_stamps", "frame interval of 1e+308 s at index 1")


@pytest.mark.parametrize("index", [(0, 0), (1, 1)])
@pytest.mark.parametrize("value", [0.0, -700.0])
def test_non_positive_focal_length(tmp_path, index, value):
    arrays = valid_arrays()
    K = arrays["K"].copy()
    K[index] = value
    assert_refused(write(tmp_path / "k.npz", dict(arrays, K=K)), "K", "positive")


@pytest.mark.parametrize("row", [[0.0, 0.0, 2.0], [0.0, 1e-3, 1.0], [1.0, 0.0, 1.0]])
def test_malformed_K_last_row(tmp_path, row):
    arrays = valid_arrays()
    K = arrays["K"].copy()
    K[2] = row
    assert_refused(write(tmp_path / "k.npz", dict(arrays, K=K)), "K", "[0, 0, 1]")


def test_K_with_skew_is_refused(tmp_path):
    arrays = valid_arrays()
    K = arrays["K"].copy()
    K[0, 1] = 0.5
    assert_refused(write(tmp_path / "k.npz", dict(arrays, K=K)), "K", "skew", "K[0,1] = 0.5,")


def _not_rigid():
    base = make_pose(so3_exp([0.1, 0.2, 0.3]), [1.0, 2.0, 3.0])
    scaled = base.copy()
    scaled[:3, :3] *= 1.01
    reflected = base.copy()
    reflected[:3, 0] *= -1
    bad_row = base.copy()
    bad_row[3] = [0.0, 0.0, 0.1, 1.0]
    sheared = base.copy()
    sheared[0, 1] += 1e-4
    return [scaled, reflected, bad_row, sheared]


@pytest.mark.parametrize("case", range(4))
@pytest.mark.parametrize("convention", ["report", "later"])
def test_non_rigid_transform(tmp_path, case, convention):
    arrays = valid_arrays()
    bad = _not_rigid()[case]
    if convention == "report":
        arrays["cam_T_imu"] = bad
        key = "cam_T_imu"
    else:
        arrays = later_arrays(arrays)
        arrays["imu_T_cam"] = bad
        key = "imu_T_cam"
    assert_refused(write(tmp_path / "r.npz", arrays), key, "rigid")


def test_rigid_transform_within_tolerance_is_accepted(tmp_path):
    arrays = valid_arrays()
    T = arrays["cam_T_imu"].copy()
    T[0, 0] += 1e-9
    load_sequence(write(tmp_path / "r.npz", dict(arrays, cam_T_imu=T)))


@pytest.mark.parametrize("T", [0, 1])
def test_fewer_than_two_frames(tmp_path, T):
    arrays = valid_arrays()
    arrays = {
        "time_stamps": arrays["time_stamps"][:, :T],
        "features": arrays["features"][:, :, :T],
        "linear_velocity": arrays["linear_velocity"][:, :T],
        "rotational_velocity": arrays["rotational_velocity"][:, :T],
        "K": arrays["K"],
        "b": arrays["b"],
        "cam_T_imu": arrays["cam_T_imu"],
    }
    assert_refused(write(tmp_path / "s.npz", arrays), "time_stamps", "at least 2 frames")


def test_header_claiming_gigantic_shape_is_refused_before_allocating(tmp_path):
    import tracemalloc

    arrays = valid_arrays()
    members = {f"{k}.npy": array_npy(v) for k, v in arrays.items()}
    header = {"descr": "<f8", "fortran_order": False, "shape": (4, 10**9, T0)}  # 384 GB declared
    members["features.npy"] = npy_bytes(header, b"\x00" * 800)
    path = write_zip(tmp_path / "g.npz", members)
    tracemalloc.start()
    try:
        assert_refused(path, "features", "bytes")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 20 * 2**20


def test_forged_uncompressed_size_in_zip_directory_is_refused(tmp_path):
    """A directory entry claiming far more uncompressed bytes than deflate can produce."""
    arrays = valid_arrays()
    M = 2**22  # declares 4 * 2**22 * 12 * 8 bytes = 1.5 GiB of features
    header = {"descr": "<f8", "fortran_order": False, "shape": (4, M, T0)}
    head = npy_bytes(header, b"")
    members = {f"{k}.npy": array_npy(v) for k, v in arrays.items() if k != "features"}
    members["features.npy"] = head + b"\x00" * 1000
    path = tmp_path / "f.npz"
    write_zip(path, members, compression=zipfile.ZIP_DEFLATED)
    data = bytearray(path.read_bytes())
    # patch the uncompressed size of features.npy in its central directory record
    name = b"features.npy"
    cd = data.find(b"PK\x01\x02")
    while cd >= 0:
        name_len = int.from_bytes(data[cd + 28 : cd + 30], "little")
        if bytes(data[cd + 46 : cd + 46 + name_len]) == name:
            data[cd + 24 : cd + 28] = (len(head) + 4 * M * T0 * 8).to_bytes(4, "little")
            break
        cd = data.find(b"PK\x01\x02", cd + 4)
    assert cd >= 0
    path.write_bytes(bytes(data))
    assert_refused(path, "features")


# ----------------------------------------------------------------------------- summary


def test_summarize_sequence_counts(tmp_path):
    T, M = 5, 4
    feats = np.full((4, M, T), -1.0)
    feats[:, 0, 0:5] = [[100.0], [50.0], [90.0], [50.5]]  # disparity 10, track 5, |vL-vR| 0.5
    feats[:, 1, 1:3] = [[200.0], [60.0], [201.0], [60.0]]  # disparity -1 (x2), track 2
    feats[:, 3, 2] = [300.0, 70.0, 280.0, 72.0]  # disparity 20, track 1, |vL-vR| 2
    arrays = valid_arrays()
    arrays.update(
        time_stamps=np.array([[10.0, 10.1, 10.2, 10.3, 10.5]]),
        features=feats,
        linear_velocity=np.array([[3.0, 0, 0, 0, 0], [4.0, 1, 0, 0, 0], [0.0, 0, 2, 0, 0]]),
        rotational_velocity=np.zeros((3, T)),
    )
    s = summarize_sequence(load_sequence(write(tmp_path / "s.npz", arrays)))
    assert s["frames"] == 5
    assert s["duration_s"] == pytest.approx(0.5)
    assert s["mean_frame_rate_hz"] == pytest.approx(8.0)
    assert s["landmarks"] == {"total": 4, "observed": 3}
    assert s["observations"]["total"] == 8
    assert s["observations"]["per_frame"] == {"min": 1.0, "mean": 1.6, "max": 3.0}
    assert s["observations"]["frames_without"] == 0
    assert s["track_length_frames"] == {"min": 1.0, "median": 2.0, "max": 5.0}
    assert s["disparity_px"] == {"min": -1.0, "median": 10.0, "max": 20.0, "non_positive": 2}
    assert s["row_mismatch_px"]["max"] == pytest.approx(2.0)
    assert s["speed_mps"] == {"min": 0.0, "mean": pytest.approx(1.6), "max": 5.0}
    assert s["calibration"]["fsu"] == arrays["K"][0, 0]
    assert s["calibration"]["M"][2][3] == pytest.approx(-arrays["K"][0, 0] * float(arrays["b"]))
    np.testing.assert_array_equal(s["cam_T_imu"], arrays["cam_T_imu"])


# ----------------------------------------------------------------------------- shared data

SHARED = {  # frames and landmarks from ../shared/data/README.md
    "sparse/0020.npz": (1104, 260),
    "sparse/0027.npz": (1106, 206),
    "sparse/0042.npz": (500, 104),
    "dense/0022.npz": (800, 3220),
    "dense/0027.npz": (1106, 3950),
    "dense/0034.npz": (1224, 4815),
}


@pytest.mark.shared
@pytest.mark.parametrize("relative", sorted(SHARED))
def test_shared_dataset_streamed_equals_naive(relative):
    path = shared_file(relative)
    ds = load_dataset(path)
    seq = ds.sequence
    assert (seq.n_frames, seq.n_landmarks) == SHARED[relative]
    assert ds.convention == "report"
    with np.load(path, allow_pickle=False) as z:
        ref = StereoObservations.from_dense(z["features"])
        np.testing.assert_array_equal(seq.timestamps_s, z["time_stamps"].ravel())
        np.testing.assert_array_equal(seq.linear_velocity_in_imu_mps, z["linear_velocity"].T)
        np.testing.assert_array_equal(seq.angular_velocity_in_imu_radps, z["rotational_velocity"].T)
        np.testing.assert_array_equal(seq.cam_T_imu, z["cam_T_imu"])
        np.testing.assert_array_equal(seq.camera.K, z["K"])
        assert seq.camera.baseline_m == float(z["b"])
    obs = seq.observations
    assert obs.n_landmarks == ref.n_landmarks
    np.testing.assert_array_equal(obs.frame_offsets, ref.frame_offsets)
    np.testing.assert_array_equal(obs.landmark_ids, ref.landmark_ids)
    np.testing.assert_array_equal(obs.pixels, ref.pixels)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.uint32, np.uint64])
@pytest.mark.parametrize("order", ["C", "F"])
def test_unsigned_features_cannot_mark_missing_and_are_refused(tmp_path, dtype, order):
    # issue 22.4: uint16 turned every -1 into 65535, i.e. ~all cells became "observations"
    arrays = valid_arrays(seed=8)
    feats = np.round(arrays["features"]).astype(dtype)  # -1 wraps to the dtype's maximum
    assert np.count_nonzero(feats != np.round(arrays["features"])) > 0
    feats = np.asfortranarray(feats) if order == "F" else feats
    path = write(tmp_path / "u.npz", dict(arrays, features=feats))
    assert_refused(path, "features", np.dtype(dtype).name, "cannot hold -1", "signed integer or float")
    with pytest.raises(DatasetError, match="cannot hold -1"):
        dataset_io.iter_frames(path)
