"""The three estimators of the report, as drivers that run a whole :class:`Sequence`.

* :func:`run_localization` — EKF prediction of the IMU pose only (Section III-A).
* :func:`run_mapping` — EKF update of landmarks with the poses known (Section III-B).
* :func:`run_slam` — the joint EKF over pose and landmarks (Section III-C).
* :func:`run` — dispatch on a mode name.

Each returns a :class:`vislam.core.results.RunResult`. ``progress`` (optional) is called
with the number of frames done, for a progress bar; the library prints nothing.

SLAM processing order at frame t:

1. predict with the velocity of frame t over [t−1, t] (see :mod:`.propagation`);
2. update pose and landmarks with the observations of landmarks in the state, each
   first tested against the chi-square gate;
3. reject landmarks whose observations failed the gate ``max_consecutive_gated`` frames
   in a row (they leave the state and stay in the map flagged as rejected);
4. marginalize landmarks whose track ended (not observed at t): their rows and columns
   leave Σ — exact for a Gaussian — and their mean and marginal covariance are frozen
   into the map (``keep_all_landmarks`` keeps them, the report's variant);
5. initialize new landmarks from their first observation that passes the guards
   (:func:`vislam.core.updaters.initialization_guard`).

A landmark observed again after its track ended (never the case in the KITTI files,
whose tracks are contiguous) starts a new track: a new state entry and a new map entry
with ``track`` incremented.

Numerical health: after each frame the state and covariance are checked for
non-finite values (and the innovation covariance must admit a Cholesky factor); on
failure the run stops and returns a *partial* result with the frames done so far.
"""

from __future__ import annotations

import logging
import time
from typing import Callable

import numpy as np
from threadpoolctl import threadpool_limits

from vislam.core.lie import se3_adjoint, se3_inverse
from vislam.core.options import MODES, FilterOptions
from vislam.core.propagation import dead_reckoning, motion_increments, predict_state
from vislam.core.results import LANDMARK_OK, LANDMARK_REJECTED, LandmarkMap, RunResult, RunStats
from vislam.core.sequence import Sequence
from vislam.core.state import SlamState
from vislam.core.updaters import (
    StereoModel,
    initialization_guard,
    mapping_initialize,
    mapping_update,
    slam_initialize_landmarks,
    conditional_residual_model,
    slam_predict_nis,
    slam_update,
    schmidt_update,
    slam_update_reference,
    static_consistency_nis,
)
from vislam.errors import ConfigError, EstimationError, GeometryError

logger = logging.getLogger(__name__)

__all__ = ["run", "run_localization", "run_mapping", "run_slam"]

Progress = Callable[[int], None] | None


def run(sequence: Sequence, mode: str, options: FilterOptions | None = None, progress: Progress = None,
        world_T_imu: np.ndarray | None = None) -> RunResult:
    """Run one of the report's estimators (``mode`` in :data:`vislam.core.options.MODES`).

    ``world_T_imu`` (mapping only): the known poses; by default the localization result.
    """
    options = options or FilterOptions()
    if mode not in MODES:
        raise ConfigError(f"unknown mode {mode!r}; expected one of {', '.join(MODES)}")
    # The filter's matrices are small (a few hundred rows): multi-threaded BLAS only adds
    # synchronization cost there (measured 4x slower on 2 cores), so use one thread.
    with threadpool_limits(limits=1, user_api="blas"):
        if mode == "localization":
            return run_localization(sequence, options, progress)
        if mode == "mapping":
            return run_mapping(sequence, options, world_T_imu=world_T_imu, progress=progress)
        return run_slam(sequence, options, progress)


# ----------------------------------------------------------------------------- localization


def run_localization(sequence: Sequence, options: FilterOptions | None = None, progress: Progress = None) -> RunResult:
    """EKF prediction only: μ ← exp(−τ û) μ, Σ ← F Σ Fᵀ + τ² W for every frame."""
    options = options or FilterOptions()
    t0 = time.perf_counter()
    means, covs = dead_reckoning(sequence, options.W, options.initial_pose_covariance)
    elapsed = time.perf_counter() - t0
    T = sequence.n_frames
    if progress:
        progress(T)
    stats = RunStats(frames=T, frames_processed=T, observations_total=sequence.observations.n_observations,
                     frame_seconds=np.full(T, elapsed / T))
    return RunResult("localization", sequence.name, sequence.timestamps_s.copy(), se3_inverse(means), covs,
                     None, options, stats)


