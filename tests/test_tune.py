"""vislam tune: the innovation likelihood recovers a simulated drive's noise; the search,
its Dask rounds and the CLI (outputs, errors, tuned.yaml usable by `vislam run`)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import yaml

from vislam.cli import main
from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.core.tune import Candidate, NoiseSearch, SearchSpace, TuneScore, evaluate_candidate, student_t_logpdf
from vislam.tools.config import resolve_options
from vislam.tools.dataset_io import save_sequence

TRUTH = Candidate(velocity_noise_mps=0.3, angular_noise_radps=0.01, pixel_noise_px=1.0)


@pytest.fixture(scope="module")
def drive():
    return simulate_drive(SimulationOptions(n_frames=100, seed=3, velocity_noise_mps=TRUTH.velocity_noise_mps,
                                            angular_noise_radps=TRUTH.angular_noise_radps,
                                            pixel_noise_px=TRUTH.pixel_noise_px))


def test_student_t_tends_to_the_gaussian_and_penalizes_tiny_noise():
    nis, logdet = np.array([0.5, 4.0, 30.0]), np.array([1.0, 2.0, 3.0])
    gauss = student_t_logpdf(nis, logdet, nu=math.inf)
    np.testing.assert_allclose(student_t_logpdf(nis, logdet, nu=1e7), gauss, rtol=1e-5)
    # residual r fixed, S = s² I: as s -> 0 the density must fall (a proper density), not rise
    r2 = 1.0
    values = [float(student_t_logpdf(r2 / s**2, 4 * math.log(s**2))) for s in (1.0, 0.1, 0.01, 0.001)]
    assert values == sorted(values, reverse=True)


def test_objective_peaks_at_the_simulated_noise(drive):
    """The objective at the simulator's true noise beats 4x more and 4x less of each noise."""
    seq = drive.sequence
    at_truth = evaluate_candidate(seq, TRUTH)
    assert at_truth.error is None and at_truth.n_predicted > 1000
    for name in ("velocity_noise_mps", "angular_noise_radps", "pixel_noise_px"):
        for factor in (0.25, 4.0):
            values = TRUTH.to_dict()
            values[name] *= factor
            other = evaluate_candidate(seq, Candidate(**values))
            assert other.objective < at_truth.objective, (name, factor, other.objective, at_truth.objective)


def test_search_rounds_and_parabola_on_a_known_objective():
    """NoiseSearch on a smooth log-concave stand-in objective finds its maximum within
    the last round's step."""
    target = np.log10([0.4, 0.03, 1.3])

    def score(c: Candidate) -> TuneScore:
        return TuneScore(c, objective=-float(np.sum((c.log10 - target) ** 2)))

    search = NoiseSearch(SearchSpace(), start_pixel_noise_px=2.0)
    n_runs = 0
    while batch := search.next_round():
        n_runs += len(batch)
        search.tell([score(c) for c in batch])
    assert n_runs <= SearchSpace().max_runs
    assert np.all(np.abs(search.best.candidate.log10 - target) < 0.06)  # within 15 %


def test_search_walks_to_maxima_far_from_the_grid_along_correlated_ridges():
    """On 20 random asymmetric objectives whose velocity and angular noise are correlated
    (rotated, ill-conditioned, exponential on one side, as the innovation likelihood is:
    steep toward too little noise, flat toward too much), the search ends within 20 % of
    each maximum. A step that halves every round regardless stops short of maxima that
    are several coarse steps from the grid's best point (it ended a factor 20 away on
    these objectives)."""
    rng = np.random.default_rng(0)
    space = SearchSpace(pixel_noise_px=(1.0, 1.0), pixel_points=1)
    for _ in range(20):
        target = np.array([rng.uniform(-2.0, 0.18), rng.uniform(-3.5, -0.82), 0.0])
        th = rng.uniform(0.0, np.pi)
        R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
        a = np.array([1.0, rng.uniform(1.0, 15.0)])

        def score(c: Candidate) -> TuneScore:
            u = 2.0 * R @ (c.log10 - target)[:2]
            return TuneScore(c, objective=-float(np.sum(a * (np.exp(u) - 1.0 - u))))

        search = NoiseSearch(space, start_pixel_noise_px=1.0)
        n_runs = 0
        while batch := search.next_round():
            n_runs += len(batch)
            search.tell([score(c) for c in batch])
        assert n_runs <= space.max_runs
        err = np.abs(search.best.candidate.log10 - target)[:2]
        assert np.all(err < np.log10(1.2)), (target, search.best.candidate)


def test_tune_on_a_local_cluster_recovers_the_noise(drive, tmp_path):
    """The whole search, on a 2-worker LocalCluster started and stopped here: velocity and
    angular noise within a factor 2 of the truth (small grid, short drive)."""
    from vislam.tools.cluster import open_engine
    from vislam.tools.tune import run_tune, write_tune_outputs

    path = tmp_path / "sim.npz"
    save_sequence(drive.sequence, path)
    # grid 0.02, 0.2, 2 m/s x 5e-4, 5e-3, 0.05 rad/s (the truth is off the grid), then one
    # pattern-search round (x and / by 10^0.5); the pixel noise is held at its true value
    space = SearchSpace(velocity_noise_mps=(0.02, 2.0), angular_noise_radps=(5e-4, 0.05), pixel_noise_px=(1.0, 1.0),
                        coarse_points=3, pixel_points=1, refine_rounds=1, parabola=False)
    with open_engine(workers=2) as engine:
        result = run_tune(str(path), engine, space=space, frames=50)
    tuned = result.tuned
    for name in ("velocity_noise_mps", "angular_noise_radps"):
        assert 0.5 <= tuned[name] / TRUTH.to_dict()[name] <= 2.0, (name, tuned)
    assert len(result.scores) <= space.max_runs
    paths = write_tune_outputs(result, tmp_path / "out")
    assert sorted(p.name for p in paths) == ["tune.json", "tune.png", "tuned.yaml"]
    data = json.loads((tmp_path / "out" / "tune.json").read_text())
    assert data["tuned"] == tuned and len(data["candidates"]) == len(result.scores)
    assert len(data["check_estimates"]["velocity_noise_mps"]) == 3


