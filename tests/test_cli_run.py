"""``vislam run`` and ``vislam demo`` end to end: in subprocesses where the process
matters (exit code, streams, file names, start time), else by the entry point in this
process; plus in-process checks of partial runs and Ctrl-C."""

from __future__ import annotations

import json
import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import HALF_SCENE, in_process, shared_file
from vislam.cli import main
from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.errors import EstimationError
from vislam.tools.dataset_io import save_sequence
from vislam.tools.trajectory_io import read_tum, write_kitti

N_FRAMES = 100
TRAJ = {"trajectory.tum", "trajectory.kitti", "trajectory.png", "summary.json"}
LANDMARKS = {"landmarks.ply", "landmarks.npz"}


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """A short simulated drive saved in the dataset format, with its truth."""
    directory = tmp_path_factory.mktemp("data")
    drive = simulate_drive(SimulationOptions(n_frames=N_FRAMES, **HALF_SCENE))
    path = directory / "drive.npz"
    save_sequence(drive.sequence, path)
    return path, drive


def vislam(*args, timeout=300):
    return subprocess.run([sys.executable, "-m", "vislam", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)


def _lines(path):
    return [line for line in path.read_text().splitlines() if line.strip()]


@pytest.mark.parametrize("mode", ["localization", "mapping", "slam"])
def test_run_writes_the_outputs_of_each_mode(tmp_path, sim, mode, capsys):
    """SLAM in a process of its own, the other modes in this one."""
    data, drive = sim
    out = tmp_path / "out"
    args = ("run", data, "--mode", mode, "--out", out)
    proc = vislam(*args) if mode == "slam" else in_process(capsys, *args)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""  # not a terminal: no progress bar
    assert str(out) in proc.stdout and "filter time" in proc.stdout
    expected = TRAJ | (LANDMARKS if mode != "localization" else set())
    assert {p.name for p in out.iterdir()} == expected
    assert len(_lines(out / "trajectory.tum")) == N_FRAMES
    assert len(_lines(out / "trajectory.kitti")) == N_FRAMES
    summary = json.loads((out / "summary.json").read_text())
    assert summary["mode"] == mode and summary["frames"] == N_FRAMES and summary["partial"] is False
    assert summary["dataset"]["name"] == "drive" and summary["dataset"]["path"] == str(data.resolve())
    if mode == "slam":  # which arithmetic the EKF ran (vislam.core.kernels)
        from vislam.core import kernels

        assert summary["filter_arithmetic"] == ("compiled" if kernels.kernels_enabled() else "numpy")
    else:
        assert "filter_arithmetic" not in summary
    ts, poses = read_tum(out / "trajectory.tum")
    np.testing.assert_allclose(ts, drive.sequence.timestamps_s, atol=1e-9)
    # pixel noise only, no IMU noise: every mode follows the true drive closely
    err = np.linalg.norm(poses[:, :3, 3] - drive.world_T_imu[:, :3, 3], axis=1)
    assert err.max() < 1.0, err.max()


def test_quiet_prints_nothing(tmp_path, sim, capsys):
    data, _ = sim
    proc = in_process(capsys, "run", data, "--mode", "slam", "--out", tmp_path / "q", "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == "" and proc.stderr == ""
    assert {p.name for p in (tmp_path / "q").iterdir()} == TRAJ | LANDMARKS


def test_config_file_and_flags_reach_the_filter(tmp_path, sim, capsys):
    data, _ = sim
    config = tmp_path / "filter.toml"
    config.write_text('velocity_noise_mps = 0.5\nangular_noise_radps = 0.05\nekf = "standard"\n')
    proc = in_process(capsys, "run", data, "--out", tmp_path / "o", "--quiet", "--config", config,
                      "--angular-noise", "0.01", "--gate", "off", "--keep-all-landmarks")
    assert proc.returncode == 0, proc.stderr
    options = json.loads((tmp_path / "o" / "summary.json").read_text())["options"]
    assert options["velocity_noise_mps"] == 0.5  # file
    assert options["ekf"] == "standard"  # file
    assert options["angular_noise_radps"] == 0.01  # flag beats file
    assert options["gating_probability"] is None and options["keep_all_landmarks"] is True  # flags
    assert options["pixel_noise_px"] == 2.0  # default


def test_mapping_with_given_poses(tmp_path, sim, capsys):
    data, drive = sim
    poses = tmp_path / "truth.kitti"
    write_kitti(poses, drive.world_T_imu)
    proc = in_process(capsys, "run", data, "--mode", "mapping", "--poses", poses, "--out", tmp_path / "m", "--quiet")
    assert proc.returncode == 0, proc.stderr
    _, est = read_tum(tmp_path / "m" / "trajectory.tum")
    np.testing.assert_allclose(est, drive.world_T_imu, atol=1e-6)
    summary = json.loads((tmp_path / "m" / "summary.json").read_text())
    assert summary["dataset"]["poses"] == str(poses.resolve())


def _bad_inputs(tmp_path, data, drive):
    bad_npz = tmp_path / "bad.npz"
    bad_npz.write_bytes(b"this is not a zip file")
    bad_yaml = tmp_path / "bad.yaml"
    bad_yaml.write_text("velocity_noise_mps: [0.5\n")
    unknown = tmp_path / "unknown.toml"
    unknown.write_text("velocity_noise = 0.5\n")
    blocker = tmp_path / "blocker"
    blocker.write_text("a file, not a directory")
    short = tmp_path / "short.kitti"
    write_kitti(short, drive.world_T_imu[:10])
    return {
        "missing data": (["run", tmp_path / "missing.npz"], "missing.npz"),
        "bad npz": (["run", bad_npz], "bad.npz"),
        "bad config syntax": (["run", data, "--config", bad_yaml], "bad.yaml"),
        "unknown config key": (["run", data, "--config", unknown], "velocity_noise"),
        "missing config": (["run", data, "--config", tmp_path / "nope.yaml"], "nope.yaml"),
        "bad flag value": (["run", data, "--pixel-noise", "-1"], "--pixel-noise"),
        "out is a file": (["run", data, "--out-override", blocker], "blocker"),
        "out under a file": (["run", data, "--out-override", blocker / "sub"], "blocker"),
        "wrong pose count": (["run", data, "--mode", "mapping", "--poses", short], "short.kitti"),
        "poses without mapping": (["run", data, "--poses", short], "--poses"),
    }


@pytest.mark.parametrize("argv, named", [
    (["run", "{data}", "--out", ""], "--out is empty; expected DIR"),  # `--out "$OUT"`, OUT unset: was the cwd
    (["run", "{data}", "--out", "{tmp}/o", "--gt", ""], "--gt is empty; expected FILE"),  # was: no evaluation
    (["run", " ", "--out", "{tmp}/o"], "the DATA argument is empty; expected a path"),
    (["compare", "{data}", "--out", "{tmp}/o", "--config", ""], "--config is empty; expected FILE"),
    (["eval", "{tmp}/a.tum", "", "--out", "{tmp}/o"], "the GT argument is empty"),
    (["sweep", "", "--out", "{tmp}/o"], "the SPEC argument is empty"),
])
def test_an_empty_path_argument_is_a_one_line_error(tmp_path, sim, monkeypatch, capsys, argv, named):
    """An empty string where a path is expected is refused before anything runs: the
    current directory stays empty and no output folder is made."""
    data, _ = sim
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    argv = [a.format(data=data, tmp=tmp_path) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and named in err, err
    assert not list(cwd.iterdir()) and not (tmp_path / "o").exists()


def _out_of(tmp_path, name, args):
    """(args without ``--out-override``, the output folder the case names)."""
    out = tmp_path / f"out-{name.replace(' ', '-')}"
    if "--out-override" in args:
        i = args.index("--out-override")
        out = args[i + 1]
        args = args[:i] + args[i + 2:]
    return args, out


def _assert_one_line_error(name, code, stdout, stderr, needle, out, tmp_path):
    assert code != 0, name
    lines = stderr.splitlines()
    assert len(lines) == 1, (name, stderr)
    assert "Traceback" not in stderr
    assert lines[0].startswith("vislam run: error:"), (name, lines[0])
    assert needle in lines[0], (name, lines[0])
    assert stdout == ""
    if out.name != "blocker":
        assert not out.exists(), name
    assert (tmp_path / "blocker").read_text() == "a file, not a directory"


def test_bad_inputs_give_one_line_and_no_output(tmp_path, sim, capsys):
    """Each bad input by the command's entry point in this process (the exit code it
    returns is the process's, see __main__), and one of them in a process of its own."""
    data, drive = sim
    cases = _bad_inputs(tmp_path, data, drive)
    for name, (args, needle) in cases.items():
        args, out = _out_of(tmp_path, name, args)
        proc = in_process(capsys, *args, "--out", out)
        _assert_one_line_error(name, proc.returncode, proc.stdout, proc.stderr, needle, out, tmp_path)
    args, out = _out_of(tmp_path, "bad npz", cases["bad npz"][0])
    proc = vislam(*args, "--out", out)
    _assert_one_line_error("bad npz (process)", proc.returncode, proc.stdout, proc.stderr, "bad.npz", out, tmp_path)


def test_partial_run_writes_outputs_and_fails(tmp_path, sim, monkeypatch, capsys):
    from vislam.core import kernels, updaters

    data, _ = sim
    calls = {"n": 0}

    def failing(real_update):
        def failing_update(*args, **kwargs):
            calls["n"] += 1
            if calls["n"] >= 50:
                raise EstimationError("simulated divergence")
            return real_update(*args, **kwargs)
        return failing_update

    # the update of either arithmetic (compiled kernels or the numpy reference)
    monkeypatch.setattr(kernels.KernelOps, "update", failing(kernels.KernelOps.update))
    monkeypatch.setattr(updaters, "slam_update", failing(updaters.slam_update))
    out = tmp_path / "partial"
    code = main(["run", str(data), "--out", str(out), "--quiet"])
    captured = capsys.readouterr()
    assert code != 0
    assert captured.out == ""
    lines = captured.err.splitlines()
    assert len(lines) == 1 and "simulated divergence" in lines[0] and "partial" in lines[0]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["partial"] is True and "simulated divergence" in summary["error"]
    assert 0 < summary["frames_processed"] < N_FRAMES
    assert len(_lines(out / "trajectory.tum")) == summary["frames_processed"]
    assert {p.name for p in out.iterdir()} == TRAJ | LANDMARKS


def test_ctrl_c_leaves_no_output_and_says_so(tmp_path, sim, monkeypatch, capsys):
    from vislam.core import estimators

    data, _ = sim

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(estimators, "run_slam", interrupted)
    out = tmp_path / "interrupted"
    code = main(["run", str(data), "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 130
    assert "interrupted" in captured.err and "no output" in captured.err
    assert len(captured.err.splitlines()) == 1
    assert not out.exists()


def test_demo(tmp_path, capsys):
    out = tmp_path / "demo"
    proc = vislam("demo", "--out", out, "--frames", 150, "--seed", 3)
    assert proc.returncode == 0, proc.stderr
    assert "ATE" in proc.stdout
    names = {p.name for p in out.iterdir()}
    assert names >= TRAJ | LANDMARKS | {"groundtruth.tum", "groundtruth.kitti"}
    summary = json.loads((out / "summary.json").read_text())
    assert summary["mode"] == "slam" and summary["frames"] == 150
    assert summary["options"]["velocity_noise_mps"] == 0.5 and summary["options"]["angular_noise_radps"] == 0.05
    assert summary["dataset"]["simulation"]["seed"] == 3
    ate = summary["ground_truth"]["ate_m"]
    assert 0 < ate["slam"] < ate["localization"]
    assert len(_lines(out / "groundtruth.tum")) == 150
    quiet = in_process(capsys, "demo", "--out", tmp_path / "q", "--frames", 60, "--quiet")
    assert quiet.returncode == 0 and quiet.stdout == "" and quiet.stderr == ""


def test_run_on_shared_sparse_0042(tmp_path):
    data = shared_file("sparse/0042.npz")
    out = tmp_path / "0042"
    proc = vislam("run", data, "--mode", "slam", "--out", out, "--quiet")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == summary["frames_processed"] == 500
    assert len(_lines(out / "trajectory.tum")) == 500
    assert summary["landmarks_in_map"] > 0
    assert summary["real_time_factor"] < 1.0


def test_non_utf8_file_name_runs_and_checks(tmp_path, sim):
    # issue 22.5: a byte that is not UTF-8 in the name crashed run (matplotlib title) and check (print)
    data, _ = sim
    name = tmp_path / os.fsdecode(b"drive\xff.npz")
    name.write_bytes(data.read_bytes())
    out = tmp_path / "out"
    proc = vislam("run", name, "--out", out, "--mode", "localization")
    assert proc.returncode == 0, proc.stderr
    assert "drive\\xff" in proc.stdout
    assert {p.name for p in out.iterdir()} == TRAJ
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    assert summary["dataset"]["name"] == "drive\\xff"
    assert summary["dataset"]["path"].endswith("drive\\xff.npz")
    proc = vislam("check", name)
    assert proc.returncode == 0, proc.stderr
    assert "drive\\xff.npz" in proc.stdout and "Traceback" not in proc.stderr


@pytest.mark.skipif(not Path("/proc/self/stat").exists() or shutil.which("sh") is None,
                    reason="needs /proc and a POSIX shell")
def test_total_time_counts_the_command_not_what_its_process_ran_before(sim, tmp_path):
    """A shell runs the last command of ``sh -c '...; vislam ...'`` in its own process (here
    with an explicit exec): the 5 s the shell spent before are not the command's (they
    were). A command in a new process counts from that process's start."""
    data, _ = sim
    exec_out, own_out = tmp_path / "exec", tmp_path / "own"
    script = f"sleep 5; exec {shlex.quote(sys.executable)} -m vislam run {shlex.quote(str(data))} " \
             f"--out {shlex.quote(str(exec_out))} --quiet"
    # the command in a process of its own runs while the shell sleeps (it has the CPU to itself)
    own = subprocess.Popen([sys.executable, "-m", "vislam", "run", str(data), "--out", str(own_out), "--quiet"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    subprocess.run(["sh", "-c", script], check=True, timeout=300)
    _, stderr = own.communicate(timeout=300)
    assert own.returncode == 0, stderr
    after_exec = json.loads((exec_out / "summary.json").read_text())
    own = json.loads((own_out / "summary.json").read_text())
    assert after_exec["filter_seconds"] < after_exec["total_seconds"] < own["total_seconds"] + 3.0
    assert own["filter_seconds"] < own["total_seconds"]


def test_the_real_time_factor_reads_as_faster_or_slower():
    from vislam.cli.common import _times_real_time

    assert _times_real_time(0.029) == "34x faster than real time"
    assert _times_real_time(0.8) == "1.2x faster than real time"
    assert _times_real_time(19.4) == "19x slower than real time"
    assert _times_real_time(1.5) == "1.5x slower than real time"