# ----------------------------------------------------------------------------- shared pieces


class _RepeatDetector:
    """Flags, frame by frame, observations whose four pixels repeat the same landmark's
    observation in the previous frame bit for bit (see
    :meth:`vislam.core.sequence.StereoObservations.repeated_mask`, which is the same test
    over a whole sequence). Memory: one pixel row per landmark id."""

    def __init__(self, M: int, options: FilterOptions, stats: RunStats):
        self.enabled = options.repeated_observations != "use"
        self.px = np.zeros((M, 4))
        self.frame = np.full(M, -2, dtype=np.int64)
        self.stats = stats

    def __call__(self, t: int, ids: np.ndarray, z: np.ndarray) -> np.ndarray:
        if not self.enabled:
            return np.zeros(ids.size, dtype=bool)
        rep = (self.frame[ids] == t - 1) & np.all(self.px[ids] == z, axis=1)
        self.px[ids] = z
        self.frame[ids] = t
        self.stats.observations_repeated += int(rep.sum())
        return rep


class _MapBuilder:
    """Collects frozen landmark entries (marginalized, rejected or final) in fixed-size
    chunks of columns: no per-entry small arrays, no doubling slack, and :meth:`build`
    frees each column's chunks as soon as its sorted copy exists."""

    _COLUMNS = {"ids": ((), np.int64), "track": ((), np.int64), "p": ((3,), np.float64),
                "cov": ((3, 3), np.float64), "nobs": ((), np.int64), "ngated": ((), np.int64),
                "first": ((), np.int64), "last": ((), np.int64), "status": ((), np.uint8),
                "v": ((3,), np.float64)}
    CHUNK = 4096

    def __init__(self):
        self.n = 0
        self._chunks: list[dict[str, np.ndarray]] = []

    def _new_chunk(self) -> dict[str, np.ndarray]:
        chunk = {k: np.zeros((self.CHUNK,) + shape, dtype=dt) for k, (shape, dt) in self._COLUMNS.items()}
        self._chunks.append(chunk)
        return chunk

    def add(self, ids, track, p, cov, nobs, ngated, first, last, status, v=None) -> None:
        k = int(np.size(ids))
        values = {"ids": ids, "track": track, "p": np.reshape(p, (k, 3)), "cov": np.reshape(cov, (k, 3, 3)),
                  "nobs": nobs, "ngated": ngated, "first": first, "last": last,
                  "status": np.broadcast_to(status, (k,)), "v": np.zeros((k, 3)) if v is None else np.reshape(v, (k, 3))}
        done = 0
        while done < k:
            offset = self.n % self.CHUNK
            chunk = self._chunks[-1] if offset else self._new_chunk()
            m = min(k - done, self.CHUNK - offset)
            for key, value in values.items():
                chunk[key][offset:offset + m] = value[done:done + m] if np.ndim(value) else value
            done += m
            self.n += m

    def build(self) -> LandmarkMap:
        """The map sorted by (id, track); each column's chunks are released once its
        sorted copy exists."""
        n = self.n

        def column(key: str) -> np.ndarray:
            shape, dt = self._COLUMNS[key]
            parts = [c.pop(key) for c in self._chunks]
            return np.concatenate(parts)[:n] if parts else np.zeros((0,) + shape, dtype=dt)

        ids, track = column("ids"), column("track")
        order = np.lexsort((track, ids))
        out = {"ids": ids[order], "track": track[order]}
        del ids, track
        for key in self._COLUMNS:
            if key not in out:
                out[key] = column(key)[order]
        self._chunks, self.n = [], 0
        return LandmarkMap(ids=out["ids"], track=out["track"], p_lm_in_world=out["p"], covariance=out["cov"],
                           n_observations=out["nobs"], n_gated=out["ngated"], first_frame=out["first"],
                           last_frame=out["last"], status=out["status"], v_lm_in_world=out["v"])


