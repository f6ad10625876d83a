"""Ctrl-C during ``vislam run`` leaves either complete outputs or none, and says so in
one line — at any moment, including while Python is still importing (the first delays
land there, see ``vislam._launcher``). A signal that arrives before the interpreter
has run any of vislam's code (its own start-up, ~20-100 ms) is Python's to report."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import time

import pytest

from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.tools.dataset_io import save_sequence

EXPECTED = {"trajectory.tum", "trajectory.kitti", "trajectory.png", "summary.json", "landmarks.ply", "landmarks.npz"}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "drive.npz"
    save_sequence(simulate_drive(SimulationOptions(seed=0, n_frames=600)).sequence, path)
    return path


def _before_vislam_started(stderr: str) -> bool:
    """True if the interrupt landed before the launcher's code ran: Python's own start-up
    (runpy, the standard library it imports, the import of ``vislam.__main__``), whose
    report is Python's — a traceback that ends in KeyboardInterrupt and passes through no
    file of vislam but ``__main__.py``."""
    files = re.findall(r'File "([^"]+)"', stderr)
    lines = stderr.strip().splitlines()
    return (bool(lines) and lines[-1] == "KeyboardInterrupt"
            and all(not re.search(r"[/\\]vislam[/\\]", f) or f.endswith("__main__.py") for f in files))


def _launcher_script(path, definitions: str, main: str):
    """A script at ``path`` that runs vislam's launcher as ``vislam run`` with
    ``vislam.cli.main`` replaced by ``main`` (an expression over ``definitions``, which
    come after ``import sys, time`` and ``import vislam.cli``)."""
    path.write_text("import sys, time\nimport vislam.cli\n" + definitions + f"vislam.cli.main = {main}\n"
                    "from vislam._launcher import entry_point\nsys.argv = ['vislam', 'run']\nentry_point()\n")
    return path


@contextlib.contextmanager
def _sigint_default():
    """Children started in the block get SIGINT's default, as a terminal's Ctrl-C: a pytest
    started with SIGINT ignored (`cmd &` in a script, nohup) would pass that on through
    exec, and the child would finish every run; a Python handler in this process for the
    moment of the fork leaves the child the default."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _processes_marked(marker: str) -> list[int]:
    """Pids of the processes whose environment holds ``marker`` (a run and the helper
    process it started for its figure, vislam.tools.figure_process, inherit it)."""
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/environ", "rb") as f:
                    if marker.encode() in f.read():
                        found.append(int(entry))
            except OSError:  # gone meanwhile, or not ours
                pass
    return found


def _marked_env(tmp_path) -> tuple[dict, str]:
    marker = f"VISLAM_TEST_MARK={tmp_path.name}-{os.getpid()}-{time.monotonic_ns()}"
    return {**os.environ, marker.split("=")[0]: marker.split("=")[1]}, marker


