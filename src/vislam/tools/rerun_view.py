"""A 3D view of a run in the Rerun viewer (``rerun-sdk``, the optional extra ``vislam[viewer]``).

Usage::

    vislam run DATA --mode slam --out DIR --rerun run.rrd    # record the run, then: rerun run.rrd
    vislam run DATA --mode slam --out DIR --rerun-spawn      # stream it to a live viewer

    from vislam.tools.rerun_view import RerunRecorder
    with RerunRecorder(sequence.camera, sequence.cam_T_imu, path="run.rrd") as rec:
        rec.log_result(result, sequence)        # a finished run, frame by frame
    # or, from a filter loop, one call per frame:
    #     rec.log_frame(t, timestamp_s, world_T_imu, pose_covariance, live_ids, live_p_lm_in_world,
    #                   frozen_ids, frozen_p_lm_in_world, frozen_rejected, stats={"name": value})

Open the file with ``rerun run.rrd`` (the viewer ships with ``rerun-sdk``) and scrub
through the ``frame`` or ``time`` timeline.

What is recorded (entity paths; the world frame is the first IMU pose, x forward,
y left, z up, so the view is ``RIGHT_HAND_Z_UP``):

* ``world/imu`` — the IMU pose world_T_imu (Transform3D, with axes), per frame;
* ``world/imu/camera`` — the left camera (static cam-from-IMU transform) with a Pinhole
  frustum from K; the image size is the camera's, else 2·cu x 2·cv;
* ``world/trajectory/<k>`` — the trajectory so far as line strips;
* ``world/position_covariance`` — the 3σ ellipsoid of the IMU position in the world
  frame, R_wi Σ[:3, :3] R_wiᵀ (Σ: the filter's left perturbation of imu_T_world in the
  (v, ω) order, see :meth:`vislam.core.results.RunResult.position_covariance_in_world`);
* ``world/landmarks/live`` — the landmarks in the state at this frame (cyan), with their
  dataset ids as the ``landmark_id`` component;
* ``world/landmarks/map/<k>`` — the frozen (marginalized) map: green, rejected red;
* ``height/imu_z_m`` — the IMU height over the first pose, and ``stats/<name>`` — the
  per-frame statistics, as time series.

Rerun stores positions as float32 (about 1e-7 relative: sub-millimetre over the
kilometres of a drive). ``log_result`` also records the statistics ``frame_ms``,
``live_landmarks`` and ``position_sigma_m`` (√trace of the world position covariance),
plus every per-frame array of ``result.frame_stats`` when the result has one.

Layout (sent with the recording): a "3D" view and a "top view" (tabs), the IMU height
and one plot per statistic given at the first frame.

Timelines: ``frame`` (sequence = frame index) and ``time`` — an absolute timestamp when
the first frame's time looks like UNIX seconds (≥ 1e8, the datasets'), else a duration
in seconds.

File size: the trajectory and the frozen map grow with the run, and Rerun shows the
latest value of an entity at the current time, so they are split into blocks (entities
``<k>``) of at most :data:`BLOCK_POINTS` points. Each frame re-logs only its block's
points so far: the file grows like frames x block size, not frames², and scrubbing back
in time still shows exactly the map of that time.

Atomicity: the recording goes to a temporary file next to ``path``; :meth:`RerunRecorder.close`
renames it onto ``path``, :meth:`RerunRecorder.abort` (or leaving the ``with`` block by
an exception) deletes it. An interrupted run leaves no half file.

Live viewer (``spawn=True``): if there is no display (Linux without ``DISPLAY`` or
``WAYLAND_DISPLAY``) or the viewer cannot be started, a warning is logged and the
recorder goes on (recording to ``path`` if one is given): a missing viewer never costs
the recording or the run. With no file and no viewer the recorder is disabled
(``enabled`` is False) and logs nothing.

``rerun`` is imported when a recorder is created, not when this module is imported; a
missing ``rerun-sdk`` raises :class:`~vislam.errors.ConfigError`.
"""

