"""vislam: stereo visual-inertial SLAM on SE(3) — the report's extended Kalman filter.

The public Python API (see docs/api.md)::

    import vislam
    seq = vislam.load_sequence("drive.npz")
    f = vislam.SlamFilter(seq.calibration, vislam.FilterOptions(velocity_noise_mps=0.5))
    for t, world_T_imu in vislam.final_poses(f, seq.frames()):
        ...  # frame t's final pose (f.world_T_imu is the live, predicted one)

Names are imported lazily (on first use), so ``import vislam`` is instant and the
command line can handle Ctrl-C from its very first moment.
"""

from vislam.errors import (
    ConfigError,
    DatasetError,
    EstimationError,
    GeometryError,
    GroundTruthError,
    OutputError,
    SequenceError,
    VislamError,
)

__version__ = "0.1.0"

#: Public name -> module that defines it (imported on first access).
_LAZY = {
    # data
    "load_sequence": "vislam.tools.dataset_io",
    "load_dataset": "vislam.tools.dataset_io",
    "save_sequence": "vislam.tools.dataset_io",
    "iter_frames": "vislam.tools.dataset_io",
    "Sequence": "vislam.core.sequence",
    "Frame": "vislam.core.sequence",
    "Calibration": "vislam.core.sequence",
    "StereoCamera": "vislam.core.camera",
    # options and estimators
    "FilterOptions": "vislam.core.options",
    "apply_corrections": "vislam.core.corrections",
    "remap_sequence": "vislam.core.stalls",
    "LocalizationFilter": "vislam.core.filters",
    "MappingFilter": "vislam.core.filters",
    "SlamFilter": "vislam.core.filters",
    "FrameStats": "vislam.core.filters",
    "final_poses": "vislam.core.filters",
    "SmootherFilter": "vislam.core.smoother",
    "run": "vislam.core.estimators",
    "RunResult": "vislam.core.results",
    "LandmarkMap": "vislam.core.results",
    # simulation and evaluation
    "simulate_drive": "vislam.core.simulate",
    "SimulationOptions": "vislam.core.simulate",
    "evaluate": "vislam.tools.evaluation",
}

__all__ = [
    "ConfigError",
    "DatasetError",
    "EstimationError",
    "SequenceError",
    "GeometryError",
    "GroundTruthError",
    "OutputError",
    "VislamError",
    "__version__",
    *sorted(_LAZY),
]


def __getattr__(name: str):
    module_name = _LAZY.get(name)
    if module_name is None:
        raise AttributeError(f"module 'vislam' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(module_name), name)
    globals()[name] = value  # cache: the next access does not come here
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
