"""The compiled kernels of the SLAM EKF (vislam.core._ekf, through vislam.core.kernels)
against their numpy twins, the reference: each step on states taken from a simulated
drive and on synthetic ones (ill-conditioned, not positive definite, large), and whole
runs of the filter both ways. The two paths sum in different orders, so they agree to
rounding, not bit for bit: the tolerances below are a few hundred ulps of the values
compared, and whole runs agree to 1e-8 m."""

import copy

import numpy as np
import pytest

import vislam
from vislam.core import kernels, updaters
from vislam.core.filters import SlamFilter
from vislam.core.lie import se3_adjoint, se3_exp
from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.core.state import SlamState

from conftest import HALF_SCENE

needs_kernels = pytest.mark.skipif(not kernels.kernels_available(), reason=str(kernels.UNAVAILABLE))

RTOL = 1e-10


def _close(a, b, rtol=RTOL, what=""):
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    assert a.shape == b.shape, what
    scale = max(float(np.max(np.abs(b), initial=0.0)), 1e-300)
    err = float(np.max(np.abs(a - b), initial=0.0))
    assert err <= rtol * scale, f"{what}: largest difference {err:.3e} against a scale of {scale:.3e}"


@pytest.fixture(scope="module")
def drive():
    return simulate_drive(SimulationOptions(n_frames=40, seed=3, velocity_noise_mps=0.3, angular_noise_radps=0.02,
                                            **HALF_SCENE))


def _filter_at(drive, frame: int, **options):
    """A numpy SLAM filter stepped up to ``frame`` (exclusive), and that frame."""
    opts = vislam.FilterOptions(velocity_noise_mps=0.3, angular_noise_radps=0.02, **options)
    with kernels.use_kernels(False):
        f = SlamFilter(drive.sequence.calibration, opts)
    frames = list(drive.sequence.frames())
    for fr in frames[:frame]:
        f.step(fr)
    return f, frames[frame]


def _observed(f, frame):
    """(slots, pixels) of the frame's observations of landmarks in the state."""
    slots = f.state.slots_of(frame.landmark_ids)
    live = slots >= 0
    return slots[live], frame.pixels[live]


def _both(state):
    """Two independent copies of ``state``: for the numpy path and for the kernels."""
    a, b = copy.deepcopy(state), copy.deepcopy(state)
    a.compiled, b.compiled = False, True
    return a, b


def _ops():
    assert kernels._ready()
    return kernels.NumpyOps(), kernels.KernelOps()


CHARTS = [dict(), dict(landmark_parametrization="cartesian"), dict(update={"ekf": "standard"})]


@needs_kernels
@pytest.mark.parametrize("velocity_frame", ["level", "body"])
@pytest.mark.parametrize("jacobian", [True, False])
@pytest.mark.parametrize("eps", [None, np.zeros(6), np.array([0.01, -0.02, 0.005, 1e-3, -2e-3, 5e-4])])
def test_predict_matches_numpy(drive, velocity_frame, jacobian, eps):
    f, frame = _filter_at(drive, 12)
    a, b = _both(f.state)
    num, ker = _ops()
    u = np.array([8.0, 0.3, -0.1, 0.01, -0.02, 0.15])
    num.predict(a, 0.1, u, f.options.W, eps, velocity_frame, jacobian)
    ker.predict(b, 0.1, u, f.options.W, eps, velocity_frame, jacobian)
    _close(b.imu_T_world, a.imu_T_world, what="pose")
    _close(b.cov, a.cov, what="covariance")
    assert np.array_equal(b.cov, b.cov.T)


@needs_kernels
@pytest.mark.parametrize("options", CHARTS)
@pytest.mark.parametrize("with_prior", [False, True])
def test_linearize_matches_numpy(drive, options, with_prior):
    f, frame = _filter_at(drive, 15, **options)
    slots, z = _observed(f, frame)
    assert slots.size >= 10
    N_pose = -se3_adjoint(f.state.imu_T_world) if f.options.ekf == "oc" else None
    a, b = _both(f.state)
    prior = None
    if with_prior:  # a prior the iterate has moved away from (pose and landmarks)
        prior = (a.imu_T_world.copy(), a.imu_bias.copy(), a.lm_mean.copy(), a.v_lm_in_world.copy())
        for s in (a, b):
            s.imu_T_world = se3_exp(np.array([0.05, -0.02, 0.01, 2e-3, -1e-3, 3e-3])) @ s.imu_T_world
            s.lm_mean = s.lm_mean + 1e-3 * np.cos(np.arange(s.lm_mean.size)).reshape(-1, 3)
    num, ker = _ops()
    out_n = num.linearize(a, f._model, slots, z, N_pose, prior)
    out_k = ker.linearize(b, f._model, slots, z, N_pose, prior)
    for name, x, y in zip(("r", "H_pose", "H_lm"), out_k[:3], out_n[:3]):
        _close(x, y, rtol=1e-9, what=name)
    assert np.array_equal(out_k[3], out_n[3])