class _Tracks:
    """Per-landmark bookkeeping by dataset id: counts, first/last frames, rejection."""

    def __init__(self, M: int):
        self.track_count = np.zeros(M, dtype=np.int64)  # tracks started so far
        self.rejected = np.zeros(M, dtype=bool)
        self.nobs = np.zeros(M, dtype=np.int64)
        self.ngated = np.zeros(M, dtype=np.int64)
        self.consecutive = np.zeros(M, dtype=np.int64)
        self.first = np.full(M, -1, dtype=np.int64)
        self.last = np.full(M, -1, dtype=np.int64)

    def started(self, ids: np.ndarray, t: int) -> None:
        self.track_count[ids] += 1
        self.nobs[ids] = 1
        self.ngated[ids] = 0
        self.consecutive[ids] = 0
        self.first[ids] = t
        self.last[ids] = t

    def updated(self, ids: np.ndarray, ok: np.ndarray, t: int, stats: RunStats, max_consecutive: int) -> np.ndarray:
        """Record the gate outcome of one observation per id; return the ids to reject."""
        self.nobs[ids[ok]] += 1
        self.last[ids[ok]] = t
        self.ngated[ids[~ok]] += 1
        self.consecutive[ids[ok]] = 0
        self.consecutive[ids[~ok]] += 1
        stats.observations_used += int(ok.sum())
        stats.observations_gated += int((~ok).sum())
        if not max_consecutive:
            return ids[:0]
        bad = ids[self.consecutive[ids] >= max_consecutive]
        self.rejected[bad] = True
        stats.landmarks_rejected += int(bad.size)
        return bad

    def entry(self, ids: np.ndarray) -> tuple:
        return self.track_count[ids] - 1, self.nobs[ids], self.ngated[ids], self.first[ids], self.last[ids]


class _PendingLandmarks:
    """Delayed SLAM initialization (``options.init_frames``): a landmark waits until it
    has been seen in that many consecutive frames, then its first and latest
    observations must agree with a static point (:func:`static_consistency_nis`)."""

    def __init__(self, M: int, options: FilterOptions, model: StereoModel, tau: np.ndarray, tracks: _Tracks,
                 builder: _MapBuilder):
        self.n = options.init_frames
        self.options = options
        self.model = model
        self.tau = tau
        self.tracks = tracks
        self.builder = builder
        m = M if self.n > 1 else 0  # no per-landmark memory when initializing at once
        self.start = np.full(m, -1, dtype=np.int64)  # first frame of the waiting window
        self.last = np.full(m, -2, dtype=np.int64)  # last frame seen while waiting
        self.pixels = np.zeros((m, 4))
        self.failures = np.zeros(m, dtype=np.int64)

    def admit(self, ids: np.ndarray, z: np.ndarray, t: int, imu_T_world: np.ndarray, means: np.ndarray,
              stats: RunStats):
        """Return the (ids, pixels) to initialize now among candidates observed at t."""
        if self.n <= 1:
            return ids, z
        restart = self.last[ids] != t - 1
        self.start[ids[restart]] = t
        self.pixels[ids[restart]] = z[restart]
        self.last[ids] = t
        ready = ~restart & (t - self.start[ids] + 1 >= self.n)
        if not np.any(ready):
            return ids[:0], z[:0]
        r_ids, r_z = ids[ready], z[ready]
        t0 = self.start[r_ids]
        steps = np.cumsum(np.concatenate([[0.0], self.tau**2]))
        opts = self.options
        nis = np.empty(r_ids.size)
        for f0 in np.unique(t0):  # usually one start frame per batch
            sel = t0 == f0
            Q = (steps[t] - steps[f0]) * opts.W  # Σ τ² W between the two frames
            nis[sel] = static_consistency_nis(self.model, imu_T_world, r_z[sel], means[f0], self.pixels[r_ids[sel]],
                                              opts.V, Q)
        ok = nis <= opts.gate_threshold
        bad_ids = r_ids[~ok]
        if bad_ids.size:
            self.failures[bad_ids] += 1
            stats.observations_gated += int(bad_ids.size)
            # try again from the latest observation; a second failure rejects the landmark
            self.start[bad_ids] = t
            self.pixels[bad_ids] = r_z[~ok]
            out = bad_ids[self.failures[bad_ids] >= 2]
            if out.size:
                self.tracks.rejected[out] = True
                self.tracks.started(out, t)
                stats.landmarks_rejected += int(out.size)
                sel = np.isin(r_ids, out)
                p_w, cov = mapping_initialize(self.model, imu_T_world, r_z[sel], opts.V)
                self.builder.add(out, *self.tracks.entry(out)[:1], p_w, cov, *self.tracks.entry(out)[1:],
                                 LANDMARK_REJECTED)
        self.start[r_ids[ok]] = -1
        self.last[r_ids[ok]] = -2
        return r_ids[ok], r_z[ok]