@pytest.mark.skipif(os.name != "posix", reason="SIGINT delivery")
@pytest.mark.parametrize("delay_s", [0.1, 0.2, 0.3, 0.5, 0.8, 1.5, 3.0])
def test_sigint_leaves_all_or_nothing(dataset, tmp_path, delay_s):
    out = tmp_path / "out"
    env, marker = _marked_env(tmp_path)
    with _sigint_default():
        proc = subprocess.Popen([sys.executable, "-m", "vislam", "run", str(dataset), "--mode", "slam", "--out",
                                 str(out), "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                env=env)
    time.sleep(delay_s)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    assert _processes_marked(marker) == []  # the figure's helper process ended with the run
    if _before_vislam_started(stderr):  # a loaded machine can take 0.1 s to start Python itself
        assert not out.exists()
        return
    assert "Traceback" not in stderr
    present = {p.name for p in out.iterdir()} if out.exists() else set()
    if proc.returncode == 0:  # finished before the signal arrived
        assert delay_s > 0.5, "a 600-frame run cannot finish in 0.5 s: the interrupt was lost"
        assert EXPECTED <= present
    else:
        assert proc.returncode == 130
        assert len(stderr.strip().splitlines()) == 1 and "interrupt" in stderr.lower()
        assert present in (set(), EXPECTED | present) and (not present or EXPECTED <= present)
        assert not [p for p in present if p.startswith(".")]  # no staging debris


@pytest.mark.skipif(os.name != "posix", reason="SIGINT delivery")
def test_ctrl_c_to_the_process_group_ends_the_run_and_its_figure_helper(dataset, tmp_path):
    """A terminal's Ctrl-C reaches every process of the group: the run and the helper
    process drawing its figure. The helper ignores it; the run reports the interrupt in
    one line and ends the helper."""
    out = tmp_path / "out"
    env, marker = _marked_env(tmp_path)
    with _sigint_default():
        proc = subprocess.Popen([sys.executable, "-m", "vislam", "run", str(dataset), "--mode", "slam", "--out",
                                 str(out), "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                env=env, start_new_session=True)
    deadline = time.monotonic() + 60
    while len(_processes_marked(marker)) < 2 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)  # until the helper has started
    assert len(_processes_marked(marker)) == 2, "no helper process for the figure"
    time.sleep(0.3)
    os.killpg(proc.pid, signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    assert _processes_marked(marker) == []
    assert "Traceback" not in stderr
    assert proc.returncode == 130 and not out.exists()
    assert len(stderr.strip().splitlines()) == 1 and stderr.startswith("vislam run: interrupted")


@pytest.mark.skipif(os.name != "posix", reason="process exit codes")
def test_an_interrupt_wrapped_by_python_is_still_one_line_and_130(tmp_path):
    """A Ctrl-C that lands in ``__set_name__`` while an imported module defines a class
    reaches the launcher, on Python 3.11, as a RuntimeError caused by the
    KeyboardInterrupt (seen under CPU load: a traceback ending in StereoCamera). It is an
    interrupt all the same; any other error still propagates."""
    script = _launcher_script(
        tmp_path / "boom.py",
        "class Descriptor:\n"
        "    def __set_name__(self, owner, name):\n"
        "        raise KeyboardInterrupt\n"
        "def interrupted_while_defining_a_class():\n"
        "    class Camera:\n"
        "        x = Descriptor()\n"
        "def failing():\n"
        "    raise RuntimeError('a real bug')\n",
        "interrupted_while_defining_a_class if sys.argv[1] == 'interrupt' else failing")
    proc = subprocess.run([sys.executable, str(script), "interrupt"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 130
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip() == "vislam run: interrupted; no output written"
    bug = subprocess.run([sys.executable, str(script), "bug"], capture_output=True, text=True, timeout=120)
    assert bug.returncode == 1 and "RuntimeError: a real bug" in bug.stderr


@pytest.mark.skipif(os.name != "posix", reason="process exit codes")
def test_an_interrupt_python_cannot_propagate_is_still_one_line_and_130(tmp_path):
    """A Ctrl-C that lands in a callback Python cannot propagate from (seen under CPU load:
    a weakref callback of the import system's module locks during the start-up imports)
    used to print "Exception ignored ... KeyboardInterrupt" with a traceback and be lost;
    it now ends the run as any interrupt. Other unraisable errors are still printed."""
    script = _launcher_script(
        tmp_path / "unraisable.py",
        "class Bomb:\n"
        "    def __init__(self, exc):\n"
        "        self.exc = exc\n"
        "    def __del__(self):\n"
        "        raise self.exc\n"
        "def interrupted_in_a_callback():\n"
        "    Bomb(KeyboardInterrupt())  # dropped at once: the exception of __del__ is unraisable\n"
        "    for _ in range(500):\n"
        "        time.sleep(0.01)\n"
        "    return 0\n"
        "def other_unraisable():\n"
        "    Bomb(ValueError('raised in __del__'))\n"
        "    return 0\n",
        "interrupted_in_a_callback if sys.argv[1] == 'interrupt' else other_unraisable")
    with _sigint_default():  # the interrupt is delivered through SIGINT's handler, which must be ours
        proc = subprocess.run([sys.executable, str(script), "interrupt"], capture_output=True, text=True,
                              timeout=120)
    assert proc.returncode == 130
    assert proc.stderr.strip() == "vislam run: interrupted; no output written"
    other = subprocess.run([sys.executable, str(script), "other"], capture_output=True, text=True, timeout=120)
    assert other.returncode == 0
    assert "Exception ignored" in other.stderr and "ValueError: raised in __del__" in other.stderr


@pytest.mark.skipif(os.name != "posix", reason="SIGINT delivery")
def test_an_interrupt_during_an_import_waits_for_the_import_to_finish(tmp_path):
    """A Ctrl-C that lands inside an import must not reach the module being imported: C
    code can turn it into another error (seen in CI: numpy reported an interrupted
    ``import datetime`` as "PyCapsule_Import could not import module", a traceback). The
    module here converts an interrupt into an ImportError as numpy does; the launcher holds
    the interrupt back until the import is done, then ends the run in one line with 130."""
    (tmp_path / "converting_module.py").write_text(
        "import os, signal\n"
        "try:\n"
        "    os.kill(os.getpid(), signal.SIGINT)\n"
        "    total = 0\n"
        "    for i in range(200_000):  # bytecode: where a Python signal handler runs\n"
        "        total += i\n"
        "except KeyboardInterrupt:\n"
        "    raise ImportError('the interrupt reached the import')\n"
        "print('imported to the end', flush=True)  # still inside the import: the interrupt waits\n")
    script = _launcher_script(
        tmp_path / "importing.py",
        f"sys.path.insert(0, {str(tmp_path)!r})\n"
        "def main():\n"
        "    import converting_module  # noqa: F401\n"
        "    for _ in range(500):\n"
        "        time.sleep(0.01)\n"
        "    print('not interrupted', flush=True)\n"
        "    return 0\n",
        "main")
    with _sigint_default():
        proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert proc.stdout.splitlines() == ["imported to the end"]
    assert proc.returncode == 130
    assert proc.stderr.strip() == "vislam run: interrupted; no output written"
