"""The trajectory figure drawn by a helper process, so that matplotlib's import overlaps the filter.

Importing matplotlib and drawing the first figure costs about half a second of a
`vislam run` (more than the filter of a short recording). :class:`FigureProcess` starts
a second Python process once a command has checked its inputs; that process imports
matplotlib and draws a small first figure (fonts, the PNG writer) on the other core
while this one filters, then draws :func:`vislam.tools.plotting.plot_trajectory_map` when asked — the same
function, with the same arguments, so the PNG is the one this process would draw.

The data cross a pipe as an ``.npz`` archive read with ``allow_pickle=False`` (arrays,
and the strings and numbers of the call as JSON); the answer comes back as JSON. When
the helper cannot help — it could not start, did not answer, or failed — the figure is
drawn here instead, so a figure never depends on the helper: the helper only saves time.
It is not started when matplotlib is already imported here (a long-lived process: a
test run, a notebook), where it would save nothing, nor on a single core.

The helper ignores Ctrl-C (the terminal sends it to both processes): this process
handles the interrupt and ends the helper, as it does when it has no figure to draw.
"""

from __future__ import annotations

import io
import json
import logging
import os
import signal
import subprocess
import sys
from dataclasses import fields
from pathlib import Path

import numpy as np

__all__ = ["FigureProcess"]

logger = logging.getLogger(__name__)

#: Longest wait (s) for the helper's figure before drawing it here instead.
ANSWER_TIMEOUT_S = 300.0


class FigureProcess:
    """A helper process that draws :func:`~vislam.tools.plotting.plot_trajectory_map`.

    Created idle; :meth:`start` starts the helper. Use it as a context manager (or call
    :meth:`close`): the helper ends with it. Without a helper (not started, or gone),
    :meth:`plot_trajectory_map` draws in this process.
    """

    def __init__(self) -> None:
        self._proc: subprocess.Popen | None = None

    def start(self, only_if_useful: bool = True) -> bool:
        """Start the helper; True if it runs. With ``only_if_useful``, not where it would
        save nothing: matplotlib already imported here, or a single core."""
        if self._proc is not None:
            return True
        if only_if_useful and ("matplotlib.figure" in sys.modules or (os.cpu_count() or 1) < 2):
            return False
        package_root = str(Path(__file__).resolve().parents[2])  # the folder that holds vislam/
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (package_root, env.get("PYTHONPATH")) if p)
        try:
            self._proc = subprocess.Popen([sys.executable, "-m", "vislam.tools.figure_process"],
                                          stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                          env=env)
        except OSError as exc:  # e.g. no process can be created: draw here
            logger.debug("no figure helper process: %s", exc)
            return False
        return True

    def __enter__(self) -> FigureProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """End the helper if it is still running (it has nothing more to draw)."""
        proc, self._proc = self._proc, None
        if proc is not None and proc.poll() is None:
            proc.kill()
        if proc is not None:
            proc.wait()
            for pipe in (proc.stdin, proc.stdout):
                if pipe is not None:
                    pipe.close()

    def plot_trajectory_map(self, path, curves, landmarks=None, title: str = "", subtitle: str | None = None) -> dict:
        """:func:`vislam.tools.plotting.plot_trajectory_map`, drawn by the helper (once;
        later calls, without a helper or when it failed: drawn here)."""
        if self._proc is not None:
            try:
                answer = _ask(self._proc, _encode(path, curves, landmarks, title, subtitle))
            finally:
                self.close()  # one figure per helper
            if answer is not None:
                return answer
        from vislam.tools.plotting import plot_trajectory_map

        return plot_trajectory_map(path, curves, landmarks, title=title, subtitle=subtitle)