# ----------------------------------------------------------------------------- mapping


def run_mapping(sequence: Sequence, options: FilterOptions | None = None, world_T_imu: np.ndarray | None = None,
                progress: Progress = None) -> RunResult:
    """Landmark mapping with known poses (by default the localization trajectory).

    Landmarks are independent given the poses, so each keeps its own 3x3 covariance —
    the exact block-diagonal equivalent of the report's 3M x 3M Σ.
    """
    options = options or FilterOptions()
    T = sequence.n_frames
    t_start = time.perf_counter()
    pose_cov = None
    if world_T_imu is None:
        means, pose_cov = dead_reckoning(sequence, options.W, options.initial_pose_covariance)
        world_T_imu = se3_inverse(means)
    else:
        world_T_imu = np.asarray(world_T_imu, dtype=np.float64)
        if world_T_imu.shape != (T, 4, 4):
            raise ConfigError(f"mapping needs one pose per frame: expected ({T}, 4, 4), got {world_T_imu.shape}")
    imu_T_world = se3_inverse(world_T_imu)
    model = StereoModel(sequence.camera, sequence.cam_T_imu)
    V = options.V
    gate = options.gate_threshold
    M = sequence.n_landmarks
    mean = np.zeros((M, 3))
    cov = np.zeros((M, 3, 3))
    active = np.zeros(M, dtype=bool)  # has a current estimate
    tracks = _Tracks(M)
    builder = _MapBuilder()
    stats = RunStats(frames=T, observations_total=sequence.observations.n_observations)
    obs = sequence.observations
    repeated = _RepeatDetector(M, options, stats)
    split = options.repeated_observations == "split"
    frame_seconds = np.zeros(T)
    frame_seconds[0] = time.perf_counter() - t_start

    def freeze(ids: np.ndarray, status: int) -> None:
        if ids.size:
            builder.add(ids, *tracks.entry(ids)[:1], mean[ids], cov[ids], *tracks.entry(ids)[1:], status)
            active[ids] = False

    for t in range(T):
        tic = time.perf_counter()
        ids, z = obs.frame(t)
        rep = repeated(t, ids, z)
        if split and np.any(rep & active[ids]):
            freeze(ids[rep & active[ids]], LANDMARK_OK)  # the track ends; the repeat starts a new one
            rep = np.zeros_like(rep)
        keep = ~rep & ~tracks.rejected[ids]
        ids, z = ids[keep], z[keep]
        upd = active[ids]
        if np.any(upd):
            u_ids = ids[upd]
            mean[u_ids], cov[u_ids], ok, _ = mapping_update(model, imu_T_world[t], mean[u_ids], cov[u_ids], z[upd],
                                                             V, gate)
            bad = tracks.updated(u_ids, ok, t, stats, options.max_consecutive_gated)
            freeze(bad, LANDMARK_REJECTED)
        new = ~upd
        if np.any(new):
            c_ids, c_z = ids[new], z[new]
            good = initialization_guard(sequence.camera, c_z, options)
            stats.observations_not_initialized += int((~good).sum())
            if np.any(good):
                g_ids = c_ids[good]
                mean[g_ids], cov[g_ids] = mapping_initialize(model, imu_T_world[t], c_z[good], V)
                active[g_ids] = True
                tracks.started(g_ids, t)
                stats.landmarks_initialized += int(g_ids.size)
                stats.observations_used += int(g_ids.size)
        frame_seconds[t] += time.perf_counter() - tic
        if progress:
            progress(t + 1)
    freeze(np.nonzero(active)[0], LANDMARK_OK)
    stats.frames_processed = T
    stats.frame_seconds = frame_seconds
    return RunResult("mapping", sequence.name, sequence.timestamps_s.copy(), world_T_imu, pose_cov, builder.build(),
                     options, stats)


