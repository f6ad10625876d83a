"""The figures of a run drawn by a helper process, so that matplotlib's import overlaps the filter.

Importing matplotlib and drawing the first figure costs about half a second of a
`vislam run` (more than the filter of a short recording). :class:`FigureProcess` starts
a second Python process as a command starts; that process imports matplotlib and the
PNG writer on the other core while this one loads and filters, then draws the run's
figures when asked —
:func:`vislam.tools.plotting.plot_trajectory_map` and, with a ground truth,
:func:`vislam.tools.evaluation.plot_error_over_distance`: the same functions, with the
same arguments, so the PNGs are those this process would draw.

The data cross a pipe as an ``.npz`` archive read with ``allow_pickle=False`` (arrays,
and the strings and numbers of the call as JSON); the answer comes back as JSON. When
the helper cannot help — it could not start, did not answer, or failed — the figure is
drawn here instead, so a figure never depends on the helper: the helper only saves time.
The helper draws once: the error figure is queued and sent with the trajectory figure,
which a run draws last.
It is not started when matplotlib is already imported here (a long-lived process: a
test run, a notebook), where it would save nothing, nor on a single core.

The helper ignores Ctrl-C (the terminal sends it to both processes): this process
handles the interrupt and ends the helper, as it does when it has no figure to draw.
"""

from __future__ import annotations

import contextlib
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

from vislam.signals import replaced_handler

__all__ = ["FigureProcess"]

logger = logging.getLogger(__name__)

#: Longest wait (s) for the helper's figure before drawing it here instead.
ANSWER_TIMEOUT_S = 300.0


class FigureProcess:
    """A helper process that draws the figures of a run (module docstring).

    Created idle; :meth:`start` starts the helper. Use it as a context manager (or call
    :meth:`close`): the helper ends with it. Without a helper (not started, or gone), the
    figures are drawn in this process.
    """

    def __init__(self) -> None:
        self._proc: subprocess.Popen | None = None
        self._queued: list[tuple[str, tuple]] = []  # figures sent with the next trajectory figure

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
        # Ctrl-C is held back while the process is created: an interrupt raised inside Popen,
        # after the fork, would leave a helper that nothing ends (Popen never returned it);
        # held back, it is delivered just after, with the helper known (and ended by close())
        with _sigint_held():
            try:
                self._proc = subprocess.Popen([sys.executable, "-m", "vislam.tools.figure_process"],
                                              stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                              stderr=subprocess.DEVNULL, env=env)
            except OSError as exc:  # e.g. no process can be created: draw here
                logger.debug("no figure helper process: %s", exc)
                return False
        return True

    def __enter__(self) -> FigureProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """End the helper if it is still running (it has nothing more to draw). Queued
        figures are dropped: a command that fails before its trajectory figure writes none."""
        self._queued = []
        proc, self._proc = self._proc, None
        if proc is not None and proc.poll() is None:
            proc.kill()
        if proc is not None:
            proc.wait()
            for pipe in (proc.stdin, proc.stdout):
                if pipe is not None:
                    pipe.close()

    def plot_error_over_distance(self, result, path, title: str | None = None) -> None:
        """:func:`vislam.tools.evaluation.plot_error_over_distance` (``result``: an
        EvaluationResult or its ErrorFigureData). With a helper, queued and drawn by it
        with the next :meth:`plot_trajectory_map`; without one, drawn here now."""
        from vislam.tools.evaluation import ErrorFigureData, plot_error_over_distance

        if self._proc is None:
            plot_error_over_distance(result, path, title=title)
            return
        data = result if isinstance(result, ErrorFigureData) else ErrorFigureData.from_result(result)
        self._queued.append((_ERROR, (data, path, title)))

    def plot_trajectory_map(self, path, curves, landmarks=None, title: str = "", subtitle: str | None = None) -> dict:
        """:func:`vislam.tools.plotting.plot_trajectory_map`, drawn by the helper with the
        figures queued before it (once; later calls, without a helper or when it failed:
        drawn here)."""
        calls = [*self._queued, (_MAP, (path, curves, landmarks, title, subtitle))]
        self._queued = []
        answers: list = [None] * len(calls)
        if self._proc is not None:
            try:
                answers = _ask(self._proc, _encode(calls), [kind for kind, _ in calls])
            finally:
                self.close()  # one payload per helper
        for i, call in enumerate(calls):
            if answers[i] is None:  # the helper could not draw it: here
                answers[i] = _draw(*call)
        return answers[-1]


