"""``vislam tune DATA [--out DIR] [--scheduler ADDR] [--workers N] [--sequential]``: the
filter's noise chosen without ground truth.

The objective and the search are :mod:`vislam.core.tune`'s, the parallel rounds and the
outputs (tuned.yaml, tune.json, tune.png) :mod:`vislam.tools.tune`'s; this module parses,
reports each round and prints a summary that compares the answer with ``vislam check``'s
signal-based estimates.
"""

from __future__ import annotations

import sys
from pathlib import Path

__all__ = ["register", "run"]


def register(subparsers) -> None:
    from vislam.cli.common import add_engine_arguments

    parser = subparsers.add_parser(
        "tune",
        help="choose the filter's noise without ground truth (innovation likelihood, parallel search on Dask)",
        description="Choose velocity_noise_mps, angular_noise_radps and pixel_noise_px for DATA without ground "
        "truth: each candidate is a SLAM run scored by the mean robust (Student-t) predictive log-density of its "
        "innovations, every observation of a landmark in the state counted before gating; a log-spaced coarse grid, "
        "a pixel-noise line and a compass search with a fitted-quadratic proposal, the runs of each round in parallel "
        "on a Dask cluster. Writes "
        "DIR/tuned.yaml (for `vislam run --config`), DIR/tune.json (every candidate, the choice, run time, "
        "`vislam check`'s estimates) and DIR/tune.png.",
    )
    parser.add_argument("data", metavar="DATA", help="dataset file (.npz)")
    parser.add_argument("--out", metavar="DIR", default="tune-out", help="output directory (default: tune-out)")
    parser.add_argument("--mode", default="slam", choices=["slam"],
                        help="estimator whose innovations are scored (only slam: the others do not predict the "
                        "observations from the IMU)")
    parser.add_argument("--config", metavar="FILE",
                        help="options file (YAML/TOML) with the other options; its noise values are replaced")
    parser.add_argument("--frames", type=int, metavar="N",
                        help="score each candidate on the first N frames only (cheaper; default: all)")
    parser.add_argument("--grid", type=int, default=4, metavar="N",
                        help="points of the coarse log grid per IMU noise and of the pixel-noise line, 2 to 30 "
                        "(default 4: 16 + 4 runs)")
    parser.add_argument("--refine", type=int, default=3, metavar="N",
                        help="step sizes of the compass search after the grid (each half the one before; a step is "
                        "polled, 4-8 runs a round, until a round no longer improves the best; 0 to 20, default 3, at "
                        "most 10 rounds)")
    parser.add_argument("--pixel-noise", choices=["keep", "tune"], default="keep",
                        help="keep (default): search the IMU noise only, with the options file's (or the default) "
                        "pixel_noise_px; tune: search it too (the robust likelihood drives it to the bottom of its "
                        "range on the KITTI tracks: dense 0027 0.5 px, 44 %% of the landmarks rejected, ATE 6.3 m "
                        "against 3.2 m with it kept at 2 px)")
    add_engine_arguments(parser)
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors and the output paths")
    parser.set_defaults(func=run)


def _base_options(config) -> dict:
    """The options file's values (validated; off-words normalized), without the tuned noises."""
    if config is None:
        return {}
    from vislam.core.options import FilterOptions
    from vislam.tools.config import load_options_file, resolve_options

    options = resolve_options(config)  # every problem a one-line ConfigError naming the file
    keys = load_options_file(config)
    full = FilterOptions.to_dict(options)
    return {k: full[k] for k in keys}


#: Largest --grid: its square is the coarse round's runs (--grid 1000000 ran for ever).
MAX_GRID = 30
#: Largest --refine: step sizes halve each time, 2^-20 of the coarse spacing is far below
#: what an innovation likelihood can tell apart.
MAX_REFINE = 20


