#!/usr/bin/env python
"""The stalled-track policy measured on every shared file (issue 12).

Usage::

    PYTHONPATH=src python benchmarks/stalled_tracks.py [--data DIR] [--out FILE.json] [--no-sensitivity]

For every ``sparse/{0020,0027,0042}.npz`` and ``dense/{0022,0027,0034}.npz`` under
``--data`` (default ``../shared/data`` next to the repository):

* the ground-truth-free diagnostics of :func:`vislam.core.stalls.stall_diagnostics`:
  stall counts and the ratio of observed to odometry-predicted pixel and disparity
  motion, before and after the remap;
* the EKF SLAM (``estimators.run(seq, "slam", options)``) on the original sequence
  (the current default: repeats skipped, ``repeated_observations="skip"``), on
  :func:`vislam.core.stalls.remap_sequence` of it, and on the original with the existing
  ``repeated_observations="split"`` (a repeat ends the track and starts a new one, the
  repeat included: the model the segment timing residuals support); dense files with
  ``FilterOptions(velocity_noise_mps=0.5, angular_noise_radps=0.05)``, sparse files with
  the defaults;
* where ground truth exists (``groundtruth/0020.txt``, ``0027.txt``: left-camera poses,
  converted to the IMU), the ATE (RMSE after SE(3) alignment) and the KITTI odometry
  t-error (%) and r-error (deg/100 m), for both runs and for dead reckoning
  (localization mode) as a reference;
* landmarks initialized / rejected and the gated share of the observations:
  ``observations_gated / (observations_gated + observations_used)``.

Unless ``--no-sensitivity``: the filter's pixel noise σ (``pixel_noise_px``) 1, 2, 3 px
on dense 0027, original (skip), remapped and split.

Writes ``benchmarks/results/stalled_tracks.json`` (or ``--out``) and prints a table.
About a minute of filter time on an idle core (each dense SLAM run ~3 s); several on a shared one.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import logging
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from vislam.core.estimators import run as run_estimator  # noqa: E402
from vislam.core.options import FilterOptions  # noqa: E402
from vislam.core.stalls import remap_sequence, stall_diagnostics  # noqa: E402
from vislam.tools.comparison import evaluate_run  # noqa: E402
from vislam.tools.dataset_io import load_sequence  # noqa: E402
from vislam.tools.evaluation import load_ground_truth  # noqa: E402
from vislam.tools.jsonio import write_json  # noqa: E402

DEFAULT_DATA = REPO.parent / "shared" / "data"
DEFAULT_OUT = REPO / "benchmarks" / "results" / "stalled_tracks.json"
FILES = (("sparse", "0020"), ("sparse", "0027"), ("sparse", "0042"), ("dense", "0022"), ("dense", "0027"),
         ("dense", "0034"))
#: The dense datasets' velocities carry added white noise (see the data README).
DENSE_NOISE = {"velocity_noise_mps": 0.5, "angular_noise_radps": 0.05}
SENSITIVITY_FILE = ("dense", "0027")
SENSITIVITY_PIXEL_NOISE = (1.0, 2.0, 3.0)


def _git(*args: str) -> str | None:
    try:
        return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def _run(seq, mode: str, options: FilterOptions, truth) -> dict:
    tic = time.perf_counter()
    result = run_estimator(seq, mode, options)
    wall = time.perf_counter() - tic
    st = result.stats
    out = {
        "wall_s": wall,
        "filter_s": st.filter_seconds,
        "partial": result.partial,
        "error": result.error,
    }
    if mode == "slam":
        used, gated = st.observations_used, st.observations_gated
        out.update({
            "observations_total": st.observations_total,
            "observations_used": used,
            "observations_gated": gated,
            "observations_repeated_skipped": st.observations_repeated,
            "gated_share": gated / (gated + used) if gated + used else None,
            "landmarks_initialized": st.landmarks_initialized,
            "landmarks_rejected": st.landmarks_rejected,
            "landmarks_moving": st.landmarks_moving,
            "map_rejected": int(result.landmarks.rejected.sum()) if result.landmarks is not None else None,
        })
    if truth is not None:
        ev = evaluate_run(result, truth, seq)
        out.update({
            "ate_rmse_m": ev.ape.rmse,
            "kitti_t_pct": ev.kitti.t_pct,
            "kitti_r_deg_per_100m": ev.kitti.r_deg_per_100m,
            "frames_compared": ev.n_frames_compared,
        })
    return out


def _fmt(x, spec: str) -> str:
    return "-" if x is None or x != x else format(x, spec)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--no-sensitivity", action="store_true", help="skip the pixel-noise runs on dense 0027")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

    started = time.time()
    report = {
        "machine": {
            "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "nproc": os.cpu_count(),
            "python": platform.python_version(),
            "loadavg_before": list(os.getloadavg()),
            "git_commit": _git("rev-parse", "HEAD"),
            "git_dirty": bool(_git("status", "--porcelain", "--untracked-files=no")),
        },
        "command": "PYTHONPATH=src python benchmarks/stalled_tracks.py" + (" " + " ".join(argv or sys.argv[1:])).rstrip(),
        "files": {},
        "sensitivity": {},
    }
    sequences = {}
    for kind, name in FILES:
        path = args.data / kind / f"{name}.npz"
        key = f"{kind}/{name}"
        if not path.is_file():
            report["files"][key] = {"skipped": f"{path} not found"}
            print(f"{key}: skipped ({path} not found)")
            continue
        seq = load_sequence(path)
        remapped = remap_sequence(seq)
        gt_path = args.data / "groundtruth" / f"{name}.txt"
        truth = load_ground_truth(gt_path, "kitti", "cam", seq.cam_T_imu) if gt_path.is_file() else None
        options = FilterOptions(**DENSE_NOISE) if kind == "dense" else FilterOptions()
        entry = {
            "path": str(path),
            "ground_truth": str(gt_path) if truth is not None else None,
            "filter_options": {k: v for k, v in options.to_dict().items() if v != getattr(FilterOptions(), k)},
            "diagnostics": stall_diagnostics(seq).to_dict(),
            "observations_remapped": remapped.observations.n_observations,
        }
        if truth is not None:
            entry["dead_reckoning"] = _run(seq, "localization", options, truth)
        entry["slam_original"] = _run(seq, "slam", options, truth)
        entry["slam_remapped"] = _run(remapped, "slam", options, truth)
        entry["slam_split"] = _run(seq, "slam", options.replace(repeated_observations="split"), truth)
        report["files"][key] = entry
        sequences[key] = (seq, remapped, truth, options)
        o, r = entry["slam_original"], entry["slam_remapped"]
        print(f"{key}: ATE {_fmt(o.get('ate_rmse_m'), '.2f')} -> {_fmt(r.get('ate_rmse_m'), '.2f')} m, "
              f"KITTI t {_fmt(o.get('kitti_t_pct'), '.2f')} -> {_fmt(r.get('kitti_t_pct'), '.2f')} %", flush=True)

    key = "/".join(SENSITIVITY_FILE)
    if not args.no_sensitivity and key in sequences:
        seq, remapped, truth, options = sequences[key]
        for px in SENSITIVITY_PIXEL_NOISE:
            opts = options.replace(pixel_noise_px=px)
            report["sensitivity"][f"{key} pixel_noise_px={px:g}"] = {
                "pixel_noise_px": px,
                "slam_original": _run(seq, "slam", opts, truth),
                "slam_remapped": _run(remapped, "slam", opts, truth),
                "slam_split": _run(seq, "slam", opts.replace(repeated_observations="split"), truth),
            }
            print(f"{key} pixel_noise_px={px:g} done", flush=True)

    report["machine"]["loadavg_after"] = list(os.getloadavg())
    report["machine"]["total_wall_s"] = time.time() - started
    write_json(args.out, report)
    print()
    print(format_table(report))
    print(f"\nwrote {args.out}")
    return 0


def format_table(report: dict) -> str:
    """Markdown tables of a report written by this script."""
    lines = [
        "| file | run | ATE m | KITTI t % | KITTI r deg/100m | lm init | lm rejected | gated % | "
        "cont. px ratio | cont. disp ratio | lagged cont. disp ratio | ordinary disp ratio |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for key, e in report["files"].items():
        if "skipped" in e:
            lines.append(f"| {key} | skipped | | | | | | | | | | |")
            continue
        d = e["diagnostics"]
        rows = [("dead reckoning", e.get("dead_reckoning"), None),
                ("SLAM original", e["slam_original"], d["flow_ratio_before"]),
                ("SLAM remapped", e["slam_remapped"], d["flow_ratio_after"]),
                ("SLAM split", e.get("slam_split"), None)]
        for label, r, flow in rows:
            if r is None:
                continue
            gated = r.get("gated_share")
            cells = [
                key, label, _fmt(r.get("ate_rmse_m"), ".2f"), _fmt(r.get("kitti_t_pct"), ".2f"),
                _fmt(r.get("kitti_r_deg_per_100m"), ".3f"), _fmt(r.get("landmarks_initialized"), "d"),
                _fmt(r.get("landmarks_rejected"), "d"), _fmt(None if gated is None else 100 * gated, ".1f"),
                _fmt(flow["continuing"]["median"], ".2f") if flow else "",
                _fmt(flow["continuing"]["disparity_median"], ".2f") if flow else "",
                _fmt(flow["continuing_lagged"]["disparity_median"], ".2f") if flow else "",
                _fmt(flow["ordinary"]["disparity_median"], ".2f") if flow else "",
            ]
            lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "| file | stall frames | repeats | lagged share | max lag | segment residual px, in sync: "
              "lagged / repeats | same, lag model | never-stalled segments px |", "|---|---|---|---|---|---|---|---|"]
    for key, e in report["files"].items():
        if "skipped" in e:
            continue
        d = e["diagnostics"]
        t = d["segment_timing_residuals"]
        lines.append(f"| {key} | {d['n_stall_frames']} | {d['n_repeats']} | {100 * d['lagged_share']:.1f} % | "
                     f"{d['max_lag']} | " + " | ".join(
                         f"{_fmt(t[h]['lagged_median_px'], '.2f')} / {_fmt(t[h]['repeat_median_px'], '.2f')}"
                         for h in ("in_sync", "lag")) + f" | {_fmt(t['lag']['in_sync_tracks_median_px'], '.2f')} |")
    if report.get("sensitivity"):
        lines += ["", "| sensitivity | run | ATE m | KITTI t % | KITTI r deg/100m | lm rejected | gated % |",
                  "|---|---|---|---|---|---|---|"]
        for key, s in report["sensitivity"].items():
            for label in ("slam_original", "slam_remapped", "slam_split"):
                r = s.get(label)
                if r is None:
                    continue
                lines.append(f"| {key} | {label} | {_fmt(r.get('ate_rmse_m'), '.2f')} | "
                             f"{_fmt(r.get('kitti_t_pct'), '.2f')} | {_fmt(r.get('kitti_r_deg_per_100m'), '.3f')} | "
                             f"{r['landmarks_rejected']} | {100 * r['gated_share']:.1f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
