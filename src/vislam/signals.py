"""A signal's handler replaced for the length of a block (the CLI's SIGTERM-as-Ctrl-C,
the figure helper's start). Handlers live in the main thread: elsewhere nothing is
replaced."""

from __future__ import annotations

import contextlib
import signal

__all__ = ["replaced_handler"]


@contextlib.contextmanager
def replaced_handler(signum: int, handler):
    """Install ``handler`` for ``signum`` for the block and restore the previous handler
    when it is left; yields the previous handler (None outside the main thread, where
    nothing is installed)."""
    try:
        previous = signal.signal(signum, handler)
    except ValueError:  # not the main thread
        yield None
        return
    try:
        yield previous
    finally:
        signal.signal(signum, previous)