# ----------------------------------------------------------------------------- SLAM


def run_slam(sequence: Sequence, options: FilterOptions | None = None, progress: Progress = None,
             reference: bool = False) -> RunResult:
    """The joint EKF over the IMU pose and the landmarks (the report's Section III-C).

    ``reference=True`` uses the plain dense update (:func:`slam_update_reference`) —
    slow, for tests that check the fast block form against it.
    """
    options = options or FilterOptions()
    T = sequence.n_frames
    M = sequence.n_landmarks
    model = StereoModel(sequence.camera, sequence.cam_T_imu)
    V, W = options.V, options.W
    gate = options.gate_threshold
    oc = options.ekf == "oc"
    tau, u = motion_increments(sequence)
    update = slam_update_reference if reference else slam_update

    motion = options.landmark_motion
    state = SlamState(np.eye(4), options.initial_pose_covariance, n_ids=M, lm_dim=6 if motion else 3)
    velocity_var = options.landmark_velocity_std_mps**2
    accel_var = options.landmark_acceleration_std_mps2**2
    tracks = _Tracks(M)
    builder = _MapBuilder()
    means = np.zeros((T, 4, 4))
    covs = np.zeros((T, 6, 6))
    stats = RunStats(frames=T, observations_total=sequence.observations.n_observations)
    frame_seconds = np.zeros(T)
    obs = sequence.observations
    repeated = _RepeatDetector(M, options, stats)
    split = options.repeated_observations == "split"
    seen = np.zeros(M, dtype=bool)
    last_correction = np.zeros(6)  # pose correction of the previous update (OC transition)
    pending = _PendingLandmarks(M, options, model, tau, tracks, builder)
    drift_gate = options.drift_threshold
    m_drift = M if drift_gate < np.inf else 0
    drift_sum = np.zeros((m_drift, 4))  # per landmark: Σ of whitened innovations and their count
    drift_n = np.zeros(m_drift)
    error = None
    done = 0

    def freeze(slots: np.ndarray, status: int) -> None:
        if slots.size == 0:
            return
        ids = state.landmark_ids[slots]
        track, nobs, ngated, first, last = tracks.entry(ids)
        builder.add(ids, track, state.p_lm_in_world[slots], state.landmark_cov(slots), nobs, ngated, first, last,
                    status, state.v_lm_in_world[slots])
        state.remove_slots(slots)

    for t in range(T):
        tic = time.perf_counter()
        try:
            # overflow/NaN is detected by the health check below and reported as an error
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                # ---- 1. prediction
                correction = np.zeros(6)
                if t > 0:
                    predict_state(state, tau[t - 1], u[t - 1], W, last_correction if oc else None)
                    if motion:
                        state.predict_landmarks(tau[t - 1], accel_var)
                mu_prior = state.imu_T_world
                # unobservable directions of the pose at the prior (OC variant)
                N_pose = -se3_adjoint(mu_prior) if oc else None
                ids_seen, z = obs.frame(t)
                rep = repeated(t, ids_seen, z)
                if split and np.any(rep):
                    slots_rep = state.slot_of[ids_seen[rep]]
                    freeze(slots_rep[slots_rep >= 0], LANDMARK_OK)  # the track ends; the repeat starts a new one
                    rep = np.zeros_like(rep)
                usable = ~rep & ~tracks.rejected[ids_seen]
                ids, z = ids_seen[usable], z[usable]
                slot_arr = state.slot_of[ids]
                live = slot_arr >= 0
                # ---- 2. update with the landmarks in the state
                if np.any(live):
                    slots, lids = slot_arr[live], ids[live]
                    r, Hp, Hl, in_front, nis, blocks = slam_predict_nis(state, model, slots, z[live], V, N_pose)
                    ok = in_front & (nis <= gate)
                    young = tracks.nobs[lids] <= options.probation_frames  # init counts as 1
                    joint = ok & ~young
                    if drift_gate < np.inf and np.any(ok):
                        Ht, Lt = conditional_residual_model(blocks, Hp, Hl, V)
                    correction = update(state, slots[joint], r[joint], Hp[joint], Hl[joint], V)
                    if drift_gate < np.inf and np.any(ok):
                        # innovation drift test: beyond the frame's consensus pose correction,
                        # a static landmark's whitened residuals are white, so Σ w / √k ~
                        # N(0, I₄); a point on a moving vehicle drifts one way
                        w = np.linalg.solve(Lt, (r - Ht @ correction)[:, :, None])[:, :, 0]
                        drift_sum[lids] += np.where(ok[:, None], w, 0.0)
                        drift_n[lids] += ok
                        stat = np.einsum("ki,ki->k", drift_sum[lids], drift_sum[lids]) / np.maximum(drift_n[lids], 1)
                        moving = ok & (drift_n[lids] >= 2) & (stat > drift_gate)
                        if np.any(moving):
                            stats.landmarks_moving += int(moving.sum())
                            ok &= ~moving
                            # rejected at once (below): it moves
                            tracks.consecutive[lids[moving]] = max(options.max_consecutive_gated, 1) - 1
                    probe = ok & young
                    if np.any(probe):
                        # slots are unchanged by the joint update; re-linearize at the new pose
                        r2, Hp2, Hl2, _, _, _ = slam_predict_nis(state, model, slots[probe], z[live][probe], V, N_pose)
                        schmidt_update(state, slots[probe], r2, Hp2, Hl2, V)
                    # ---- 3. reject landmarks that keep failing the gate
                    bad = tracks.updated(lids, ok, t, stats, options.max_consecutive_gated)
                    freeze(state.slot_of[bad], LANDMARK_REJECTED)
                # ---- 4. marginalize landmarks whose track ended
                if not options.keep_all_landmarks and state.n_landmarks:
                    seen[ids_seen] = True  # a skipped repeat keeps its track alive
                    freeze(np.nonzero(~seen[state.landmark_ids])[0], LANDMARK_OK)
                    seen[ids_seen] = False
                # ---- 5. initialize new landmarks
                new = ~live
                if np.any(new):
                    n_ids, n_z = ids[new], z[new]
                    good = initialization_guard(sequence.camera, n_z, options)
                    stats.observations_not_initialized += int((~good).sum())
                    if np.any(good):
                        g_ids, g_z = pending.admit(n_ids[good], n_z[good], t, state.imu_T_world, means, stats)
                        if g_ids.size:
                            slam_initialize_landmarks(state, model, g_ids, g_z, V, N_pose, velocity_var)
                            tracks.started(g_ids, t)
                            if m_drift:
                                drift_sum[g_ids] = 0.0
                                drift_n[g_ids] = 0
                            stats.landmarks_initialized += int(g_ids.size)
                            stats.observations_used += int(g_ids.size)
                if oc:
                    last_correction = correction
                stats.max_state_landmarks = max(stats.max_state_landmarks, state.n_landmarks)
                if not state.is_finite():
                    raise EstimationError(f"non-finite state or covariance at frame {t}", frame=t)
                if np.any(np.diagonal(state.cov) < -1e-9):
                    raise EstimationError(f"covariance lost positive semi-definiteness at frame {t}", frame=t)
        except (EstimationError, GeometryError, np.linalg.LinAlgError) as exc:
            error = str(exc) if isinstance(exc, EstimationError) else f"numerical failure at frame {t}: {exc}"
            logger.info("%s; stopping with a partial result", error)  # reported by the caller (result.error)
            break
        means[t] = state.imu_T_world
        covs[t] = state.pose_cov
        frame_seconds[t] = time.perf_counter() - tic
        done = t + 1
        if progress:
            progress(done)

    # Landmarks still in the state enter the map with their final estimate (after a
    # failure, only those whose mean and covariance are still finite).
    if state.n_landmarks:
        slots = np.arange(state.n_landmarks)
        if error is not None:
            finite = np.all(np.isfinite(state.p_lm_in_world), axis=1)
            finite &= np.all(np.isfinite(state.landmark_cov(slots)), axis=(1, 2))
            slots = slots[finite]
        freeze(slots, LANDMARK_OK)
    stats.frames_processed = done
    stats.frame_seconds = frame_seconds[:done]
    world_T_imu = se3_inverse(means[:done]) if done else np.zeros((0, 4, 4))
    return RunResult("slam", sequence.name, sequence.timestamps_s[:done].copy(), world_T_imu, covs[:done],
                     builder.build(), options, stats, partial=error is not None, error=error)
