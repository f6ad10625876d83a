"""``vislam sweep`` and the Dask engine: a small sweep of simulated drives on a local
cluster the tests start and stop, against the same cells run in this process; resuming;
failed cells; SPEC errors. (``vislam report`` on its cluster against its sequential run:
tests/test_report.py.)"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path

import pytest

from vislam.cli import main
from vislam.core.lie import se3_inverse
from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.errors import ClusterError, ConfigError
from vislam.tools.cluster import SequentialEngine, open_engine
from vislam.tools.dataset_io import save_sequence
from vislam.tools.sweep import (COLUMNS, RESULTS_FILE, SUMMARY_FIGURE, load_spec, read_results, rows_equal,
                                run_sweep)
from vislam.tools.trajectory_io import write_kitti, write_tum

from conftest import HALF_SCENE

N_FRAMES = 40
INJECTED_V, INJECTED_W = 0.1, 0.002


@pytest.fixture(scope="module")
def cluster():
    """A local Dask cluster (2 worker processes), started and stopped by this module."""
    with open_engine(workers=2) as engine:
        yield engine


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Two simulated drives as npz: one with TUM ground truth of the IMU, one with KITTI
    ground truth of the left camera (the layout of the shared data)."""
    root = tmp_path_factory.mktemp("sweepdata")
    for seed, stem in ((0, "a"), (1, "b")):
        drive = simulate_drive(SimulationOptions(n_frames=N_FRAMES, seed=seed, **HALF_SCENE))
        seq = drive.sequence
        save_sequence(seq, root / f"{stem}.npz")
        if stem == "a":
            write_tum(root / "a.tum", seq.timestamps_s, drive.world_T_imu)
        else:
            write_kitti(root / "b.txt", seq.cam_T_imu @ drive.world_T_imu @ se3_inverse(seq.cam_T_imu))
    return root


def write_spec(directory: Path, extra_dataset: str = "") -> Path:
    spec = directory / "spec.yaml"
    spec.write_text(f"""
datasets:
  - path: a.npz                 # relative: to the SPEC's folder
    groundtruth: a.tum
    gt_format: tum
  - path: b.npz
    groundtruth: b.txt
    gt_frame: cam
{extra_dataset}
modes: [slam]
options:
  default: {{}}
  told: {{velocity_noise_mps: {math.hypot(0.02, INJECTED_V)}, angular_noise_radps: {INJECTED_W}}}
noise:
  imu: {{velocity_noise_mps: {INJECTED_V}, angular_noise_radps: {INJECTED_W}}}
seeds: [0, 1]
""", encoding="utf-8")
    return spec


BROKEN = """  - path: missing.npz
    name: broken"""


@pytest.fixture(scope="module")
def sweeps(data, cluster, tmp_path_factory):
    """The same SPEC (2 drives + a broken path, x 2 option sets x 2 seeds) swept on the
    local cluster and in this process."""
    spec = load_spec(write_spec(data, BROKEN))
    out = tmp_path_factory.mktemp("sweeps")
    on_cluster = run_sweep(spec, out / "cluster", cluster)
    in_process = run_sweep(spec, out / "sequential", SequentialEngine())
    return spec, on_cluster, in_process


def test_cluster_sweep_equals_sequential_run_cell_by_cell(sweeps):
    spec, on_cluster, in_process = sweeps
    assert on_cluster.n_cells == in_process.n_cells == 3 * 2 * 2
    assert rows_equal(on_cluster.rows, in_process.rows) == []
    # and the file on disk is that table, one row per cell, in grid order
    on_disk = read_results(on_cluster.results_path)
    assert [tuple(r[c] for c in ("dataset", "options", "seed")) for r in on_disk] == [
        (d, o, s) for d in ("a", "b", "broken") for o in ("default", "told") for s in ("0", "1")]
    # the cluster's rows were computed by its worker processes, not by this one
    pids = {r["worker"].rsplit(":", 1)[1] for r in on_cluster.rows}
    assert str(os.getpid()) not in pids
    assert str(os.getpid()) in {r["worker"].rsplit(":", 1)[1] for r in in_process.rows}


def test_sweep_recovers_the_simulated_ground_truth(sweeps):
    _, on_cluster, _ = sweeps
    ok = [r for r in on_cluster.rows if r["dataset"] != "broken"]
    assert all(r["status"] == "ok" for r in ok)
    for r in ok:
        assert int(r["frames_processed"]) == N_FRAMES
        assert int(r["n_frames_compared"]) == N_FRAMES
        # a 40-frame drive (4 s) with small injected IMU noise: SLAM stays within a metre
        assert 0 < float(r["ate_m"]) < 1.0
        assert int(r["landmarks_in_map"]) > 0 and int(r["observations_used"]) > 0
        assert r["nis_mean"] == "" or math.isfinite(float(r["nis_mean"]))
    # the seed changes the injected noise, hence the result
    by_key = {(r["dataset"], r["options"], r["seed"]): float(r["ate_m"]) for r in ok}
    assert by_key["a", "default", "0"] != by_key["a", "default", "1"]
    assert on_cluster.figure_path is not None and on_cluster.figure_path.name == SUMMARY_FIGURE
    assert on_cluster.figure_path.stat().st_size > 0


