"""The SLAM EKF's stall handling on simulated drives with either stall model.

For each seed, a drive with stalled tracks every 10 frames (``SimulationOptions
(stall_period=10)``) under each stall model — ``lag`` (the track shows the frame before
from then on) and ``restart`` (the track restarts on a new point in sync, what the KITTI
feature files do) — with a noisy IMU (0.5 m/s, 0.05 rad/s, filter told); SLAM with
``repeated_observations`` ``auto`` (split, in the EKF) and ``skip`` (with the remap).
Prints the ATE (m, SE(3)-aligned, IMU frame) of each. tests/test_stalls.py checks the
orderings on 200 frames, seeds 4-6::

    PYTHONPATH=src python benchmarks/stall_models.py --seeds 4,5,6 --frames 200
"""

from __future__ import annotations

import argparse
import sys

import vislam
from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.tools.evaluation import evaluate


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="4,5,6", help="simulator seeds, comma-separated")
    parser.add_argument("--frames", type=int, default=200)
    args = parser.parse_args(argv)
    noise = {"velocity_noise_mps": 0.5, "angular_noise_radps": 0.05}
    for seed in [int(x) for x in args.seeds.split(",")]:
        for model in ("lag", "restart"):
            sim = simulate_drive(SimulationOptions(seed=seed, n_frames=args.frames, stall_period=10,
                                                   stall_model=model, **noise))
            line = f"seed {seed} {model:8s}"
            for policy in ("auto", "skip"):
                r = vislam.run(sim.sequence, "slam", vislam.FilterOptions(**noise, repeated_observations=policy))
                line += f" | {policy}: {evaluate(r.world_T_imu, sim.world_T_imu).ape.rmse:.3f} m"
            print(line, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
