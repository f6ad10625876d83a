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

from vislam.core.bookkeeping import IdTable, MapBuilder, RepeatDetector, TrackTable, in_sorted
from vislam.core.lie import se3_adjoint, se3_inverse
from vislam.core.options import MODES, FilterOptions
from vislam.core.propagation import dead_reckoning, motion_increments, predict_state
from vislam.core.results import LANDMARK_OK, LANDMARK_REJECTED, RunResult, RunStats
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


class _PendingLandmarks:
    """Delayed SLAM initialization (``options.init_frames``): a landmark waits until it
    has been seen in that many consecutive frames, then its first and latest
    observations must agree with a static point (:func:`static_consistency_nis`).
    Memory: one row per landmark waiting in view."""

    def __init__(self, options: FilterOptions, model: StereoModel, tau: np.ndarray, tracks: TrackTable,
                 builder: MapBuilder):
        self.n = options.init_frames
        self.options = options
        self.model = model
        self.tau = tau
        self.tracks = tracks
        self.builder = builder
        # start: first frame of the waiting window; last: last frame seen while waiting
        self.waiting = IdTable({"start": ((), np.int64, -1), "last": ((), np.int64, -2),
                                "pixels": ((4,), np.float64, 0.0), "failures": ((), np.int64, 0)}, capacity=16)

    def forget_unseen(self, ids_seen: np.ndarray) -> None:
        """Landmarks out of view stop waiting (seen again, they start over)."""
        if self.n > 1 and len(self.waiting):
            ids = self.waiting.ids
            self.waiting.remove(ids[~in_sorted(ids, ids_seen)])

    def admit(self, ids: np.ndarray, z: np.ndarray, t: int, imu_T_world: np.ndarray, means: np.ndarray,
              stats: RunStats):
        """Return the (ids, pixels) to initialize now among candidates observed at t."""
        if self.n <= 1:
            return ids, z
        w = self.waiting
        rows = w.rows(ids)
        w.add(ids[rows < 0])
        rows = w.rows(ids)
        start, last, pixels, failures = w["start"], w["last"], w["pixels"], w["failures"]
        restart = last[rows] != t - 1
        start[rows[restart]] = t
        pixels[rows[restart]] = z[restart]
        last[rows] = t
        ready = ~restart & (t - start[rows] + 1 >= self.n)
        if not np.any(ready):
            return ids[:0], z[:0]
        r_ids, r_z, r_rows = ids[ready], z[ready], rows[ready]
        t0 = start[r_rows]
        steps = np.cumsum(np.concatenate([[0.0], self.tau**2]))
        opts = self.options
        nis = np.empty(r_ids.size)
        for f0 in np.unique(t0):  # usually one start frame per batch
            sel = t0 == f0
            Q = (steps[t] - steps[f0]) * opts.W  # Σ τ² W between the two frames
            nis[sel] = static_consistency_nis(self.model, imu_T_world, r_z[sel], means[f0], pixels[r_rows[sel]],
                                              opts.V, Q)
        ok = nis <= opts.gate_threshold
        bad_rows = r_rows[~ok]
        if bad_rows.size:
            failures[bad_rows] += 1
            stats.observations_gated += int(bad_rows.size)
            # try again from the latest observation; a second failure rejects the landmark
            start[bad_rows] = t
            pixels[bad_rows] = r_z[~ok]
            out_sel = ~ok & (failures[r_rows] >= 2)
            if np.any(out_sel):
                out = r_ids[out_sel]
                w.remove(out)
                rows_out = self.tracks.started(out, t)
                self.tracks["rejected"][rows_out] = True
                stats.landmarks_rejected += int(out.size)
                p_w, cov = mapping_initialize(self.model, imu_T_world, r_z[out_sel], opts.V)
                self.builder.add(out, p_w, cov, *self.tracks.entry(out), LANDMARK_REJECTED)
        w.remove(r_ids[ok])
        return r_ids[ok], r_z[ok]


# ----------------------------------------------------------------------------- mapping