from __future__ import annotations

import logging
import os
import shutil
import sys
import uuid
from pathlib import Path
from typing import Mapping

import numpy as np

from vislam.core.lie import quaternion_from_rotation
from vislam.errors import ConfigError, OutputError

__all__ = ["RerunRecorder", "import_rerun", "BLOCK_POINTS", "SIGMA_SCALE", "VIEWER_PORT"]

logger = logging.getLogger(__name__)

#: Largest number of points of one trajectory/map block entity (see the module docstring).
BLOCK_POINTS = 400
#: The covariance ellipsoid is drawn at this many standard deviations.
SIGMA_SCALE = 3.0
#: Port of a spawned viewer (Rerun's default).
VIEWER_PORT = 9876
#: Timestamps from this value on are taken for UNIX seconds (1973-03-03).
_UNIX_TIME_MIN_S = 1e8

_LIVE_COLOR = (0, 190, 255)
_MAP_COLOR = (40, 200, 60)
_REJECTED_COLOR = (230, 30, 30)
_TRAJECTORY_COLOR = (255, 140, 0)
_COVARIANCE_COLOR = (255, 220, 0)
_FRUSTUM_COLOR = (220, 220, 220)

_INSTALL_HINT = "install the viewer extra: pip install 'vislam[viewer]'"


def import_rerun():
    """The ``rerun`` module, or a ConfigError telling how to install it."""
    try:
        import rerun
    except ImportError as exc:
        raise ConfigError(f"the Rerun viewer needs the rerun-sdk package ({exc}); {_INSTALL_HINT}") from None
    return rerun


class _Blocks:
    """Points that only accumulate (trajectory, frozen map), split into blocks of at most
    ``capacity`` points. :meth:`add` returns (block index, all points of the current
    block so far, their attributes, whether the block is new): what is logged at this frame."""

    def __init__(self, capacity: int, overlap: int = 0):
        self.capacity = capacity
        self.overlap = overlap  # points carried into a new block (1 keeps a line strip connected)
        self.index = -1
        self.points = np.zeros((0, 3))
        self.attrs: dict[str, np.ndarray] = {}

    def add(self, points: np.ndarray, **attrs: np.ndarray) -> tuple[int, np.ndarray, dict[str, np.ndarray], bool]:
        new = self.index < 0 or len(self.points) + len(points) > self.capacity and len(self.points) > self.overlap
        if new:
            keep = self.overlap if self.index >= 0 else 0
            self.index += 1
            self.points = self.points[len(self.points) - keep:]
            self.attrs = {k: v[len(v) - keep:] for k, v in self.attrs.items()}
        self.points = np.concatenate([self.points, points])
        for k, v in attrs.items():
            self.attrs[k] = np.concatenate([self.attrs[k], v]) if k in self.attrs else np.asarray(v)
        return self.index, self.points, self.attrs, new


def _has_display() -> bool:
    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY") or os.environ.get("WAYLAND_SOCKET"))


def _viewer_executable() -> str | None:
    """The ``rerun`` viewer next to this Python (a venv's bin/) or on PATH."""
    local = Path(sys.executable).parent / "rerun"
    if local.is_file() and os.access(local, os.X_OK):
        return str(local)
    return shutil.which("rerun")


def _ellipsoid(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(half sizes at SIGMA_SCALE σ, rotation quaternion xyzw) of a 3x3 covariance: the
    ellipsoid's axes are the eigenvectors, its half sizes SIGMA_SCALE √eigenvalues."""
    cov = 0.5 * (cov + cov.T)
    eigval, eigvec = np.linalg.eigh(cov)
    if np.linalg.det(eigvec) < 0:
        eigvec[:, 0] = -eigvec[:, 0]
    half = SIGMA_SCALE * np.sqrt(np.clip(eigval, 0.0, None))
    return half, quaternion_from_rotation(eigvec)


def _check_array(name: str, a, shape: tuple) -> np.ndarray:
    """``a`` as float64, checked against ``shape`` (None: any length)."""
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)):
        raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")
    return a