def _ask(proc: subprocess.Popen, payload: bytes) -> dict | None:
    """Send the call, wait for the answer: the figure's dict, or None (drawn here then)."""
    try:
        out, _ = proc.communicate(payload, timeout=ANSWER_TIMEOUT_S)
    except (OSError, ValueError, subprocess.TimeoutExpired) as exc:  # a broken pipe, a closed helper
        logger.debug("figure helper did not answer (%s): drawing here", exc)
        return None
    try:
        answer = json.loads(out.decode("utf-8")) if proc.returncode == 0 else None
    except (UnicodeDecodeError, json.JSONDecodeError):
        answer = None
    if not isinstance(answer, dict) or "xlim" not in answer:
        logger.debug("figure helper failed (exit %s): drawing here", proc.returncode)
        return None
    return {"xlim": tuple(map(float, answer["xlim"])), "ylim": tuple(map(float, answer["ylim"])),
            "landmarks_outside_view": int(answer["landmarks_outside_view"])}


# ----------------------------------------------------------------------------- the wire format


def _encode(path, curves, landmarks, title: str, subtitle: str | None) -> bytes:
    """The call as an .npz archive: arrays as arrays, everything else as JSON text."""
    arrays: dict[str, np.ndarray] = {}
    styles = []
    for i, c in enumerate(curves):
        arrays[f"curve_{i}"] = np.asarray(c.world_T_imu, dtype=np.float64)
        styles.append({f.name: getattr(c, f.name) for f in fields(c) if f.name != "world_T_imu"})  # (no copy)
    if landmarks is not None:
        arrays["p_lm_in_world"] = np.asarray(landmarks.p_lm_in_world, dtype=np.float64)
        arrays["status"] = np.asarray(landmarks.status)
    call = {"path": str(Path(path).resolve()), "title": title, "subtitle": subtitle, "curves": styles,
            "landmarks": landmarks is not None}
    arrays["call"] = np.array(json.dumps(call))
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


class _Landmarks:
    """What plot_trajectory_map reads of a LandmarkMap."""

    def __init__(self, p_lm_in_world: np.ndarray, status: np.ndarray) -> None:
        self.p_lm_in_world, self.status = p_lm_in_world, status

    def __len__(self) -> int:
        return len(self.p_lm_in_world)


def _decode(payload: bytes):
    from vislam.tools.plotting import TrajectoryCurve

    with np.load(io.BytesIO(payload), allow_pickle=False) as z:
        call = json.loads(str(z["call"]))
        curves = [TrajectoryCurve(z[f"curve_{i}"], **style) for i, style in enumerate(call["curves"])]
        landmarks = _Landmarks(z["p_lm_in_world"], z["status"]) if call["landmarks"] else None
    return call["path"], curves, landmarks, call["title"], call["subtitle"]


# ----------------------------------------------------------------------------- the helper


def _warm_up() -> None:
    """Import what the figure needs and draw a small one (into a temporary folder): the
    first figure of a process pays for fonts, the PNG writer and lazy imports."""
    import tempfile

    from vislam.tools.plotting import TrajectoryCurve, plot_trajectory_map

    world_T_imu = np.tile(np.eye(4), (2, 1, 1))
    world_T_imu[1, :3, 3] = (1.0, 1.0, 0.1)
    landmarks = _Landmarks(np.array([[0.0, 2.0, 0.0], [1e4, 0.0, 0.0]]), np.array([0, 1], dtype=np.int8))
    with tempfile.TemporaryDirectory(prefix="vislam-figure-") as folder:
        plot_trajectory_map(Path(folder) / "warm-up.png", [TrajectoryCurve(world_T_imu, "warm-up")], landmarks,
                            title="warm-up — x", subtitle="warm-up")


def _main() -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and ends this process
    _warm_up()
    payload = sys.stdin.buffer.read()
    if not payload:  # the parent needs no figure
        return 0
    from vislam.tools.plotting import plot_trajectory_map

    path, curves, landmarks, title, subtitle = _decode(payload)
    view = plot_trajectory_map(path, curves, landmarks, title=title, subtitle=subtitle)
    sys.stdout.write(json.dumps(view))
    sys.stdout.flush()
    os._exit(0)  # the figure is written: skip the interpreter's teardown (~0.1 s), which the parent would wait for


if __name__ == "__main__":
    sys.exit(_main())
