"""Reading and writing datasets in the report's npz format.

File format
-----------
An ``.npz`` (zip of ``.npy`` members) with these keys; two key conventions exist:

=====================  ======================  =================================================
report convention      later convention        content
=====================  ======================  =================================================
``time_stamps``        ``t``                   (1, T) or (T,) seconds, strictly increasing
``features``           ``features``            (4, M, T) pixels uL, vL, uR, vR; -1 in all four
                                               where landmark j is not seen at frame t (a
                                               signed integer or float dtype: unsigned ones
                                               cannot hold -1 and are refused)
``linear_velocity``    ``linear_velocity``     (3, T) m/s, IMU frame
``rotational_velocity`` ``angular_velocity``   (3, T) rad/s, IMU frame
``K``                  ``K``                   (3, 3) left intrinsics [[fsu,0,cu],[0,fsv,cv],[0,0,1]]
``b``                  ``b``                   scalar or size-1 array, stereo baseline (m)
``cam_T_imu``          ``imu_T_cam``           (4, 4) rigid transform; ``imu_T_cam`` is the inverse
=====================  ======================  =================================================

Loading
-------
:func:`load_sequence` (and :func:`load_dataset`, which also reports the key convention)
never unpickles anything and never materializes the dense ``features`` array: the zip
member is streamed in chunks of :data:`CHUNK_BYTES`, validated chunk by chunk, and only
the observed entries are kept (the sparse :class:`~vislam.core.sequence.StereoObservations`).
Every declared array size is checked against the member's size in the zip directory
before anything is read, so a forged header cannot make the loader allocate memory the
file does not contain. Every problem is a :class:`~vislam.errors.DatasetError` whose
one-line message names the file, the key and what was expected.

The loader enforces the *format* only. Observations with zero or negative disparity,
or ``vL != vR``, are valid input (the real datasets contain them); the estimators
decide what to do with them.
"""

from __future__ import annotations

import logging
import lzma
import math
import struct
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vislam.core.camera import StereoCamera, intrinsics_problem
from vislam.core.lie import is_rigid_transform, se3_inverse
from vislam.core.options import MAX_LEVER_ARM_M
from vislam.core.sequence import MAX_IMU_SAMPLE, MAX_PIXEL_COORD, MAX_TIME_STEP_S, MISSING_PIXEL, Sequence, StereoObservations
from vislam.errors import DatasetError, OutputError
from vislam.text import printable
from vislam.tools.npz import write_npz

__all__ = [
    "load_sequence",
    "load_dataset",
    "save_sequence",
    "iter_frames",
    "FrameStream",
    "summarize_sequence",
    "DatasetFile",
    "CONVENTIONS",
    "CHUNK_BYTES",
]

logger = logging.getLogger(__name__)

#: Bytes of the features member decoded at a time while streaming.
CHUNK_BYTES = 4 * 1024 * 1024

#: Keys of each convention, by quantity.
CONVENTIONS: dict[str, dict[str, str]] = {
    "report": {
        "timestamps": "time_stamps",
        "features": "features",
        "linear_velocity": "linear_velocity",
        "angular_velocity": "rotational_velocity",
        "K": "K",
        "b": "b",
        "transform": "cam_T_imu",
    },
    "later": {
        "timestamps": "t",
        "features": "features",
        "linear_velocity": "linear_velocity",
        "angular_velocity": "angular_velocity",
        "K": "K",
        "b": "b",
        "transform": "imu_T_cam",
    },
}

_COORDS = ("uL", "vL", "uR", "vR")

# Deflate cannot expand data by more than ~1032:1; a directory entry claiming more is forged.
# (Other compression methods are not ratio-checked; reads are bounded by the data anyway.)
_MAX_DEFLATE_RATIO = 1100
_RIGID_TOL = 1e-6

# Exceptions that reading a damaged file can raise from zipfile / zlib / numpy's header
# parser; all are turned into DatasetError naming the file.
_READ_ERRORS = (
    OSError,
    EOFError,
    zipfile.BadZipFile,
    zlib.error,
    lzma.LZMAError,
    struct.error,
    ValueError,
    OverflowError,
    SyntaxError,
    RuntimeError,  # zipfile: encrypted member; also RecursionError from a nested header
    NotImplementedError,  # zipfile: unsupported compression method
)


@dataclass(frozen=True)
class DatasetFile:
    """A loaded dataset file: the :class:`Sequence` plus how it was stored.

    Attributes:
        sequence: the recording.
        path: the file it came from.
        convention: ``"report"``, ``"later"`` or ``"mixed"`` (keys of both, never for the
            same quantity).
        keys: quantity -> key used (quantities: timestamps, features, linear_velocity,
            angular_velocity, K, b, transform).
        extra_keys: keys of the archive that were ignored.
        features_dtype: dtype of the stored features (e.g. ``"float64"``).
        features_fortran_order: whether the stored features were Fortran-ordered.
    """

    sequence: Sequence
    path: str
    convention: str
    keys: dict[str, str] = field(default_factory=dict)
    extra_keys: tuple[str, ...] = ()
    features_dtype: str = "float64"
    features_fortran_order: bool = False


