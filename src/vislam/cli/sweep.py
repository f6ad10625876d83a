"""``vislam sweep SPEC --out DIR [--scheduler ADDR] [--workers N]``: a grid of runs on Dask.

The SPEC format, the cells, results.csv and resuming are :mod:`vislam.tools.sweep`'s;
the engine (a LocalCluster by default, any running scheduler with ``--scheduler``) is
:mod:`vislam.tools.cluster`'s. This module parses, shows a progress bar (tqdm, on a
terminal) and prints a summary.
"""

from __future__ import annotations

import sys

from vislam.cli.common import add_engine_arguments, configure_dask_logging, terminate_as_interrupt  # noqa: F401

__all__ = ["register", "run", "add_engine_arguments", "terminate_as_interrupt", "configure_dask_logging"]


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "sweep",
        help="run a grid of datasets x modes x option sets x noise x seeds on a Dask cluster",
        description="Run the grid of a SPEC file (YAML/TOML: datasets with optional ground truth, modes, named "
        "option sets, named injected-noise settings, seeds), one task per cell, on a Dask cluster, and write "
        "DIR/results.csv (one row per cell: metrics, landmark counts, timings, status, error) as cells finish, and "
        "DIR/summary.png. Rerunning with the same --out resumes: cells already done are skipped, cells that "
        "failed are run again. A failed cell is a row with its error, never the end of the sweep; the exit status is 1 "
        "when some cell of the grid has status error.",
    )
    parser.add_argument("spec", metavar="SPEC", help="sweep specification (.yaml/.yml/.toml)")
    parser.add_argument("--out", metavar="DIR", required=True, help="output directory (created if needed)")
    add_engine_arguments(parser)
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")
    parser.set_defaults(func=run)


def run(args) -> int:
    from vislam.tools.cluster import open_engine
    from vislam.tools.sweep import RESULTS_FILE, load_spec, run_sweep, spec_summary

    spec = load_spec(args.spec)
    quiet = args.quiet
    bar = None

    def say(text: str) -> None:
        if not quiet:
            print(f"vislam sweep: {text}", file=sys.stderr, flush=True)

    def on_start(n_todo: int, n_done: int) -> None:
        nonlocal bar
        say(f"{spec_summary(spec)}; {n_done} already in {args.out}/{RESULTS_FILE}, {n_todo} to run")
        if not quiet and sys.stderr.isatty() and n_todo:
            from tqdm import tqdm

            bar = tqdm(total=n_todo, desc="cells", unit="cell", file=sys.stderr, dynamic_ncols=True)

    def on_row(row: dict, done: int, total: int) -> None:
        if bar is not None:
            bar.update(1)
            if row["status"] == "error":
                key = "/".join(str(row[k]) for k in ("dataset", "mode", "options", "noise", "seed"))
                bar.write(f"vislam sweep: {key}: error: {row['error']}", file=sys.stderr)
        elif not quiet:
            ate, cam = row.get("ate_m"), row.get("cam_ate_m")
            what = ("done" if ate in (None, "") else f"ATE {float(ate):.3f} m" if cam in (None, "")
                    else f"ATE camera {float(cam):.3f} m, IMU {float(ate):.3f} m")
            what = row["error"] if row["status"] == "error" else what
            say(f"[{done}/{total}] {'/'.join(str(row[k]) for k in ('dataset', 'mode', 'options', 'noise', 'seed'))}: "
                f"{row['status']}, {what}")

    if args.sequential and args.scheduler:
        from vislam.errors import ConfigError

        raise ConfigError("--sequential and --scheduler exclude each other")
    workers = 0 if args.sequential else args.workers
    configure_dask_logging(args.verbose)
    try:
        with terminate_as_interrupt(), open_engine(args.scheduler, workers) as engine:
            say(f"engine: {engine.name}")
            result = run_sweep(spec, args.out, engine, on_row=on_row, on_start=on_start)
    except KeyboardInterrupt:
        if bar is not None:
            bar.close()
        print(f"vislam sweep: interrupted; the finished cells are in {args.out}/{RESULTS_FILE}; rerun the same "
              f"command to run the others", file=sys.stderr)
        return 130
    finally:
        if bar is not None:
            bar.close()
    if not quiet:
        print(f"{result.results_path}\n" + (f"{result.figure_path}\n" if result.figure_path else "")
              + f"({result.n_cells} cells: {result.n_run} run now, {result.n_skipped} done before; "
              f"{result.n_errors} with errors; {result.seconds:.1f} s on {result.engine})", flush=True)
        for note in result.notes:
            print(f"vislam sweep: {note}", file=sys.stderr)
    return 1 if result.n_errors else 0