class RerunRecorder:
    """Record a run for the Rerun viewer, frame by frame (see the module docstring).

    Args:
        camera: the stereo camera (its K gives the frustum).
        cam_T_imu: (4, 4) maps IMU coordinates into the left camera frame.
        path: the .rrd file to write (atomically, on :meth:`close`), or None.
        spawn: also stream to a live viewer (skipped with a warning when there is none).
        application_id, recording_name: shown by the viewer.

    Raises ConfigError when rerun-sdk is missing, OutputError when ``path`` cannot be
    written (before anything is recorded).
    """

    def __init__(self, camera, cam_T_imu, *, path: str | Path | None = None, spawn: bool = False,
                 application_id: str = "vislam", recording_name: str = ""):
        rr = import_rerun()
        self._rr = rr
        self.path = Path(path) if path is not None else None
        self.spawned = False
        self.enabled = False
        self._closed = False
        self._atomic = None
        cam_T_imu = _check_array("cam_T_imu", cam_T_imu, (4, 4))
        self._trajectory = _Blocks(BLOCK_POINTS, overlap=1)
        self._map = _Blocks(BLOCK_POINTS)
        self._time_kind: str | None = None
        self._blueprint_sent = False
        #: (centre, half width) of the xy region the top view shows; set by log_result
        self._top_view: tuple[np.ndarray, float] | None = None
        self.frames_logged = 0
        self._rec = rr.RecordingStream(application_id, recording_id=uuid.uuid4())
        rr.set_log_time_enabled(False, recording=self._rec)  # the frame and time timelines only
        try:
            sinks = []
            if self.path is not None:
                from vislam.tools.atomic import atomic_path

                if self.path.is_dir():
                    raise OutputError(f"{self.path}: is a directory (a .rrd file path is expected)")
                self._atomic = atomic_path(self.path)
                sinks.append(rr.FileSink(str(self._atomic.__enter__())))  # the temporary file
            if spawn:
                url = self._spawn_viewer()
                if url is not None:
                    sinks.append(rr.GrpcSink(url))
            #: False when there is nowhere to record to (no path, no viewer): then nothing is logged,
            #: rather than buffered in memory for nobody
            self.enabled = bool(sinks)
            if not self.enabled:
                return
            self._rec.set_sinks(*sinks)
            if recording_name:
                self._rec.send_recording_name(recording_name)
            self._log_static(camera, cam_T_imu)
        except BaseException:
            self.abort()
            raise

    # ------------------------------------------------------------------ setup

    def _spawn_viewer(self) -> str | None:
        """Start a viewer (or reuse one on VIEWER_PORT); its gRPC URL, or None with a warning."""
        if not _has_display():
            logger.warning("rerun: no display (DISPLAY/WAYLAND_DISPLAY unset): not opening a live viewer")
            return None
        executable = _viewer_executable()
        if executable is None:
            logger.warning("rerun: no 'rerun' viewer executable found: not opening a live viewer")
            return None
        try:
            self._rr.spawn(port=VIEWER_PORT, connect=False, executable_path=executable)
        except Exception as exc:  # the SDK raises RuntimeError and friends
            logger.warning("rerun: cannot start the viewer (%s): not opening a live viewer", str(exc).splitlines()[0])
            return None
        self.spawned = True
        return f"rerun+http://127.0.0.1:{VIEWER_PORT}/proxy"

    def _send_blueprint(self, stat_names) -> None:
        """The layout: a 3D view and a top view (tabs) of the world, the IMU height and one
        plot per statistic known at the first frame (later ones are in the recording, without a plot)."""
        import rerun.blueprint as rrb

        centre, half_width = self._top_view or (np.zeros(3), 150.0)
        eye = np.array([centre[0], centre[1], centre[2] + 2.5 * half_width])
        eye_controls = rrb.EyeControls3D(position=eye, look_target=centre, eye_up=(1.0, 0.0, 0.0))  # x up on screen
        top = rrb.Spatial3DView(origin="world", name="top view", eye_controls=eye_controls)
        plots = [rrb.TimeSeriesView(origin="height", name="IMU height (m)")]
        plots += [rrb.TimeSeriesView(origin=f"stats/{name}", name=name) for name in stat_names]
        blueprint = rrb.Blueprint(
            rrb.Horizontal(
                rrb.Tabs(rrb.Spatial3DView(origin="world", name="3D"), top, active_tab=0),
                rrb.Vertical(*plots),
                column_shares=[3, 1],
            ),
            collapse_panels=False,
        )
        self._rec.send_blueprint(blueprint, make_active=True, make_default=True)
        self._blueprint_sent = True

    def _log_static(self, camera, cam_T_imu: np.ndarray) -> None:
        rr = self._rr
        rec = self._rec
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log("world/imu", rr.TransformAxes3D(1.5), static=True)
        imu_T_cam = np.linalg.inv(cam_T_imu)
        rec.log("world/imu/camera", rr.Transform3D(translation=imu_T_cam[:3, 3], mat3x3=imu_T_cam[:3, :3]),
                static=True)
        size = camera.image_size_px or (2.0 * camera.cu, 2.0 * camera.cv)
        rec.log("world/imu/camera", rr.Pinhole(image_from_camera=np.asarray(camera.K), resolution=list(size),
                                               camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=2.0,
                                               color=_FRUSTUM_COLOR), static=True)
        rec.log("world/position_covariance", rr.Ellipsoids3D.from_fields(colors=[_COVARIANCE_COLOR],
                                                                         fill_mode="MajorWireframe"), static=True)
        rec.log("world/landmarks/live", rr.Points3D.from_fields(colors=[_LIVE_COLOR],
                                                                radii=rr.Radius.ui_points(3.0)), static=True)

    # ------------------------------------------------------------------ frames

    def _set_time(self, t: int, timestamp_s: float) -> None:
        self._rec.set_time("frame", sequence=int(t))
        if self._time_kind is None:
            self._time_kind = "timestamp" if timestamp_s >= _UNIX_TIME_MIN_S else "duration"
        self._rec.set_time("time", **{self._time_kind: float(timestamp_s)})

    def log_frame(self, t: int, timestamp_s: float, world_T_imu, pose_covariance, live_ids, live_p_lm_in_world,
                  frozen_ids=None, frozen_p_lm_in_world=None, frozen_rejected=None,
                  stats: Mapping[str, float] | None = None) -> None:
        """Record frame ``t``.

        Args:
            t, timestamp_s: frame index and time (s).
            world_T_imu: (4, 4) IMU pose.
            pose_covariance: (6, 6) covariance of the left perturbation of imu_T_world,
                (v, ω) order, or None (no ellipsoid).
            live_ids, live_p_lm_in_world: (k,) ids and (k, 3) positions of the landmarks
                in the state now (all of them, every frame).
            frozen_ids, frozen_p_lm_in_world, frozen_rejected: (n,), (n, 3), (n,) bool —
                the landmarks frozen into the map at this frame only (they stay visible).
            stats: scalars logged as ``stats/<name>``.
        """
        if self._closed:
            raise RuntimeError("RerunRecorder used after close()")
        self.frames_logged += 1
        if not self.enabled:
            return
        rr, rec = self._rr, self._rec
        pose = _check_array("world_T_imu", world_T_imu, (4, 4))
        if not self._blueprint_sent:
            self._send_blueprint(list(stats or ()))
        self._set_time(t, timestamp_s)
        R, p = pose[:3, :3], pose[:3, 3]
        rec.log("world/imu", rr.Transform3D.from_fields(translation=p, mat3x3=R))  # 3x faster than Transform3D()
        rec.log("height/imu_z_m", rr.Scalars(float(p[2])))

        k, strip, _, new = self._trajectory.add(p[None, :])
        if new:  # the static look of a new block
            rec.log(f"world/trajectory/{k}", rr.LineStrips3D.from_fields(colors=[_TRAJECTORY_COLOR],
                                                                         radii=rr.Radius.ui_points(1.5)), static=True)
        rec.log(f"world/trajectory/{k}", rr.LineStrips3D([strip]))
        if pose_covariance is not None:
            cov = _check_array("pose_covariance", pose_covariance, (6, 6))
            half, quat = _ellipsoid(R @ cov[:3, :3] @ R.T)
            rec.log("world/position_covariance", rr.Ellipsoids3D(centers=[p], half_sizes=[half], quaternions=[quat]))

        live_p = _check_array("live_p_lm_in_world", live_p_lm_in_world, (None, 3)).reshape(-1, 3)
        live_ids = np.asarray(live_ids, dtype=np.int64).reshape(-1)
        if live_ids.shape[0] != live_p.shape[0]:
            raise ValueError(f"live_ids ({live_ids.shape[0]}) and live_p_lm_in_world ({live_p.shape[0]}) differ")
        rec.log("world/landmarks/live", rr.Points3D(live_p), rr.AnyValues(landmark_id=live_ids))

        if frozen_p_lm_in_world is not None and len(frozen_p_lm_in_world):
            fp = _check_array("frozen_p_lm_in_world", frozen_p_lm_in_world, (None, 3))
            n = fp.shape[0]
            fid = np.asarray(frozen_ids if frozen_ids is not None else np.full(n, -1), dtype=np.int64).reshape(-1)
            rej = np.asarray(frozen_rejected if frozen_rejected is not None else np.zeros(n, bool), bool).reshape(-1)
            if fid.shape[0] != n or rej.shape[0] != n:
                raise ValueError("frozen_ids, frozen_p_lm_in_world and frozen_rejected differ in length")
            colors = np.where(rej[:, None], np.array(_REJECTED_COLOR), np.array(_MAP_COLOR)).astype(np.uint8)
            k, points, attrs, new = self._map.add(fp, ids=fid, colors=colors)
            if new:  # the static look of a new block
                rec.log(f"world/landmarks/map/{k}", rr.Points3D.from_fields(radii=rr.Radius.ui_points(2.5)),
                        static=True)
            rec.log(f"world/landmarks/map/{k}", rr.Points3D(points, colors=attrs["colors"]),
                    rr.AnyValues(landmark_id=attrs["ids"]))

        for name, value in (stats or {}).items():
            rec.log(f"stats/{name}", rr.Scalars(float(value)))

    def log_result(self, result, sequence=None) -> None:
        """Record a finished run (:class:`~vislam.core.results.RunResult`) frame by frame.

        At frame t the live landmarks are the map entries with first_frame ≤ t ≤
        last_frame (at their final estimates); an entry is frozen into the map at
        last_frame + 1. Per-frame stats: ``frame_ms`` (result.stats.frame_seconds),
        ``live_landmarks``, ``position_sigma_m`` (√trace of the world position
        covariance) and every array of ``result.frame_stats`` if the result has one.
        ``sequence`` is accepted for the callers' convenience and not needed.
        """
        if not self.enabled:
            return
        n = int(result.world_T_imu.shape[0])
        timestamps = np.asarray(result.timestamps_s)[:n]
        if n and not self._blueprint_sent:
            positions = result.world_T_imu[:, :3, 3]
            lo, hi = positions.min(axis=0), positions.max(axis=0)
            self._top_view = (0.5 * (lo + hi), max(0.5 * float(np.max(hi[:2] - lo[:2])), 10.0))
        cov = result.pose_covariance
        frame_ms = np.asarray(result.stats.frame_seconds, dtype=np.float64) * 1e3
        extra_stats: dict[str, np.ndarray] = {}
        for name, values in (getattr(result, "frame_stats", None) or {}).items():
            values = np.asarray(values, dtype=np.float64).reshape(-1)
            if str(name) in ("frame", "live_landmarks"):
                continue  # the frame is the timeline; live_landmarks is logged from the map above
            if values.shape[0] >= n:
                extra_stats[str(name)] = values
            else:
                logger.warning("rerun: frame_stats[%r] has %d values for %d frames: not recorded", name,
                               values.shape[0], n)
        lm = result.landmarks
        if lm is not None and len(lm):
            first = np.asarray(lm.first_frame)
            last = np.asarray(lm.last_frame)
            # entries by first frame / by freeze frame, so each frame costs O(live + frozen)
            order_first = np.argsort(first, kind="stable")
            order_last = np.argsort(last, kind="stable")
            starts = np.searchsorted(first[order_first], np.arange(n + 1), side="left")
            ends = np.searchsorted(last[order_last], np.arange(-2, n - 1), side="right")  # count of last <= t - 2
            live_set = np.zeros(len(lm), dtype=bool)
        for t in range(n):
            live_ids, live_p = np.zeros(0, np.int64), np.zeros((0, 3))
            f_ids = f_p = f_rej = None
            if lm is not None and len(lm):
                live_set[order_first[starts[t]:starts[t + 1]]] = True
                frozen = order_last[ends[t]:ends[t + 1]]  # last_frame == t - 1
                live_set[frozen] = False
                live = np.flatnonzero(live_set)
                live_ids, live_p = lm.ids[live], lm.p_lm_in_world[live]
                if frozen.size:
                    f_ids, f_p, f_rej = lm.ids[frozen], lm.p_lm_in_world[frozen], lm.rejected[frozen]
            stats = {"frame_ms": frame_ms[t]} if t < frame_ms.shape[0] else {}
            if lm is not None:
                stats["live_landmarks"] = float(live_ids.shape[0])
            if cov is not None:
                stats["position_sigma_m"] = float(np.sqrt(max(np.trace(cov[t, :3, :3]), 0.0)))
            stats.update({name: values[t] for name, values in extra_stats.items()})
            self.log_frame(t, float(timestamps[t]), result.world_T_imu[t], None if cov is None else cov[t],
                           live_ids, live_p, f_ids, f_p, f_rej, stats=stats)

    # ------------------------------------------------------------------ end

    def close(self) -> None:
        """Flush everything and move the recording onto ``path``."""
        if self._closed:
            return
        self._closed = True
        try:
            self._rec.flush(timeout_sec=60.0)
        except Exception as exc:
            if not self.spawned:  # only the file: it may be incomplete
                self.abort()
                raise OutputError(f"{self.path}: cannot write the recording: {exc}") from None
            # a viewer that went away (closed by the user) must not cost the file
            logger.warning("rerun: sending the recording to the viewer failed: %s", str(exc).splitlines()[0])
        self._rec.disconnect()
        if self._atomic is not None:
            atomic, self._atomic = self._atomic, None
            try:
                atomic.__exit__(None, None, None)
            except OSError as exc:
                raise OutputError(f"{self.path}: cannot move the recording into place: {exc.strerror or exc}") \
                    from None

    def abort(self) -> None:
        """Stop recording and delete the temporary file: ``path`` is left as it was."""
        self._closed = True
        try:
            self._rec.disconnect()
        except Exception:  # noqa: BLE001 - best effort on an error path
            pass
        if self._atomic is not None:
            atomic, self._atomic = self._atomic, None
            atomic.__exit__(_Aborted, _Aborted(), None)

    def __enter__(self) -> "RerunRecorder":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


class _Aborted(Exception):
    """Thrown into the atomic-path context to make it delete its temporary file."""
