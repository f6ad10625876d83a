"""Text that can always be printed, drawn and written as UTF-8.

A file name may hold bytes that are not UTF-8 (POSIX names are bytes); Python then
decodes them as lone surrogates (``surrogateescape``), which ``print``, matplotlib and
UTF-8 writers refuse. :func:`printable` shows such a byte as ``\\xff`` (any other lone
surrogate as ``\\udNNN``); everything else is returned unchanged. The same rule is the
codec error handler :data:`ERRORS` (the CLI sets it on stdout and stderr). Used for
names and paths shown to a person (titles, messages, JSON, text files), never for the
path that is opened.
"""

from __future__ import annotations

import codecs

__all__ = ["printable", "ERRORS"]

#: Name of the codec error handler that writes an undecodable byte as ``\xNN``.
ERRORS = "vislam-printable"


def _escape(exc: UnicodeError):
    if not isinstance(exc, UnicodeEncodeError):
        raise exc
    bad = exc.object[exc.start:exc.end]
    out = "".join(f"\\x{ord(c) - 0xDC00:02x}" if 0xDC80 <= ord(c) <= 0xDCFF else f"\\u{ord(c):04x}" for c in bad)
    return out, exc.end


codecs.register_error(ERRORS, _escape)


def printable(text) -> str:
    """``text`` (a str or path) with every lone surrogate written as ``\\xNN`` / ``\\uNNNN``."""
    text = str(text)
    try:
        text.encode("utf-8")
        return text
    except UnicodeEncodeError:
        return text.encode("utf-8", ERRORS).decode("utf-8")
