"""``vislam simulate --out DIR``: simulate a drive with ground truth and write it.

The library (:func:`vislam.core.simulate.simulate_drive`) makes the drive and
:func:`vislam.tools.simulate_io.write_simulated_drive` writes it; this module parses the
options and prints a short summary.
"""

from __future__ import annotations

import argparse

from vislam.core.simulate import MEMORY_LIMIT_GB, SimulationOptions, check_simulation_memory, simulate_drive
from vislam.errors import ConfigError
from vislam.tools.simulate_io import write_simulated_drive

__all__ = ["register", "run", "format_summary"]

_DEFAULTS = SimulationOptions()

#: command-line flag -> SimulationOptions field
_FLAGS = {
    "seed": "seed",
    "frames": "n_frames",
    "moving_fraction": "moving_fraction",
    "outlier_fraction": "outlier_fraction",
    "pixel_noise": "pixel_noise_px",
    "velocity_noise": "velocity_noise_mps",
    "angular_noise": "angular_noise_radps",
    "imu_frame_rotation": "imu_frame_rotation_deg",
    "extrinsic_error_deg": "extrinsic_error_deg",
    "velocity_shift": "velocity_shift",
    "time_offset": "time_offset_s",
    "gyro_bias": "gyro_bias_radps",
    "velocity_scale": "velocity_scale",
    "lever_arm_error": "lever_arm_error_m",
    "lever_arm_swapped": "lever_arm_swapped",
}


