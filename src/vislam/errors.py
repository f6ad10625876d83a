"""Exceptions raised by vislam.

Every error a user can cause (a bad file, a bad option, a filter that diverged on
their data) is a subclass of :class:`VislamError`; the CLI catches that base class,
prints its message on one line and exits non-zero. Anything else escaping is a bug.
"""

from __future__ import annotations


class VislamError(Exception):
    """Base class of every error vislam raises on purpose."""

    exit_code = 2


class DatasetError(VislamError):
    """A dataset file is missing, unreadable or malformed."""


class SequenceError(DatasetError, ValueError):
    """A recording built in memory (``Sequence``, ``StereoObservations``, ``Calibration``)
    breaks their invariants; also a ValueError, which these constructors raised before."""


class GroundTruthError(VislamError):
    """A ground-truth trajectory file is missing, unreadable or does not match."""


class ConfigError(VislamError):
    """An options file or a command-line option is invalid."""


class GeometryError(VislamError):
    """A geometric operation is undefined for its input (e.g. zero disparity)."""


class EstimationError(VislamError):
    """The filter reached a non-finite or otherwise invalid state."""

    def __init__(self, message: str, frame: int | None = None):
        super().__init__(message)
        self.frame = frame


class OutputError(VislamError):
    """An output directory or file cannot be written."""


class ClusterError(VislamError):
    """The Dask cluster of a batch command cannot be started or reached."""
