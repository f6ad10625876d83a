"""Deterministic, atomic ``.npz`` writing.

``numpy.savez`` stamps every zip entry with the current time, so two runs with the same
data give different bytes. :func:`write_npz` writes the same layout (one ``.npy`` per
key, readable by ``numpy.load``) with a fixed entry date, so equal inputs give equal
bytes, and it writes atomically (a temporary file renamed onto the destination).
"""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np

from vislam.tools.atomic import atomic_path

__all__ = ["write_npz"]

_FIXED_DATE = (1980, 1, 1, 0, 0, 0)


def write_npz(path, arrays: dict[str, np.ndarray], compress: bool = True) -> None:
    """Write ``arrays`` (name -> numeric array) to ``path`` as an npz, deterministically."""
    compression = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with atomic_path(Path(path), suffix=".npz") as tmp:
        with zipfile.ZipFile(tmp, mode="w", compression=compression, allowZip64=True) as zf:
            for name, value in arrays.items():
                array = np.asanyarray(value)
                if array.dtype.hasobject:
                    raise TypeError(f"write_npz: array {name!r} has dtype object; only numeric arrays are written")
                buf = io.BytesIO()
                np.lib.format.write_array(buf, array, allow_pickle=False)
                info = zipfile.ZipInfo(f"{name}.npy", date_time=_FIXED_DATE)
                info.compress_type = compression
                info.external_attr = 0o644 << 16
                zf.writestr(info, buf.getvalue())
