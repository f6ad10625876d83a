"""Frame-to-frame camera motion measured from the stereo tracks alone (no IMU).

:func:`visual_frame_motion` estimates, for pairs of consecutive frames (k, k+1), the
relative pose ``cam_k_T_cam_{k+1}`` (maps points in camera k+1 into camera k) from the
landmarks seen in both: points triangulated at k+1 are reprojected into the stereo
pair of frame k. A RANSAC over three-point Kabsch fits finds the inliers (4-D stereo
reprojection error below ``inlier_px``), Gauss-Newton on the inliers' reprojection
errors refines the pose, and its 6x6 covariance is ``σ² (JᵀJ)⁻¹`` with σ the inliers'
RMS residual per coordinate. Tangent order (v, ω), left perturbation
``T = exp(δ) T̂``, as in :mod:`vislam.core.lie`.

Only observations of a track *before* its first exact repeat are used: at the KITTI
files' re-detection frames every continuing track repeats its previous pixels and is
one frame late from then on (see the data README and
:meth:`~vislam.core.sequence.StereoObservations.repeated_mask`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vislam.core.lie import se3_exp, so3_hat
from vislam.core.sequence import Sequence, StereoObservations

__all__ = ["VisualMotion", "in_sync_mask", "kabsch", "visual_frame_motion", "usable_observations"]


def in_sync_mask(obs: StereoObservations) -> np.ndarray:
    """(N,) True for the observations of a track before its first exact repeat."""
    n = obs.n_observations
    out = np.ones(n, dtype=bool)
    if n < 2:
        return out
    rep = obs.repeated_mask()
    order = np.lexsort((obs.frame_index, obs.landmark_ids))
    ids = obs.landmark_ids[order]
    c = np.cumsum(rep[order])
    start = np.r_[True, ids[1:] != ids[:-1]]
    before = np.where(start, np.r_[0, c[:-1]], 0)
    base = np.maximum.accumulate(before)  # repeats counted before each landmark's first row
    out[order] = (c - base) == 0
    return out


def usable_observations(sequence: Sequence, min_disparity_px: float = 1.0, max_row_difference_px: float = 3.0,
                        max_depth_m: float = 60.0) -> np.ndarray:
    """(N,) in-sync observations with a disparity and row agreement good for triangulation."""
    obs = sequence.observations
    px = obs.pixels
    disparity = px[:, 0] - px[:, 2]
    depth = np.divide(sequence.camera.fsu * sequence.camera.baseline_m, disparity,
                      out=np.full(disparity.shape, np.inf), where=disparity > 0)
    return (in_sync_mask(obs) & (disparity >= min_disparity_px) & (np.abs(px[:, 1] - px[:, 3]) <= max_row_difference_px)
            & (depth <= max_depth_m))


def kabsch(A: np.ndarray, B: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Batched weighted Kabsch: R, t minimizing Σ w |A − (R B + t)|²; A, B (..., n, 3)."""
    if w is None:
        w = np.ones(A.shape[:-1])
    w = w / np.sum(w, axis=-1, keepdims=True)
    ca = np.einsum("...n,...ni->...i", w, A)
    cb = np.einsum("...n,...ni->...i", w, B)
    H = np.einsum("...n,...ni,...nj->...ij", w, B - cb[..., None, :], A - ca[..., None, :])
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, -1, -2)
    Ut = np.swapaxes(U, -1, -2)
    d = np.sign(np.linalg.det(V @ Ut))
    D = np.zeros(H.shape)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = np.where(d == 0, 1.0, d)
    R = V @ D @ Ut
    t = ca - np.einsum("...ij,...j->...i", R, cb)
    return R, t


@dataclass(frozen=True)
class VisualMotion:
    """Visual relative poses of consecutive frame pairs.

    Attributes:
        frames: (P,) index k of each pair (k, k+1).
        cam_k_T_cam_k1: (P, 4, 4) relative pose (maps camera k+1 coordinates into camera k).
        covariance: (P, 6, 6) its covariance ((v, ω), left perturbation).
        n_inliers: (P,) landmarks used.
        residual_px: (P,) RMS inlier reprojection residual per coordinate (px).
    """

    frames: np.ndarray
    cam_k_T_cam_k1: np.ndarray
    covariance: np.ndarray
    n_inliers: np.ndarray
    residual_px: np.ndarray

    @property
    def n_pairs(self) -> int:
        return int(self.frames.shape[0])


def _project(camera, q: np.ndarray) -> np.ndarray:
    z = q[..., 2:3]
    fsu, fsv, cu, cv, b = camera.fsu, camera.fsv, camera.cu, camera.cv, camera.baseline_m
    u = fsu * q[..., 0:1] / z + cu
    v = fsv * q[..., 1:2] / z + cv
    return np.concatenate([u, v, u - fsu * b / z, v], axis=-1)