# ----------------------------------------------------------------------------- writing


def save_sequence(sequence: Sequence, path, compress: bool = True, convention: str = "report",
                  fortran_order: bool = False) -> None:
    """Write ``sequence`` as an npz (atomically, deterministically).

    Report convention keys: time_stamps (1, T), features (4, M, T) with -1 where
    unobserved, linear_velocity / rotational_velocity (3, T), K (3, 3), b (), cam_T_imu
    (4, 4). ``convention="later"`` writes t, angular_velocity and imu_T_cam instead.
    ``fortran_order=True`` stores the features frame-major, so :func:`iter_frames` can
    stream them one frame at a time.
    """
    if convention not in CONVENTIONS:
        raise ValueError(f"unknown key convention {convention!r}; expected one of {sorted(CONVENTIONS)}")
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{path}: is a directory; expected the path of the .npz file to write")
    keys = CONVENTIONS[convention]
    transform = sequence.cam_T_imu if convention == "report" else sequence.imu_T_cam
    arrays = {
        keys["timestamps"]: sequence.timestamps_s[None, :],
        keys["features"]: (np.asfortranarray if fortran_order else np.asarray)(sequence.observations.dense()),
        keys["linear_velocity"]: sequence.linear_velocity_in_imu_mps.T,
        keys["angular_velocity"]: sequence.angular_velocity_in_imu_radps.T,
        keys["K"]: sequence.camera.K,
        keys["b"]: np.array(sequence.camera.baseline_m),
        keys["transform"]: transform,
    }
    try:
        write_npz(path, arrays, compress=compress)
    except OSError as exc:  # e.g. a read-only or full file system (atomic_path removed its temporary file)
        raise OutputError(f"{path}: cannot write: {exc.strerror or exc}") from None


# ----------------------------------------------------------------------------- reading


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _shape_str(shape) -> str:
    return "(" + ", ".join(str(int(s)) for s in shape) + ("," if len(shape) == 1 else "") + ")"


@dataclass(frozen=True)
class _Header:
    key: str
    dtype: np.dtype
    shape: tuple[int, ...]
    fortran_order: bool

    @property
    def size(self) -> int:
        return math.prod(self.shape)


class _CountingReader:
    """Wraps a zip member stream; counts bytes and reads exactly what is asked."""

    def __init__(self, fp):
        self._fp = fp
        self.position = 0

    def read(self, n: int = -1) -> bytes:
        data = self._fp.read(n)
        self.position += len(data)
        return data


