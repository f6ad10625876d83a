"""Atomic file output: a file either appears complete or not at all.

Writers produce a temporary file in the destination directory and ``os.replace`` it
onto the final name, which is atomic on POSIX file systems. A failure or Ctrl-C in the
middle leaves the previous state (no file, or the old file) and no temporary debris.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

from vislam.errors import OutputError
from vislam.text import printable

__all__ = ["atomic_path", "write_text_atomic", "write_bytes_atomic"]


@contextlib.contextmanager
def atomic_path(path, suffix: str | None = None):
    """Yield a temporary path next to ``path``; on success rename it onto ``path``.

    ``suffix`` defaults to the final suffix of ``path`` (some writers, e.g. numpy's
    ``savez`` and matplotlib's ``savefig``, choose the format from it).
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create directory {path.parent}: {exc.strerror or exc}") from exc
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix if suffix is not None else path.suffix,
                                   dir=path.parent)
    except OSError as exc:
        raise OutputError(f"cannot write in {path.parent}: {exc.strerror or exc}") from exc
    # mkstemp creates the file 0600; give the final file the usual 0666 minus the umask.
    os.fchmod(fd, 0o666 & ~_umask())
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp_path.unlink()
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_text_atomic(path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(printable(text), encoding="utf-8")


def write_bytes_atomic(path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
