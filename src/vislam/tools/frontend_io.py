"""Stereo image folders as vislam input: readers, tracking, the tracked recording.

:func:`open_stereo_source` recognizes three folder layouts and returns a
:class:`StereoSource` (calibration of the *rectified* pair, frame times, velocities,
the image files); :func:`track_source` runs :class:`vislam.core.tracking.StereoTracker`
over its pairs (one pair in memory at a time) and returns the recording as a
:class:`~vislam.core.sequence.Sequence`; :func:`write_tracks` writes it (the dataset
npz, atomically) with the tracker's statistics as JSON beside it.

Layouts
-------
**KITTI raw drive** — the ``YYYY_MM_DD_drive_NNNN_sync`` folder is SOURCE::

    YYYY_MM_DD/calib_cam_to_cam.txt, calib_velo_to_cam.txt, calib_imu_to_velo.txt
    YYYY_MM_DD/YYYY_MM_DD_drive_NNNN_sync/image_00/data/*.png, image_00/timestamps.txt
                                          image_01/... (grey pair; image_02/03: colour)
                                          oxts/data/*.txt, oxts/timestamps.txt

K and the baseline come from ``P_rect_0i`` of the pair (b = (P_l[0,3] - P_r[0,3]) / fx);
``cam_T_imu = T_rect0_to_cami · R_rect_00 · T_velo→cam · T_imu→velo`` where
``T_rect0_to_cami`` is the translation ``P_rect_0i[:, 3] / fx`` of the rectified left
camera of the pair relative to rectified camera 0 (identity for the grey pair).
Velocities: the OXTS packets' ``vf vl vu`` (m/s, forward/left/up, levelled as the course
files hold them) and ``wf wl wu`` (rad/s, IMU axes), linearly interpolated at the left
images' times.

**EuRoC / ASL** — SOURCE holds ``mav0/`` (or is it)::

    mav0/cam0/data.csv (timestamp ns, file name), mav0/cam0/data/*.png, mav0/cam0/sensor.yaml
    mav0/cam1/...

``sensor.yaml``: ``intrinsics`` (fu fv cu cv), ``distortion_coefficients``
(radial-tangential k1 k2 p1 p2), ``resolution``, ``T_BS`` (body_T_sensor; the body
frame is the IMU's). The pair is rectified with ``cv2.stereoRectify`` (zero disparity
at infinity, alpha 0) and ``cv2.initUndistortRectifyMap``; the written K, baseline and
``cam_T_imu = [R_rect | 0] · inv(T_BS_cam0)`` are those of the rectified left camera.
EuRoC's IMU measures accelerations, not velocities: without ``velocities=FILE.csv``
the recording is written with NaN velocities, which every filter command refuses with a
message saying so (never zeros in silence).

**Plain folder** — SOURCE holds::

    left/*.png, right/*.png        rectified pairs, matched by sorted file name
    calibration.yaml               K: 3x3, baseline: m, cam_T_imu: 4x4 (IMU -> left camera)
    velocities.csv                 t,vx,vy,vz,wx,wy,wz: one row per pair (s, m/s, rad/s, IMU frame)

A velocity CSV (EuRoC's ``velocities=``) has the same columns, a header line allowed,
and is linearly interpolated at the image times (it must cover them).

Images: any format OpenCV decodes, grey or colour (read as grey), 8 or 16 bits (16-bit
images scaled to 8 bits by one factor for the whole recording, from the bit depth of the
first left image: 12-bit data by 255/4095). Image files of a folder are ordered by name with
the numbers in it compared as numbers (``2.png`` before ``10.png``; zero-padded names sort
as usual).

Every problem with a folder is a :class:`~vislam.errors.DatasetError` naming the file
and what was expected; nothing is written before the whole recording has been tracked.
A right image identical to its left one, fewer pairs than ``min_track_length`` and images
too small for the detector are refused; a first pair that matches far better with left
and right exchanged is a warning of the statistics.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import math
import re
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import yaml

from vislam.core.camera import StereoCamera, intrinsics_problem
from vislam.core.lie import is_rigid_transform, se3_inverse
from vislam.core.options import MAX_LEVER_ARM_M
from vislam.core.sequence import MAX_IMU_SAMPLE, MAX_TIME_STEP_S, Sequence
from vislam.errors import DatasetError
from vislam.tools.config import YAML_VALUE_ERRORS

__all__ = ["StereoSource", "open_stereo_source", "is_image_folder", "track_source", "write_tracks", "load_recording",
           "CACHE_NAME", "image_layout_of",
           "read_kitti_calibration", "kitti_cam_T_imu", "LAYOUTS", "stats_path_for"]

logger = logging.getLogger(__name__)

LAYOUTS = ("kitti-raw", "euroc", "folder")
_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".ppm", ".bmp", ".tif", ".tiff")
#: Largest image side a calibration may state (px): beyond any camera; rectification maps of
#: a 2e6 px square asked OpenCV for 16 TB.
_MAX_IMAGE_SIDE_PX = 100_000
_LAYOUT_HELP = ("expected a KITTI raw drive folder (image_00/, image_01/, oxts/; calib_*.txt one level up), "
                "an EuRoC/ASL folder (mav0/cam0, mav0/cam1) or a folder with left/, right/, calibration.yaml "
                "and velocities.csv")


@dataclass(frozen=True, eq=False)
class StereoSource:
    """A stereo image recording: what the tracker reads and what the npz gets.

    Attributes:
        name: recording name (the folder's).
        root: the SOURCE folder.
        layout: one of :data:`LAYOUTS`.
        left_files, right_files: image files of each frame (T each).
        timestamps_s: (T,) frame times (s).
        K, baseline_m, cam_T_imu: calibration of the rectified pair.
        image_size_px: (width, height) of the rectified images.
        velocities: (T, 6) (v, ω) in the IMU frame, or None (unknown: NaN in the npz).
        velocity_note: why velocities are None (for messages).
        rectify_maps: None (images already rectified) or ((map1x, map1y), (map2x, map2y)).
        inputs: every file read besides the images (calibration, CSV), for the cache key.
        extra: layout-specific facts (e.g. EuRoC: the unrectified extrinsics).
    """

    name: str
    root: Path
    layout: str
    left_files: tuple
    right_files: tuple
    timestamps_s: np.ndarray
    K: np.ndarray
    baseline_m: float
    cam_T_imu: np.ndarray
    image_size_px: tuple
    velocities: np.ndarray | None
    velocity_note: str = ""
    rectify_maps: tuple | None = None
    inputs: tuple = ()
    extra: dict = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return len(self.left_files)

    def read_pair(self, t: int, exchanged: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The rectified grey (uint8) pair of frame ``t``; DatasetError for an unreadable image,
        one of another size or bit depth than the recording's, or a right image identical to
        its left one.

        16-bit images are scaled to 8 bits by one factor for the whole recording, from the
        bit depth of frame 0's left image (its largest value: 12-bit data in a 16-bit PNG
        is scaled by 255/4095), so the grey levels of a point agree between frames and
        between the two cameras. ``exchanged``: the right file as the left image and the left
        file as the right one (each rectified as the other camera), to test whether the
        folders are swapped."""
        from vislam.core.tracking import require_cv2

        cv2 = require_cv2()
        files = (self.right_files[t], self.left_files[t]) if exchanged else (self.left_files[t], self.right_files[t])
        out = []
        for path in files:
            image = _read_grey(cv2, path, self.image_size_px)
            if image.dtype != np.uint8:
                dtype, scale = self._depth
                if image.dtype != dtype:
                    raise DatasetError(f"{path}: has {image.dtype} pixels, {self.left_files[0]} {dtype}; expected "
                                       f"one bit depth for every image of the recording")
                image = cv2.convertScaleAbs(image, alpha=scale)
            if self.rectify_maps is None and (image.shape[1], image.shape[0]) != tuple(self.image_size_px):
                raise DatasetError(f"{path}: is {image.shape[1]}x{image.shape[0]} px; expected "
                                   f"{self.image_size_px[0]}x{self.image_size_px[1]} px like the calibration")
            out.append(image)
        if out[0].shape == out[1].shape and np.array_equal(out[0], out[1]) and out[0].max() > out[0].min():
            raise DatasetError(f"{self.right_files[t]}: is the same image as {self.left_files[t]}; expected the "
                               f"right camera's view of the pair (identical images have zero disparity, no depth)")
        if self.rectify_maps is not None:
            expected = self.extra.get("raw_size_px")
            for path, image in zip(files, out):
                if expected and (image.shape[1], image.shape[0]) != tuple(expected):
                    raise DatasetError(f"{path}: is {image.shape[1]}x{image.shape[0]} px; expected "
                                       f"{expected[0]}x{expected[1]} px (sensor.yaml resolution)")
            out = [cv2.remap(im, m[0], m[1], cv2.INTER_LINEAR) for im, m in zip(out, self.rectify_maps)]
        return out[0], out[1]

    @cached_property
    def _depth(self) -> tuple:
        """(dtype, factor to 8 bits) of the recording's 16-bit images, from frame 0's left image."""
        from vislam.core.tracking import require_cv2

        cv2 = require_cv2()
        first = _read_grey(cv2, self.left_files[0])
        if first.dtype == np.uint8:
            return np.dtype(np.uint8), 1.0
        bits = min(16, max(8, int(first.max()).bit_length()))
        return first.dtype, 255.0 / (2 ** bits - 1)

    def fingerprint(self) -> str:
        """A digest of every input (file names, sizes and modification times) — the cache key."""
        h = hashlib.sha256()
        for path in (*self.inputs, *self.left_files, *self.right_files):
            try:
                st = Path(path).stat()
                h.update(f"{path}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
            except OSError:
                h.update(f"{path}\0missing\n".encode())
        return h.hexdigest()


# ----------------------------------------------------------------------------- helpers


def _read_grey(cv2, path, size_px=None) -> np.ndarray:
    """One image as grey pixels of its own bit depth (uint8 or uint16); DatasetError naming
    the file for one that cannot be decoded or has floating-point pixels. ``size_px``: the
    (width, height) expected, for the messages."""
    expected = f" ({size_px[0]}x{size_px[1]} px)" if size_px else ""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot be read ({exc.strerror or exc}); expected a readable PNG/JPEG "
                           f"image{expected}") from None
    if data.startswith(_PNG_SIGNATURE) and _PNG_END not in data:
        # a cut-off PNG (an interrupted copy): said here, before libpng prints its own line on stderr
        raise DatasetError(f"{path}: is a truncated PNG ({len(data)} bytes, no IEND chunk); expected a complete "
                           f"image{expected}")
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)  # OpenCV's decoder warnings: our one line
    try:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH) \
            if data else None
    finally:
        cv2.utils.logging.setLogLevel(level)
    if image is None:
        raise DatasetError(f"{path}: cannot be read as an image; expected a readable PNG/JPEG image{expected}")
    if image.dtype not in (np.uint8, np.uint16):
        raise DatasetError(f"{path}: has {image.dtype} pixels; expected an 8- or 16-bit grey or colour image")
    return image


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"IEND\xaeB`\x82"  # the last chunk of every PNG, with its CRC


