"""Property tests: corrupted dataset files end in a valid Sequence or a DatasetError.

Never another exception, a hang, or a memory blow-up. Each property runs a modest
number of examples on tiny files so the module stays fast.
"""

from __future__ import annotations

import io
import json
import tracemalloc
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from vislam.tools.jsonio import json_safe as _json_safe
from vislam.core.lie import make_pose, so3_exp
from vislam.core.sequence import Sequence
from vislam.errors import DatasetError
from vislam.tools.dataset_io import CONVENTIONS, load_sequence, summarize_sequence

KEYS = ["time_stamps", "features", "linear_velocity", "rotational_velocity", "K", "b", "cam_T_imu"]
ALL_CONVENTION_KEYS = {k for c in CONVENTIONS.values() for k in c.values()}
T, M = 6, 4

FUZZ = settings(
    max_examples=40,
    deadline=2000,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
    derandomize=True,
)

# tracemalloc peak allowed while loading a fuzzed tiny file (the valid file's arrays are < 1 kB)
MEMORY_LIMIT = 16 * 2**20


def valid_arrays() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(1)
    features = np.full((4, M, T), -1.0)
    for j in range(M):
        n = T - j
        uL = rng.uniform(10, 1200, n)
        v = rng.uniform(5, 370, n)
        features[:, j, j:] = [uL, v, uL - rng.uniform(1, 50, n), v]
    return {
        "time_stamps": (1000.0 + 0.1 * np.arange(T))[None, :],
        "features": features,
        "linear_velocity": rng.normal(0, 5, (3, T)),
        "rotational_velocity": rng.normal(0, 0.1, (3, T)),
        "K": np.array([[707.0, 0.0, 601.0], [0.0, 707.0, 183.0], [0.0, 0.0, 1.0]]),
        "b": np.array(0.54),
        "cam_T_imu": make_pose(so3_exp([0.3, -0.2, 0.1]), [1.1, -0.3, 0.7]),
    }


def npz_bytes(arrays: dict, compressed: bool = True) -> bytes:
    buf = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(buf, **arrays)
    return buf.getvalue()


VALID = {True: npz_bytes(valid_arrays(), True), False: npz_bytes(valid_arrays(), False)}


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


def load_outcome(path):
    """Load ``path``; return the Sequence or the DatasetError. Anything else fails the test."""
    tracemalloc.start()
    try:
        try:
            result = load_sequence(path)
            assert isinstance(result, Sequence)
            # whatever loads must also summarize, as strict JSON (what `vislam info --json` prints)
            json.dumps(_json_safe(summarize_sequence(result)), allow_nan=False)
        except DatasetError as exc:
            message = str(exc)
            assert str(path) in message and "\n" not in message
            result = exc
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < MEMORY_LIMIT, f"loading used {peak / 2**20:.1f} MiB"
    return result


def write_bytes(workdir, data: bytes):
    path = workdir / "fuzz.npz"
    path.write_bytes(data)
    return path


def write_arrays(workdir, arrays: dict, compressed: bool = False):
    return write_bytes(workdir, npz_bytes(arrays, compressed))


@FUZZ
@given(compressed=st.booleans(), data=st.data())
def test_truncated_at_any_byte(workdir, compressed, data):
    valid = VALID[compressed]
    cut = data.draw(st.integers(0, len(valid) - 1))
    assert isinstance(load_outcome(write_bytes(workdir, valid[:cut])), DatasetError)


@FUZZ
@given(
    compressed=st.booleans(),
    flips=st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(1, 255)), min_size=1, max_size=8),
)
def test_flipped_bytes(workdir, compressed, flips):
    data = bytearray(VALID[compressed])
    for where, mask in flips:
        data[int(where * len(data))] ^= mask
    load_outcome(write_bytes(workdir, bytes(data)))


@FUZZ
@given(
    key=st.sampled_from(KEYS),
    flips=st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(1, 255)), min_size=1, max_size=4),
)
def test_flipped_bytes_inside_npy_member_with_valid_crc(workdir, key, flips):
    """Corrupt one .npy member and re-zip it (CRC correct), so our parser sees the damage."""
    arrays = valid_arrays()
    members = {}
    for k, v in arrays.items():
        buf = io.BytesIO()
        np.lib.format.write_array(buf, v, allow_pickle=False)
        members[k] = bytearray(buf.getvalue())
    target = members[key]
    for where, mask in flips:
        target[int(where * len(target))] ^= mask
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for k, v in members.items():
            zf.writestr(f"{k}.npy", bytes(v))
    load_outcome(write_bytes(workdir, buf.getvalue()))


def _wrong_dtype(kind: str, like: np.ndarray) -> np.ndarray:
    if kind == "object":
        out = np.empty(like.shape, dtype=object)
        out[...] = 1.0
        return out
    if kind == "str":
        return like.astype(str)
    if kind == "complex":
        return like.astype(np.complex128)
    if kind == "bool":
        return like > 0
    if kind == "structured":
        return np.zeros(like.shape, dtype=[("a", "f8"), ("b", "i4")])
    if kind == "bytes":
        return like.astype("S8")
    raise AssertionError(kind)


