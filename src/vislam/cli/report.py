"""``vislam report --data DIR --out DIR``: the report's whole results section in one command.

The experiments and files are :func:`vislam.tools.report.generate_report`'s; this module
parses, prints one progress line per step on stderr (unless ``--quiet``) and the paths
of the report at the end.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import time

from vislam.errors import ConfigError

__all__ = ["register", "run"]

_COMMAND_START = time.time()


def _noise_levels(text: str):
    from vislam.tools.report import NoiseLevel

    if text.strip().lower() in ("", "none", "off"):
        return ()
    levels = []
    for item in text.split(","):
        try:
            values = [float(x) for x in item.split(":")]
        except ValueError:
            values = []
        if len(values) not in (2, 3) or not all(v >= 0 and v < float("inf") for v in values):
            raise argparse.ArgumentTypeError(
                f"expected VELOCITY:ANGULAR[:PIXEL] noise levels separated by commas (e.g. 0.1:0.002,0.3:0.006), "
                f"got {item!r}")
        levels.append(NoiseLevel(*values))
    return tuple(levels)


def register(subparsers) -> None:
    from vislam.core.simulate import SimulationOptions

    parser = subparsers.add_parser(
        "report",
        help="regenerate the report's whole results section (figures, tables, metrics) in one command",
        description="Run every experiment of the report's results section on a data folder laid out like the shared "
        "data (sparse/*.npz, dense/*.npz, groundtruth/<stem>.txt with KITTI left-camera poses; any subset): "
        "localization + mapping, SLAM, the sliding-window smoother and its refinement on every dataset (Figs 1-6; "
        "each dataset checked first and run with the check's suggestions, as --auto), with metrics where ground "
        "truth exists; the "
        "comparison under artificially increased IMU noise on the sparse datasets (Figs 7-9); the moving-landmark "
        "failure and its fixes on the simulator (Figs 10-11); and a summary table. Writes DIR/report.md, "
        "DIR/report.html (self-contained), DIR/figures/ and the per-run outputs under DIR/runs/, all together or "
        "not at all. The runs go to a Dask cluster: a local one with 2 worker processes by default, --scheduler for a "
        "running one, --sequential for none. About 1-2 minutes on the shared data on 2 cores.",
    )
    parser.add_argument("--data", metavar="DIR", required=True, help="data folder (sparse/, dense/, groundtruth/)")
    parser.add_argument("--out", metavar="DIR", required=True, help="output directory (created if needed)")
    parser.add_argument("--noise-levels", type=_noise_levels, metavar="V:W[,V:W...]",
                        help="noise levels of the noise comparison: added velocity noise (m/s) : angular noise "
                        "(rad/s) [: pixel noise (px)], comma-separated, or 'none' (default: 0.1:0.002,0.3:0.006)")
    parser.add_argument("--sim-frames", type=int, metavar="N", default=SimulationOptions().n_frames,
                        help="frames of the simulated drives of the moving-landmark section; 0 leaves it out "
                        "(default: %(default)s)")
    parser.add_argument("--no-smoother", action="store_true",
                        help="leave the sliding-window smoother and its refinement out of the per-dataset tables "
                        "(they cost about 4x SLAM's time per frame, ~20 s more per dense drive)")
    from vislam.cli.common import add_engine_arguments

    add_engine_arguments(parser, sequential_help="run every experiment in this process, one after the other, as "
                         "before (no Dask)")
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")
    parser.set_defaults(func=run)


def run(args) -> int:
    from vislam.cli.common import configure_dask_logging, terminate_as_interrupt
    from vislam.tools.cluster import open_engine
    from vislam.tools.outputs import command_start_time
    from vislam.tools.report import ReportSettings, generate_report

    if args.sim_frames < 0 or args.sim_frames == 1:
        raise ConfigError(f"--sim-frames must be 0 (no simulation) or at least 2, got {args.sim_frames}")
    from vislam.core.simulate import check_simulation_memory

    check_simulation_memory(args.sim_frames, "--sim-frames")
    settings = ReportSettings(simulation_frames=args.sim_frames, smoother=not args.no_smoother)
    if args.noise_levels is not None:
        settings = dataclasses.replace(settings, noise_levels=args.noise_levels)

    def log(line: str) -> None:
        print(f"vislam report: {line}", file=sys.stderr, flush=True)

    package_logger = logging.getLogger("vislam")
    level = package_logger.level
    if args.quiet:
        package_logger.setLevel(logging.ERROR)  # e.g. the expected numerical failure of SLAM without gating
    if args.sequential and args.scheduler:
        raise ConfigError("--sequential and --scheduler exclude each other")
    configure_dask_logging(args.verbose)
    try:
        with terminate_as_interrupt(), open_engine(args.scheduler, 0 if args.sequential else args.workers) as engine:
            result = generate_report(args.data, args.out, settings, log=None if args.quiet else log,
                                     start_time=command_start_time() or _COMMAND_START, engine=engine)
    finally:
        package_logger.setLevel(level)
    if not args.quiet:
        for note in result.notes:  # a dataset or ground truth left out is in the report, and said here
            log(f"note: {note}")
        try:
            print(f"{result.markdown_path}\n{result.html_path}\n({len(result.rows)} runs, {len(result.figures)} "
                  f"figures, {result.seconds:.0f} s on {engine.name})", flush=True)
        except BrokenPipeError:
            pass
    return 0
