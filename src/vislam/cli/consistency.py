"""``vislam consistency [--runs N] [--out DIR] ...``: Monte Carlo NEES of the filter on the simulator.

The runs and outputs are :mod:`vislam.tools.consistency`'s, the NEES math
:mod:`vislam.core.consistency`'s; this module parses, prints progress and the summary.
"""

from __future__ import annotations

import sys

__all__ = ["register", "run"]


def register(subparsers) -> None:
    from vislam.cli.common import add_engine_arguments

    parser = subparsers.add_parser(
        "consistency",
        help="Monte Carlo consistency of the filter on simulated drives: pose and landmark NEES with chi-square bands",
        description="Simulate N drives (seeds 0..N-1; IMU noise of the dense KITTI files and 0.5 px pixel noise by "
        "default), run the filter on each, and average its pose NEES (6 dof) and landmark NEES (3 dof) over the runs "
        "frame by frame, with the 95 %% chi-square band of an average of N runs. By default the filter is told the "
        "simulator's true noise. Writes DIR/consistency.json and DIR/consistency.png. Runs go to a Dask cluster "
        "(local by default).",
    )
    parser.add_argument("--runs", type=int, default=20, metavar="N", help="Monte Carlo runs (seeds), default 20")
    parser.add_argument("--frames", type=int, default=250, metavar="N", help="frames per simulated drive, default 250")
    parser.add_argument("--first-seed", type=int, default=0, metavar="S", help="first simulator seed (default 0)")
    parser.add_argument("--out", metavar="DIR", default="consistency", help="output directory (default ./consistency)")
    parser.add_argument("--mode", choices=("slam", "localization", "mapping"), default="slam",
                        help="estimator: slam (default), localization (IMU only), mapping (true poses given)")
    parser.add_argument("--filter-noise", choices=("true", "default"), default="true",
                        help="true (default): tell the filter the simulator's noise; default: the filter's own options "
                        "(FilterOptions defaults, or --config)")
    parser.add_argument("--config", metavar="FILE", help="filter options file (YAML/TOML) for the other options")
    parser.add_argument("--landmarks", choices=("inverse_depth", "cartesian"),
                        help="landmark parametrization of the SLAM filter (default: the options')")
    parser.add_argument("--sim-velocity-noise", type=float, default=0.5, metavar="M/S",
                        help="simulator: white noise per linear-velocity sample and axis (default 0.5 m/s)")
    parser.add_argument("--sim-angular-noise", type=float, default=0.05, metavar="RAD/S",
                        help="simulator: white noise per angular-velocity sample and axis (default 0.05 rad/s)")
    parser.add_argument("--sim-pixel-noise", type=float, default=0.5, metavar="PX",
                        help="simulator: pixel noise per coordinate (default 0.5 px)")
    add_engine_arguments(parser)
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")
    parser.set_defaults(func=run)


def run(args) -> int:
    from vislam.cli.common import configure_dask_logging, terminate_as_interrupt
    from vislam.core.options import FilterOptions
    from vislam.errors import ConfigError
    from vislam.tools.cluster import open_engine
    from vislam.tools.consistency import ConsistencySettings, run_consistency, write_consistency

    if args.sequential and args.scheduler:
        raise ConfigError("--sequential and --scheduler exclude each other")
    settings = ConsistencySettings(runs=args.runs, frames=args.frames, first_seed=args.first_seed, mode=args.mode,
                                   filter_noise=args.filter_noise, velocity_noise_mps=args.sim_velocity_noise,
                                   angular_noise_radps=args.sim_angular_noise, pixel_noise_px=args.sim_pixel_noise)
    if args.config:
        from vislam.tools.config import resolve_options

        options = resolve_options(args.config, {}, {})
    else:
        options = FilterOptions()
    if args.landmarks:
        options = options.replace(landmark_parametrization=args.landmarks)

    def say(text: str) -> None:
        if not args.quiet:
            print(f"vislam consistency: {text}", file=sys.stderr, flush=True)

    workers = 0 if args.sequential else args.workers
    configure_dask_logging(args.verbose)
    try:
        with terminate_as_interrupt(), open_engine(args.scheduler, workers) as engine:
            say(f"{settings.runs} runs x {settings.frames} frames ({settings.mode}) on {engine.name}")
            result = run_consistency(settings, engine, options,
                                     on_run=lambda seed, done, total: say(f"[{done}/{total}] seed {seed} done"))
    except KeyboardInterrupt:
        print("vislam consistency: interrupted; nothing written", file=sys.stderr)
        return 130
    files = write_consistency(result, args.out)
    if not args.quiet:
        d = result.to_dict()
        print("\n".join(str(f) for f in files))
        print(f"pose NEES mean {d['pose_nees_mean']:.2f} (6 ideal; 95 % band of the mean of {d['runs']} runs "
              f"[{d['pose_band_95'][0]:.2f}, {d['pose_band_95'][1]:.2f}], {100 * d['pose_share_inside_band']:.0f} % of "
              f"frames inside)" + (f"; landmark NEES mean {d['landmark_nees_mean']:.2f} (3 ideal, "
                                   f"{100 * d['landmark_share_inside_band']:.0f} % inside)"
                                   if d['landmark_nees_mean'] == d['landmark_nees_mean'] else "")
              + f" — {result.seconds:.0f} s on {result.engine}")
        for e in result.errors:
            print(f"vislam consistency: {e}", file=sys.stderr)
    return 0