def test_broken_dataset_is_an_error_row_and_the_sweep_completes(sweeps):
    _, on_cluster, _ = sweeps
    broken = [r for r in on_cluster.rows if r["dataset"] == "broken"]
    assert len(broken) == 4
    assert all(r["status"] == "error" and "missing.npz" in r["error"] for r in broken)
    assert on_cluster.n_errors == 4


def test_resume_runs_only_missing_and_failed_cells(sweeps, data, tmp_path):
    spec, on_cluster, _ = sweeps
    path = tmp_path / RESULTS_FILE
    rows = read_results(on_cluster.results_path)
    removed = {("a", "told", "1"), ("b", "default", "0")}
    kept = [r for r in rows if (r["dataset"], r["options"], r["seed"]) not in removed]
    with open(path, "w", encoding="utf-8", newline="") as fp:
        w = csv.writer(fp, lineterminator="\n")
        w.writerow(COLUMNS)
        w.writerows([r[c] for c in COLUMNS] for r in kept)
        fp.write("a,slam,default,imu,0,ok,,40")  # a line cut short by a kill: no newline
    before = {(r["dataset"], r["options"], r["seed"]): r for r in kept}

    result = run_sweep(spec, tmp_path, SequentialEngine())
    assert result.n_skipped == 12 - 2 - 4  # the 4 error rows of the broken dataset run again
    assert result.n_run == 2 + 4
    after = {(r["dataset"], r["options"], r["seed"]): r for r in read_results(path)}
    assert len(after) == 12 and len(read_results(path)) == 12
    for key, row in after.items():
        if key in removed or key[0] == "broken":
            assert key not in before or row["finished_at"] != before[key]["finished_at"]
            assert row["worker"].endswith(f":{os.getpid()}")  # recomputed now, here
        else:
            assert row == before[key]  # untouched
    assert rows_equal(after.values(), on_cluster.rows) == []

    again = run_sweep(spec, tmp_path, SequentialEngine(), figure=False)
    assert again.n_run == 4 and again.n_skipped == 8  # only the failed cells


@pytest.mark.parametrize("text, expected", [
    ("datasets: []\n", "datasets"),
    ("datasets: [{path: a.npz, gt_frame: cam}]\n", "gt_format/gt_frame given without a groundtruth"),
    ("datasets: [{path: a.npz, colour: red}]\n", "datasets[0]: unknown key 'colour'"),
    ("datasets: [a.npz]\nmodes: [flying]\n", "modes: unknown mode 'flying'"),
    ("datasets: [a.npz]\noptions: {fast: {velocity_noise_mps: -1}}\n", "options.fast"),
    ("datasets: [a.npz]\noptions: {fast: {warp: 9}}\n", "unknown option(s) 'warp'"),
    ("datasets: [a.npz]\nnoise: {x: {seed: 3}}\n", "noise.x: 'seed' is not a noise setting"),
    ("datasets: [a.npz]\nnoise: {x: {outlier_fraction: 1.5}}\n", "noise.x"),
    ("datasets: [a.npz]\nseeds: [0, -1]\n", "seeds"),
    ("datasets: [a.npz, {path: sub/a.npz}]\n", "name 'a' is used twice"),
    ("datasets: [a.npz]\nsedes: [1]\n", "unknown key 'sedes'"),
    ("datasets: [a.npz\n", "invalid YAML"),
])
def test_spec_errors_are_one_line_config_errors(tmp_path, text, expected):
    spec = tmp_path / "bad.yaml"
    spec.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_spec(spec)
    message = str(info.value)
    assert "\n" not in message and str(spec) in message and expected in message


def test_cli_sweep_sequential_and_spec_error(data, tmp_path, capsys):
    spec = tmp_path / "one.toml"
    spec.write_text(f'datasets = [{{ path = "{data / "a.npz"}" }}]\nmodes = ["localization"]\n', encoding="utf-8")
    assert main(["sweep", str(spec), "--out", str(tmp_path / "out"), "--sequential", "--quiet"]) == 0
    rows = read_results(tmp_path / "out" / RESULTS_FILE)
    assert [(r["mode"], r["status"], r["ate_m"]) for r in rows] == [("localization", "ok", "")]  # no ground truth
    assert run_sweep(load_spec(spec), tmp_path / "out", figure=False).n_run == 0  # done
    spec.write_text(spec.read_text() + "[options.default]\nvelocity_noise_mps = 0.05\n", encoding="utf-8")
    edited = run_sweep(load_spec(spec), tmp_path / "out", figure=False)  # same names, new values: run again
    assert (edited.n_run, edited.rows[0]["options_values"]) == (1, '{"velocity_noise_mps":0.05}')
    capsys.readouterr()
    bad = tmp_path / "bad.yaml"
    bad.write_text("datasets: 3\n", encoding="utf-8")
    assert main(["sweep", str(bad), "--out", str(tmp_path / "out2")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(bad) in err and "datasets" in err
    assert not (tmp_path / "out2").exists()


def test_unreachable_scheduler_is_a_one_line_error(monkeypatch):
    import vislam.tools.cluster as cluster_module

    monkeypatch.setattr(cluster_module, "CONNECT_TIMEOUT_S", 1)
    with pytest.raises(ClusterError, match="--scheduler tcp://127.0.0.1:9: cannot connect") as info:
        with open_engine("tcp://127.0.0.1:9"):
            pass
    assert "\n" not in str(info.value)
