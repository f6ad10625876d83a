"""Tests of ``vislam info`` (vislam.cli.info)."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest

from conftest import REPO_ROOT, shared_file
from vislam.cli import main
from vislam.core.lie import make_pose, so3_exp


def small_dataset(path, T: int = 9, M: int = 5) -> str:
    """A valid report-convention npz: landmark j seen in frames j .. j+2 (clipped), disparity 10 + j."""
    features = np.full((4, M, T), -1.0)
    for j in range(M):
        for t in range(j, min(j + 3, T)):
            features[:, j, t] = [100.0 + t, 50.0 + j, 90.0 + t - j, 50.0 + j]
    np.savez(
        path,
        time_stamps=(100.0 + 0.1 * np.arange(T))[None, :],
        features=features,
        linear_velocity=np.tile([[3.0], [4.0], [0.0]], (1, T)),
        rotational_velocity=np.zeros((3, T)),
        K=np.array([[700.0, 0.0, 600.0], [0.0, 710.0, 180.0], [0.0, 0.0, 1.0]]),
        b=np.array(0.54),
        cam_T_imu=make_pose(so3_exp([0.1, -0.2, 0.3]), [1.0, -0.3, 0.7]),
    )
    return str(path)


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "vislam", "info", *args],
        capture_output=True,
        text=True,
        cwd=REPO_ROOT,
        timeout=120,
    )


def field(output: str, name: str) -> str:
    match = re.search(rf"^{re.escape(name)}:\s+(.*)$", output, flags=re.MULTILINE)
    assert match, f"no '{name}:' line in:\n{output}"
    return match.group(1)


def test_info_small_file_subprocess(tmp_path):
    path = small_dataset(tmp_path / "small.npz")
    proc = run_cli(path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    out = proc.stdout
    assert field(out, "frames") == "9"
    assert field(out, "file") == path
    assert field(out, "key convention").startswith("report")
    assert field(out, "landmarks").startswith("5 (5 observed")
    # 5 landmarks x 3 frames, minus the clipped ends of landmarks 7, 8 (none here: M=5, T=9)
    assert field(out, "observations").startswith("15 ")
    assert "(0 non-positive)" in field(out, "disparity")
    assert "max 5.000" in field(out, "speed")
    assert "baseline 0.540000 m" in field(out, "calibration")
    assert "-378." in out  # M[2, 3] = -fsu * b = -378


def test_info_json(tmp_path, capsys):
    path = small_dataset(tmp_path / "small.npz", T=6, M=5)
    assert main(["info", "--json", path]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 6
    assert summary["file"] == path
    assert summary["convention"] == "report"
    assert summary["landmarks"] == {"total": 5, "observed": 5}
    # track of landmark j covers frames j..min(j+2, 5): lengths 3, 3, 3, 3, 2
    assert summary["observations"]["total"] == 14
    assert summary["track_length_frames"] == {"min": 2.0, "median": 3.0, "max": 3.0}
    assert summary["disparity_px"]["min"] == 10.0 and summary["disparity_px"]["max"] == 14.0
    assert summary["calibration"]["M"][2][3] == pytest.approx(-700.0 * 0.54)
    assert summary["mean_frame_rate_hz"] == pytest.approx(10.0)


SHARED_FRAMES = {  # from ../shared/data/README.md
    "sparse/0020.npz": 1104,
    "sparse/0027.npz": 1106,
    "sparse/0042.npz": 500,
    "dense/0022.npz": 800,
    "dense/0027.npz": 1106,
    "dense/0034.npz": 1224,
}


@pytest.mark.shared
@pytest.mark.parametrize("relative", sorted(SHARED_FRAMES))
def test_info_shared_datasets(relative, capsys):
    path = shared_file(relative)
    assert main(["info", str(path)]) == 0
    captured = capsys.readouterr()
    assert captured.err == ""
    assert field(captured.out, "frames") == str(SHARED_FRAMES[relative])


def _assert_one_line_error(proc: subprocess.CompletedProcess, path: str) -> None:
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, proc.stderr
    assert path in lines[0]
    assert lines[0].startswith("vislam info: error:")
    assert proc.stdout == ""


def test_info_missing_file(tmp_path):
    path = str(tmp_path / "missing.npz")
    _assert_one_line_error(run_cli(path), path)


def test_info_not_an_npz(tmp_path):
    path = tmp_path / "notes.npz"
    path.write_text("this is not a dataset\n")
    _assert_one_line_error(run_cli(str(path)), str(path))


def test_info_missing_key(tmp_path):
    path = small_dataset(tmp_path / "small.npz")
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if k != "rotational_velocity"}
    np.savez(tmp_path / "nokey.npz", **arrays)
    bad = str(tmp_path / "nokey.npz")
    proc = run_cli(bad)
    _assert_one_line_error(proc, bad)
    assert "'rotational_velocity'" in proc.stderr and "'angular_velocity'" in proc.stderr


def _command_helps(parser) -> dict[str, str]:
    import argparse

    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {a.dest: a.help for a in sub._choices_actions}


def test_command_table_lists_every_command_with_its_modules_own_help_line():
    """``vislam --help`` is built from vislam.cli.COMMANDS without importing the commands:
    its one-line helps and its order must be those the command modules register."""
    from vislam.cli import COMMANDS, build_parser

    assert _command_helps(build_parser("*")) == {name: help_line for name, _, help_line in COMMANDS}
    assert list(_command_helps(build_parser(None))) == [name for name, _, _ in COMMANDS]
    for name, _, help_line in COMMANDS:  # one command's full parser beside the placeholders
        helps = _command_helps(build_parser(name))
        assert list(helps) == [n for n, _, _ in COMMANDS] and helps[name] == help_line


def test_top_level_help_imports_no_command_module_nor_numpy():
    code = ("import sys, contextlib, io\nfrom vislam.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()) as out:\n"
            "    try:\n        main(['--help'])\n    except SystemExit:\n        pass\n"
            "assert 'run' in out.getvalue() and 'simulate' in out.getvalue()\n"
            "print(sorted(m for m in sys.modules if m == 'numpy' or m.startswith('vislam.cli.')))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"


def test_a_command_parser_imports_that_command_only():
    code = ("import sys\nfrom vislam.cli import build_parser\nbuild_parser('eval')\n"
            "print(sorted(m for m in sys.modules if m.startswith('vislam.cli.')))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "['vislam.cli.eval']"
