"""Process entry point of the ``vislam`` command (and ``python -m vislam``).

Nothing heavy is imported at module level: the command-line interface, numpy, scipy
and matplotlib are imported inside :func:`entry_point`, under the same handler for
Ctrl-C as the command itself. An interrupt at any moment — during the start-up imports
included, also one that lands in a callback of the import system and cannot propagate
from there (:func:`_unraisable_interrupts_reach_main`) — ends the process with one line on stderr and exit code 130, never a
traceback; outputs are written all at once or not at all (the commands stage them).
"""

import sys

INTERRUPT_EXIT_CODE = 130


def _interrupted(message: str) -> int:
    """Report an interrupt in one line and return its exit code (ignoring further Ctrl-C)."""
    import signal

    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C must not interrupt the report
    except (ValueError, OSError):  # not the main thread / not supported
        pass
    try:
        print(message, file=sys.stderr, flush=True)
    except (OSError, ValueError):
        pass
    return INTERRUPT_EXIT_CODE


def _is_interrupt(exc: BaseException) -> bool:
    """True for a KeyboardInterrupt, also one Python wrapped on its way out: Python 3.11
    turns an exception raised in ``__set_name__`` while a class is created (a Ctrl-C
    landing while an imported module defines a dataclass) into a RuntimeError whose
    cause is the interrupt."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def _unraisable_interrupts_reach_main(default=sys.unraisablehook):
    """A ``sys.unraisablehook`` for Ctrl-C: a KeyboardInterrupt raised where Python cannot
    propagate it (a weakref callback of the import system's module locks, when the
    interrupt lands during the start-up imports) would be printed as "Exception ignored"
    with a traceback and then lost. This hook prints nothing and raises it again in the
    main thread (``_thread.interrupt_main``), where :func:`entry_point` reports it in one
    line; every other unraisable exception goes to ``default``. The interrupt is raised
    from a helper thread a moment later, once this hook has returned: raised inside the
    hook it would be unraisable again."""
    import _thread
    import threading

    def hook(unraisable) -> None:
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            threading.Timer(0.01, _thread.interrupt_main).start()
            return
        default(unraisable)

    return hook


def entry_point() -> None:
    """Run the command line and exit with its code."""
    command = next((a for a in sys.argv[1:] if not a.startswith("-")), None)
    name = f"vislam {command}" if command else "vislam"
    sys.unraisablehook = _unraisable_interrupts_reach_main(sys.unraisablehook)
    try:
        from vislam.cli import main

        code = main()
    except BaseException as exc:  # noqa: B036 - only interrupts are handled here
        if not _is_interrupt(exc):
            raise
        code = _interrupted(f"{name}: interrupted; no output written")
    if code == INTERRUPT_EXIT_CODE:
        # After an interrupt, leave without the interpreter's shutdown: CPython ends a
        # process that saw an unhandled KeyboardInterrupt anywhere (in an import, say)
        # by re-raising SIGINT, which turns our exit code 130 into "killed by signal".
        # The commands have already removed their staging directories at this point.
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError, AttributeError):
                pass
        import os

        os._exit(code)
    sys.exit(code)