class _NpzReader:
    """Reads validated numeric arrays from the ``.npy`` members of an open zip."""

    def __init__(self, path: Path, zf: zipfile.ZipFile):
        self.path = path
        self.zf = zf
        self.archive_size = path.stat().st_size
        self.members: dict[str, zipfile.ZipInfo] = {}
        duplicates = set()
        for info in zf.infolist():
            if not info.filename.endswith(".npy"):  # (ZipInfo.is_dir fails on an empty name)
                continue
            key = info.filename[: -len(".npy")]
            if key in self.members:
                duplicates.add(key)
            self.members[key] = info
        if not self.members:
            raise self.error(None, "contains no .npy arrays; expected an npz dataset archive")
        self.duplicates = duplicates
        self.current_key: str | None = None  # the member being read, for error messages

    # -- messages
    def error(self, key: str | None, what: str) -> DatasetError:
        where = f"{self.path}: key '{key}' " if key is not None else f"{self.path}: "
        return DatasetError(_one_line(where + what))

    # -- members
    def open_member(self, key: str) -> tuple[_CountingReader, _Header, zipfile.ZipExtFile]:
        """Open member ``key``, parse and check its header; return (stream, header, raw file)."""
        if key in self.duplicates:
            raise self.error(key, "appears more than once in the archive; refusing the ambiguous file")
        info = self.members[key]
        self.current_key = key
        if (info.compress_type == zipfile.ZIP_STORED and info.file_size != info.compress_size) or (
            info.compress_type == zipfile.ZIP_DEFLATED
            and info.file_size > info.compress_size * _MAX_DEFLATE_RATIO + 65536
        ):
            raise self.error(
                key,
                f"has a corrupt zip directory entry (claims {info.file_size} bytes uncompressed from "
                f"{info.compress_size} bytes stored); the archive is damaged",
            )
        if info.compress_size > self.archive_size:
            raise self.error(key, "is truncated (its zip entry extends past the end of the file)")
        try:
            raw = self.zf.open(info)
        except (zipfile.BadZipFile, zlib.error, OSError, EOFError, RuntimeError, NotImplementedError):
            raise
        except Exception as exc:  # noqa: BLE001 - zipfile parsing a damaged local header
            raise self.error(key, f"cannot be opened; the zip archive is corrupt ({type(exc).__name__}: {exc})") from exc
        try:
            fp = _CountingReader(raw)
            try:
                version = np.lib.format.read_magic(fp)
            except ValueError as exc:
                raise self.error(key, f"is not a .npy array ({_one_line(exc)})") from exc
            if version not in ((1, 0), (2, 0)):
                raise self.error(key, f"uses .npy format version {version[0]}.{version[1]}; expected 1.0 or 2.0")
            read_header = (
                np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            )
            try:
                # numpy parses the header text with ast.literal_eval (and tokenize for old
                # headers), never with pickle; a damaged header can make those raise almost
                # anything (ValueError, SyntaxError, tokenize.TokenError, RecursionError...).
                shape, fortran, dtype = read_header(fp)
                header = _Header(key, np.dtype(dtype), tuple(int(s) for s in shape), bool(fortran))
            except (zipfile.BadZipFile, zlib.error, OSError, EOFError):
                raise
            except Exception as exc:  # noqa: BLE001 - untrusted header text, see above
                raise self.error(
                    key, f"has a corrupt .npy header ({type(exc).__name__}: {_one_line(exc)}); expected a numeric array"
                ) from exc
            self._check_dtype(header)
            if any(s < 0 for s in header.shape):
                raise self.error(key, f"declares a negative dimension {header.shape}")
            declared = header.size * header.dtype.itemsize
            available = info.file_size - fp.position
            if declared != available:
                raise self.error(
                    key,
                    f"declares shape {_shape_str(header.shape)} of {header.dtype} ({declared} bytes) but its "
                    f"member holds {available} bytes of data; the file is corrupt or truncated",
                )
            return fp, header, raw
        except BaseException:
            raw.close()
            raise

    def _check_dtype(self, header: _Header) -> None:
        dt = header.dtype
        if dt.hasobject:
            raise self.error(
                header.key, f"is an object array (dtype {dt}, pickled data); expected a numeric array (never unpickled)"
            )
        if dt.fields is not None or dt.subdtype is not None or dt.kind not in "iuf":
            raise self.error(header.key, f"has dtype {dt}; expected a real numeric dtype (integer or float)")

    def check_features_dtype(self, header: _Header) -> None:
        """The features mark an unobserved cell with -1: refuse a dtype that cannot hold it
        (unsigned integers would turn every missing cell into an "observation" at 65535)."""
        if header.dtype.kind == "u":
            raise self.error(
                header.key,
                f"has dtype {header.dtype}, which cannot hold -1 (the mark of an unobserved cell); "
                f"expected a signed integer or float dtype",
            )

    def read_exact(self, fp: _CountingReader, n: int, key: str) -> bytes:
        data = fp.read(n)
        if len(data) != n:
            raise self.error(key, f"is truncated: expected {n} more bytes of data, found {len(data)}")
        return data

    def finish(self, fp: _CountingReader, key: str) -> None:
        """Read past the end of a member so that zipfile verifies its CRC."""
        if fp.read(1):
            raise self.error(key, "has trailing data after its array")

    def read_array(self, key: str, check_shape=None) -> tuple[np.ndarray, _Header]:
        """Read a whole (small) array as float64; ``check_shape(header)`` runs before the data is read."""
        fp, header, raw = self.open_member(key)
        with raw:
            if check_shape is not None:
                check_shape(header)
            data = self.read_exact(fp, header.size * header.dtype.itemsize, key)
            self.finish(fp, key)
        array = np.frombuffer(data, dtype=header.dtype).reshape(
            header.shape, order="F" if header.fortran_order else "C"
        )
        return array.astype(np.float64), header


def _key_list(keys, limit: int = 12) -> str:
    keys = sorted(keys)
    shown = ", ".join(repr(k)[1:-1] for k in keys[:limit])
    return shown + (f", ... ({len(keys)} keys)" if len(keys) > limit else "") if keys else "none"


def _resolve_keys(reader: _NpzReader) -> tuple[dict[str, str], str, tuple[str, ...]]:
    """Map each quantity to its key; refuse missing and ambiguous keys."""
    present = set(reader.members)
    keys: dict[str, str] = {}
    used_conventions = set()
    for quantity in CONVENTIONS["report"]:
        report_key, later_key = CONVENTIONS["report"][quantity], CONVENTIONS["later"][quantity]
        candidates = [k for k in dict.fromkeys((report_key, later_key)) if k in present]
        if len(candidates) == 2:
            raise reader.error(
                None,
                f"keys '{report_key}' (report convention) and '{later_key}' (later convention) are both "
                f"present; refusing the ambiguous file (keep exactly one)",
            )
        if not candidates:
            alternatives = f"'{report_key}'" if report_key == later_key else f"'{report_key}' (or '{later_key}')"
            raise reader.error(
                None,
                f"key {alternatives} is missing; expected the report convention keys "
                f"({', '.join(CONVENTIONS['report'].values())}) or the later convention keys "
                f"({', '.join(CONVENTIONS['later'].values())}); the file has keys: {_key_list(present)}",
            )
        keys[quantity] = candidates[0]
        if report_key != later_key:
            used_conventions.add("report" if candidates[0] == report_key else "later")
    convention = used_conventions.pop() if len(used_conventions) == 1 else "mixed"
    extra = tuple(sorted(present - set(keys.values())))
    return keys, convention, extra


def _first_index(bad: np.ndarray) -> int:
    return int(np.flatnonzero(np.ravel(bad))[0])


