"""``vislam report`` on a tiny data folder laid out like the shared data: the command
(on its default local Dask cluster, in a subprocess) and the library in this process
without Dask, which must write the same report."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import pytest

from vislam.cli import main
from vislam.core.lie import se3_inverse
from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.tools.cluster import SequentialEngine
from vislam.tools.dataset_io import save_sequence
from vislam.tools.report import NoiseLevel, ReportSettings, generate_report
from vislam.tools.trajectory_io import write_kitti

from conftest import HALF_SCENE

N_FRAMES = 90  # 116 m: KITTI t needs 100 m segments
N_FRAMES_NO_GT = 40  # the dataset without ground truth: no metric needs its length
SIM_FRAMES = 30
SMALL = ["--sim-frames", str(SIM_FRAMES), "--noise-levels", "0.3:0.006"]
#: SMALL as the library's settings.
SMALL_SETTINGS = ReportSettings(noise_levels=(NoiseLevel(0.3, 0.006),), simulation_frames=SIM_FRAMES)
#: What may differ between two runs of the same report: the time it took.
TIMING_KEYS = ("_seconds", "real_time_factor", "frame_ms_median", "frame_ms_p95")


def vislam(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "vislam", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    """sparse/0100.npz (with KITTI left-camera ground truth) and sparse/0101.npz (without);
    no dense/ folder; a ground-truth file that matches no dataset."""
    root = tmp_path_factory.mktemp("data")
    (root / "sparse").mkdir()
    (root / "groundtruth").mkdir()
    for seed, stem, n_frames in ((0, "0100", N_FRAMES), (1, "0101", N_FRAMES_NO_GT)):
        drive = simulate_drive(SimulationOptions(n_frames=n_frames, seed=seed, **HALF_SCENE))
        save_sequence(drive.sequence, root / "sparse" / f"{stem}.npz")
        if stem == "0100":
            cam_T_imu = drive.sequence.cam_T_imu
            write_kitti(root / "groundtruth" / "0100.txt", cam_T_imu @ drive.world_T_imu @ se3_inverse(cam_T_imu))
    write_kitti(root / "groundtruth" / "0999.txt", drive.world_T_imu)
    return root


@pytest.fixture(scope="module")
def report(data_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("report") / "out"
    proc = vislam("report", "--data", data_dir, "--out", out, "--quiet", *SMALL)
    return out, proc


@pytest.fixture(scope="module")
def sequential(data_dir, tmp_path_factory):
    """The same report by the library, in this process without Dask, and its log lines."""
    lines = []
    result = generate_report(data_dir, tmp_path_factory.mktemp("sequential") / "out", SMALL_SETTINGS,
                             log=lines.append, engine=SequentialEngine())
    return result, lines


def without_timing(value):
    """A JSON value without its timing entries (keys ending in TIMING_KEYS)."""
    if isinstance(value, dict):
        return {k: without_timing(v) for k, v in value.items() if not k.endswith(TIMING_KEYS)}
    if isinstance(value, list):
        return [without_timing(v) for v in value]
    return value


def referenced_figures(markdown: str) -> list[str]:
    return re.findall(r"!\[[^\]]*\]\(([^)]+)\)", markdown)


def table_rows(markdown: str, first_cell: str) -> list[list[str]]:
    rows = []
    for line in markdown.splitlines():
        if line.startswith("| ") and line.split("|")[1].strip() == first_cell:
            rows.append([c.strip() for c in line.strip().strip("|").split("|")])
    return rows


def test_report_is_written_quietly_with_every_figure(report):
    out, proc = report
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == "" and proc.stderr == ""
    assert {p.name for p in out.iterdir()} == {"report.md", "report.html", "runs", "figures"}
    md = (out / "report.md").read_text()
    figures = referenced_figures(md)
    assert len(figures) >= 10
    for rel in figures:
        assert not rel.startswith("/")
        path = out / rel
        assert path.is_file() and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", rel
    # only the figures the report shows are drawn: no run folder holds another PNG
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*.png")) == sorted(figures)
    html = (out / "report.html").read_text()
    assert html.startswith("<!DOCTYPE html>")
    assert html.count('src="data:image/png;base64,') == len(figures)  # self-contained
    for heading in ("## 1. ", "## 2. ", "## 3. ", "## 4. Summary"):
        assert heading in md
        assert heading[3:] in html


def test_report_metrics_row_for_the_dataset_with_ground_truth(report):
    out, _ = report
    md = (out / "report.md").read_text()
    header = next(line for line in md.splitlines() if line.startswith("| Section |"))
    columns = [c.strip() for c in header.strip().strip("|").split("|")]
    ate = columns.index("IMU ATE (m)")
    cam_ate = columns.index("Camera ATE (m)")
    rows = table_rows(md, "datasets")
    with_gt = [r for r in rows if "0100" in r[1]]
    without = [r for r in rows if "0101" in r[1]]
    assert {r[2] for r in with_gt} == {"separately", "SLAM", "smoother", "refined"} and len(without) == 4
    keys = {"separately": "separate", "SLAM": "slam", "smoother": "smoother", "refined": "refine"}
    for r in with_gt:
        key = keys[r[2]]
        metrics = json.loads((out / "runs" / "sparse-0100" / key / "metrics.json").read_text())
        assert r[ate] == f"{metrics['ape_rmse_m']:.2f}"
        assert float(r[ate]) < 5.0  # the camera ground truth was converted to the IMU
        assert r[cam_ate] == f"{metrics['cam_ape_rmse_m']:.2f}"  # and the camera frame evaluated as it is
    assert all(r[ate] == "n/a" and r[cam_ate] == "n/a" for r in without)
    # the noise comparison ran on both sparse datasets, twice per level (filter default / told)
    noise = table_rows(md, "noise")
    assert len(noise) == 2 * 2 * 2
    assert all(r[3] == "σv 0.3 m/s, σω 0.006 rad/s" for r in noise)
    summary = json.loads((out / "runs" / "noise-sparse-0100-v0.3-w0.006-filter-told" / "slam" /
                          "summary.json").read_text())
    assert summary["injected_noise"]["velocity_noise_mps"] == 0.3
    assert summary["options"]["velocity_noise_mps"] == pytest.approx((0.02**2 + 0.3**2) ** 0.5)
    # the moving-landmark section: localization + 4 SLAM variants on two scenes, all graded
    moving = table_rows(md, "moving")
    # (graded against the simulator's IMU truth: no camera frame there)
    assert len(moving) == 10 and all(r[ate] != "n/a" and r[cam_ate] == "n/a" for r in moving)
    # what was missing is said
    assert "dense" in md and "0999.txt" in md


def test_report_progress_lines_on_stderr(data_dir, tmp_path, capsys):
    out = tmp_path / "r"
    code = main(["report", "--data", str(data_dir), "--out", str(out), "--sim-frames", "0", "--noise-levels", "none",
                 "--no-smoother", "--sequential"])
    assert code == 0
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    progress = [line for line in lines if re.match(r"vislam report: \[\d+/4\] ", line)]
    assert len(progress) == 4  # load, two datasets, write
    # then the report's notes, one line each: what was left out is said, not only written in report.md
    notes = lines[len(progress):]
    assert lines[:len(progress)] == progress and all(line.startswith("vislam report: note: ") for line in notes)
    assert any("0999.txt: no dataset named 0999.npz" in line for line in notes)
    assert any("dense: not found" in line for line in notes)
    md = (out / "report.md").read_text()
    assert "section skipped" in md
    assert not table_rows(md, "noise") and not table_rows(md, "moving")
    assert [r[2] for r in table_rows(md, "datasets")] == ["separately", "SLAM"] * 2  # --no-smoother


def test_library_returns_the_structured_result(sequential):
    result, lines = sequential
    out = result.out_dir
    assert result.markdown_path.is_file() and result.html_path.is_file()
    assert result.seconds > 0
    assert len(lines) >= 4 and [re.match(r"\[(\d+)/(\d+)\] ", line).groups() for line in lines] == [
        (str(i), str(len(lines))) for i in range(1, len(lines) + 1)]
    datasets = [r for r in result.rows if r.section == "datasets"]
    assert [r.method for r in datasets] == ["separately", "SLAM", "smoother", "refined"] * 2
    assert len(result.rows) == 2 * 4 + 2 * 2 * 2 + 2 * 5  # datasets, noise (2 sparse x told or not x 2), moving
    assert all((out / f).is_file() for f in result.figures)
    gt_rows = [r for r in datasets if "0100" in r.dataset]
    assert gt_rows and all(r.ate_m is not None and r.kitti_t_pct is not None for r in gt_rows)
    assert all(r.ate_m is None for r in result.rows if "0101" in r.dataset)


def test_report_on_the_cluster_equals_the_sequential_one(report, sequential):
    """The command's runs on its local cluster (worker processes) and the library's in this
    process: the same files, the same estimates and metrics, the same tables but for time."""
    out, proc = report
    assert proc.returncode == 0, proc.stderr
    result, _ = sequential
    seq = result.out_dir
    files = sorted(p.relative_to(out).as_posix() for p in out.rglob("*"))
    assert files == sorted(p.relative_to(seq).as_posix() for p in seq.rglob("*"))
    exact = [f for f in files if f.rsplit("/", 1)[-1] in ("trajectory.tum", "trajectory.kitti", "landmarks.ply",
                                                          "landmarks.npz", "metrics.json")]
    runs = [f.rsplit("/", 1)[0] for f in files if f.endswith("/summary.json")]
    assert len(runs) == len(result.rows) and all(f"{run}/trajectory.tum" in exact for run in runs)
    for f in exact:
        assert (out / f).read_bytes() == (seq / f).read_bytes(), f
    for f in (f for f in files if f.endswith(("comparison.json", "summary.json"))):
        a, b = (json.loads((root / f).read_text()) for root in (out, seq))
        assert without_timing(a) == without_timing(b), f
    md, seq_md = (out / "report.md").read_text(), result.markdown_path.read_text()
    for section in ("datasets", "noise", "moving"):
        timed = len(table_rows(md, section)[0]) - 2  # the last two columns: filter time and RTF
        assert [r[:timed] for r in table_rows(md, section)] == [r[:timed] for r in table_rows(seq_md, section)]


def test_nothing_usable_is_a_clear_error(tmp_path, capsys, monkeypatch):
    """One line, nothing written, and no Dask worker started for a report with no work."""
    from vislam.tools import cluster

    def no_cluster(n):
        raise AssertionError("a local cluster was started for a report with nothing to run")

    monkeypatch.setattr(cluster, "_local_cluster", no_cluster)
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "sparse").mkdir()
    (empty / "sparse" / "notes.txt").write_text("no datasets here")
    broken = tmp_path / "broken"
    (broken / "dense").mkdir(parents=True)
    (broken / "dense" / "0001.npz").write_bytes(b"not a zip")
    for data, words in ((empty, "no usable dataset"), (broken, "0001.npz"), (tmp_path / "missing", "no such")):
        out = tmp_path / f"out-{data.name}"
        code = main(["report", "--data", str(data), "--out", str(out), "--quiet"])
        err = capsys.readouterr().err
        assert code != 0
        assert len(err.strip().splitlines()) == 1 and words in err, err
        assert not out.exists()


def test_bad_report_options(tmp_path, data_dir, capsys):
    code = main(["report", "--data", str(data_dir), "--out", str(tmp_path / "o"), "--sim-frames", "-5"])
    assert code != 0 and "--sim-frames" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_every_dataset_runs_with_its_checks_suggestions(tmp_path):
    """No dense/ special case: a noisy dataset gets the noise vislam check measures, per
    axis, and the report says which options were applied."""
    root = tmp_path / "data"
    (root / "dense").mkdir(parents=True)
    drive = simulate_drive(SimulationOptions(n_frames=150, seed=2, velocity_noise_mps=0.5, angular_noise_radps=0.05))
    save_sequence(drive.sequence, root / "dense" / "0102.npz")
    result = generate_report(root, tmp_path / "r", ReportSettings(noise_levels=(), simulation_frames=0,
                                                                  smoother=False))
    assert [r.method for r in result.rows] == ["separately", "SLAM"]
    summary = json.loads((tmp_path / "r" / "runs" / "dense-0102" / "slam" / "summary.json").read_text())
    suggested = summary["auto"]["suggested"]
    assert summary["options"]["velocity_noise_mps"] == suggested["velocity_noise_mps"]
    assert summary["options"]["angular_noise_radps"] == suggested["angular_noise_radps"]
    # the check measured the simulated noise (per axis, within 30 %)
    assert len(suggested["velocity_noise_mps"]) == 3
    for value in suggested["velocity_noise_mps"]:
        assert value == pytest.approx(0.5, rel=0.3)
    for value in suggested["angular_noise_radps"]:
        assert value == pytest.approx(0.05, rel=0.3)
    md = result.markdown_path.read_text()
    assert "Options from `vislam check`: velocity_noise_mps (" in md
    assert "WARN noise" in md


def test_slam_beats_separately_says_it_by_each_metric():
    from types import SimpleNamespace

    from vislam.tools.report import slam_beats_separately

    def row(cam_ate, cam_t, ate=None, t=None):
        return SimpleNamespace(cam_ate_m=cam_ate, cam_kitti_t_pct=cam_t, ate_m=ate, kitti_t_pct=t)

    # the sparse 0020 case: SLAM worse by ATE, better by KITTI t
    assert slam_beats_separately(row(13.75, 7.94), row(17.07, 6.08)) == "ATE no, KITTI t yes"
    assert slam_beats_separately(row(None, None, 3.0, 2.0), row(None, None, 2.0, 1.0)) == "ATE yes, KITTI t yes"
    assert slam_beats_separately(row(None, None), row(None, None)) == "n/a"


def test_discovery_takes_upper_case_npz_and_notes_what_it_cannot_use(tmp_path):
    """`0100.NPZ` is a dataset (it was "no usable dataset"); a ground-truth path that is a
    directory, and a ground truth that covers few of the frames, are said in the notes
    instead of being dropped or used silently."""
    from vislam.tools.report import _load_inputs, discover_datasets

    drive = simulate_drive(SimulationOptions(n_frames=30, seed=4))
    root = tmp_path / "data"
    (root / "sparse").mkdir(parents=True)
    (root / "groundtruth" / "0102.txt").mkdir(parents=True)  # a directory, not a file
    save_sequence(drive.sequence, root / "sparse" / "0100.npz")
    (root / "sparse" / "0100.npz").rename(root / "sparse" / "0100.NPZ")
    save_sequence(drive.sequence, root / "sparse" / "0102.npz")
    cam_T_imu = drive.sequence.cam_T_imu
    write_kitti(root / "groundtruth" / "0100.txt", (cam_T_imu @ drive.world_T_imu @ se3_inverse(cam_T_imu))[:5])
    found, notes = discover_datasets(root)
    assert sorted(d.path.name for d in found) == ["0100.NPZ", "0102.npz"]
    assert any("0102.txt: is not a file" in n for n in notes)
    usable = _load_inputs(found, notes)
    assert len(usable) == 2
    assert any("covers 5 of the 30 frames" in n and "0100.NPZ" in n for n in notes)
