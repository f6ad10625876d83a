#!/usr/bin/env python
"""The smoother's window length against its accuracy and CPU time (issue 23's smoother item).

Usage (from the repository root)::

    PYTHONPATH=src python benchmarks/smoother_window.py --windows 3,2,1.5 --seeds 0,1,2,3 [--data ../shared/data]
    PYTHONPATH=src python benchmarks/noise_draws.py --depths 200 --lever-arm corrected --mode smoother \\
        --options '{"smoother_window_s": W}'          # dense 0027's seven variants, per window W

For each window (``smoother_window_s``) it runs the smoother with the defaults otherwise on
simulated drives (300 frames, IMU noise 0.5 m/s and 0.05 rad/s, the filter told so; seeds
``--seeds``) and, when the shared data is there, on sparse 0020 and 0027 and dense 0027
(dense told 0.5 / 0.05), and prints the ATE (SE(3)-aligned, IMU frame) of each and the CPU
time (``time.process_time``) of all runs of that window.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import vislam
from vislam.tools.evaluation import evaluate

SHARED = [("sparse/0020", "0020"), ("sparse/0027", "0027"), ("dense/0027", "0027")]


def _options(window_s: float, noisy: bool) -> vislam.FilterOptions:
    kw = dict(velocity_noise_mps=0.5, angular_noise_radps=0.05) if noisy else {}
    return vislam.FilterOptions(**kw).replace(smoother_window_s=window_s)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--windows", default="3,2,1.5")
    parser.add_argument("--seeds", default="0,1,2,3")
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    args = parser.parse_args()
    windows = [float(w) for w in args.windows.split(",")]
    drives = [vislam.simulate_drive(vislam.SimulationOptions(n_frames=args.frames, seed=int(s), velocity_noise_mps=0.5,
                                                             angular_noise_radps=0.05))
              for s in args.seeds.split(",") if s]
    shared = []
    data = Path(args.data)
    if data.is_dir():
        from vislam.tools.comparison import evaluate_run, load_run_ground_truth
        from vislam.tools.dataset_io import load_sequence

        for name, gt in SHARED:
            seq = load_sequence(data / f"{name}.npz")
            shared.append((name, seq, load_run_ground_truth(data / "groundtruth" / f"{gt}.txt", seq)))
    for w in windows:
        cpu, sim_ate, parts = 0.0, [], []
        for d in drives:
            c = time.process_time()
            r = vislam.run(d.sequence, "smoother", _options(w, True))
            cpu += time.process_time() - c
            sim_ate.append(evaluate(r.world_T_imu, d.world_T_imu[:len(r.world_T_imu)]).ape.rmse)
        for name, seq, gt in shared:
            c = time.process_time()
            r = vislam.run(seq, "smoother", _options(w, name.startswith("dense")))
            cpu += time.process_time() - c
            parts.append(f"{name} {evaluate_run(r, gt, seq).ape.rmse:.3f} m")
        sims = " ".join(f"{a:.3f}" for a in sim_ate)
        print(f"window {w:g} s: simulated ATE mean {np.mean(sim_ate):.4f} m ({sims}); " + "; ".join(parts)
              + f"; CPU {cpu:.1f} s", flush=True)


if __name__ == "__main__":
    main()