@needs_kernels
def test_a_landmark_behind_the_camera_is_flagged_as_numpy_flags_it(drive):
    f, frame = _filter_at(drive, 15, landmark_parametrization="cartesian")
    slots, z = _observed(f, frame)
    a, b = _both(f.state)
    cam_T_world = f._model.cam_T_imu @ a.imu_T_world
    world_T_cam = np.linalg.inv(cam_T_world)
    for s in (a, b):  # the first two landmarks 10 m behind the camera
        s.lm_mean[slots[:2]] = (world_T_cam @ np.array([1.0, 0.5, -10.0, 1.0]))[:3]
    num, ker = _ops()
    r_n, Hp_n, Hl_n, front_n, nis_n, _ = num.predict_nis(a, f._model, slots, z, f.options.V, None)
    r_k, Hp_k, Hl_k, front_k, nis_k, _ = ker.predict_nis(b, f._model, slots, z, f.options.V, None)
    assert not front_k[:2].any() and front_k[2:].all() and np.array_equal(front_k, front_n)
    assert np.isinf(nis_k[:2]).all()
    _close(nis_k[2:], nis_n[2:], rtol=1e-9, what="NIS")


@needs_kernels
@pytest.mark.parametrize("options", CHARTS)
def test_nis_blocks_and_drift_model_match_numpy(drive, options):
    f, frame = _filter_at(drive, 20, **options)
    slots, z = _observed(f, frame)
    N_pose = -se3_adjoint(f.state.imu_T_world) if f.options.ekf == "oc" else None
    V = f.options.V
    a, b = _both(f.state)
    num, ker = _ops()
    out_n = num.predict_nis(a, f._model, slots, z, V, N_pose)
    out_k = ker.predict_nis(b, f._model, slots, z, V, N_pose)
    _close(out_k[4], out_n[4], rtol=1e-9, what="NIS")
    for name, x, y in zip(("S_pp", "S_ps", "S_ss"), out_k[5], out_n[5]):
        assert np.array_equal(x, y), name  # copied, not computed
    Ht_n, Lt_n = num.residual_model(out_n[5], out_n[1], out_n[2], V)
    Ht_k, Lt_k = ker.residual_model(out_k[5], out_k[1], out_k[2], V)
    _close(Ht_k, Ht_n, rtol=1e-9, what="H~")
    _close(Lt_k, Lt_n, rtol=1e-9, what="L~")


def _synthetic(L: int, seed: int, spread: float = 1.0, inverse_depth: bool = False) -> SlamState:
    """A state with L landmarks and a random symmetric positive definite Σ (its landmark
    block scaled by ``spread``²)."""
    rng = np.random.default_rng(seed)
    n = 6 + 3 * L
    A = rng.standard_normal((n, n))
    scale = np.r_[np.full(6, 0.1), np.full(3 * L, spread)]
    P = (A @ A.T / n + 0.05 * np.eye(n)) * np.outer(scale, scale)
    state = SlamState(se3_exp(rng.normal(0.0, 0.3, 6)), P[:6, :6], capacity_landmarks=L, inverse_depth=inverse_depth)
    if L:
        anchors = se3_exp(rng.normal(0.0, 0.5, (L, 6))) if inverse_depth else None
        lm = np.c_[rng.normal(0.0, 0.2, (L, 2)), rng.uniform(0.02, 0.5, L)] if inverse_depth else rng.normal(0, 20, (L, 3))
        state.add_landmarks(np.arange(L) * 7 + 3, lm, P[6:, :6], P[6:, 6:], world_T_anchor=anchors)
    state.cov[...] = P
    return state


def _observations(state: SlamState, k: int, seed: int):
    rng = np.random.default_rng(seed)
    slots = np.sort(rng.choice(state.n_landmarks, size=k, replace=False))
    Hp = rng.standard_normal((k, 4, 6)) * 50
    Hl = rng.standard_normal((k, 4, 3)) * 50
    Hp[:, 3] = Hp[:, 1]  # a stereo pair: the two rows' Jacobians agree
    Hl[:, 3] = Hl[:, 1]
    return slots, rng.standard_normal((k, 4)), Hp, Hl


