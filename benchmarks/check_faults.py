"""What `vislam check` finds on the shared files and on altered copies of them.

For each original file, and for altered copies of some of them written to a temporary
directory with :func:`vislam.tools.dataset_io.save_sequence` (the shared data is never
modified):

* ``a-frame180x``: velocities (linear and angular) expressed in a frame turned 180°
  about the IMU x axis (y and z flipped);
* ``b-shift+1``: velocity samples shifted by one index (sample k holds sample k+1);
* ``c-rot3<axis>``: cam_T_imu's rotation turned by 3° about a camera axis (x, y or z);
* ``d-kmh``: linear velocities times 3.6 (speeds in km/h stored as m/s);

it runs the check (as ``vislam check`` does: load the file, check_sequence) and prints
a Markdown table: the findings that are not OK, the rotation error, the association,
the time offset, the noise and the time taken. With ``--json FILE`` it also writes the
rows.

Usage::

    PYTHONPATH=src python benchmarks/check_faults.py [--data ../shared/data] [--files dense/0027 sparse/0027]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from vislam.core.check import check_sequence
from vislam.core.corrections import rotate_cam_T_imu
from vislam.tools.dataset_io import load_sequence, save_sequence

ORIGINALS = ["sparse/0020", "sparse/0027", "sparse/0042", "dense/0022", "dense/0027", "dense/0034"]
ALTERED = ["dense/0027", "sparse/0027", "sparse/0020", "dense/0034"]


def variants(seq):
    """(name, altered sequence, what check should report) for the faults."""
    flip = np.diag([1.0, -1.0, -1.0])
    yield "a-frame180x", seq.replace(linear_velocity_in_imu_mps=seq.linear_velocity_in_imu_mps @ flip,
                                     angular_velocity_in_imu_radps=seq.angular_velocity_in_imu_radps @ flip), \
        "imu-camera-rotation ERROR"
    u = seq.velocities()
    shifted = u[np.minimum(np.arange(len(u)) + 1, len(u) - 1)]
    yield "b-shift+1", seq.replace(linear_velocity_in_imu_mps=shifted[:, :3],
                                   angular_velocity_in_imu_radps=shifted[:, 3:]), "velocity-association"
    for i, axis in enumerate("xyz"):
        phi = np.zeros(3)
        phi[i] = 3.0
        yield f"c-rot3{axis}", seq.replace(cam_T_imu=rotate_cam_T_imu(seq.cam_T_imu, phi)), "imu-camera-rotation 3°"
    yield "d-kmh", seq.replace(linear_velocity_in_imu_mps=3.6 * seq.linear_velocity_in_imu_mps), "velocity-scale"


def row(file: str, variant: str, expected: str, path: Path) -> dict:
    t0 = time.perf_counter()
    seq = load_sequence(path)
    result = check_sequence(seq)
    elapsed = time.perf_counter() - t0
    e = result.estimates
    assoc = e.get("velocity_association", {})
    return {
        "file": file, "variant": variant, "expected": expected,
        "not_ok": [f"{f.code} {f.severity}" for f in result.findings if f.severity != "OK"],
        "rotation_error_deg": e.get("imu_camera_rotation_error_deg"),
        "rotation_error_deg_se": e.get("imu_camera_rotation_error_deg_se"),
        "rotation_correction_deg": e.get("imu_camera_rotation_correction_deg"),
        "body_roll_sensitivity_deg": e.get("body_roll_sensitivity_deg"),
        "best_shift": assoc.get("best_shift"), "association_z": assoc.get("z_vs_next"),
        "time_offset_s": e.get("time_offset_s"), "time_offset_s_se": e.get("time_offset_s_se"),
        "velocity_scale": e.get("velocity_scale"), "velocity_scale_se": e.get("velocity_scale_se"),
        "moving_landmarks": {k: v for k, v in (e.get("moving_landmarks") or {}).items() if k != "landmark_ids"},
        "velocity_noise_mps": e["imu_noise"]["velocity_mps"], "angular_noise_radps": e["imu_noise"]["angular_radps"],
        "gyro_bias_radps": e.get("gyro_bias_radps"),
        "reprojection_before_px": e.get("reprojection_before_px"),
        "reprojection_after_px": e.get("reprojection_after_px"),
        "suggested": result.suggested, "seconds": elapsed, "check_seconds": result.elapsed_s,
    }


def _f(x, spec=".2f"):
    return "–" if x is None else format(x, spec)


def table(rows: list[dict]) -> str:
    lines = ["| file | variant | not OK | rot. error (deg) | shift (z) | speed factor | time offset (ms) | σv (m/s) | "
             "σω (rad/s) | reproj. median before/after (px) | time (s) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        b = (r["reprojection_before_px"] or {}).get("median")
        a = (r["reprojection_after_px"] or {}).get("median")
        toff = r["time_offset_s"]
        lines.append(
            f"| {r['file']} | {r['variant']} | {', '.join(r['not_ok']) or '—'} | "
            f"{_f(r['rotation_error_deg'])} ± {_f(r['rotation_error_deg_se'])} | "
            f"{r['best_shift']} ({_f(r['association_z'], '.1f')}) | {_f(r['velocity_scale'], '.3f')} | "
            f"{_f(None if toff is None else 1000 * toff, '.0f')} ± "
            f"{_f(None if r['time_offset_s_se'] is None else 1000 * r['time_offset_s_se'], '.0f')} | "
            f"{', '.join(format(v, '.3f') for v in r['velocity_noise_mps'])} | "
            f"{', '.join(format(v, '.4f') for v in r['angular_noise_radps'])} | "
            f"{_f(b)} / {_f(a)} | {r['seconds']:.1f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data"))
    parser.add_argument("--files", nargs="*", default=ORIGINALS, help="originals to check")
    parser.add_argument("--altered", nargs="*", default=ALTERED, help="files to alter")
    parser.add_argument("--json", help="also write the rows to this JSON file")
    args = parser.parse_args(argv)
    data = Path(args.data)
    rows = []
    for f in args.files:
        rows.append(row(f, "original", "nothing", data / f"{f}.npz"))
        print(table(rows[-1:]).splitlines()[-1], file=sys.stderr, flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for f in args.altered:
            seq = load_sequence(data / f"{f}.npz")
            for name, altered, expected in variants(seq):
                path = Path(tmp) / f"{f.replace('/', '-')}-{name}.npz"
                save_sequence(altered, path)
                rows.append(row(f, name, expected, path))
                print(table(rows[-1:]).splitlines()[-1], file=sys.stderr, flush=True)
    print(table(rows))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
