"""CPU time of the figures `vislam run` draws: the trajectory map and, with ``--gt``, the
error over distance, on one real run (SLAM with the defaults, evaluated against its
ground truth).

Usage (from the repository root)::

    PYTHONPATH=src python benchmarks/figure_speed.py [--data ../shared/data] [--file sparse/0027] [--repeat 5]

Each figure is drawn and saved ``--repeat`` times into a temporary folder after one
warm-up (matplotlib's imports and font cache); the best (minimum) CPU time of the
process (``time.process_time``) is printed per figure, with the median. Best-of is the
figure to compare on a shared machine.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path


def _times(draw, repeat: int) -> list[float]:
    draw(-1)  # warm-up: imports, font cache
    out = []
    for i in range(repeat):
        t0 = time.process_time()
        draw(i)
        out.append(time.process_time() - t0)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default="../shared/data", help="the shared data folder")
    parser.add_argument("--file", default="sparse/0027", help="recording under --data (its ground truth must exist)")
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()

    from vislam.core.estimators import run
    from vislam.core.options import FilterOptions
    from vislam.tools.comparison import evaluate_run, load_run_ground_truth
    from vislam.tools.dataset_io import load_sequence
    from vislam.tools.evaluation import plot_error_over_distance
    from vislam.tools.plotting import TrajectoryCurve, plot_trajectory_map

    data = Path(args.data)
    sequence = load_sequence(data / f"{args.file}.npz")
    result = run(sequence, "slam", FilterOptions())
    gt = load_run_ground_truth(data / "groundtruth" / f"{Path(args.file).name}.txt", sequence)
    evaluation = evaluate_run(result, gt, sequence)
    curves = [TrajectoryCurve(world_T_imu=result.world_T_imu, label="trajectory")]
    with tempfile.TemporaryDirectory() as tmp:
        figures = {
            "trajectory map (trajectory.png)": lambda i: plot_trajectory_map(
                Path(tmp) / f"map{i}.png", curves, result.landmarks, title=args.file),
            "error over distance (error_over_distance.png)": lambda i: plot_error_over_distance(
                evaluation, Path(tmp) / f"error{i}.png", f"{args.file} SLAM vs ground truth"),
        }
        print(f"{args.file}, SLAM, {sequence.n_frames} frames; CPU seconds per figure, best / median of {args.repeat}")
        for name, draw in figures.items():
            t = _times(draw, args.repeat)
            print(f"  {name:48s} {min(t):.3f} / {statistics.median(t):.3f}")


if __name__ == "__main__":
    main()
