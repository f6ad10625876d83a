"""A run folder is committed in one step (issue 22.6): a run killed (SIGKILL) at any
moment of its commit leaves the previous complete folder or the new complete one, never
a mix; the staging directories of killed runs are removed by the next run."""

from __future__ import annotations

import os
import shutil
import signal
import time

import pytest

from vislam.tools import outputs
from vislam.tools.outputs import OutputStage, clean_stale_staging

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="kills a forked child")

OLD = {"trajectory.tum": "old tum", "summary.json": "old summary", "landmarks.ply": "old ply"}
NEW = {"trajectory.tum": "new tum", "summary.json": "new summary", "trajectory.png": "new png"}
FOREIGN = {"notes.txt": "the user's own file", "sub/deeper.txt": "and a folder of theirs"}


def _write(out, files):
    with OutputStage(out) as stage:
        for name, text in files.items():
            stage.path(name).write_text(text)
        stage.commit(order=("trajectory.tum",))


def _state(out) -> dict[str, str]:
    return {str(p.relative_to(out)): p.read_text() for p in sorted(out.rglob("*")) if p.is_file()}


def _debris(out) -> list[str]:
    near = list(out.iterdir()) + list(out.parent.iterdir())
    return sorted(p.name for p in near if "vislam-staging" in p.name)


def _commit_killed_at(out, n: int) -> bool:
    """Commit NEW in a forked child that SIGKILLs itself at the n-th file-system step of
    the commit; True if the child finished (n beyond the last step)."""
    pid = os.fork()
    if pid == 0:  # the child: never returns into pytest
        try:
            calls = [0]

            def killing(fn):
                def wrapper(*args, **kwargs):
                    calls[0] += 1
                    if calls[0] == n:
                        os.kill(os.getpid(), signal.SIGKILL)
                    return fn(*args, **kwargs)
                return wrapper

            stage = OutputStage(out).__enter__()
            for name, text in NEW.items():
                stage.path(name).write_text(text)
            for mod, name in ((os, "replace"), (os, "link"), (os, "mkdir"), (os, "unlink"), (shutil, "rmtree"),
                              (outputs, "_exchange")):
                setattr(mod, name, killing(getattr(mod, name)))
            stage.commit(order=("trajectory.tum",))
            stage.__exit__(None, None, None)
        finally:
            os._exit(0)
    _, status = os.waitpid(pid, 0)
    return os.WIFEXITED(status)


def test_a_kill_at_any_step_of_the_commit_leaves_a_complete_folder(tmp_path):
    out = tmp_path / "out"
    old, new = {**OLD, **FOREIGN}, {**NEW, **FOREIGN}
    for n in range(1, 60):
        if out.exists():
            shutil.rmtree(out)
        _write(out, OLD)
        (out / "sub").mkdir()
        for name, text in FOREIGN.items():
            (out / name).write_text(text)
        assert _state(out) == old
        finished = _commit_killed_at(out, n)
        state = _state(out)
        assert state in (old, new), f"killed at step {n}: a mixed folder {state}"
        if finished:
            assert state == new
            break
    else:
        pytest.fail("the commit never finished")
    assert n > 3  # the commit has several steps (links, the exchange, the clean-up), each one was a kill
    # the next run removes what killed runs left
    _write(out, NEW)
    assert _debris(out) == [] and _state(out) == new


def test_stale_staging_directories_are_removed_and_live_ones_kept(tmp_path):
    out = tmp_path / "out"
    _write(out, OLD)
    old_style = out / ".vislam-staging-k2j4h5g6"  # left by a kill -9 of an earlier version
    old_style.mkdir()
    (old_style / "trajectory.tum").write_text("partial")
    past = time.time() - 2 * outputs._OLD_STAGE_AGE_S
    os.utime(old_style, (past, past))
    pid = os.fork()
    if pid == 0:
        os._exit(0)
    os.waitpid(pid, 0)  # a process that no longer exists
    dead = tmp_path / f".out.vislam-staging-{outputs._host()}-{pid}-abcd1234"
    dead.mkdir()
    live = out / f".vislam-staging-{outputs._host()}-{os.getpid()}-abcd1234"
    live.mkdir()
    removed = clean_stale_staging(out)
    assert sorted(p.name for p in removed) == sorted([old_style.name, dead.name])
    assert live.exists()
    shutil.rmtree(live)
    _write(out, NEW)
    assert _debris(out) == [] and _state(out) == NEW


def test_without_renameat2_the_commit_falls_back_to_renames(tmp_path, monkeypatch):
    out = tmp_path / "out"
    _write(out, OLD)
    (out / "notes.txt").write_text(FOREIGN["notes.txt"])
    monkeypatch.setattr(outputs, "_exchange", lambda a, b: False)
    _write(out, NEW)  # landmarks.ply (a mode file this run did not make) goes, the user's file stays
    assert _state(out) == {**NEW, "notes.txt": FOREIGN["notes.txt"]} and _debris(out) == []