V4 = np.diag([1.0, 1.0, 1.0, 1.0])
V_UNEQUAL = np.diag([1.0, 0.5, 1.0, 2.0])  # rows vL and vR of unequal noise: not compressed


@needs_kernels
@pytest.mark.parametrize("L, k", [(3, 2), (12, 8), (30, 25), (90, 80)])  # m = 3k: 6 ... 240 (blocked solve)
@pytest.mark.parametrize("V", [V4, V_UNEQUAL], ids=["compressed", "four rows"])
def test_update_matches_numpy(L, k, V):
    a, b = _both(_synthetic(L, seed=L))
    slots, r, Hp, Hl = _observations(a, k, seed=k)
    num, ker = _ops()
    fa, fb = {}, {}
    dxa = num.update(a, slots, r, Hp, Hl, V, factors=fa)
    dxb = ker.update(b, slots, r, Hp, Hl, V, factors=fb)
    _close(dxb, dxa, what="pose correction")
    _close(b.imu_T_world, a.imu_T_world, what="pose")
    _close(b.lm_mean, a.lm_mean, what="landmarks")
    _close(b.cov, a.cov, what="covariance")
    assert np.array_equal(b.cov, b.cov.T)
    # what the adaptive iteration asks of the gain: K dr, step sizes, the prior back
    dr = np.sin(np.arange(4 * k)).reshape(k, 4)
    _close(ker.gain_times(fb, dr), num.gain_times(fa, dr), what="K dr")
    assert abs(ker.step_size(b, slots, fb["dx"]) - num.step_size(a, slots, fa["dx"])) <= 1e-9 * num.step_size(
        a, slots, fa["dx"])
    prior = _synthetic(L, seed=L)
    for ops, s, fac in ((num, a, fa), (ker, b, fb)):
        ops.restore_prior(s, prior.imu_T_world, prior.imu_bias, prior.lm_mean, prior.v_lm_in_world, None, fac)
    _close(b.cov, prior.cov, rtol=1e-9, what="restored covariance")
    _close(a.cov, prior.cov, rtol=1e-9, what="restored covariance (numpy)")


@needs_kernels
def test_an_ill_conditioned_innovation_is_solved_as_numpy_solves_it():
    """A prior far wider than the pixel noise (here 1e7 m landmarks, as after an hour
    without frames): S's condition number ~1e15. The kernels' blocked solve falls back to
    substitution there (its explicit block inverses would lose the digits); the update
    must succeed where numpy's does, and agree with it."""
    a, b = _both(_synthetic(40, seed=5, spread=1e7))
    slots, r, Hp, Hl = _observations(a, 30, seed=9)
    Hl[:5] *= 1e-6  # a few observations nearly blind to their landmark
    num, ker = _ops()
    prior_scale = np.abs(a.cov).max()
    fallbacks = kernels._ekf.counters()["solve_fallbacks"]
    num.update(a, slots, r, Hp, Hl, V4)
    ker.update(b, slots, r, Hp, Hl, V4)
    assert kernels._ekf.counters()["solve_fallbacks"] > fallbacks
    _close(b.imu_T_world, a.imu_T_world, rtol=1e-9, what="pose")
    # Σ loses ~14 digits to cancellation in both (numpy's own diagonal goes negative
    # here): they agree to the rounding of the prior's largest entries
    assert np.abs(b.cov - a.cov).max() <= 1e-11 * prior_scale


@needs_kernels
def test_an_innovation_that_is_not_positive_definite_raises_as_numpy_raises():
    a, b = _both(_synthetic(8, seed=2))
    slots, r, Hp, Hl = _observations(a, 5, seed=1)
    V = -1e9 * np.eye(4)
    num, ker = _ops()
    P_before = b.cov.copy()
    with pytest.raises(np.linalg.LinAlgError):
        num.update(a, slots, r, Hp, Hl, V)
    with pytest.raises(np.linalg.LinAlgError):
        ker.update(b, slots, r, Hp, Hl, V)
    assert np.array_equal(b.cov, P_before)  # left untouched