def _natural_key(path: Path):
    """Sort key of a file name with its digit runs compared as numbers: 2.png before 10.png
    (the same order as plain sorting for zero-padded names)."""
    parts = re.split(r"([0-9]+)", path.name)
    return [(0, int(p), "") if "0" <= p[0] <= "9" else (1, 0, p) for p in parts if p], path.name


def _images_in(folder: Path) -> list[Path]:
    try:
        return sorted((p for p in folder.iterdir() if p.suffix.lower() in _IMAGE_SUFFIXES and p.is_file()),
                      key=_natural_key)
    except OSError as exc:
        raise DatasetError(f"{folder}: cannot be listed ({exc.strerror or exc})") from None


def _read_text(path: Path, what: str) -> str:
    if not path.is_file():
        raise DatasetError(f"{path}: missing; expected {what}")
    try:
        return path.read_text(encoding="utf-8-sig")  # a byte-order mark (spreadsheet exports) is not data
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: cannot be read ({exc}); expected {what}") from None


def _check_counts(left: list, right: list, left_dir: Path, right_dir: Path) -> None:
    if not left:
        raise DatasetError(f"{left_dir}: holds no images; expected the left images (PNG)")
    if len(left) != len(right):
        raise DatasetError(f"{right_dir}: holds {len(right)} images, {left_dir} {len(left)}; expected one right "
                           f"image per left image")
    # pairs are taken in order: with the same names on both sides, the order must pair equal names
    # (a frame missing on each side, a different one, paired every later frame with its neighbour)
    left_names, right_names = [p.name for p in left], [p.name for p in right]
    if left_names != right_names and set(left_names) & set(right_names):
        k = next(i for i, (a, b) in enumerate(zip(left_names, right_names)) if a != b)
        raise DatasetError(f"{right[k]}: would be paired with {left[k]} (frame {k} of each folder in name order); "
                           f"expected the same file names in {left_dir} and {right_dir}, one right image per left "
                           f"image")


def _check_times(t: np.ndarray, path: Path) -> None:
    if not np.all(np.isfinite(t)):
        raise DatasetError(f"{path}: has a non-finite time stamp; expected finite times")
    if t.size > 1 and np.any(np.diff(t) <= 0):
        k = int(np.argmax(np.diff(t) <= 0)) + 1
        raise DatasetError(f"{path}: time stamp {k} ({float(t[k])!r}) is not after the previous one; expected strictly "
                           f"increasing times")
    if t.size > 1 and np.any(np.diff(t) > MAX_TIME_STEP_S):
        k = int(np.argmax(np.diff(t) > MAX_TIME_STEP_S)) + 1
        raise DatasetError(f"{path}: time stamp {k} ({float(t[k])!r}) is {float(t[k] - t[k - 1]):.3g} s after the "
                           f"previous one; expected at most {MAX_TIME_STEP_S:g} s")


