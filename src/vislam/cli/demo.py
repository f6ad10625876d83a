"""``vislam demo [--out DIR]``: SLAM on a built-in simulated drive, graded against its truth.

Simulates the default drive with a noisy IMU (0.5 m/s and 0.05 rad/s white noise per
axis and sample, the simulator's default 0.5 px pixel noise: the case where SLAM
shines), runs SLAM with matching
filter noise and IMU-only localization for comparison, and writes the outputs of
``vislam run`` plus the ground truth (``groundtruth.tum``/``.kitti``), the localization
trajectory (``localization.tum``) and, in summary.json, the ATE of both
(:func:`vislam.tools.outputs.write_demo_outputs`). This module parses, calls and prints.
"""

from __future__ import annotations

import argparse
import sys
import time

from vislam.cli.common import finish, interrupted_message, make_progress

__all__ = ["register", "run", "DEMO_NOISE"]

_COMMAND_START = time.time()

#: IMU noise of the demo drive (and of the filter), per axis and sample (the simulator's
#: default drive otherwise, with 0.5 px pixel noise).
DEMO_NOISE = {"velocity_noise_mps": 0.5, "angular_noise_radps": 0.05}


def register(subparsers) -> None:
    from vislam.core.simulate import SimulationOptions

    default_frames = SimulationOptions().n_frames
    parser = subparsers.add_parser(
        "demo",
        help="run SLAM on a built-in simulated drive and grade it against the truth",
        description="Simulate a KITTI-like drive with a noisy IMU (0.5 m/s, 0.05 rad/s per axis and sample), run "
        "visual-inertial SLAM and IMU-only localization on it, and write DIR/trajectory.tum, trajectory.kitti, "
        "landmarks.ply, landmarks.npz, trajectory.png, summary.json (with the ATE of both against the truth), "
        "groundtruth.tum (true IMU poses), groundtruth.kitti (true left-camera poses, the KITTI convention) and "
        "localization.tum.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--out", metavar="DIR", default="vislam-demo", help="output directory (created if needed)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the simulated drive")
    parser.add_argument("--frames", type=int, default=default_frames, metavar="N",
                        help="number of frames of the drive (10 Hz)")
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")
    parser.set_defaults(func=run)


def run(args) -> int:
    from vislam.tools.figure_process import FigureProcess

    with FigureProcess() as figures:
        return _run(args, figures)


def _run(args, figures) -> int:
    from vislam.core.estimators import run as run_estimator
    from vislam.core.options import FilterOptions
    from vislam.core.simulate import SimulationOptions, check_simulation_memory, simulate_drive
    from vislam.tools.outputs import OutputStage, command_start_time, write_demo_outputs

    start_time = command_start_time() or _COMMAND_START
    sim_options = SimulationOptions(seed=args.seed, n_frames=args.frames, **DEMO_NOISE)  # ConfigError if bad
    check_simulation_memory(sim_options.n_frames, "--frames")
    filter_options = FilterOptions(velocity_noise_mps=DEMO_NOISE["velocity_noise_mps"],
                                   angular_noise_radps=DEMO_NOISE["angular_noise_radps"])
    figures.start()  # its helper process imports matplotlib while this one simulates and filters
    stage = OutputStage(args.out)
    close = lambda: None  # noqa: E731
    try:
        with stage:
            drive = simulate_drive(sim_options)
            seq = drive.sequence
            progress, close = make_progress(seq.n_frames, "slam", args.quiet)
            try:
                slam = run_estimator(seq, "slam", filter_options, progress=progress)
            finally:
                close()
            localization = run_estimator(seq, "localization", filter_options)
            dataset = {"name": seq.name, "label": f"Simulated drive (seed {args.seed})", "path": None,
                       "source": "simulator", "frames": seq.n_frames, "landmarks": seq.n_landmarks,
                       "duration_s": seq.duration_s, "cam_T_imu": seq.cam_T_imu.tolist(),
                       "simulation": sim_options.to_dict()}
            summary = write_demo_outputs(stage, slam, localization, drive.world_T_imu, dataset=dataset,
                                         duration_s=seq.duration_s, start_time=start_time,
                                         plot=figures.plot_trajectory_map)
    except KeyboardInterrupt:
        close()
        print(interrupted_message("demo", stage), file=sys.stderr)
        return 130
    return finish(summary, slam, stage, args.quiet)