@needs_kernels
@pytest.mark.parametrize("inverse_depth", [False, True])
def test_compaction_and_marginals_match_numpy(inverse_depth):
    a, b = _both(_synthetic(20, seed=4, inverse_depth=inverse_depth))
    slots = np.array([0, 3, 4, 11, 19])
    pa, ca = a.landmark_marginals(slots)
    pb, cb = b.landmark_marginals(slots)
    _close(pb, pa, what="positions")
    _close(cb, ca, what="covariances")
    a.remove_slots(slots)
    b.remove_slots(slots)
    assert np.array_equal(b.cov, a.cov)  # entries moved, not computed
    assert np.array_equal(b.landmark_ids, a.landmark_ids) and b.dim == a.dim == 6 + 3 * 15


@needs_kernels
def test_health_finds_what_numpy_finds():
    num, ker = _ops()
    for poison in (None, "cov", "pose", "landmark", "diagonal"):
        a, b = _both(_synthetic(6, seed=1))
        for s in (a, b):
            if poison == "cov":
                s.cov[9, 4] = np.nan
            elif poison == "pose":
                s.imu_T_world = s.imu_T_world.copy()
                s.imu_T_world[0, 3] = np.inf
            elif poison == "landmark":
                s.lm_mean[2, 1] = np.nan
            elif poison == "diagonal":
                s.cov[7, 7] = -1e-6
        assert ker.health(b) == num.health(a) == {None: 0, "diagonal": 2}.get(poison, 1), poison


@needs_kernels
def test_drift_sums_match_numpy():
    rng = np.random.default_rng(0)
    k, R = 12, 20
    A = rng.standard_normal((k, 4, 4))
    Lt = np.linalg.cholesky(A @ np.swapaxes(A, 1, 2) + 4 * np.eye(4))
    Ht, r, eps = rng.standard_normal((k, 4, 6)), rng.standard_normal((k, 4)) * 3, rng.standard_normal(6) * 0.1
    ok = rng.random(k) < 0.8
    rows = rng.choice(R, size=k, replace=False)
    sums = [rng.standard_normal((R, 4)), rng.standard_normal((R, 4))]
    counts = rng.integers(0, 4, R).astype(np.float64)
    sa, na, sb, nb = sums[0].copy(), counts.copy(), sums[0].copy(), counts.copy()
    num, ker = _ops()
    ma = num.drift_sums(Lt, Ht, r, eps, ok, rows, sa, na, 3.0)
    mb = ker.drift_sums(Lt, Ht, r, eps, ok, rows, sb, nb, 3.0)
    assert np.array_equal(ma, mb) and ma.any() and not ma.all()
    _close(sb, sa, what="sums")
    assert np.array_equal(nb, na)


RUN_OPTIONS = [dict(), dict(landmark_parametrization="cartesian"), dict(update={"ekf": "standard"}),
               dict(update_iterations=1), dict(update_iteration_tolerance=0.0),
               dict(gating={"drift_test_probability": None}), dict(landmarks={"probation_frames": 2, "init_frames": 3})]


@needs_kernels
@pytest.mark.parametrize("options", RUN_OPTIONS)
def test_whole_runs_agree_with_numpy(drive, options):
    opts = vislam.FilterOptions(velocity_noise_mps=0.3, angular_noise_radps=0.02, **options)
    runs = {}
    for on in (False, True):
        with kernels.use_kernels(on):
            runs[on] = vislam.run(drive.sequence, "slam", opts)
    a, b = runs[False], runs[True]
    assert not a.partial and not b.partial
    assert np.abs(b.world_T_imu[:, :3, 3] - a.world_T_imu[:, :3, 3]).max() < 1e-8
    _close(b.pose_covariance, a.pose_covariance, rtol=1e-6, what="pose covariances")
    assert np.array_equal(b.landmarks.ids, a.landmarks.ids) and np.array_equal(b.landmarks.status, a.landmarks.status)
    assert np.abs(b.landmarks.p_lm_in_world - a.landmarks.p_lm_in_world).max() < 1e-8
    for name in ("observations_used", "observations_gated", "landmarks_rejected", "landmarks_moving"):
        assert getattr(b.stats, name) == getattr(a.stats, name), name


@needs_kernels
def test_the_filter_takes_the_kernels_where_they_cover_its_state(drive, monkeypatch):
    monkeypatch.setattr(kernels, "_ENABLED", True)  # also under VISLAM_KERNELS=0
    cal = drive.sequence.calibration
    assert SlamFilter(cal)._ops.compiled
    assert SlamFilter(cal, vislam.FilterOptions(landmark_parametrization="cartesian",
                                                update={"ekf": "standard"}))._ops.compiled
    assert not SlamFilter(cal, reference=True)._ops.compiled
    assert not SlamFilter(cal, vislam.FilterOptions(landmark_motion=True))._ops.compiled
    assert not SlamFilter(cal, vislam.FilterOptions(imu_bias_sigma_mps=0.1))._ops.compiled
    with kernels.use_kernels(False):
        assert not SlamFilter(cal)._ops.compiled
    assert SlamFilter(cal)._ops.compiled