_MAP, _ERROR = "trajectory_map", "error_over_distance"


def _draw(kind: str, args: tuple):
    """One figure drawn in this process: the trajectory figure's view dict, or True."""
    if kind == _MAP:
        from vislam.tools.plotting import plot_trajectory_map

        path, curves, landmarks, title, subtitle = args
        return plot_trajectory_map(path, curves, landmarks, title=title, subtitle=subtitle)
    from vislam.tools.evaluation import plot_error_over_distance

    data, path, title = args
    plot_error_over_distance(data, path, title=title)
    return True


def _ask(proc: subprocess.Popen, payload: bytes, kinds: list) -> list:
    """Send the calls (of ``kinds``), wait for the answers: one per call, None where the
    helper did not draw that figure (drawn here then)."""
    n = len(kinds)
    try:
        out, _ = proc.communicate(payload, timeout=ANSWER_TIMEOUT_S)
    except (OSError, ValueError, subprocess.TimeoutExpired) as exc:  # a broken pipe, a closed helper
        logger.debug("figure helper did not answer (%s): drawing here", exc)
        return [None] * n
    try:
        answers = json.loads(out.decode("utf-8")) if proc.returncode == 0 else None
    except (UnicodeDecodeError, json.JSONDecodeError):
        answers = None
    if not isinstance(answers, list) or len(answers) != n:
        logger.debug("figure helper failed (exit %s): drawing here", proc.returncode)
        return [None] * n
    return [_answer(kind, a) for kind, a in zip(kinds, answers)]


def _answer(kind: str, a):
    """A figure's answer checked: the trajectory figure's view dict, True for the error
    figure, or None."""
    if kind == _ERROR:
        return True if a is True else None
    if isinstance(a, dict) and {"xlim", "ylim", "landmarks_outside_view"} <= a.keys():
        return {"xlim": tuple(map(float, a["xlim"])), "ylim": tuple(map(float, a["ylim"])),
                "landmarks_outside_view": int(a["landmarks_outside_view"])}
    return None


# ----------------------------------------------------------------------------- the wire format


def _encode(calls: list) -> bytes:
    """The calls as an .npz archive: arrays as arrays (named by the call's index),
    everything else as JSON text."""
    arrays: dict[str, np.ndarray] = {}
    described = []
    for i, (kind, args) in enumerate(calls):
        prefix = f"{i}_"
        described.append(_encode_map(arrays, prefix, *args) if kind == _MAP else _encode_error(arrays, prefix, *args))
    arrays["calls"] = np.array(json.dumps(described))
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def _encode_map(arrays: dict, prefix: str, path, curves, landmarks, title: str, subtitle: str | None) -> dict:
    styles = []
    for i, c in enumerate(curves):
        arrays[f"{prefix}curve_{i}"] = np.asarray(c.world_T_imu, dtype=np.float64)
        styles.append({f.name: getattr(c, f.name) for f in fields(c) if f.name != "world_T_imu"})  # (no copy)
    if landmarks is not None:
        arrays[f"{prefix}p_lm_in_world"] = np.asarray(landmarks.p_lm_in_world, dtype=np.float64)
        arrays[f"{prefix}status"] = np.asarray(landmarks.status)
    return {"kind": _MAP, "path": str(Path(path).resolve()), "title": title, "subtitle": subtitle,
            "curves": styles, "landmarks": landmarks is not None}


def _encode_error(arrays: dict, prefix: str, data, path, title: str | None) -> dict:
    return {"kind": _ERROR, "path": str(Path(path).resolve()), "title": title,
            "data": _encode_fields(arrays, f"{prefix}d_", data)}


def _encode_fields(arrays: dict, prefix: str, obj) -> dict:
    """A dataclass of arrays, numbers and such dataclasses (ErrorFigureData, its
    KittiOdometryErrors): arrays into ``arrays``, the rest as a JSON-able dict."""
    out: dict = {}
    for f in fields(obj):
        value = getattr(obj, f.name)
        if isinstance(value, np.ndarray):
            arrays[prefix + f.name] = value
            out[f.name] = {"array": prefix + f.name}
        elif isinstance(value, np.generic):
            out[f.name] = value.item()
        elif value is None or isinstance(value, (bool, int, float, str)):
            out[f.name] = value
        else:  # a nested dataclass
            out[f.name] = {"fields": _encode_fields(arrays, f"{prefix}{f.name}_", value)}
    return out