def _three_numbers(text: str) -> tuple[float, float, float]:
    """argparse type for "X,Y,Z"."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected three numbers X,Y,Z, got {text!r}") from None
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"expected three numbers X,Y,Z, got {text!r}")
    return values


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "simulate",
        help="simulate a KITTI-like drive with ground truth",
        description="Simulate a stereo visual-inertial drive (KITTI-like road, camera and feature tracks) and "
        "write DIR/sequence.npz (dataset format), DIR/groundtruth.tum (true IMU poses), DIR/groundtruth.kitti "
        "(true left-camera poses, the KITTI convention, as the shared data's ground truth) "
        "and DIR/landmarks_true.npz (true landmarks, moving flags, outlier flags). The same options always give "
        "the same files.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--out", required=True, metavar="DIR", default=argparse.SUPPRESS,
                        help="output directory (created if needed)")
    parser.add_argument("--seed", type=int, default=_DEFAULTS.seed, help="random seed")
    parser.add_argument("--frames", type=int, default=_DEFAULTS.n_frames, help="number of frames (10 Hz)")
    parser.add_argument("--max-memory", type=float, default=MEMORY_LIMIT_GB, metavar="GB",
                        help="refuse, before simulating, a drive whose simulation would need more memory than this "
                        "(the estimate grows with the square of the frames)")
    parser.add_argument("--moving-fraction", type=float, default=_DEFAULTS.moving_fraction, metavar="F",
                        help="share of the landmarks on moving vehicles, in [0, 1)")
    parser.add_argument("--outlier-fraction", type=float, default=_DEFAULTS.outlier_fraction, metavar="F",
                        help="share of the observations replaced by gross mismatches, in [0, 1)")
    parser.add_argument("--pixel-noise", type=float, default=_DEFAULTS.pixel_noise_px, metavar="PX",
                        help="1-sigma pixel noise per coordinate (px)")
    parser.add_argument("--velocity-noise", type=float, default=_DEFAULTS.velocity_noise_mps, metavar="MPS",
                        help="1-sigma white noise on each linear-velocity sample, per axis (m/s)")
    parser.add_argument("--angular-noise", type=float, default=_DEFAULTS.angular_noise_radps, metavar="RADPS",
                        help="1-sigma white noise on each angular-velocity sample, per axis (rad/s)")
    faults = parser.add_argument_group("recording faults", "what `vislam check` should find (all off by default)")
    faults.add_argument("--imu-frame-rotation", type=_three_numbers, default=_DEFAULTS.imu_frame_rotation_deg,
                        metavar="X,Y,Z", help="record the velocities in a frame turned by this rotation vector "
                        "(degrees, IMU axes), e.g. 180,0,0")
    faults.add_argument("--extrinsic-error-deg", type=_three_numbers, default=_DEFAULTS.extrinsic_error_deg,
                        metavar="X,Y,Z", help="record cam_T_imu with its rotation turned by this rotation vector "
                        "(degrees, camera axes)")
    faults.add_argument("--velocity-shift", type=int, default=_DEFAULTS.velocity_shift, metavar="N",
                        help="recorded velocity sample k is the true sample k+N (1: sample k describes k->k+1)")
    faults.add_argument("--time-offset", type=float, default=_DEFAULTS.time_offset_s, metavar="S",
                        help="the velocity sample stamped t describes the motion at t+S (s)")
    faults.add_argument("--gyro-bias", type=_three_numbers, default=_DEFAULTS.gyro_bias_radps, metavar="X,Y,Z",
                        help="constant bias added to the angular velocities (rad/s, IMU axes)")
    faults.add_argument("--velocity-scale", type=float, default=_DEFAULTS.velocity_scale, metavar="F",
                        help="record the linear velocities times F (e.g. 3.6: km/h stored as m/s)")
    faults.add_argument("--lever-arm-error", type=_three_numbers, default=_DEFAULTS.lever_arm_error_m,
                        metavar="X,Y,Z", help="record cam_T_imu with this error added to its translation (m, camera "
                        "axes)")
    faults.add_argument("--lever-arm-swapped", action="store_true", default=_DEFAULTS.lever_arm_swapped,
                        help="record imu_T_cam's translation as cam_T_imu's (the KITTI course files' mix-up)")
    parser.add_argument("--images", action="store_true",
                        help="also render the drive's rectified grey stereo images (1242x375, textured road and "
                        "facades) and write DIR as a KITTI raw date folder: calib_*.txt and sim_drive_SEED_sync/ "
                        "(image_00, image_01, oxts) beside the files above (see docs/frontend.md)")
    parser.set_defaults(func=run)


def options_from_args(args) -> SimulationOptions:
    values = {field: getattr(args, flag) for flag, field in _FLAGS.items()}
    try:
        return SimulationOptions(**values)
    except ConfigError as exc:
        # Name the command-line flag rather than the option field.
        message = str(exc)
        for flag, field in _FLAGS.items():
            message = message.replace(field, "--" + flag.replace("_", "-"))
        raise ConfigError(message) from None


def format_summary(stats, paths) -> str:
    s = stats
    lines = [
        f"frames:        {s.n_frames} ({s.duration_s:.1f} s)",
        f"distance:      {s.distance_m:.0f} m (speed {s.speed_min_mps:.1f}-{s.speed_max_mps:.1f} m/s, "
        f"heading change {s.heading_change_deg:.0f} deg)",
        f"landmarks:     {s.n_landmarks} ({s.n_moving_landmarks} moving)",
        f"observations:  {s.n_observations} ({s.n_outliers} outliers); per frame mean "
        f"{s.observations_per_frame_mean:.1f}, min {s.observations_per_frame_min}, "
        f"max {s.observations_per_frame_max}",
        f"track length:  median {s.track_length_median:g} frames, max {s.track_length_max}",
        "wrote:",
    ]
    lines += [f"  {p}" for p in paths]
    return "\n".join(lines)


def run(args) -> int:
    options = options_from_args(args)
    check_simulation_memory(options.n_frames, "--frames", args.max_memory, "--max-memory")
    drive = simulate_drive(options)
    if getattr(args, "images", False):
        from vislam.cli.common import make_progress
        from vislam.tools.simulate_images import write_rendered_drive

        progress, close = make_progress(drive.n_frames, "render", False)
        try:
            paths = write_rendered_drive(drive, args.out, progress=progress)
        finally:
            close()
    else:
        paths = write_simulated_drive(drive, args.out)
    print(format_summary(drive.statistics(), paths))
    return 0