def _read_timestamps(reader: _NpzReader, key: str) -> np.ndarray:
    def check(h: _Header):
        if not (len(h.shape) == 1 or (len(h.shape) == 2 and h.shape[0] == 1)):
            raise reader.error(key, f"has shape {_shape_str(h.shape)}; expected (1, T) or (T,)")
        if h.size < 2:
            raise reader.error(key, f"has {h.size} frame(s); at least 2 frames are required")

    t, header = reader.read_array(key, check)
    t = t.ravel()
    bad = ~np.isfinite(t)
    if bad.any():
        i = _first_index(bad)
        raise reader.error(key, f"has a non-finite value {t[i]} at index {i}; expected finite seconds")
    with np.errstate(over="ignore"):
        step = np.diff(t)
    bad = ~(step > 0)
    if bad.any():
        i = _first_index(bad) + 1
        hint = ""
        if header.dtype.kind == "f" and header.dtype.itemsize < 8:  # e.g. Unix seconds in float32: 128 s apart
            spacing = float(np.spacing(np.abs(t[i]).astype(header.dtype)))
            hint = (f" (stored as {header.dtype.name}, whose values near {float(t[i]):.3g} are {spacing:.3g} apart: "
                    f"store time stamps as float64)")
        raise reader.error(
            key,
            f"is not strictly increasing at index {i} ({float(t[i])!r} after {float(t[i - 1])!r}); "
            f"expected strictly increasing timestamps{hint}",
        )
    long = step > MAX_TIME_STEP_S
    if long.any():
        i = _first_index(long) + 1
        raise reader.error(key, f"has a frame interval of {float(step[i - 1]):.3g} s at index {i}; expected at most "
                                f"{MAX_TIME_STEP_S:g} s (time stamps in seconds, or in ms, µs or ns)")
    return t


def _read_velocity(reader: _NpzReader, key: str, tkey: str, T: int, unit: str) -> np.ndarray:
    def check(h: _Header):
        if h.shape != (3, T):
            raise reader.error(
                key, f"has shape {_shape_str(h.shape)}; expected (3, T) with T = {T} from '{tkey}'"
            )

    v, _ = reader.read_array(key, check)
    bad = ~np.isfinite(v)
    if bad.size and np.isnan(v).all():  # vislam track without velocities (EuRoC): never run on zeros
        raise reader.error(key, f"holds no velocities (NaN throughout: tracked from images without IMU velocities, "
                           f"e.g. EuRoC, whose IMU gives accelerations); expected {unit}: track again with "
                           f"`vislam track SOURCE --velocities FILE.csv` (t,vx,vy,vz,wx,wy,wz)")
    if bad.any():
        r, c = np.unravel_index(_first_index(bad), v.shape)
        raise reader.error(key, f"has a non-finite value {v[r, c]} at row {r}, frame {c}; expected finite {unit}")
    far = np.abs(v) > MAX_IMU_SAMPLE
    if far.any():
        r, c = np.unravel_index(_first_index(far), v.shape)
        raise reader.error(key, f"has {v[r, c]:.3g} at row {r}, frame {c}; expected {unit} within "
                           f"±{MAX_IMU_SAMPLE:g} (a corrupt sample, or another unit)")
    return np.ascontiguousarray(v.T)