def _plain_fields(z, described: dict) -> dict:
    return {name: z[v["array"]] if isinstance(v, dict) else v for name, v in described.items()}


def _decode_error_data(z, described: dict):
    """The ErrorFigureData of :func:`_encode_fields`."""
    from vislam.core.metrics import KittiOdometryErrors
    from vislam.tools.evaluation import ErrorFigureData

    rest = {k: v for k, v in described.items() if k not in ("kitti", "camera")}
    camera = described["camera"]
    return ErrorFigureData(**_plain_fields(z, rest),
                           kitti=KittiOdometryErrors(**_plain_fields(z, described["kitti"]["fields"])),
                           camera=None if camera is None else _decode_error_data(z, camera["fields"]))


class _Landmarks:
    """What plot_trajectory_map reads of a LandmarkMap."""

    def __init__(self, p_lm_in_world: np.ndarray, status: np.ndarray) -> None:
        self.p_lm_in_world, self.status = p_lm_in_world, status

    def __len__(self) -> int:
        return len(self.p_lm_in_world)


def _decode_call(z, i: int, call: dict) -> tuple[str, tuple]:
    """Call ``i`` of :func:`_encode`'s archive ``z`` (its ``calls`` entry ``call``): (kind,
    args) as the parent made them. Decoded one by one, so that one that fails costs only
    its own figure."""
    from vislam.tools.plotting import TrajectoryCurve

    prefix = f"{i}_"
    if call["kind"] == _MAP:
        curves = [TrajectoryCurve(z[f"{prefix}curve_{j}"], **style) for j, style in enumerate(call["curves"])]
        landmarks = _Landmarks(z[f"{prefix}p_lm_in_world"], z[f"{prefix}status"]) if call["landmarks"] else None
        return _MAP, (call["path"], curves, landmarks, call["title"], call["subtitle"])
    return _ERROR, (_decode_error_data(z, call["data"]), call["path"], call["title"])


@contextlib.contextmanager
def _sigint_held():
    """SIGINT's Python handler is replaced by one that only notes the interrupt (a signal,
    or ``_thread.interrupt_main``, which the launcher uses to deliver an interrupt it held
    back during an import), and the interrupt is delivered to the previous handler when
    the block is left. Only in the main thread (where handlers live); elsewhere a no-op."""
    noted = []
    previous = None
    try:
        with replaced_handler(signal.SIGINT, lambda signum, frame: noted.append(signum)) as previous:
            yield
    finally:
        if noted:
            if callable(previous):
                previous(signal.SIGINT, None)
            elif previous == signal.SIG_DFL:
                raise KeyboardInterrupt


# ----------------------------------------------------------------------------- the helper


def _prepare() -> None:
    """Import what the figures need (matplotlib's figure, the Agg canvas, the PNG writer):
    most of a first figure's cost. (A first figure drawn ahead, as this helper once did,
    bought nothing more: a process's first trajectory figure took 0.16-0.20 s, as its
    second, measured 2026-12-07, and it delayed a short run's figure by that much.)"""
    import matplotlib.backends.backend_agg  # noqa: F401
    import matplotlib.figure  # noqa: F401
    import matplotlib.lines  # noqa: F401
    import PIL.PngImagePlugin  # noqa: F401

    import vislam.tools.plotting  # noqa: F401


def _main() -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and ends this process
    _prepare()
    payload = sys.stdin.buffer.read()
    if not payload:  # the parent needs no figure
        return 0
    answers = []
    with np.load(io.BytesIO(payload), allow_pickle=False) as z:
        for i, call in enumerate(json.loads(str(z["calls"]))):
            try:
                answers.append(_draw(*_decode_call(z, i, call)))
            except Exception:  # noqa: BLE001 - this figure is drawn by the parent instead
                answers.append(None)
    sys.stdout.write(json.dumps(answers))
    sys.stdout.flush()
    os._exit(0)  # the figures are written: skip the interpreter's teardown (~0.1 s), which the parent would wait for


if __name__ == "__main__":
    sys.exit(_main())