def run(args) -> int:
    from vislam.cli.common import configure_dask_logging, terminate_as_interrupt
    from vislam.errors import ConfigError, DatasetError, OutputError
    from vislam.core.tune import SearchSpace
    from vislam.tools.cluster import open_engine
    from vislam.tools.tune import write_tune_outputs, run_tune

    data = Path(args.data)
    if not data.exists():
        raise DatasetError(f"{data}: no such dataset file")
    if data.is_dir():
        raise DatasetError(f"{data}: is a directory (a dataset .npz file is expected)")
    out = Path(args.out)
    if out.exists() and not out.is_dir():  # before minutes of work
        raise OutputError(f"{out}: exists and is not a directory (an output directory is expected)")
    if args.frames is not None and args.frames < 2:
        raise ConfigError(f"--frames must be >= 2, got {args.frames}")
    if args.sequential and args.scheduler:
        raise ConfigError("--sequential and --scheduler exclude each other")
    if not (2 <= args.grid <= MAX_GRID and 0 <= args.refine <= MAX_REFINE):
        raise ConfigError(f"--grid must be in [2, {MAX_GRID}] (its square is the first round's runs: "
                          f"{MAX_GRID ** 2} at most) and --refine in [0, {MAX_REFINE}] (each step half the one "
                          f"before), got {args.grid} and {args.refine}")
    base = _base_options(args.config)
    if args.pixel_noise == "keep":
        from vislam.core.options import FilterOptions

        px = float(base.get("pixel_noise_px", FilterOptions().pixel_noise_px))
        space = SearchSpace(pixel_noise_px=(px, px), coarse_points=args.grid, pixel_points=1,
                            refine_rounds=args.refine)
    else:
        space = SearchSpace(coarse_points=args.grid, pixel_points=args.grid, refine_rounds=args.refine)
    quiet = args.quiet

    def say(text: str) -> None:
        if not quiet:
            print(f"vislam tune: {text}", file=sys.stderr, flush=True)

    def on_round(i, scores, best):
        failed = sum(s.error is not None for s in scores)
        b = best.candidate if best is not None else None
        say(f"round {i}: {len(scores)} runs" + (f" ({failed} failed)" if failed else "")
            + (f"; best so far σ_v {b.velocity_noise_mps:g} m/s, σ_ω {b.angular_noise_radps:g} rad/s, "
               f"σ_px {b.pixel_noise_px:g} px (objective {best.objective:.4f})" if b is not None else ""))

    from vislam.tools.dataset_io import load_sequence

    sequence = load_sequence(data)  # a bad file is a one-line error before any worker starts
    workers = 0 if args.sequential else args.workers
    configure_dask_logging(args.verbose)
    try:
        with terminate_as_interrupt(), open_engine(args.scheduler, workers) as engine:
            say(f"engine: {engine.name}; {args.data}" + (f", first {args.frames} frames" if args.frames else ""))
            result = run_tune(str(data.resolve()), engine, base=base, frames=args.frames, space=space,
                              on_round=on_round, sequence=sequence)
    except KeyboardInterrupt:
        print("vislam tune: interrupted; nothing written", file=sys.stderr)
        return 130
    paths = write_tune_outputs(result, out)
    t = result.tuned
    c = result.check
    lines = [f"tuned ({result.to_dict()['runs']} runs in {result.seconds:.1f} s on {result.engine}):",
             f"  velocity_noise_mps  {t['velocity_noise_mps']:<10.4g} check: {_vec(c.get('velocity_noise_mps'))}",
             f"  angular_noise_radps {t['angular_noise_radps']:<10.4g} check: {_vec(c.get('angular_noise_radps'))}",
             f"  pixel_noise_px      {t['pixel_noise_px']:<10.4g} check: {_vec(c.get('pixel_noise_px'))} (track "
             f"jitter; the filter's value also covers linearization and lag)"]
    if not quiet:
        print("\n".join(lines), file=sys.stderr)
        for note in result.notes:
            print(f"vislam tune: note: {note}", file=sys.stderr)
    print("\n".join(str(p) for p in paths), flush=True)
    return 0


def _vec(v) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, (list, tuple)):
        return "(" + ", ".join(f"{x:.3g}" for x in v) + ") per axis"
    return f"{v:.3g}"
