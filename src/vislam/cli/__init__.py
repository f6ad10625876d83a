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
import re
import sys

from vislam import __version__
from vislam.core.suggest import did_you_mean
from vislam.errors import VislamError
from vislam.text import ERRORS as TEXT_ERRORS

#: The commands, in the order ``vislam --help`` lists them: (name, module, one-line help).
#: Each module defines ``register(subparsers)``, which adds its parser (with this help
#: line) and sets ``func`` (args -> exit code). The parser imports only the module of
#: the command being run, so ``vislam --help`` and a command's start-up do not pay for
#: the others (numpy, scipy, matplotlib, Dask ...); tests/test_cli_info.py checks that
#: these lines are the modules' own.
COMMANDS = (
    ("demo", "vislam.cli.demo", "run SLAM on a built-in simulated drive and grade it against the truth"),
    ("track", "vislam.cli.track",
     "track stereo features in an image folder (KITTI raw, EuRoC, plain) into a dataset .npz"),
    ("run", "vislam.cli.run", "run IMU localization, landmark mapping, SLAM or the sliding-window smoother on a dataset"),
    ("compare", "vislam.cli.compare", "localization + mapping (separately), SLAM, the smoother and its refinement on "
     "the same data, one comparison figure"),
    ("eval", "vislam.cli.eval", "evaluate an estimated trajectory against ground truth"),
    ("report", "vislam.cli.report",
     "regenerate the report's whole results section (figures, tables, metrics) in one command"),
    ("sweep", "vislam.cli.sweep", "run a grid of datasets x modes x option sets x noise x seeds on a Dask cluster"),
    ("tune", "vislam.cli.tune",
     "choose the filter's noise without ground truth (innovation likelihood, parallel search on Dask)"),
    ("consistency", "vislam.cli.consistency", "Monte Carlo consistency of the filter on simulated drives: pose and "
     "landmark NEES with chi-square bands"),
    ("info", "vislam.cli.info", "validate a dataset file and summarize it"),
    ("check", "vislam.cli.check", "learn the noise, biases and conventions of a recording (no ground truth)"),
    ("simulate", "vislam.cli.simulate", "simulate a KITTI-like drive with ground truth"),
)

#: Subcommand modules, in the order ``vislam --help`` lists them.
COMMAND_MODULES = [module for _, module, _ in COMMANDS]


class _Parser(argparse.ArgumentParser):
    """argparse with "did you mean" for a misspelt flag, command or choice (the
    subcommands' parsers are of this class too: ``add_subparsers`` copies it)."""

    _CHOICE = re.compile(r"invalid choice: '([^']*)' \(choose from (.*)\)")

    def parse_args(self, args=None, namespace=None):
        namespace, extras = self.parse_known_args(args, namespace)
        if extras:
            parser = self._chosen_subparser(namespace) or self
            flags = [o for a in parser._actions for o in a.option_strings if o.startswith("--")]
            hints = [f"{flag}: {hint}" for flag in (arg.split("=", 1)[0] for arg in extras if arg.startswith("-"))
                     for hint in [did_you_mean(flag, flags)] if hint]
            parser.error("unrecognized arguments: " + " ".join(extras) + ("; " + "; ".join(hints) if hints else ""))
        return namespace

    def _chosen_subparser(self, namespace):
        for action in self._actions:
            if isinstance(action, argparse._SubParsersAction):
                return action.choices.get(getattr(namespace, action.dest, None) or "")
        return None

    def error(self, message):
        match = self._CHOICE.search(message)
        if match:
            hint = did_you_mean(match.group(1), re.findall(r"'([^']*)'", match.group(2)))
            if hint:
                message = f"{message}; {hint}"
        super().error(message)


def _command_of(argv: list[str]) -> str | None:
    """The command named on the command line: its first argument that is not an option
    (the top-level options take no values)."""
    return next((a for a in argv if not a.startswith("-")), None)


def build_parser(command: str | None = "*") -> argparse.ArgumentParser:
    """The parser of ``vislam``. ``"*"`` (default): every command's full parser. A
    command name: only that command's module is imported and builds its full parser; the
    other commands get a one-line placeholder (enough for ``vislam --help`` and for "did
    you mean"). None: placeholders only (what :func:`main` uses without a command)."""
    parser = _Parser(
        prog="vislam",
        description="Stereo visual-inertial SLAM on SE(3) with an extended Kalman filter.",
    )
    parser.add_argument("--version", action="version", version=f"vislam {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module_name, help_line in COMMANDS:
        if command not in (name, "*"):
            subparsers.add_parser(name, help=help_line)
            continue
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:  # a command not built yet
            if exc.name == module_name:
                continue
            raise
        module.register(subparsers)
    return parser


def say_phase(text: str, quiet: bool) -> None:
    """One status line on stderr for a phase of several seconds without a progress bar
    (e.g. ``vislam check``'s analyses) — only on a terminal and not quiet."""
    if not quiet and sys.stderr.isatty():
        print(f"{text} ...", file=sys.stderr, flush=True)


def _configure_logging(verbosity: int) -> None:
    level = logging.WARNING if verbosity <= 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)


#: String arguments that may be empty (a figure title).
_MAY_BE_EMPTY = ("title",)


def _empty_argument(parser, args) -> tuple[str, str] | None:
    """(flag or positional's name, what it expects: its metavar) of the command's first
    string argument given as an empty or blank string, else None."""
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            sub = action.choices.get(args.command)
            for a in sub._actions if sub is not None else ():
                value = getattr(args, a.dest, None)
                if isinstance(value, str) and not value.strip() and value != a.default and a.dest not in _MAY_BE_EMPTY:
                    if a.option_strings:
                        return a.option_strings[-1], a.metavar or "a value"
                    return f"the {a.metavar or a.dest} argument", "a path"
    return None


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(_command_of(argv))
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    for stream in (sys.stdout, sys.stderr):  # a file name's non-UTF-8 byte prints as \xff, not a traceback
        if hasattr(stream, "reconfigure"):
            stream.reconfigure(errors=TEXT_ERRORS)
    _configure_logging(args.verbose)
    empty = _empty_argument(parser, args)
    if empty:  # `--out "$OUT"` with OUT unset: not the current directory, not "no ground truth"
        print(f"vislam {args.command}: error: {empty[0]} is empty; expected {empty[1]}", file=sys.stderr)
        return 2
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
