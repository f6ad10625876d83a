"""Process entry point of the ``vislam`` command (and ``python -m vislam``).

Nothing heavy is imported at module level: the command-line interface, numpy, scipy
and matplotlib are imported inside :func:`entry_point`, under the same handler for
Ctrl-C as the command itself. An interrupt at any moment — during the start-up imports
included — ends the process with one line on stderr and exit code 130, never a
traceback; outputs are written all at once or not at all (the commands stage them).

A Ctrl-C that lands while a module is being imported is held back until the import has
finished (:func:`_sigint_outside_imports`): raised inside an import, C code can turn it
into another error (numpy's extension module reports an interrupted ``import datetime``
as "PyCapsule_Import could not import module"), or the import system can swallow it in
a callback (:func:`_unraisable_interrupts_reach_main`, kept as a safety net).
"""

import sys
import time

INTERRUPT_EXIT_CODE = 130
#: When the command's Python code began (this module is its first): the start of a
#: command whose process was something else before (``bash -c '... && vislam demo'``
#: execs the last command in the shell's own process), see
#: :func:`vislam.tools.outputs.command_start_time`.
STARTED = time.time()


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

    def hook(unraisable) -> None:
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            _thread.start_new_thread(_interrupt_main_later, (0.01,))
            return
        default(unraisable)

    return hook


def _in_import(frame) -> bool:
    """True if ``frame`` or a frame that called it belongs to the import system."""
    while frame is not None:
        if frame.f_code.co_filename.startswith(("<frozen importlib._bootstrap", "<frozen zipimport")):
            return True
        frame = frame.f_back
    return False


def _interrupt_main_later(delay_s: float) -> None:
    """Raise SIGINT's handler in the main thread after ``delay_s`` (run in a new thread)."""
    import _thread
    import time

    time.sleep(delay_s)
    _thread.interrupt_main()


def _sigint_outside_imports(retry_s: float = 0.02):
    """A SIGINT handler that raises KeyboardInterrupt as Python's default one does, except
    while an import is in progress: then it asks again ``retry_s`` later
    (``_thread.interrupt_main`` from a new thread calls this handler anew), until the
    import is done. Imports end in well under a second, so the command still stops at
    once, and the interrupt reaches :func:`entry_point` as a plain KeyboardInterrupt.
    Only built-in modules are used (``_thread``, ``time``): nothing here runs an import
    of Python code."""
    import _thread

    def handler(signum, frame) -> None:
        if _in_import(frame if frame is not None else sys._getframe(1)):
            _thread.start_new_thread(_interrupt_main_later, (retry_s,))
            return
        raise KeyboardInterrupt

    return handler


def _install_interrupt_handling() -> None:
    """The unraisable hook and the SIGINT handler above (``_signal``: the built-in module;
    importing ``signal`` would run Python code, enum's, before the handler is in place)."""
    import _signal

    sys.unraisablehook = _unraisable_interrupts_reach_main(sys.unraisablehook)
    try:
        if _signal.getsignal(_signal.SIGINT) is _signal.default_int_handler:  # not when started with SIGINT ignored
            _signal.signal(_signal.SIGINT, _sigint_outside_imports())
    except (ValueError, OSError):  # not the main thread / not supported
        pass


def entry_point() -> None:
    """Run the command line and exit with its code."""
    command = next((a for a in sys.argv[1:] if not a.startswith("-")), None)
    name = f"vislam {command}" if command else "vislam"
    try:
        _install_interrupt_handling()
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
