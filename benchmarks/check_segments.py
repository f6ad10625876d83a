"""How stable is `vislam check`'s IMU–camera rotation across parts of one drive?

For each file, the check runs on the whole drive, on its halves and on its thirds
(frames [a, b), the same data, nothing altered) and prints the rotation correction
(degrees about camera x, y, z) with the check's standard error of its norm. A correction
that is a property of the sensor rig (a wrong cam_T_imu) is the same in every part; one
that comes from the drive (the vehicle's roll against levelled angular rates, which the
correction about the optical axis z absorbs) changes from part to part by more than its
standard error.

Usage::

    PYTHONPATH=src python benchmarks/check_segments.py [--data ../shared/data] [--files dense/0027 dense/0034]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from vislam.core.check import check_sequence
from vislam.core.sequence import StereoObservations
from vislam.tools.dataset_io import load_sequence


def frames(seq, a: int, b: int):
    """The frames [a, b) of a sequence, as a sequence."""
    o = seq.observations
    lo, hi = o.frame_offsets[a], o.frame_offsets[b]
    obs = StereoObservations(o.frame_offsets[a:b + 1] - lo, o.landmark_ids[lo:hi], o.pixels[lo:hi], o.n_landmarks)
    return seq.replace(timestamps_s=seq.timestamps_s[a:b], linear_velocity_in_imu_mps=seq.linear_velocity_in_imu_mps[a:b],
                       angular_velocity_in_imu_radps=seq.angular_velocity_in_imu_radps[a:b], observations=obs)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data"))
    parser.add_argument("--files", nargs="*", default=["dense/0022", "dense/0027", "dense/0034", "sparse/0020", "sparse/0027"])
    args = parser.parse_args(argv)
    print("| file | frames | correction x, y, z (deg) | ± (norm) |")
    print("|---|---|---|---|")
    for f in args.files:
        seq = load_sequence(Path(args.data) / f"{f}.npz")
        T = seq.n_frames
        for a, b in [(0, T), (0, T // 2), (T // 2, T), (0, T // 3), (T // 3, 2 * T // 3), (2 * T // 3, T)]:
            e = check_sequence(frames(seq, a, b)).estimates
            c = e["imu_camera_rotation_correction_deg"]
            print(f"| {f} | {a}–{b} | {', '.join(f'{x:+.2f}' for x in c)} | {e['imu_camera_rotation_error_deg_se']:.2f} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