def _check_pair_times(t_left: np.ndarray, t_right: np.ndarray, left: Path, right: Path) -> None:
    if t_left.shape != t_right.shape:
        raise DatasetError(f"{right}: has {t_right.size} time stamps, {left} {t_left.size}; expected one per frame")
    dt = float(np.median(np.diff(t_left))) if t_left.size > 1 else 1.0
    tol = min(0.005, 0.25 * dt)
    bad = np.abs(t_left - t_right) > tol
    if bad.any():
        k = int(np.argmax(bad))
        raise DatasetError(f"{right}: time stamp of frame {k} differs from {left}'s by "
                           f"{abs(t_left[k] - t_right[k]) * 1e3:.3f} ms; expected the same times within "
                           f"{tol * 1e3:.1f} ms")


def _floats(text: str, path: Path, key: str, n: int) -> np.ndarray:
    try:
        values = np.array([float(v) for v in text.split()])
    except ValueError:
        raise DatasetError(f"{path}: key '{key}' is not a list of numbers; expected {n} numbers") from None
    if values.size != n:
        raise DatasetError(f"{path}: key '{key}' has {values.size} values; expected {_numbers(n)}")
    if not np.all(np.isfinite(values)):
        raise DatasetError(f"{path}: key '{key}' has a non-finite value ({text.strip()[:60]}); expected {_numbers(n)}")
    return values


def _numbers(n: int) -> str:
    return "1 finite number" if n == 1 else f"{n} finite numbers"


def _kitti_keys(path: Path) -> dict[str, str]:
    text = _read_text(path, "a KITTI calibration file (KEY: values lines)")
    out = {}
    for line in text.splitlines():
        if ":" in line:
            key, _, value = line.partition(":")
            out[key.strip()] = value.strip()
    return out


def _kitti_get(keys: dict, path: Path, key: str, n: int) -> np.ndarray:
    if key not in keys:
        raise DatasetError(f"{path}: key '{key}' missing; expected {n} numbers")
    return _floats(keys[key], path, key, n)


def _rigid(R: np.ndarray, T: np.ndarray, path: Path, what: str) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3] = R.reshape(3, 3)
    M[:3, 3] = T.reshape(3)
    if not is_rigid_transform(M, tol=1e-5):
        raise DatasetError(f"{path}: {what} is not a rotation (R Rᵀ ≠ I or det ≠ 1 to 1e-5); expected a rigid "
                           f"transform")
    return M


# ----------------------------------------------------------------------------- KITTI raw