@FUZZ
@given(key=st.sampled_from(KEYS), kind=st.sampled_from(["object", "str", "complex", "bool", "structured", "bytes"]))
def test_wrong_dtype_per_key(workdir, key, kind):
    arrays = valid_arrays()
    arrays[key] = _wrong_dtype(kind, arrays[key])
    outcome = load_outcome(write_arrays(workdir, arrays))
    assert isinstance(outcome, DatasetError)
    assert f"'{key}'" in str(outcome)


@FUZZ
@given(
    key=st.sampled_from(KEYS),
    value=st.sampled_from([np.nan, np.inf, -np.inf, 1e308, -1e308, 1e30, 0.0, -1.0, 5e-324]),
    where=st.floats(0, 1, exclude_max=True),
)
def test_special_values_in_any_key(workdir, key, value, where):
    arrays = valid_arrays()
    target = np.array(arrays[key], dtype=np.float64)
    target.flat[int(where * target.size)] = value
    arrays[key] = target
    outcome = load_outcome(write_arrays(workdir, arrays))
    if not np.isfinite(value):  # every key requires finite values
        assert isinstance(outcome, DatasetError)
        assert f"'{key}'" in str(outcome)


@pytest.mark.parametrize("translation", [1e300, -1e4])
def test_a_lever_arm_beyond_a_vehicle_is_refused(workdir, translation):
    """cam_T_imu with a translation of 1e300 m (finite, rigid) overflowed every projection
    to a non-finite state with numpy warnings; any beyond ±1 km is refused, naming the key."""
    arrays = valid_arrays()
    arrays["cam_T_imu"] = arrays["cam_T_imu"].copy()
    arrays["cam_T_imu"][1, 3] = translation
    outcome = load_outcome(write_arrays(workdir, arrays))
    assert isinstance(outcome, DatasetError)
    assert "'cam_T_imu'" in str(outcome) and "lever arm within ±1000 m" in str(outcome)


@FUZZ
@given(key=st.sampled_from(KEYS), axis=st.integers(0, 2))
def test_empty_arrays(workdir, key, axis):
    arrays = valid_arrays()
    shape = list(arrays[key].shape) or [1]
    shape[min(axis, len(shape) - 1)] = 0
    arrays[key] = np.zeros(shape)
    outcome = load_outcome(write_arrays(workdir, arrays))
    if key != "features" or shape[1] != 0:  # only a features array without landmarks is valid
        assert isinstance(outcome, DatasetError)


@FUZZ
@given(key=st.sampled_from(KEYS), value=st.floats(allow_nan=True, allow_infinity=True))
def test_zero_dimensional_arrays(workdir, key, value):
    arrays = valid_arrays()
    arrays[key] = np.array(value)
    outcome = load_outcome(write_arrays(workdir, arrays))
    if key != "b" or not value > 0:  # only b is a scalar
        assert isinstance(outcome, DatasetError)


_extra_names = st.text(alphabet="abcdefghijklmnopqrstuvwxyz_0123456789", min_size=1, max_size=12).filter(
    lambda s: s not in ALL_CONVENTION_KEYS and s not in ("file", "allow_pickle")  # np.savez's own arguments
)
_extra_values = st.one_of(
    st.builds(np.zeros, st.tuples(st.integers(0, 3), st.integers(0, 3))),
    st.builds(np.array, st.text(max_size=5)),
    st.builds(np.array, st.floats(allow_nan=True)),
    st.builds(lambda n: np.arange(n, dtype=np.complex64), st.integers(0, 4)),
)


@FUZZ
@given(extra=st.dictionaries(_extra_names, _extra_values, max_size=4))
def test_extra_keys_are_ignored(workdir, extra):
    arrays = valid_arrays()
    outcome = load_outcome(write_arrays(workdir, {**arrays, **extra}))
    assert isinstance(outcome, Sequence)
    np.testing.assert_array_equal(outcome.observations.dense(), arrays["features"])


@FUZZ
@given(
    key=st.sampled_from(KEYS),
    shape=st.lists(st.integers(0, 2**40), min_size=0, max_size=4).map(tuple),
    payload=st.integers(0, 2000),
    descr=st.sampled_from(["<f8", ">f4", "<i2", "|u1"]),
    fortran=st.booleans(),
)
def test_header_with_arbitrary_shape_never_allocates_it(workdir, key, shape, payload, descr, fortran):
    """A header may claim any shape; the loader checks it against the member size first."""
    arrays = valid_arrays()
    members = {}
    for k, v in arrays.items():
        buf = io.BytesIO()
        np.lib.format.write_array(buf, v, allow_pickle=False)
        members[k] = buf.getvalue()
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": fortran, "shape": shape})
    members[key] = buf.getvalue() + b"\x00" * payload
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for k, v in members.items():
            zf.writestr(f"{k}.npy", v)
    load_outcome(write_bytes(workdir, out.getvalue()))
