"""Strict JSON output: numpy types converted, non-finite floats written as null."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from vislam.text import printable
from vislam.tools.atomic import write_text_atomic

__all__ = ["json_safe", "dumps", "write_json"]


def json_safe(value):
    """Plain JSON types; numpy scalars/arrays converted, non-finite floats -> None."""
    if isinstance(value, Mapping):
        return {printable(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return value if math.isfinite(value) else None
    if isinstance(value, (str, Path)):  # a file name may hold bytes that are not UTF-8
        return printable(value)
    return value


def dumps(data: Any) -> str:
    """Strict JSON text of ``data`` (indented, NaN/inf as null)."""
    return json.dumps(json_safe(data), indent=2, allow_nan=False)


def write_json(path, data: Mapping[str, Any]) -> None:
    """Write strict JSON, atomically."""
    write_text_atomic(path, dumps(data) + "\n")