def test_cli_tune_writes_a_config_that_vislam_run_loads(drive, tmp_path, capsys):
    path = tmp_path / "sim.npz"
    save_sequence(drive.sequence, path)
    base = tmp_path / "base.yaml"
    base.write_text("gating_probability: 0.99\nvelocity_noise_mps: 9.0\n")
    out = tmp_path / "tuned"
    assert main(["tune", str(path), "--out", str(out), "--sequential", "--frames", "40", "--grid", "2",
                 "--refine", "0", "--config", str(base), "--quiet"]) == 0
    text = (out / "tuned.yaml").read_text()
    values = yaml.safe_load(text)
    assert values["gating_probability"] == 0.99 and values["velocity_noise_mps"] != 9.0  # base kept, noise tuned
    options = resolve_options(out / "tuned.yaml")
    assert options.velocity_noise_mps == values["velocity_noise_mps"]
    assert main(["run", str(path), "--config", str(out / "tuned.yaml"), "--out", str(tmp_path / "run"),
                 "--quiet"]) == 0


@pytest.mark.parametrize("args, expected", [
    (["/nonexistent/x.npz"], "no such dataset"),
    (["{data}", "--frames", "1"], "--frames must be >= 2"),
    (["{data}", "--config", "{tmp}/missing.yaml"], "missing.yaml"),
    (["{data}", "--sequential", "--scheduler", "tcp://127.0.0.1:9"], "exclude each other"),
    (["{data}", "--grid", "1"], "--grid must be in [2, 30]"),
    (["{data}", "--grid", "1000000"], "--grid must be in [2, 30]"),  # 1e12 runs: it ran for ever
    (["{data}", "--refine", "500"], "--refine in [0, 20]"),
])
def test_cli_tune_bad_input_is_one_line_exit_2(drive, tmp_path, capsys, args, expected):
    path = tmp_path / "sim.npz"
    save_sequence(drive.sequence, path)
    args = [a.format(data=path, tmp=tmp_path) for a in args]
    assert main(["tune", *args, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expected in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_cli_tune_rejects_a_bad_file_before_starting_workers(tmp_path, capsys, monkeypatch):
    """A file that is not a dataset is a one-line error naming it, before any cluster starts."""
    import vislam.tools.cluster as cluster

    def no_engine(*args, **kwargs):
        raise AssertionError("the engine was started before the data file was validated")

    monkeypatch.setattr(cluster, "open_engine", no_engine)
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"this is not a zip archive")
    assert main(["tune", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "bad.npz" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_a_tuned_imu_noise_far_above_the_signal_white_noise_gets_a_note():
    """tune's answer is flagged when it is several times both check's white-noise
    estimate and the filter's default (the sparse KITTI files: slowly varying IMU errors
    bought with white noise), and not when it matches the white noise (dense files)."""
    from vislam.core.options import FilterOptions
    from vislam.tools.tune import _systematic_error_notes

    opts = FilterOptions()
    sparse_like = _systematic_error_notes({"velocity_noise_mps": 0.22, "angular_noise_radps": 0.0093},
                                          {"velocity_noise_mps": [0.0, 0.0, 0.0], "angular_noise_radps": [0.0] * 3},
                                          opts)
    assert len(sparse_like) == 2 and "velocity_noise_mps = 0.22 m/s" in sparse_like[0]
    dense_like = _systematic_error_notes({"velocity_noise_mps": 0.51, "angular_noise_radps": 0.047},
                                         {"velocity_noise_mps": [0.51, 0.52, 0.50],
                                          "angular_noise_radps": [0.05, 0.048, 0.047]}, opts)
    assert dense_like == []


def test_a_recording_in_nanoseconds_fails_with_the_unit_named(tmp_path, capsys):
    """Every candidate fails on frames 1e8 apart; the error said only "every candidate
    failed: ... not positive definite". It names the unit and the fix now, and the fix works."""
    seq = simulate_drive(SimulationOptions(n_frames=40, seed=1, facade_density_per_m=0.5)).sequence
    path = tmp_path / "ns.npz"
    save_sequence(seq.replace(timestamps_s=seq.timestamps_s * 1e9), path)
    code = main(["tune", str(path), "--out", str(tmp_path / "t"), "--sequential", "--frames", "20", "--grid", "2"])
    err = capsys.readouterr().err
    assert code == 2
    assert "every candidate failed" in err and "with time stamps in nanoseconds, add timestamp_scale 1e-09" in err
    config = tmp_path / "ts.yaml"
    config.write_text("timestamp_scale: 1.0e-9\n")
    assert main(["tune", str(path), "--config", str(config), "--out", str(tmp_path / "t2"), "--sequential",
                 "--frames", "20", "--grid", "2"]) == 0
