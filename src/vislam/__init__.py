"""vislam: stereo visual-inertial SLAM on SE(3) with an extended Kalman filter."""

from vislam.errors import (
    ConfigError,
    DatasetError,
    EstimationError,
    GeometryError,
    GroundTruthError,
    OutputError,
    VislamError,
)

__version__ = "0.1.0"

__all__ = [
    "ConfigError",
    "DatasetError",
    "EstimationError",
    "GeometryError",
    "GroundTruthError",
    "OutputError",
    "VislamError",
    "__version__",
]