def _read_K(reader: _NpzReader, key: str) -> np.ndarray:
    def check(h: _Header):
        if h.shape != (3, 3):
            raise reader.error(key, f"has shape {_shape_str(h.shape)}; expected (3, 3)")

    K, _ = reader.read_array(key, check)
    if not np.all(np.isfinite(K)):
        raise reader.error(key, f"has non-finite entries {K.tolist()}; expected finite intrinsics")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise reader.error(
            key, f"has focal lengths K[0,0] = {float(K[0, 0])!r}, K[1,1] = {float(K[1, 1])!r}; "
            "expected both positive (pixels)"
        )
    if not np.array_equal(K[2], [0.0, 0.0, 1.0]):
        raise reader.error(key, f"has last row {K[2].tolist()}; expected [0, 0, 1]")
    problem = intrinsics_problem(K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    if problem:
        raise reader.error(key, problem)
    if K[0, 1] != 0.0 or K[1, 0] != 0.0:
        raise reader.error(
            key,
            f"has K[0,1] = {float(K[0, 1])!r}, K[1,0] = {float(K[1, 0])!r}; "
            "expected [[fsu, 0, cu], [0, fsv, cv], [0, 0, 1]] "
            f"(the stereo model has no skew)",
        )
    return K


def _read_baseline(reader: _NpzReader, key: str) -> float:
    def check(h: _Header):
        if h.size != 1:
            raise reader.error(key, f"has shape {_shape_str(h.shape)}; expected a scalar (the baseline in metres)")

    b, _ = reader.read_array(key, check)
    value = float(b.ravel()[0])
    if not (np.isfinite(value) and value > 0):
        raise reader.error(key, f"is {value!r}; expected a finite positive baseline in metres")
    return value


def _read_transform(reader: _NpzReader, key: str) -> np.ndarray:
    def check(h: _Header):
        if h.shape != (4, 4):
            raise reader.error(key, f"has shape {_shape_str(h.shape)}; expected (4, 4)")

    T, _ = reader.read_array(key, check)
    if not np.all(np.isfinite(T)):
        raise reader.error(key, "has non-finite entries; expected a finite 4x4 rigid transform")
    with np.errstate(all="ignore"):  # huge finite entries overflow RᵀR: still "not rigid"
        rigid = is_rigid_transform(T, tol=_RIGID_TOL)
        R = T[:3, :3]
        orth = float(np.max(np.abs(R.T @ R - np.eye(3))))
        det = float(np.linalg.det(R))
    if not rigid:
        raise reader.error(
            key,
            f"is not a rigid transform (max |RᵀR - I| = {orth:.3g}, det R = {det:.6g}, last row "
            f"{T[3].tolist()}); expected a rotation block and last row [0, 0, 0, 1] within {_RIGID_TOL:g}",
        )
    if np.abs(T[:3, 3]).max() > MAX_LEVER_ARM_M:
        raise reader.error(key, f"has translation {T[:3, 3].tolist()} (m); expected an IMU-camera lever arm within "
                                f"±{MAX_LEVER_ARM_M:g} m")
    return T


def _stream_features(reader: _NpzReader, key: str, tkey: str, T: int) -> tuple[StereoObservations, _Header]:
    """Stream the (4, M, T) features member into sparse observations (bounded memory)."""
    fp, header, raw = reader.open_member(key)
    with raw:
        shape = header.shape
        if len(shape) != 3 or shape[0] != 4 or shape[2] != T:
            raise reader.error(
                key, f"has shape {_shape_str(shape)}; expected (4, M, T) with T = {T} from '{tkey}'"
            )
        reader.check_features_dtype(header)
        M = shape[1]
        dtype = header.dtype
        itemsize = dtype.itemsize
        native_f8 = dtype == np.dtype(np.float64)

        def decode(n_items: int) -> np.ndarray:
            a = np.frombuffer(reader.read_exact(fp, n_items * itemsize, key), dtype=dtype)
            return a if native_f8 else a.astype(np.float64)

        def fail_entry(j: int, t: int, what: str) -> DatasetError:
            return reader.error(
                key,
                f"landmark {j} at frame {t}: {what}; expected four finite pixels within ±{MAX_PIXEL_COORD:g} or -1 "
                f"in all four coordinates (not observed)",
            )

        if header.fortran_order:
            observations = _stream_fortran(fp, decode, M, T, fail_entry)
        else:
            observations = _stream_c(fp, decode, M, T, fail_entry)
        reader.finish(fp, key)
    return observations, header


def _stream_c(fp, decode, M: int, T: int, fail_entry) -> StereoObservations:
    """C order: the stream is coordinate-major (all uL in (landmark, frame) order, then vL, ...).

    Memory: the flat positions of the observed cells (8 bytes per observation, from the
    uL plane) and the observed values, never a landmarks x frames array (a mask of the
    whole plane cost 1-2 bytes per cell: 0.7 GB for a 10,000-frame drive).

    A bad entry is reported as the first one in frame-major order (earliest frame, then
    lowest landmark), as for Fortran order; so the scan continues after a first error.
    """
    plane = M * T
    chunk = max(1, CHUNK_BYTES // 8)
    seen_at = None  # (N,) sorted flat positions (landmark * T + frame) of the observed cells
    values: list[np.ndarray] = []
    first: tuple[int, int, int, str] | None = None  # (frame-major rank, j, t, what)

    def note(bad_idx: np.ndarray, pos: int, a: np.ndarray, describe) -> None:
        nonlocal first
        j, t = np.divmod(pos + bad_idx, T)
        rank = t * M + j
        k = int(np.argmin(rank))
        if first is None or rank[k] < first[0]:
            first = (int(rank[k]), int(j[k]), int(t[k]), describe(int(bad_idx[k])))

    for c in range(4):
        at_parts: list[np.ndarray] = []
        parts: list[np.ndarray] = []
        pos = 0
        while pos < plane:
            n = min(chunk, plane - pos)
            a = decode(n)
            finite = np.abs(a) <= MAX_PIXEL_COORD  # finite, and not beyond any image (NaN fails)
            missing = a == MISSING_PIXEL
            if c == 0:
                seen = ~missing
                at_parts.append(pos + np.flatnonzero(seen))
                if not finite.all():
                    note(np.flatnonzero(~finite), pos, a, lambda i: f"{_COORDS[c]} is {a[i]}")
            else:
                lo, hi = np.searchsorted(seen_at, (pos, pos + n))
                seen = np.zeros(n, dtype=bool)
                seen[seen_at[lo:hi] - pos] = True
                # -1 where observed, not -1 where unobserved, or not finite
                bad = (missing == seen) | ~finite
                if bad.any():
                    def describe(i, c=c, a=a, seen=seen):
                        if not abs(a[i]) <= MAX_PIXEL_COORD:
                            return f"{_COORDS[c]} is {a[i]}"
                        if seen[i]:
                            return f"{_COORDS[c]} is -1 but uL is not"
                        return f"uL is -1 but {_COORDS[c]} is {float(a[i])!r}"

                    note(np.flatnonzero(bad), pos, a, describe)
            if first is None:
                parts.append(a[seen])
            pos += n
        if c == 0:
            seen_at = np.concatenate(at_parts) if at_parts else np.zeros(0, dtype=np.int64)
            del at_parts
        values.append(np.concatenate(parts) if parts else np.zeros(0))
        del parts
    if first is not None:
        _, j, t, what = first
        raise fail_entry(j, t, what)
    lm, fr = np.divmod(seen_at, T)  # landmark-major, the order of `values`
    del seen_at
    order = np.lexsort((lm, fr))  # frame-major, landmarks increasing within a frame
    pixels = np.empty((order.size, 4))
    for c in range(4):
        pixels[:, c] = values[c][order]
        values[c] = None
    offsets = np.zeros(T + 1, dtype=np.int64)
    np.cumsum(np.bincount(fr, minlength=T), out=offsets[1:])
    return StereoObservations(offsets, lm[order], pixels, M)


def _stream_fortran(fp, decode, M: int, T: int, fail_entry) -> StereoObservations:
    """Fortran order: the stream is frame-major, landmark next, the four coordinates innermost."""
    entries = M * T
    chunk = max(1, CHUNK_BYTES // 32)
    ids: list[np.ndarray] = []
    parts: list[np.ndarray] = []
    pos = 0
    while pos < entries:
        n = min(chunk, entries - pos)
        a = decode(4 * n).reshape(n, 4)
        missing = a == MISSING_PIXEL
        unseen = missing.all(axis=1)
        finite = (np.abs(a) <= MAX_PIXEL_COORD).all(axis=1)  # finite, and not beyond any image
        bad = ~finite | (missing.any(axis=1) & ~unseen)
        if bad.any():
            i = _first_index(bad)
            t, j = divmod(pos + i, M)
            raise fail_entry(j, t, f"has [uL, vL, uR, vR] = {a[i].tolist()}")
        seen = np.flatnonzero(~unseen)
        ids.append(pos + seen)
        parts.append(a[seen])
        pos += n
    flat = np.concatenate(ids) if ids else np.zeros(0, dtype=np.int64)
    fr, lm = np.divmod(flat, M) if M else (flat, flat)
    pixels = np.concatenate(parts) if parts else np.zeros((0, 4))
    offsets = np.zeros(T + 1, dtype=np.int64)
    np.cumsum(np.bincount(fr, minlength=T), out=offsets[1:])
    return StereoObservations(offsets, lm, pixels, M)


def _read_small(reader: _NpzReader):
    """Keys and every array but the features: (keys, convention, extra, timestamps,
    linear, angular, K, baseline, transform)."""
    keys, convention, extra = _resolve_keys(reader)
    tkey = keys["timestamps"]
    timestamps = _read_timestamps(reader, tkey)
    T = timestamps.shape[0]
    linear = _read_velocity(reader, keys["linear_velocity"], tkey, T, "m/s")
    angular = _read_velocity(reader, keys["angular_velocity"], tkey, T, "rad/s")
    K = _read_K(reader, keys["K"])
    baseline = _read_baseline(reader, keys["b"])
    with np.errstate(over="ignore"):
        fsu_b = K[0, 0] * baseline
    if not np.isfinite(fsu_b):
        raise reader.error(keys["b"], f"is {float(baseline)!r}: fsu * b overflows; expected a baseline in metres")
    transform = _read_transform(reader, keys["transform"])
    return keys, convention, extra, timestamps, linear, angular, K, baseline, transform


def _open_zip(path: Path) -> zipfile.ZipFile:
    """Open ``path`` as a zip after the checks that give the clearest one-line errors."""
    if not path.exists():
        raise DatasetError(f"{path}: file not found")
    if path.is_dir():
        raise DatasetError(f"{path}: is a directory; expected an .npz dataset file")
    if not path.is_file():
        raise DatasetError(f"{path}: is not a regular file; expected an .npz dataset file")
    size = path.stat().st_size
    if size == 0:
        raise DatasetError(f"{path}: file is empty; expected an .npz dataset file")
    with open(path, "rb") as f:
        head = f.read(8)
    if head.startswith(b"\x93NUMPY"):
        raise DatasetError(f"{path}: is a plain .npy array; expected an .npz archive of arrays")
    if not zipfile.is_zipfile(path):
        if head.startswith(b"PK"):
            raise DatasetError(f"{path}: is a truncated or corrupt zip archive; expected an .npz dataset file")
        raise DatasetError(f"{path}: is not an .npz archive (no zip structure found)")
    try:
        return zipfile.ZipFile(path)
    except (OSError, zipfile.BadZipFile):
        raise
    except Exception as exc:  # noqa: BLE001 - zipfile parsing a damaged central directory
        raise DatasetError(
            _one_line(f"{path}: is a corrupt zip archive ({type(exc).__name__}: {exc}); expected an .npz dataset")
        ) from exc


def _read_error(path: Path, reader, exc: BaseException) -> DatasetError:
    """The one-line DatasetError for a low-level read error."""
    if isinstance(exc, OSError) and reader is None:  # e.g. permission denied, name too long
        return DatasetError(_one_line(f"{path}: cannot be read ({exc.strerror or exc})"))
    key = getattr(reader, "current_key", None) if reader is not None else None
    where = f"{path}: key '{key}'" if key else f"{path}:"
    return DatasetError(
        _one_line(f"{where} cannot be read; the file is corrupt or truncated ({type(exc).__name__}: {exc})"))


def load_dataset(path, name: str | None = None) -> DatasetFile:
    """Load and validate a dataset npz (either key convention); see the module docstring.

    Raises :class:`DatasetError` (one line naming the file, the key and what was
    expected) for every missing, unreadable or malformed file.
    """
    path = Path(path)
    reader = None
    try:
        zf = _open_zip(path)
        with zf:
            reader = _NpzReader(path, zf)
            keys, convention, extra, timestamps, linear, angular, K, baseline, transform = _read_small(reader)
            T = timestamps.shape[0]
            observations, fheader = _stream_features(reader, keys["features"], keys["timestamps"], T)
    except DatasetError:
        raise
    except _READ_ERRORS as exc:
        raise _read_error(path, reader, exc) from exc
    cam_T_imu = transform if keys["transform"] == "cam_T_imu" else se3_inverse(transform)
    sequence = Sequence(
        name=name if name is not None else printable(path.stem),
        timestamps_s=timestamps,
        linear_velocity_in_imu_mps=linear,
        angular_velocity_in_imu_radps=angular,
        observations=observations,
        camera=StereoCamera(K, baseline),
        cam_T_imu=cam_T_imu,
        source=str(path),
    )
    if extra:
        logger.debug("%s: ignoring extra keys %s", path, ", ".join(extra))
    logger.info(
        "%s: %d frames, %d landmarks, %d observations (%s key convention)",
        path, T, observations.n_landmarks, observations.n_observations, convention,
    )
    return DatasetFile(
        sequence=sequence,
        path=str(path),
        convention=convention,
        keys=keys,
        extra_keys=extra,
        features_dtype=str(fheader.dtype),
        features_fortran_order=fheader.fortran_order,
    )


def load_sequence(path, name: str | None = None) -> Sequence:
    """Load a dataset npz as a :class:`Sequence` (name defaults to the file stem).

    Accepts the report key convention and the later one (see the module docstring);
    raises :class:`DatasetError` for anything malformed.
    """
    return load_dataset(path, name=name).sequence


# ----------------------------------------------------------------------------- streaming


class FrameStream:
    """The frames of a dataset file, read one at a time (:func:`iter_frames`).

    Opening reads and validates everything but the features (timestamps, velocities,
    calibration: a few kB per frame at most). Iterating yields :class:`Frame` objects:

    * **Fortran-ordered features** (frame-major on disk): streamed straight from the zip
      member, one frame (4·M values) at a time — memory is one frame of the dense array,
      whatever the length of the recording, and the first frame arrives at once;
    * **C-ordered features** (the shared files; landmark-major on disk, so frame t's
      values are spread over the whole member): the member is first read into the
      sparse observation arrays (:func:`load_sequence`, streamed in chunks; 40 bytes per
      observation, e.g. 12 MB for dense 0034) and the frames are then served from them.

    Attributes: ``path``, ``name``, ``calibration``, ``timestamps_s``, ``n_frames``,
    ``n_landmarks``, ``streams`` (True when frames are read straight from the file).
    """

    def __init__(self, path, name: str | None = None):
        self.path = Path(path)
        self.name = name if name is not None else printable(self.path.stem)
        reader = None
        try:
            with _open_zip(self.path) as zf:
                reader = _NpzReader(self.path, zf)
                small = _read_small(reader)
                self._keys = small[0]
                fp, header, raw = reader.open_member(self._keys["features"])
                raw.close()
        except DatasetError:
            raise
        except _READ_ERRORS as exc:
            raise _read_error(self.path, reader, exc) from exc
        keys, _, _, self.timestamps_s, self._linear, self._angular, K, baseline, transform = small
        T = self.timestamps_s.shape[0]
        shape = header.shape
        if len(shape) != 3 or shape[0] != 4 or shape[2] != T:
            raise reader.error(keys["features"], f"has shape {_shape_str(shape)}; expected (4, M, T) with T = {T} "
                               f"from '{keys['timestamps']}'")
        reader.check_features_dtype(header)
        self.n_frames = T
        self.n_landmarks = shape[1]
        self.streams = header.fortran_order
        cam_T_imu = transform if keys["transform"] == "cam_T_imu" else se3_inverse(transform)
        from vislam.core.sequence import Calibration

        self.calibration = Calibration(StereoCamera(K, baseline), cam_T_imu)

    def __len__(self) -> int:
        return self.n_frames

    def __iter__(self):
        if not self.streams:
            yield from load_sequence(self.path, name=self.name).frames()
            return
        from vislam.core.sequence import Frame

        path, key, M, T = self.path, self._keys["features"], self.n_landmarks, self.n_frames
        reader = None
        try:
            with _open_zip(path) as zf:
                reader = _NpzReader(path, zf)
                fp, header, raw = reader.open_member(key)
                with raw:
                    dtype = header.dtype
                    ids_all = np.arange(M, dtype=np.int64)
                    for t in range(T):
                        a = np.frombuffer(reader.read_exact(fp, 4 * M * dtype.itemsize, key), dtype=dtype)
                        a = a.astype(np.float64).reshape(M, 4)
                        missing = a == MISSING_PIXEL
                        unseen = missing.all(axis=1)
                        # finite and not beyond any image, as load_sequence (1e300 streamed through before)
                        bad = ~(np.abs(a) <= MAX_PIXEL_COORD).all(axis=1) | (missing.any(axis=1) & ~unseen)
                        if bad.any():
                            j = _first_index(bad)
                            raise reader.error(key, f"landmark {j} at frame {t}: has [uL, vL, uR, vR] = "
                                               f"{a[j].tolist()}; expected four finite pixels within "
                                               f"±{MAX_PIXEL_COORD:g} or -1 in all four coordinates (not observed)")
                        seen = ~unseen
                        dt = float(self.timestamps_s[t] - self.timestamps_s[t - 1]) if t > 0 else 0.0
                        yield Frame(t, float(self.timestamps_s[t]), dt, self._linear[t].copy(),
                                    self._angular[t].copy(), ids_all[seen], a[seen])
                    reader.finish(fp, key)
        except DatasetError:
            raise
        except _READ_ERRORS as exc:
            raise _read_error(path, reader, exc) from exc


def iter_frames(path, name: str | None = None) -> FrameStream:
    """The frames of the dataset file ``path`` one at a time (see :class:`FrameStream`):
    ``for frame in vislam.iter_frames(path): filter.step(frame)``."""
    return FrameStream(path, name=name)


# ----------------------------------------------------------------------------- summary


def _stats(values, *, mean: bool = False, median: bool = True) -> dict:
    values = np.asarray(values, dtype=np.float64)
    if values.size == 0:
        out = {"min": None, "max": None}
        if median:
            out["median"] = None
        if mean:
            out["mean"] = None
        return out
    out = {"min": float(values.min())}
    if median:
        out["median"] = float(np.median(values))
    if mean:
        out["mean"] = float(values.mean())
    out["max"] = float(values.max())
    return out


def summarize_sequence(sequence: Sequence) -> dict:
    """Plain-data summary of a sequence (JSON-serializable apart from non-finite floats).

    Keys: name, source, frames, duration_s, mean_frame_rate_hz, frame_interval_s,
    landmarks {total, observed}, observations {total, per_frame {min, mean, max},
    frames_without, repeated, repeat_evidence (see StereoObservations.repeat_evidence)}, track_length_frames {min, median, max} (over observed landmarks),
    disparity_px {min, median, max, non_positive}, row_mismatch_px {max} (|vL - vR|),
    speed_mps {min, mean, max}, angular_rate_radps {min, mean, max}, calibration {fsu,
    fsv, cu, cv, baseline_m, K, M}, cam_T_imu.
    """
    with np.errstate(all="ignore"):  # extreme (but valid) values give inf, not warnings
        return _summarize(sequence)


def _summarize(sequence: Sequence) -> dict:
    obs = sequence.observations
    T = sequence.n_frames
    duration = sequence.duration_s
    counts = obs.counts_per_frame()
    tracks = obs.track_lengths()
    tracks = tracks[tracks > 0]
    pixels = obs.pixels
    disparity = pixels[:, 0] - pixels[:, 2]
    cam = sequence.camera
    speed = np.linalg.norm(sequence.linear_velocity_in_imu_mps, axis=1)
    rate = np.linalg.norm(sequence.angular_velocity_in_imu_radps, axis=1)
    dt = np.diff(sequence.timestamps_s)
    repeated, evidence = obs.repeat_evidence(sequence.repeat_motion())
    return {
        "name": sequence.name,
        "source": sequence.source,
        "frames": T,
        "duration_s": duration,
        "mean_frame_rate_hz": (T - 1) / duration if duration > 0 else None,
        "frame_interval_s": _stats(dt, median=True),
        "landmarks": {"total": obs.n_landmarks, "observed": int(tracks.size)},
        "observations": {
            "total": obs.n_observations,
            "per_frame": _stats(counts, mean=True, median=False),
            "frames_without": int(np.count_nonzero(counts == 0)),
            "repeated": int(np.count_nonzero(repeated)),
            "repeat_evidence": evidence,
        },
        "track_length_frames": _stats(tracks),
        "disparity_px": {**_stats(disparity), "non_positive": int(np.count_nonzero(~(disparity > 0)))},
        "row_mismatch_px": {"max": float(np.abs(pixels[:, 1] - pixels[:, 3]).max()) if len(pixels) else None},
        "speed_mps": _stats(speed, mean=True, median=False),
        "angular_rate_radps": _stats(rate, mean=True, median=False),
        "calibration": {
            "fsu": cam.fsu,
            "fsv": cam.fsv,
            "cu": cam.cu,
            "cv": cam.cv,
            "baseline_m": cam.baseline_m,
            "K": cam.K.tolist(),
            "M": cam.M.tolist(),
        },
        "cam_T_imu": sequence.cam_T_imu.tolist(),
    }