def run_mapping(sequence: Sequence, options: FilterOptions | None = None, world_T_imu: np.ndarray | None = None,
                progress: Progress = None) -> RunResult:
    """Landmark mapping with known poses (by default the localization trajectory).

    Landmarks are independent given the poses, so each keeps its own 3x3 covariance —
    the exact block-diagonal equivalent of the report's 3M x 3M Σ. A landmark's track
    ends when it is not observed in a frame: its estimate enters the map then (seen
    again, it starts a new track), so memory follows the landmarks in view.
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
    # one row per track in progress, with its estimate; a track ends (its landmark is
    # frozen into the map) when the landmark is not observed in a frame
    tracks = TrackTable({"mean": ((3,), np.float64, 0.0), "cov": ((3, 3), np.float64, 0.0)})
    builder = MapBuilder()
    stats = RunStats(frames=T, observations_total=sequence.observations.n_observations)
    obs = sequence.observations
    repeated = RepeatDetector(options.repeated_observations != "use", stats)
    split = options.repeated_observations == "split"
    frame_seconds = np.zeros(T)
    frame_seconds[0] = time.perf_counter() - t_start

    def freeze(ids: np.ndarray, status: int) -> None:
        """Enter the tracks of ``ids`` into the map; a rejected track stays (flagged)
        while its landmark is in view, so that its observations keep being ignored."""
        if ids.size:
            rows = tracks.rows(ids)
            builder.add(ids, tracks["mean"][rows], tracks["cov"][rows], *tracks.entry(ids, rows), status)
            if status != LANDMARK_REJECTED:
                tracks.remove(ids)

    for t in range(T):
        tic = time.perf_counter()
        ids_seen, z = obs.frame(t)
        rep = repeated(t, ids_seen, z)
        rows, rejected = tracks.lookup(ids_seen)
        act = (rows >= 0) & ~rejected  # has a current estimate
        if split and np.any(rep & act):
            freeze(ids_seen[rep & act], LANDMARK_OK)  # the track ends; the repeat starts a new one
            rep = np.zeros_like(rep)
            rows, rejected = tracks.lookup(ids_seen)
            act = (rows >= 0) & ~rejected
        keep = ~rep & ~rejected  # rejected landmarks stay ignored while in view
        ids, z, rows, upd = ids_seen[keep], z[keep], rows[keep], act[keep]
        if np.any(upd):
            u_ids, u_rows = ids[upd], rows[upd]
            tracks["mean"][u_rows], tracks["cov"][u_rows], ok, _ = mapping_update(
                model, imu_T_world[t], tracks["mean"][u_rows], tracks["cov"][u_rows], z[upd], V, gate)
            bad = tracks.updated(u_ids, ok, t, stats, options.max_consecutive_gated, rows=u_rows)
            freeze(bad, LANDMARK_REJECTED)
        # tracks whose landmark is out of view end (a skipped repeat keeps its track alive)
        ended = ~in_sorted(tracks.ids, ids_seen) & ~tracks["rejected"][tracks.live_rows]
        freeze(tracks.ids[ended], LANDMARK_OK)
        tracks.end_unseen_rejections(ids_seen)
        new = ~upd
        if np.any(new):
            c_ids, c_z = ids[new], z[new]
            good = initialization_guard(sequence.camera, c_z, options)
            stats.observations_not_initialized += int((~good).sum())
            if np.any(good):
                g_ids = c_ids[good]
                rows = tracks.started(g_ids, t)
                tracks["mean"][rows], tracks["cov"][rows] = mapping_initialize(model, imu_T_world[t], c_z[good], V)
                stats.landmarks_initialized += int(g_ids.size)
                stats.observations_used += int(g_ids.size)
        frame_seconds[t] += time.perf_counter() - tic
        if progress:
            progress(t + 1)
    freeze(tracks.ids[~tracks["rejected"][tracks.live_rows]], LANDMARK_OK)
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
    model = StereoModel(sequence.camera, sequence.cam_T_imu)
    V, W = options.V, options.W
    gate = options.gate_threshold
    oc = options.ekf == "oc"
    tau, u = motion_increments(sequence)
    update = slam_update_reference if reference else slam_update

    motion = options.landmark_motion
    state = SlamState(np.eye(4), options.initial_pose_covariance, lm_dim=6 if motion else 3)
    velocity_var = options.landmark_velocity_std_mps**2
    accel_var = options.landmark_acceleration_std_mps2**2
    drift_gate = options.drift_threshold
    # one row per track in progress; the drift test's per-landmark sums live there too
    tracks = TrackTable({"drift_sum": ((4,), np.float64, 0.0), "drift_n": ((), np.float64, 0.0)})
    builder = MapBuilder()
    means = np.zeros((T, 4, 4))
    covs = np.zeros((T, 6, 6))
    stats = RunStats(frames=T, observations_total=sequence.observations.n_observations)
    frame_seconds = np.zeros(T)
    obs = sequence.observations
    repeated = RepeatDetector(options.repeated_observations != "use", stats)
    split = options.repeated_observations == "split"
    last_correction = np.zeros(6)  # pose correction of the previous update (OC transition)
    pending = _PendingLandmarks(options, model, tau, tracks, builder)
    error = None
    done = 0

    def freeze(slots: np.ndarray, status: int) -> None:
        if slots.size == 0:
            return
        ids = state.landmark_ids[slots]
        builder.add(ids, state.p_lm_in_world[slots], state.landmark_cov(slots), *tracks.entry(ids), status,
                    state.v_lm_in_world[slots])
        state.remove_slots(slots)
        if status != LANDMARK_REJECTED:  # a rejected track stays (flagged) while in view
            tracks.remove(ids)

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
                    slots_rep = state.slots_of(ids_seen[rep])
                    freeze(slots_rep[slots_rep >= 0], LANDMARK_OK)  # the track ends; the repeat starts a new one
                    rep = np.zeros_like(rep)
                track_rows, rejected = tracks.lookup(ids_seen)
                usable = ~rep & ~rejected
                ids, z, track_rows = ids_seen[usable], z[usable], track_rows[usable]
                slot_arr = state.slots_of(ids)
                live = slot_arr >= 0
                # ---- 2. update with the landmarks in the state
                if np.any(live):
                    slots, lids, rows = slot_arr[live], ids[live], track_rows[live]
                    r, Hp, Hl, in_front, nis, blocks = slam_predict_nis(state, model, slots, z[live], V, N_pose)
                    ok = in_front & (nis <= gate)
                    young = tracks["nobs"][rows] <= options.probation_frames  # init counts as 1
                    joint = ok & ~young
                    if drift_gate < np.inf and np.any(ok):
                        Ht, Lt = conditional_residual_model(blocks, Hp, Hl, V)
                    correction = update(state, slots[joint], r[joint], Hp[joint], Hl[joint], V)
                    if drift_gate < np.inf and np.any(ok):
                        # innovation drift test: beyond the frame's consensus pose correction,
                        # a static landmark's whitened residuals are white, so Σ w / √k ~
                        # N(0, I₄); a point on a moving vehicle drifts one way
                        w = np.linalg.solve(Lt, (r - Ht @ correction)[:, :, None])[:, :, 0]
                        drift_sum, drift_n = tracks["drift_sum"], tracks["drift_n"]
                        drift_sum[rows] += np.where(ok[:, None], w, 0.0)
                        drift_n[rows] += ok
                        stat = np.einsum("ki,ki->k", drift_sum[rows], drift_sum[rows]) / np.maximum(drift_n[rows], 1)
                        moving = ok & (drift_n[rows] >= 2) & (stat > drift_gate)
                        if np.any(moving):
                            stats.landmarks_moving += int(moving.sum())
                            ok &= ~moving
                            # rejected at once (below): it moves
                            tracks["consecutive"][rows[moving]] = max(options.max_consecutive_gated, 1) - 1
                    probe = ok & young
                    if np.any(probe):
                        # slots are unchanged by the joint update; re-linearize at the new pose
                        r2, Hp2, Hl2, _, _, _ = slam_predict_nis(state, model, slots[probe], z[live][probe], V, N_pose)
                        schmidt_update(state, slots[probe], r2, Hp2, Hl2, V)
                    # ---- 3. reject landmarks that keep failing the gate
                    bad = tracks.updated(lids, ok, t, stats, options.max_consecutive_gated, rows=rows)
                    freeze(state.slots_of(bad), LANDMARK_REJECTED)
                # ---- 4. marginalize landmarks whose track ended
                if not options.keep_all_landmarks and state.n_landmarks:
                    # a skipped repeat keeps its track alive
                    freeze(np.flatnonzero(~in_sorted(state.landmark_ids, ids_seen)), LANDMARK_OK)
                tracks.end_unseen_rejections(ids_seen)
                pending.forget_unseen(ids_seen)
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