@needs_kernels
@pytest.mark.parametrize("iterations", [1, 4])
def test_the_update_of_the_filter_is_the_ops_update(drive, iterations):
    """The plain and the iterated update go through the filter's arithmetic object: with
    its ``update`` counted, every update the run records is one of its calls; with it
    failing, the run fails there."""
    f = SlamFilter(drive.sequence.calibration, vislam.FilterOptions(update_iterations=iterations))
    real, calls = f._ops.update, []
    f._ops.update = lambda *a, **k: calls.append(1) or real(*a, **k)
    frames = list(drive.sequence.frames())
    for fr in frames:
        f.step(fr)
    assert calls
    if iterations > 1:
        assert len(calls) == sum(f.diagnostics.update_counts)
    g = SlamFilter(drive.sequence.calibration, vislam.FilterOptions(update_iterations=iterations))

    def failing(*args, **kwargs):
        raise RuntimeError("the ops update")

    g._ops.update = failing
    with pytest.raises(RuntimeError, match="the ops update"):
        for fr in frames:
            g.step(fr)
    assert updaters.slam_update_iterated.__defaults__[-1] is None  # ops: numpy unless given


def test_a_build_older_than_its_source_is_refused(monkeypatch):
    """An editable install whose _ekf.c changed since it was built: the stale extension
    is not called (its arguments may differ); the filter warns once and runs on numpy."""
    import types
    import sys

    monkeypatch.setitem(sys.modules, "vislam.core._ekf", types.SimpleNamespace(ABI_VERSION=kernels.ABI_VERSION - 1))
    module, why = kernels._load()
    assert module is None and "older than its source" in why and "pip install -e ." in why


def test_without_the_extension_the_filter_warns_once_and_runs_on_numpy(drive, monkeypatch, caplog):
    monkeypatch.setattr(kernels, "_ekf", None)
    monkeypatch.setattr(kernels, "_ENABLED", True)
    monkeypatch.setattr(kernels, "UNAVAILABLE", "the compiled extension vislam.core._ekf is not built (test)")
    monkeypatch.setattr(kernels, "_WARNED", False)
    with caplog.at_level("WARNING", logger="vislam.core.kernels"):
        filters = [SlamFilter(drive.sequence.calibration) for _ in range(2)]
    assert all(f.arithmetic == "numpy" for f in filters)
    warnings = [r for r in caplog.records if "not built" in r.getMessage()]
    assert len(warnings) == 1 and "numpy path" in warnings[0].getMessage()


def test_the_compiled_kernels_are_built():
    """The installation this suite runs on built the extension (`pip install` with a C
    compiler): else the filter silently runs 2-3x slower. Set VISLAM_KERNELS=0 to run the
    suite on the numpy path on purpose."""
    import os

    if os.environ.get("VISLAM_KERNELS", "1").strip().lower() in ("0", "false", "no", "off"):
        pytest.skip("VISLAM_KERNELS=0: the numpy path on purpose")
    assert kernels.kernels_available(), kernels.UNAVAILABLE


def test_a_filter_is_picklable_and_goes_on_as_it_would(drive, monkeypatch):
    """Checkpointing a filter (pickle, deepcopy) keeps working with the compiled path,
    and the copy continues exactly as the original; unpickled where the extension is
    missing, it goes on in numpy."""
    import pickle

    frames = list(drive.sequence.frames())
    f = SlamFilter(drive.sequence.calibration, vislam.FilterOptions(velocity_noise_mps=0.3,
                                                                    angular_noise_radps=0.02))
    for fr in frames[:15]:
        f.step(fr)
    copies = [pickle.loads(pickle.dumps(f)), copy.deepcopy(f)]
    for g in [f, *copies]:
        for fr in frames[15:]:
            g.step(fr)
    assert all(np.array_equal(g.world_T_imu, f.world_T_imu) for g in copies)
    assert all(g.arithmetic == f.arithmetic for g in copies)
    monkeypatch.setattr(kernels, "_ekf", None)
    monkeypatch.setattr(kernels, "_WARNED", True)
    g = pickle.loads(pickle.dumps(copies[0]))
    assert g.arithmetic == "numpy" and g.state.kernels is None
    g.step(frames[-1])  # goes on
