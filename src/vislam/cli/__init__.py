"""Command-line interface: ``vislam <command> ...``.

The CLI is a thin layer: each command lives in its own module of this package, parses
its options, calls the library, and prints/plots/saves what the library returns. Every
:class:`vislam.errors.VislamError` is reported as one line on stderr with a non-zero
exit code; Ctrl-C exits with code 130.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from vislam import __version__
from vislam.errors import VislamError

#: Subcommand modules, in the order ``vislam --help`` lists them. Each module defines
#: ``register(subparsers)``, which adds its parser and sets ``func`` (args -> exit code).
COMMAND_MODULES = [
    "vislam.cli.demo",
    "vislam.cli.track",
    "vislam.cli.run",
    "vislam.cli.compare",
    "vislam.cli.eval",
    "vislam.cli.report",
    "vislam.cli.sweep",
    "vislam.cli.tune",
    "vislam.cli.consistency",
    "vislam.cli.info",
    "vislam.cli.check",
    "vislam.cli.simulate",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="vislam",
        description="Stereo visual-inertial SLAM on SE(3) with an extended Kalman filter.",
    )
    parser.add_argument("--version", action="version", version=f"vislam {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:  # a command not built yet
            if exc.name == name:
                continue
            raise
        module.register(subparsers)
    return parser


def _configure_logging(verbosity: int) -> None:
    level = logging.WARNING if verbosity <= 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    _configure_logging(args.verbose)
    try:
        return int(args.func(args) or 0)
    except VislamError as exc:
        print(f"vislam {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"vislam {args.command}: interrupted", file=sys.stderr)
        return 130


def entry_point() -> None:  # pragma: no cover - kept for scripts installed before vislam._launcher
    from vislam._launcher import entry_point as launch

    launch()
