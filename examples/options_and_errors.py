"""Options from a file, flags over it, and what a misspelt key gives."""

import tempfile
from pathlib import Path

import vislam
from vislam.tools.config import resolve_options

with tempfile.TemporaryDirectory() as tmp:
    path = Path(tmp) / "dense.yaml"
    path.write_text("velocity_noise_mps: 0.5\nangular_noise_radps: 0.05\npixel_noise_px: 2.0\n")
    options = resolve_options(path, overrides={"pixel_noise_px": 1.5})  # a flag wins over the file
    print(options.velocity_noise_mps, options.angular_noise_radps, options.pixel_noise_px)

    path.write_text("velocity_noise_mp: 0.5\n")
    try:
        resolve_options(path)
    except vislam.ConfigError as exc:
        print(f"error: {exc}")
