""""Did you mean …?" for misspelt names: option keys, flags, commands, choices.

A close match (:func:`difflib.get_close_matches`) is offered when there is one; the error
messages that use it stay one line.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable

__all__ = ["close_matches", "did_you_mean", "unknown_names_message"]


def close_matches(word: str, known: Iterable[str], n: int = 3, cutoff: float = 0.6) -> list[str]:
    """Up to ``n`` names of ``known`` close to ``word``, best first (case-insensitive)."""
    known = list(dict.fromkeys(str(k) for k in known))
    by_lower = {k.lower(): k for k in known}
    hits = difflib.get_close_matches(str(word).lower(), list(by_lower), n=n, cutoff=cutoff)
    return [by_lower[h] for h in hits]


def did_you_mean(word: str, known: Iterable[str]) -> str:
    """``"did you mean 'x'?"`` (or ``"'x' or 'y'"``), or ``""`` when nothing is close."""
    hits = close_matches(word, known, n=2)
    if not hits:
        return ""
    return "did you mean " + " or ".join(repr(h) for h in hits) + "?"


def unknown_names_message(what: str, unknown: Iterable, known: Iterable[str]) -> str:
    """``unknown option(s) 'x'; did you mean 'y'?`` — or, when no name is close, the list
    of the known ones (``repr`` keeps odd keys on one line)."""
    unknown, known = list(unknown), list(known)
    names = ", ".join(repr(k) for k in unknown)
    hints = {k: did_you_mean(k, known) for k in unknown if isinstance(k, str)}
    hints = {k: h for k, h in hints.items() if h}
    if not hints:
        return f"unknown {what} {names}; known: {', '.join(known)}"
    if len(unknown) == 1:
        return f"unknown {what} {names}; {hints[unknown[0]]}"
    return f"unknown {what} {names}; " + "; ".join(f"{k!r}: {h}" for k, h in hints.items())