def read_kitti_calibration(date_dir, pair: str = "grey") -> dict:
    """K, baseline, cam_T_imu and image size of a KITTI raw date folder's rectified pair.

    ``pair``: ``"grey"`` (cameras 00/01) or ``"colour"`` (02/03). Returns a dict with
    ``K`` (3, 3), ``baseline_m``, ``cam_T_imu`` (4, 4), ``image_size_px`` (w, h) and
    ``cameras`` (the two camera numbers).
    """
    date_dir = Path(date_dir)
    if pair not in ("grey", "colour"):
        raise DatasetError(f"unknown KITTI camera pair {pair!r}; expected grey or colour")
    left, right = ("00", "01") if pair == "grey" else ("02", "03")
    c2c = date_dir / "calib_cam_to_cam.txt"
    v2c = date_dir / "calib_velo_to_cam.txt"
    i2v = date_dir / "calib_imu_to_velo.txt"
    kc, kv, ki = _kitti_keys(c2c), _kitti_keys(v2c), _kitti_keys(i2v)
    P_l = _kitti_get(kc, c2c, f"P_rect_{left}", 12).reshape(3, 4)
    P_r = _kitti_get(kc, c2c, f"P_rect_{right}", 12).reshape(3, 4)
    R_rect = _kitti_get(kc, c2c, "R_rect_00", 9).reshape(3, 3)
    size = _kitti_get(kc, c2c, f"S_rect_{left}", 2) if f"S_rect_{left}" in kc else None
    if size is not None and not np.all((size >= 1) & (size <= _MAX_IMAGE_SIDE_PX) & (size == np.round(size))):
        raise DatasetError(f"{c2c}: key 'S_rect_{left}' is {' '.join(f'{v:g}' for v in size)}; expected the width "
                           f"and height in whole pixels, 1 to {_MAX_IMAGE_SIDE_PX}")
    K = P_l[:, :3].copy()
    fx = K[0, 0]
    if not (fx > 0 and K[1, 1] > 0 and abs(K[2, 2] - 1) < 1e-9):
        raise DatasetError(f"{c2c}: key 'P_rect_{left}' has focal lengths {fx}, {K[1, 1]}; expected positive focal "
                           f"lengths and a last row 0 0 1 0")
    problem = intrinsics_problem(K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    if problem:
        raise DatasetError(f"{c2c}: key 'P_rect_{left}' {problem}")
    baseline = (P_l[0, 3] - P_r[0, 3]) / fx
    if not baseline > 0:
        raise DatasetError(f"{c2c}: keys 'P_rect_{left}'/'P_rect_{right}' give a baseline of {baseline} m; expected "
                           f"the right camera to the right of the left one (P_rect_{right}[0,3] < P_rect_{left}[0,3])")
    velo_T_imu = _rigid(_kitti_get(ki, i2v, "R", 9), _kitti_get(ki, i2v, "T", 3), i2v, "R")
    cam_T_velo = _rigid(_kitti_get(kv, v2c, "R", 9), _kitti_get(kv, v2c, "T", 3), v2c, "R")
    rect = _rigid(R_rect, np.zeros(3), c2c, "R_rect_00")
    cam_T_imu = kitti_cam_T_imu(rect, cam_T_velo, velo_T_imu, P_l)
    return {"K": K, "baseline_m": float(baseline), "cam_T_imu": cam_T_imu,
            "image_size_px": (int(size[0]), int(size[1])) if size is not None else None,
            "cameras": (left, right), "files": (c2c, v2c, i2v)}


def kitti_cam_T_imu(rect0_T_cam0, cam0_T_velo, velo_T_imu, P_rect_left) -> np.ndarray:
    """cam_T_imu of a KITTI rectified camera with projection ``P_rect_left`` (3, 4):
    ``T(P[:, 3] / fx) · R_rect_00 · T_velo→cam · T_imu→velo`` (the translation is that of
    the rectified camera relative to rectified camera 0; zero for camera 0)."""
    P = np.asarray(P_rect_left, dtype=np.float64)
    offset = np.eye(4)
    offset[:3, 3] = [P[0, 3] / P[0, 0], P[1, 3] / P[1, 1], P[2, 3]]
    return offset @ np.asarray(rect0_T_cam0) @ np.asarray(cam0_T_velo) @ np.asarray(velo_T_imu)


def parse_kitti_timestamps(path: Path) -> np.ndarray:
    """UNIX seconds of a KITTI ``timestamps.txt`` (``YYYY-MM-DD HH:MM:SS.fffffffff`` lines)."""
    text = _read_text(path, "one time stamp per line, YYYY-MM-DD HH:MM:SS.fffffffff")
    out = []
    for i, line in enumerate(text.split("\n")):
        line = line.strip()
        if not line:
            continue
        try:
            whole, _, frac = line.partition(".")
            base = _dt.datetime.strptime(whole, "%Y-%m-%d %H:%M:%S").replace(tzinfo=_dt.timezone.utc)
            out.append(base.timestamp() + (float("0." + frac) if frac else 0.0))
        except ValueError:
            raise DatasetError(f"{path}: line {i + 1} ({line[:40]!r}) is not a time stamp; expected "
                               f"YYYY-MM-DD HH:MM:SS.fffffffff") from None
    t = np.array(out)
    _check_times(t, path)
    return t


def _interpolate(t_src: np.ndarray, values: np.ndarray, t: np.ndarray, path: Path) -> np.ndarray:
    slack = 0.5 * float(np.median(np.diff(t))) if t.size > 1 else 0.05
    if t[0] < t_src[0] - slack or t[-1] > t_src[-1] + slack:
        unit = ("; its times look like nanoseconds, expected seconds" if abs(t_src[0]) > 1e6 * max(abs(t[0]), 1.0)
                else "")
        raise DatasetError(f"{path}: covers {t_src[0]:.3f}-{t_src[-1]:.3f} s; expected it to cover the image times "
                           f"{t[0]:.3f}-{t[-1]:.3f} s{unit}")
    return np.stack([np.interp(t, t_src, values[:, i]) for i in range(values.shape[1])], axis=1)


def _open_kitti(drive: Path, pair: str) -> StereoSource:
    left_cam, right_cam = ("image_00", "image_01") if pair == "grey" else ("image_02", "image_03")
    ldir, rdir = drive / left_cam / "data", drive / right_cam / "data"
    for d in (ldir, rdir):  # before the calibration: a missing pair is the clearer message
        if not d.is_dir():
            raise DatasetError(f"{d}: missing; expected the {pair} pair's images ({left_cam}, {right_cam})")
    calib = read_kitti_calibration(drive.parent, pair)
    left, right = _images_in(ldir), _images_in(rdir)
    _check_counts(left, right, ldir, rdir)
    tl = parse_kitti_timestamps(drive / left_cam / "timestamps.txt")
    tr = parse_kitti_timestamps(drive / right_cam / "timestamps.txt")
    if tl.size != len(left):
        raise DatasetError(f"{drive / left_cam / 'timestamps.txt'}: has {tl.size} time stamps; expected one per "
                           f"image of {ldir} ({len(left)})")
    _check_pair_times(tl, tr, drive / left_cam / "timestamps.txt", drive / right_cam / "timestamps.txt")
    odir = drive / "oxts" / "data"
    if not odir.is_dir():
        raise DatasetError(f"{odir}: missing; expected the OXTS packets (one .txt per frame)")
    packets = sorted(p for p in odir.iterdir() if p.suffix == ".txt")
    if not packets:
        raise DatasetError(f"{odir}: holds no OXTS packets; expected one .txt per frame")
    to = parse_kitti_timestamps(drive / "oxts" / "timestamps.txt")
    if to.size != len(packets):
        raise DatasetError(f"{drive / 'oxts' / 'timestamps.txt'}: has {to.size} time stamps; expected one per packet "
                           f"of {odir} ({len(packets)})")
    rows = []
    for p in packets:
        values = _floats(_read_text(p, "an OXTS packet (30 numbers)"), p, "packet", 30)
        velocity = values[[8, 9, 10, 20, 21, 22]]  # vf vl vu, wf wl wu
        if np.any(np.abs(velocity) > MAX_IMU_SAMPLE):
            raise DatasetError(f"{p}: velocities (vf vl vu, wf wl wu) {velocity.tolist()} beyond "
                               f"±{MAX_IMU_SAMPLE:g}; expected m/s and rad/s (a corrupt packet)")
        rows.append(velocity)
    velocities = _interpolate(to, np.array(rows), tl, drive / "oxts" / "timestamps.txt")
    size = calib["image_size_px"]
    if size is None:  # no S_rect line: the first image's size
        from vislam.core.tracking import require_cv2

        first = _read_grey(require_cv2(), left[0])
        size = (first.shape[1], first.shape[0])
    return StereoSource(
        name=drive.name, root=drive, layout="kitti-raw", left_files=tuple(left), right_files=tuple(right),
        timestamps_s=tl, K=calib["K"], baseline_m=calib["baseline_m"], cam_T_imu=calib["cam_T_imu"],
        image_size_px=tuple(size), velocities=velocities,
        inputs=(*calib["files"], drive / left_cam / "timestamps.txt", drive / right_cam / "timestamps.txt",
                drive / "oxts" / "timestamps.txt", *packets),
        extra={"pair": pair})


# ----------------------------------------------------------------------------- EuRoC


def _read_yaml(path: Path, what: str):
    text = _read_text(path, what)
    lines = text.splitlines()
    if lines and lines[0].startswith("%YAML:"):  # OpenCV's directive, not YAML's
        lines = lines[1:]
    try:
        return yaml.safe_load("\n".join(lines))
    except (yaml.YAMLError, RecursionError, *YAML_VALUE_ERRORS) as exc:
        reason = "nested too deeply" if isinstance(exc, RecursionError) else " ".join(str(exc).split())
        raise DatasetError(f"{path}: invalid YAML ({reason}); expected {what}") from None


def _yaml_numbers(doc, path: Path, key: str, n: int) -> np.ndarray:
    if not isinstance(doc, dict):
        raise DatasetError(f"{path}: holds {type(doc).__name__} {doc!r:.40}, not a mapping; expected key '{key}' "
                           f"with {_numbers(n)}")
    if key not in doc:
        raise DatasetError(f"{path}: key '{key}' is missing; expected {_numbers(n)}")
    value = doc.get(key)
    if isinstance(value, dict) and "data" in value:
        value = value["data"]
    try:
        arr = None if _holds_bool(value) else np.array(value, dtype=np.float64).ravel()  # true is not 1.0
    except (TypeError, ValueError):
        arr = None
    if value is None or arr is None or arr.size != n or not np.all(np.isfinite(arr)):
        raise DatasetError(f"{path}: key '{key}' is {value!r:.60}; expected {_numbers(n)}")
    return arr


def _holds_bool(value) -> bool:
    """Whether a YAML value is or holds a boolean (``true`` would otherwise be read as 1.0)."""
    if isinstance(value, (bool, np.bool_)):
        return True
    return isinstance(value, (list, tuple)) and any(_holds_bool(v) for v in value)


def _euroc_camera(cam_dir: Path):
    yaml_path = cam_dir / "sensor.yaml"
    what = "an EuRoC camera sensor.yaml (intrinsics, distortion_coefficients, T_BS)"
    doc = _read_yaml(yaml_path, what)
    if not isinstance(doc, dict):
        raise DatasetError(f"{yaml_path}: holds {type(doc).__name__} {doc!r:.40}, not a mapping; expected {what}")
    model = doc.get("distortion_model", "radial-tangential")
    if model not in ("radial-tangential", "radtan"):
        raise DatasetError(f"{yaml_path}: key 'distortion_model' is {model!r}; expected radial-tangential")
    fu, fv, cu, cv = _yaml_numbers(doc, yaml_path, "intrinsics", 4)
    if not (fu > 0 and fv > 0):
        raise DatasetError(f"{yaml_path}: key 'intrinsics' has focal lengths fu = {fu:g}, fv = {fv:g} px; expected "
                           "[fu, fv, cu, cv] with fu, fv > 0")
    problem = intrinsics_problem(fu, fv, cu, cv)
    if problem:
        raise DatasetError(f"{yaml_path}: key 'intrinsics' {problem}")
    D = _yaml_numbers(doc, yaml_path, "distortion_coefficients", 4)
    resolution = _yaml_numbers(doc, yaml_path, "resolution", 2)
    if not np.all((resolution >= 1) & (resolution <= _MAX_IMAGE_SIDE_PX) & (resolution == np.round(resolution))):
        raise DatasetError(f"{yaml_path}: key 'resolution' is {resolution.tolist()}; expected [width, height] in "
                           f"whole pixels, 1 to {_MAX_IMAGE_SIDE_PX}")
    size = tuple(int(v) for v in resolution)
    if not (0 <= cu <= size[0] and 0 <= cv <= size[1]):  # a principal point off the sensor rectifies to nothing
        raise DatasetError(f"{yaml_path}: key 'intrinsics' has principal point (cu, cv) = ({cu:g}, {cv:g}) px; "
                           f"expected it inside the {size[0]}x{size[1]} px image (key 'resolution')")
    body_T_cam = _yaml_numbers(doc, yaml_path, "T_BS", 16).reshape(4, 4)
    if not is_rigid_transform(body_T_cam, tol=1e-5):
        raise DatasetError(f"{yaml_path}: key 'T_BS' is not a rigid transform; expected a 4x4 body_T_sensor")
    K = np.array([[fu, 0, cu], [0, fv, cv], [0, 0, 1.0]])
    csv_path = cam_dir / "data.csv"
    text = _read_text(csv_path, "an EuRoC data.csv (timestamp [ns],filename)")
    stamps, names = [], []
    for i, line in enumerate(text.splitlines()):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = [p.strip() for p in line.split(",")]
        if len(parts) != 2 or not _NS_STAMP.fullmatch(parts[0]) or int(parts[0]) > _INT64_MAX:
            raise DatasetError(f"{csv_path}: line {i + 1} ({line[:40]!r}) is not 'timestamp_ns,filename'; expected "
                               f"an integer time stamp in nanoseconds (at most 19 digits) and a file name")
        name = Path(parts[1])
        if not parts[1] or name.is_absolute() or ".." in name.parts:
            raise DatasetError(f"{csv_path}: line {i + 1} names file {parts[1]!r}; expected a file name inside "
                               f"{cam_dir / 'data'}")
        stamps.append(int(parts[0]))
        names.append(cam_dir / "data" / name)
    if not names:
        raise DatasetError(f"{csv_path}: lists no images; expected one 'timestamp_ns,filename' line per image")
    t = np.array(stamps, dtype=np.int64)
    _check_times(t.astype(float), csv_path)
    return K, D, size, body_T_cam, t, names, (yaml_path, csv_path)


#: A data.csv time stamp: nanoseconds as ASCII digits that fit an int64 (EuRoC's have 19).
_NS_STAMP = re.compile(r"[0-9]{1,19}")
_INT64_MAX = int(np.iinfo(np.int64).max)


def _euroc_pairs(mav0: Path, left, right, t0, t1):
    """Pair cam0's images with cam1's by time stamp (within 1 ms). Every cam0 image must
    exist and have a partner; cam1 rows without a cam0 partner (an excerpt's data.csv may
    list more) are ignored."""
    csv0, csv1 = mav0 / "cam0" / "data.csv", mav0 / "cam1" / "data.csv"
    present0 = np.array([p.is_file() for p in left])
    if not present0.any():
        raise DatasetError(f"{mav0 / 'cam0' / 'data'}: holds none of the images listed in {csv0}")
    # an excerpt may list images it does not hold: keep the run of frames whose files exist
    last = int(np.flatnonzero(present0)[-1])
    first = int(np.flatnonzero(present0)[0])
    if not present0[first:last + 1].all():
        k = first + int(np.argmin(present0[first:last + 1]))
        raise DatasetError(f"{left[k]}: missing; expected the image listed in {csv0}")
    notes = []
    if first > 0 or last < len(left) - 1:
        notes.append(f"{csv0}: lists {first + len(left) - 1 - last} images that are not in {mav0 / 'cam0' / 'data'} "
                     f"(before its first or after its last image); tracked the {last + 1 - first} frames present")
    left, t0 = left[first:last + 1], t0[first:last + 1]
    j = np.searchsorted(t1, t0)
    j = np.clip(j, 0, max(t1.size - 1, 0))
    jm = np.clip(j - 1, 0, max(t1.size - 1, 0))
    best = np.where(np.abs(t1[jm] - t0) < np.abs(t1[j] - t0), jm, j)
    bad = np.abs(t1[best] - t0) > 1_000_000
    if bad.any():
        k = int(np.argmax(bad))
        raise DatasetError(f"{csv1}: has no image within 1 ms of cam0's frame {k} (t = {t0[k]} ns in {csv0}); "
                           f"expected one right image per left image at the same time")
    right = [right[i] for i in best]
    for p in right:
        if not p.is_file():
            raise DatasetError(f"{p}: missing; expected the image listed in {csv1} (the partner of a cam0 image)")
    if len(set(best.tolist())) != best.size:
        raise DatasetError(f"{csv1}: pairs one right image with two left images; expected one per left image")
    return list(left), right, t0, notes


def read_velocity_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(t (n,), velocities (n, 6)) of a ``t,vx,vy,vz,wx,wy,wz`` CSV (one header line allowed)."""
    text = _read_text(Path(path), "a velocity CSV with columns t,vx,vy,vz,wx,wy,wz")
    rows = []
    for i, line in enumerate(text.splitlines()):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(";", ",").split(",")
        try:
            values = [float(p) for p in parts]
        except ValueError:
            if not rows and i == 0:
                continue  # header
            raise DatasetError(f"{path}: line {i + 1} ({line[:40]!r}) is not 7 numbers; expected t,vx,vy,vz,wx,wy,wz")
        if len(values) != 7:
            raise DatasetError(f"{path}: line {i + 1} has {len(values)} values; expected 7 finite numbers "
                               f"t,vx,vy,vz,wx,wy,wz")
        if not all(math.isfinite(v) for v in values):
            raise DatasetError(f"{path}: line {i + 1} ({line[:60]!r}) has a non-finite value; expected 7 finite "
                               f"numbers t,vx,vy,vz,wx,wy,wz")
        if any(abs(v) > MAX_IMU_SAMPLE for v in values[1:]):
            raise DatasetError(f"{path}: line {i + 1} ({line[:60]!r}) has a velocity beyond ±{MAX_IMU_SAMPLE:g}; "
                               f"expected m/s and rad/s (a corrupt sample, or another unit)")
        rows.append(values)
    if not rows:
        raise DatasetError(f"{path}: holds no rows; expected t,vx,vy,vz,wx,wy,wz lines")
    table = np.array(rows)
    _check_times(table[:, 0], Path(path))
    return table[:, 0], table[:, 1:]


def _open_euroc(mav0: Path, velocities_csv) -> StereoSource:
    from vislam.core.tracking import require_cv2

    cv2 = require_cv2()
    K0, D0, size0, body_T_cam0, t0, left, in0 = _euroc_camera(mav0 / "cam0")
    K1, D1, size1, body_T_cam1, t1, right, in1 = _euroc_camera(mav0 / "cam1")
    yaml0, yaml1 = in0[0], in1[0]
    if size0 != size1:
        raise DatasetError(f"{yaml0} gives resolution {size0}, {yaml1} {size1}; expected one resolution for both "
                           "cameras of the stereo pair")
    cam1_T_cam0 = se3_inverse(body_T_cam1) @ body_T_cam0
    gap = float(np.linalg.norm(cam1_T_cam0[:3, 3]))
    if not gap > 1e-6:
        raise DatasetError(f"{yaml0} and {yaml1}: key 'T_BS' puts both cameras at the same place ({gap:.2g} m "
                           "apart); expected a stereo pair with a baseline")
    left, right, t0, notes = _euroc_pairs(mav0, left, right, t0, t1)
    for path, yaml_path in ((left[0], yaml0), (right[0], yaml1)):  # before maps of sensor.yaml's size are made
        image = _read_grey(cv2, path, size0)
        if (image.shape[1], image.shape[0]) != size0:
            raise DatasetError(f"{path}: is {image.shape[1]}x{image.shape[0]} px; expected {size0[0]}x{size0[1]} px "
                               f"({yaml_path} key 'resolution')")
    try:
        R1, R2, P1, P2, _, _, _ = cv2.stereoRectify(K0, D0, K1, D1, size0, cam1_T_cam0[:3, :3].copy(),
                                                    cam1_T_cam0[:3, 3].reshape(3, 1).copy(),
                                                    flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
        maps = tuple(cv2.initUndistortRectifyMap(K, D, R, P[:, :3], size0, cv2.CV_32FC1)
                     for K, D, R, P in ((K0, D0, R1, P1), (K1, D1, R2, P2)))
    except cv2.error as exc:
        raise DatasetError(f"{yaml0} and {yaml1}: OpenCV cannot rectify this stereo pair "
                           f"({' '.join(str(exc).split())[-120:]}); expected the calibration of a stereo pair") from None
    K = P1[:, :3].copy()
    baseline = -P2[0, 3] / P2[0, 0]
    if abs(P2[1, 3]) > abs(P2[0, 3]):  # OpenCV rectifies a vertical pair along y: not a left-right pair
        raise DatasetError(f"{yaml0} and {yaml1}: key 'T_BS' puts cam1 above or below cam0; expected a horizontal "
                           f"stereo pair, cam1 to the right of cam0")
    if not baseline > 0:
        raise DatasetError(f"{yaml0} and {yaml1}: key 'T_BS' puts cam1 {abs(baseline):.3g} m to the left of cam0 "
                           f"(along the rectified x axis); expected cam0 = the left camera and cam1 = the right one "
                           f"(are the two sensor.yaml files swapped?)")
    for (mx, my), yaml_path in zip(maps, (yaml0, yaml1)):
        inside = float(np.mean((mx >= 0) & (mx <= size0[0] - 1) & (my >= 0) & (my <= size0[1] - 1)))
        if not inside >= 0.5:  # alpha 0 keeps only valid pixels: a real calibration gives ~100 %
            raise DatasetError(f"{yaml_path}: keys 'intrinsics' and 'distortion_coefficients' rectify to an image of "
                               f"which {100 * inside:.0f} % lies inside the {size0[0]}x{size0[1]} px sensor; expected "
                               f"this camera's pinhole intrinsics and radial-tangential distortion (k1 k2 p1 p2)")
    rect_T_cam0 = np.eye(4)
    rect_T_cam0[:3, :3] = R1
    cam_T_imu = rect_T_cam0 @ se3_inverse(body_T_cam0)
    t = t0 * 1e-9
    inputs = (*in0, *in1)
    if velocities_csv is not None:
        tv, v = read_velocity_csv(Path(velocities_csv))
        velocities = _interpolate(tv, v, t, Path(velocities_csv))
        note = ""
        inputs = (*inputs, Path(velocities_csv))
    else:
        velocities = None
        note = ("EuRoC's IMU gives accelerations, not the velocities the filters need; give a velocity CSV "
                "(t,vx,vy,vz,wx,wy,wz) with --velocities")
    return StereoSource(
        name=mav0.parent.name if mav0.name == "mav0" else mav0.name, root=mav0, layout="euroc",
        left_files=tuple(left), right_files=tuple(right), timestamps_s=t, K=K, baseline_m=float(baseline),
        cam_T_imu=cam_T_imu, image_size_px=size0, velocities=velocities, velocity_note=note, rectify_maps=maps,
        inputs=inputs, extra={"raw_size_px": size0, "cam1_T_cam0": cam1_T_cam0, "body_T_cam0": body_T_cam0,
                              "rect_R_cam0": R1, "notes": notes})


# ----------------------------------------------------------------------------- plain folder


def _yaml_matrix(doc, path: Path, key: str, shape) -> np.ndarray:
    n = int(np.prod(shape))
    return _yaml_numbers(doc, path, key, n).reshape(shape)


def _open_folder(root: Path, velocities_csv) -> StereoSource:
    ldir, rdir = root / "left", root / "right"
    left, right = _images_in(ldir), _images_in(rdir)
    _check_counts(left, right, ldir, rdir)
    cal = root / "calibration.yaml"
    if not cal.is_file() and (root / "calibration.yml").is_file():
        cal = root / "calibration.yml"
    doc = _read_yaml(cal, "a calibration YAML with K (3x3), baseline (m) and cam_T_imu (4x4)")
    if not isinstance(doc, dict):
        raise DatasetError(f"{cal}: is not a mapping; expected keys K, baseline, cam_T_imu")
    K = _yaml_matrix(doc, cal, "K", (3, 3))
    if not (K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], [0, 0, 1]) and K[1, 0] == 0 and K[0, 1] == 0):
        raise DatasetError(f"{cal}: key 'K' is {K.tolist()}; expected [[fx,0,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0")
    problem = intrinsics_problem(K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    if problem:
        raise DatasetError(f"{cal}: key 'K' {problem}")
    baseline = float(_yaml_numbers(doc, cal, "baseline", 1)[0])
    if not baseline > 0:
        raise DatasetError(f"{cal}: key 'baseline' is {baseline}; expected a positive baseline in metres")
    cam_T_imu = _yaml_matrix(doc, cal, "cam_T_imu", (4, 4))
    if not is_rigid_transform(cam_T_imu, tol=1e-5):
        raise DatasetError(f"{cal}: key 'cam_T_imu' is not a rigid transform; expected a 4x4 [R t; 0 0 0 1]")
    vel_path = Path(velocities_csv) if velocities_csv is not None else root / "velocities.csv"
    tv, v = read_velocity_csv(vel_path)
    if velocities_csv is None:
        if tv.size != len(left):
            raise DatasetError(f"{vel_path}: has {tv.size} rows; expected one per image pair ({len(left)})")
        t, velocities = tv, v
    else:
        raise DatasetError(f"{vel_path}: --velocities is for EuRoC folders; a plain folder's velocities.csv gives "
                           f"one row per pair")
    from vislam.core.tracking import require_cv2

    first = _read_grey(require_cv2(), left[0])
    return StereoSource(
        name=root.name, root=root, layout="folder", left_files=tuple(left), right_files=tuple(right),
        timestamps_s=t, K=K, baseline_m=baseline, cam_T_imu=cam_T_imu,
        image_size_px=(first.shape[1], first.shape[0]), velocities=velocities, inputs=(cal, vel_path))


# ----------------------------------------------------------------------------- dispatch


def _layout_of(root: Path) -> tuple[str, Path] | None:
    if (root / "image_00").is_dir() or (root / "image_02").is_dir() or (root / "oxts").is_dir():
        return "kitti-raw", root
    if (root / "mav0" / "cam0").is_dir():
        return "euroc", root / "mav0"
    if root.name == "mav0" and (root / "cam0").is_dir():
        return "euroc", root
    if (root / "left").is_dir() and (root / "right").is_dir():
        return "folder", root
    return None


def image_layout_of(path) -> str | None:
    """The layout (one of :data:`LAYOUTS`) a folder matches, or None."""
    path = Path(path)
    if not path.is_dir():
        return None
    found = _layout_of(path)
    return None if found is None else found[0]


def is_image_folder(path) -> bool:
    """True when ``path`` is a directory (every image layout is a folder; npz files are not)."""
    return Path(path).is_dir()


def open_stereo_source(path, pair: str = "grey", velocities=None) -> StereoSource:
    """The :class:`StereoSource` of an image folder, its layout chosen from what it holds.

    ``pair``: KITTI only, ``"grey"`` (00/01, default) or ``"colour"`` (02/03).
    ``velocities``: a ``t,vx,vy,vz,wx,wy,wz`` CSV interpolated at the image times (EuRoC).
    """
    root = Path(path)
    if not root.exists():
        raise DatasetError(f"{root}: no such file or folder")
    if not root.is_dir():
        raise DatasetError(f"{root}: is not a folder; {_LAYOUT_HELP}")
    found = _layout_of(root)
    if found is None:
        raise DatasetError(f"{root}: matches no image layout; {_LAYOUT_HELP}")
    layout, where = found
    if layout != "kitti-raw" and pair != "grey":
        raise DatasetError(f"{root}: is an {layout} folder; the colour pair exists only in KITTI raw drives")
    if layout == "kitti-raw":
        if velocities is not None:
            raise DatasetError(f"{velocities}: --velocities is for EuRoC folders; a KITTI drive has its OXTS packets")
        source = _open_kitti(root, pair)
    elif layout == "euroc":
        source = _open_euroc(where, velocities)
    else:
        source = _open_folder(root, velocities)
    t = np.asarray(source.cam_T_imu)[:3, 3]
    if np.abs(t).max() > MAX_LEVER_ARM_M:  # 1e300 m overflowed every projection
        calib = ", ".join(str(p) for p in source.inputs if Path(p).suffix in (".txt", ".yaml", ".yml")
                          and "timestamps" not in Path(p).name)
        raise DatasetError(f"{calib or root}: the IMU-camera translation is {t.tolist()} m; expected a lever arm "
                           f"within ±{MAX_LEVER_ARM_M:g} m")
    return source


# ----------------------------------------------------------------------------- tracking


def track_source(source: StereoSource, options=None, progress=None):
    """Track every pair of ``source``; returns ``(Sequence, statistics dict)``.

    ``progress``: optional callable(n_done) after each frame. Only one image pair (and
    the tracker's previous frame) is in memory at a time; the observations are kept
    sparse. Velocities the source does not have are NaN (see the module docstring).

    A recording that cannot give a single track is refused (DatasetError): fewer pairs
    than ``min_track_length``, or images smaller than the detector's border and block
    (:meth:`~vislam.core.tracking.TrackerOptions.min_image_size_px`). One that gives few
    tracks is tracked, with warnings in the statistics (``"warnings"``): few tracks per
    frame, depths outside the filter's guards, a pair that matches far better with left
    and right exchanged (:func:`swapped_pair_warnings`), frames the layout skipped.
    """
    from vislam.core.tracking import StereoTracker, TrackerOptions, finish_tracks

    options = options or TrackerOptions()
    if source.n_frames < options.min_track_length:
        raise DatasetError(f"{_frame_listing(source)}: holds {source.n_frames} image pair"
                           f"{'s' if source.n_frames != 1 else ''}; expected at least {options.min_track_length} "
                           f"(min_track_length: tracks seen in fewer frames are left out, so none could be written)")
    tracker = StereoTracker(source.K, source.baseline_m, options)
    frames = []
    swap_warnings = []
    for t in range(source.n_frames):
        left, right = source.read_pair(t)
        if t == 0:
            _check_image_size(source, left, options)
        frames.append(tracker.process(left, right))
        if t == 0:
            swap_warnings = swapped_pair_warnings(source, frames[0][0].size, options)
        if progress is not None:
            progress(t + 1)
    observations = finish_tracks(frames, options.min_track_length)
    T = source.n_frames
    vel = source.velocities if source.velocities is not None else np.full((T, 6), np.nan)
    sequence = Sequence(
        name=source.name, timestamps_s=source.timestamps_s, linear_velocity_in_imu_mps=vel[:, :3],
        angular_velocity_in_imu_radps=vel[:, 3:], observations=observations,
        camera=StereoCamera(source.K, source.baseline_m,
                            image_size_px=tuple(int(v) for v in source.image_size_px)),
        cam_T_imu=source.cam_T_imu, source=str(source.root))
    stats = tracker.stats.to_dict(observations.track_lengths())
    stats["tracks_per_frame_output"] = _count_stats(observations.counts_per_frame())
    stats["layout"] = source.layout
    stats["source"] = str(source.root)
    stats["velocities"] = "given" if source.velocities is not None else f"missing (NaN): {source.velocity_note}"
    stats["options"] = options.to_dict()
    stats["warnings"] = (list(source.extra.get("notes", ())) + swap_warnings + tracking_warnings(stats)
                         + stereo_depth_warnings(sequence))
    for warning in stats["warnings"]:
        logger.info("%s: %s", source.root, warning)  # the commands print it as a warning
    return sequence, stats


def _frame_listing(source: StereoSource) -> Path:
    """The file or folder that lists a recording's frames (for messages)."""
    if source.layout == "euroc":
        return Path(source.root) / "cam0" / "data.csv"
    return Path(source.left_files[0]).parent


def _check_image_size(source: StereoSource, left: np.ndarray, options) -> None:
    width, height = options.min_image_size_px()
    if left.shape[1] < width or left.shape[0] < height:
        raise DatasetError(f"{source.left_files[0]}: is {left.shape[1]}x{left.shape[0]} px; expected at least "
                           f"{width}x{height} px (the tracker detects corners border_px = {options.border_px} px "
                           f"from the border, in blocks of {max(options.block_size_px, 2 * options.affine_radius_px + 1)}"
                           f" px)")


#: A first frame that gives this many times more stereo matches (and at least
#: MIN_MEAN_TRACKS_PER_FRAME) with its left and right images exchanged is a warning.
SWAPPED_MATCH_FACTOR = 3.0


def swapped_pair_warnings(source: StereoSource, n_given: int, options) -> list[str]:
    """A warning when frame 0's pair matches far better with left and right exchanged.

    In a rectified pair a point lies further left in the right image (disparity uL - uR >
    0); with the folders (or cameras) swapped every disparity is negative and only chance
    matches pass, so the tracks are few and wrong. ``n_given``: the stereo matches of the
    frame as given; the pair is read and tracked once more with the files exchanged (each
    rectified as the other camera; one frame: a few tens of milliseconds)."""
    from vislam.core.tracking import StereoTracker

    left, right = source.read_pair(0, exchanged=True)
    n_swapped = StereoTracker(source.K, source.baseline_m, options).process(left, right)[0].size
    if n_swapped >= max(SWAPPED_MATCH_FACTOR * n_given, MIN_MEAN_TRACKS_PER_FRAME):
        return [(f"{source.left_files[0]} and {source.right_files[0]}: {n_swapped} stereo matches with left and "
                 f"right exchanged, {n_given} as given: are the left and right images swapped "
                 f"({Path(source.left_files[0]).parent} should hold the left camera's images)? The tracks are few "
                 f"and wrong")]
    return []


#: Fewer tracked landmarks per frame on average than this is a warning: a stereo pair of a
#: textured scene gives tens to hundreds; the SLAM update needs a few every frame.
MIN_MEAN_TRACKS_PER_FRAME = 10.0


def tracking_warnings(stats: dict) -> list[str]:
    """One line per thing a user must know about the tracks before filtering them."""
    tpf = stats["tracks_per_frame_output"]
    if stats["frames"] and tpf["mean"] < MIN_MEAN_TRACKS_PER_FRAME:
        return [f"only {tpf['mean']:.1f} tracked landmarks per frame on average (min {tpf['min']}, max "
                f"{tpf['max']}; expected at least {MIN_MEAN_TRACKS_PER_FRAME:g}): are the images blank, dark or "
                f"blurred, or not a rectified stereo pair (a point on the same row in both)? The filters will be "
                f"close to dead reckoning"]
    return []


def stereo_depth_warnings(sequence: Sequence) -> list[str]:
    """``vislam check``'s stereo-depth finding on the tracks, when it is not OK: a baseline
    in another unit (millimetres in calibration.yaml) puts every triangulated point outside
    the filter's default depth guards, and no landmark would ever start."""
    from vislam.core.check import CheckOptions, stereo_depth_finding, stereo_depths
    from vislam.core.options import FilterOptions

    pixels = sequence.observations.pixels
    finding = stereo_depth_finding(stereo_depths(sequence.camera, pixels[:, 0] - pixels[:, 2], FilterOptions()),
                                   CheckOptions())
    return [] if finding.severity == "OK" else [finding.message]


def _count_stats(counts: np.ndarray) -> dict:
    counts = np.asarray(counts, dtype=float)
    return {"mean": float(counts.mean()) if counts.size else 0.0, "min": int(counts.min()) if counts.size else 0,
            "max": int(counts.max()) if counts.size else 0}


def stats_path_for(out) -> Path:
    """The statistics JSON written beside a tracked file: ``FILE.npz`` -> ``FILE.tracking.json``."""
    out = Path(out)
    return out.with_name(out.stem + ".tracking.json")


def write_tracks(sequence: Sequence, stats: dict, out) -> list[Path]:
    """Write the tracked recording (npz, report convention) and its statistics JSON beside it,
    each atomically; the JSON is written last (its presence means both are complete)."""
    from vislam.tools.atomic import write_text_atomic
    from vislam.tools.dataset_io import save_sequence

    out = Path(out)
    save_sequence(sequence, out)
    stats_path = stats_path_for(out)
    write_text_atomic(stats_path, json.dumps(stats, indent=2, sort_keys=True) + "\n")
    return [out, stats_path]


# ----------------------------------------------------------------------------- folders as command input

#: Names of the cached tracked recording (and its statistics) in a command's output directory.
CACHE_NAME = "tracks.npz"


def _cache_key(source: StereoSource, options) -> str:
    h = hashlib.sha256()
    h.update(source.fingerprint().encode())
    h.update(json.dumps(options.to_dict(), sort_keys=True).encode())
    h.update(json.dumps({"layout": source.layout, "extra": source.extra.get("pair", "")}).encode())
    from vislam import __version__

    h.update(__version__.encode())
    return h.hexdigest()


def load_recording(data, cache_dir=None, *, pair: str = "grey", velocities=None, tracker_options=None,
                   progress_factory=None, need_velocities: bool = True):
    """The :class:`Sequence` of ``data``: a dataset npz, or an image folder tracked first.

    For a folder, the tracked recording is cached as ``cache_dir/tracks.npz`` (with its
    statistics and the cache key in ``tracks.tracking.json``) and reused while the
    images, calibration, velocities and tracker options are unchanged (``cache_dir``
    None: no cache). ``need_velocities``: refuse a folder without velocities (EuRoC
    without ``velocities``) before tracking. ``progress_factory(total, desc)`` gives
    ``(callback, close)``. Returns ``(sequence, info)``; info is None for an npz, else a
    dict (source, layout, cache path, whether the cache was reused, the statistics).
    """
    from vislam.core.tracking import TrackerOptions
    from vislam.tools.dataset_io import load_sequence

    data = Path(data)
    if not data.is_dir():
        return load_sequence(data), None
    options = tracker_options or TrackerOptions()
    source = open_stereo_source(data, pair=pair, velocities=velocities)
    if need_velocities and source.velocities is None:
        raise DatasetError(f"{data}: has no IMU velocities for the filter: {source.velocity_note}")
    key = _cache_key(source, options)
    info = {"source": str(data.resolve()), "layout": source.layout, "cache": None, "cache_reused": False}
    if cache_dir is not None:
        cache = Path(cache_dir) / CACHE_NAME
        stats_file = stats_path_for(cache)
        info["cache"] = str(cache)
        if cache.is_file() and stats_file.is_file():
            try:
                old = json.loads(stats_file.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                old = {}
            if isinstance(old, dict) and old.get("cache_key") == key:
                try:
                    sequence = load_sequence(cache, name=source.name)
                except DatasetError:
                    sequence = None
                if sequence is not None:
                    logger.info("%s: reusing the tracks cached in %s", data, cache)
                    info.update(cache_reused=True, statistics=old)
                    return sequence.replace(source=str(data)), info
    progress, close = (progress_factory(source.n_frames, "track") if progress_factory else (None, lambda: None))
    try:
        sequence, stats = track_source(source, options, progress=progress)
    finally:
        close()
    stats["cache_key"] = key
    if cache_dir is not None:
        write_tracks(sequence, stats, Path(cache_dir) / CACHE_NAME)
    info["statistics"] = stats
    return sequence, info
