"""Build script for the one compiled part of vislam: the SLAM EKF's per-frame kernels
(src/vislam/core/_ekf.c, plain C against Python's API; BLAS and LAPACK come from scipy at
run time). The metadata lives in pyproject.toml.

The extension is optional: where no C compiler is available the install goes on
without it and vislam runs its numpy reference path (vislam.core.kernels says which).
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "vislam.core._ekf",
            sources=["src/vislam/core/_ekf.c"],
            extra_compile_args=["-O3", "-fno-math-errno", "-std=c99"],
            optional=True,
        )
    ]
)