def _reprojection(camera, R, t, Pk1, zk):
    q = Pk1 @ np.swapaxes(R, -1, -2) + t[..., None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        r = _project(camera, q) - zk
    r = np.where(q[..., 2:3] > 0.1, r, 1e6)
    return np.linalg.norm(r, axis=-1), q, r


def _refine(camera, R, t, Pk1, zk, w, iterations: int = 6):
    """Gauss-Newton on the weighted stereo reprojection residuals; returns R, t, JᵀWJ, residuals."""
    fsu, fsv, b = camera.fsu, camera.fsv, camera.baseline_m
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    A = np.eye(6)
    for _ in range(iterations):
        q = Pk1 @ T[:3, :3].T + T[:3, 3]
        x, y, z = q[:, 0], q[:, 1], q[:, 2]
        r = (_project(camera, q) - zk).ravel()
        n = q.shape[0]
        Jp = np.zeros((n, 4, 3))  # d pixels / d q
        Jp[:, 0, 0] = fsu / z
        Jp[:, 0, 2] = -fsu * x / z**2
        Jp[:, 1, 1] = fsv / z
        Jp[:, 1, 2] = -fsv * y / z**2
        Jp[:, 2, 0] = fsu / z
        Jp[:, 2, 2] = -fsu * (x - b) / z**2
        Jp[:, 3] = Jp[:, 1]
        Jq = np.concatenate([np.broadcast_to(np.eye(3), (n, 3, 3)), -so3_hat(q)], axis=2)  # dq/dδ, (v, ω)
        J = (Jp @ Jq).reshape(-1, 6)
        ww = np.repeat(w, 4)
        A = J.T @ (ww[:, None] * J)
        g = J.T @ (ww * r)
        try:
            delta = -np.linalg.solve(A + 1e-9 * np.eye(6), g)
        except np.linalg.LinAlgError:
            break
        T = se3_exp(delta) @ T
        if np.linalg.norm(delta) < 1e-10:
            break
    res, _, _ = _reprojection(camera, T[:3, :3], T[:3, 3], Pk1, zk)
    return T, A, res


def visual_frame_motion(sequence: Sequence, frames=None, inlier_px: float = 4.0, min_inliers: int = 5,
                        ransac_iterations: int = 60, seed: int = 0) -> VisualMotion:
    """Visual relative poses of the pairs (k, k+1) for ``frames`` (default: all k)."""
    obs = sequence.observations
    camera = sequence.camera
    T = sequence.n_frames
    frames = np.arange(T - 1) if frames is None else np.asarray(frames, dtype=np.int64)
    rng = np.random.default_rng(seed)
    ok = usable_observations(sequence)
    pixels = obs.pixels
    points = np.zeros((obs.n_observations, 3))
    if np.any(ok):
        points[ok] = camera.triangulate(pixels[ok])
    offs = obs.frame_offsets
    out_frames, poses, covs, n_in, rms = [], [], [], [], []
    for k in frames:
        a0, a1 = offs[k], offs[k + 1]
        b0, b1 = offs[k + 1], offs[k + 2]
        ia = np.arange(a0, a1)[ok[a0:a1]]
        ib = np.arange(b0, b1)[ok[b0:b1]]
        common, pa, pb = np.intersect1d(obs.landmark_ids[ia], obs.landmark_ids[ib], return_indices=True)
        n = common.size
        if n < max(min_inliers, 3):
            continue
        ia, ib = ia[pa], ib[pb]
        Pk, Pk1, zk = points[ia], points[ib], pixels[ia]
        # RANSAC over minimal three-point Kabsch fits, scored by the reprojection into frame k
        trip = np.stack([rng.choice(n, size=3, replace=False) for _ in range(ransac_iterations)])
        Rs, ts = kabsch(Pk[trip], Pk1[trip])
        res, _, _ = _reprojection(camera, Rs, ts, Pk1[None], zk[None])
        score = np.sum(np.minimum(res, inlier_px) ** 2, axis=1)  # MSAC
        best = int(np.argmin(score))
        inl = res[best] < inlier_px
        if np.count_nonzero(inl) < min_inliers:
            continue
        R, t = kabsch(Pk[inl], Pk1[inl])
        w = np.ones(np.count_nonzero(inl))
        Tk, A, res_all = _refine(camera, R, t, Pk1[inl], zk[inl], w)
        # re-select the inliers with the refined pose and refine once more
        res_all, _, _ = _reprojection(camera, Tk[:3, :3], Tk[:3, 3], Pk1, zk)
        inl = res_all < inlier_px
        m = int(np.count_nonzero(inl))
        if m < min_inliers:
            continue
        Tk, A, res_in = _refine(camera, Tk[:3, :3], Tk[:3, 3], Pk1[inl], zk[inl], np.ones(m), iterations=3)
        dof = max(4 * m - 6, 1)
        sigma2 = float(np.sum(res_in**2)) / dof
        try:
            cov = np.linalg.inv(A) * sigma2
        except np.linalg.LinAlgError:
            continue
        out_frames.append(int(k))
        poses.append(Tk)
        covs.append(cov)
        n_in.append(m)
        rms.append(np.sqrt(sigma2))
    return VisualMotion(
        frames=np.asarray(out_frames, dtype=np.int64),
        cam_k_T_cam_k1=np.asarray(poses).reshape(-1, 4, 4),
        covariance=np.asarray(covs).reshape(-1, 6, 6),
        n_inliers=np.asarray(n_in, dtype=np.int64),
        residual_px=np.asarray(rms, dtype=np.float64),
    )
