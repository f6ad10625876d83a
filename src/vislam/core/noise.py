"""Artificial noise injection (the report's "artificially increased noise"), seeded.

:func:`inject_noise` returns a new :class:`Sequence` with, as requested by a
:class:`NoiseSpec`:

* white Gaussian noise on every linear and angular velocity sample (σ per axis);
* constant velocity biases (added to every sample, IMU frame);
* white Gaussian noise on every pixel coordinate of every observation;
* a share of observations replaced by gross outliers: uL, vL uniform in the image
  area spanned by the recording's observations, a disparity uniform in 1–60 px, and
  vR = vL (so they pass the row check and must be caught by the gate).

The filter's own noise model (:class:`vislam.core.options.FilterOptions`) is a separate
setting: injecting noise does not change it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from vislam.core.options import MAX_STD
from vislam.core.sequence import (MAX_IMU_SAMPLE, MAX_PIXEL_COORD, Sequence, StereoObservations,
                                   first_pixel_row_beyond, first_sample_beyond)
from vislam.errors import ConfigError

__all__ = ["NoiseSpec", "inject_noise"]


@dataclass(frozen=True)
class NoiseSpec:
    """What noise to add (all zero: nothing)."""

    #: White noise on each linear-velocity sample, 1σ per axis (m/s).
    velocity_noise_mps: float = 0.0
    #: White noise on each angular-velocity sample, 1σ per axis (rad/s).
    angular_noise_radps: float = 0.0
    #: Constant bias added to every linear-velocity sample (m/s, IMU x, y, z).
    velocity_bias_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: Constant bias added to every angular-velocity sample (rad/s, IMU x, y, z).
    angular_bias_radps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: White noise on every pixel coordinate of every observation, 1σ (px).
    pixel_noise_px: float = 0.0
    #: Share of observations replaced by gross outliers, in [0, 1).
    outlier_fraction: float = 0.0
    #: Seed of the random generator.
    seed: int = 0

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "seed":
                if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                    raise ConfigError(f"noise seed must be an integer >= 0, got {v!r}")
            elif f.name.endswith("bias_mps") or f.name.endswith("bias_radps"):
                try:
                    t = tuple(float(x) for x in v)
                except (TypeError, ValueError):
                    raise ConfigError(f"{f.name} must be three numbers, got {v!r}") from None
                if len(t) != 3 or not all(math.isfinite(x) for x in t):
                    raise ConfigError(f"{f.name} must be three finite numbers, got {v!r}")
                if max(abs(x) for x in t) > MAX_STD:
                    raise ConfigError(f"{f.name} must be within ±{MAX_STD:g}, got {v!r}")
                object.__setattr__(self, f.name, t)
            else:
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                    raise ConfigError(f"{f.name} must be a finite number >= 0, got {v!r}")
                if v > MAX_STD:  # (1e300 m/s overflows the filter's state)
                    raise ConfigError(f"{f.name} must be at most {MAX_STD:g}, got {v!r}")
        if self.outlier_fraction >= 1.0:
            raise ConfigError(f"outlier_fraction must be in [0, 1), got {self.outlier_fraction!r}")

    @property
    def is_zero(self) -> bool:
        return (self.velocity_noise_mps == 0 and self.angular_noise_radps == 0 and self.pixel_noise_px == 0
                and self.outlier_fraction == 0 and not any(self.velocity_bias_mps)
                and not any(self.angular_bias_radps))

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["velocity_bias_mps"] = list(self.velocity_bias_mps)
        d["angular_bias_radps"] = list(self.angular_bias_radps)
        return d


def inject_noise(sequence: Sequence, spec: NoiseSpec) -> tuple[Sequence, dict[str, Any]]:
    """A noisy copy of ``sequence`` and a record of what was added (for summary.json)."""
    info: dict[str, Any] = {"spec": spec.to_dict(), "outliers_injected": 0}
    if spec.is_zero:
        return sequence, info
    # independent streams, so e.g. changing the pixel noise leaves the velocity noise as is
    rng_v, rng_w, rng_px, rng_out = (np.random.default_rng(s) for s in np.random.SeedSequence(spec.seed).spawn(4))
    T = sequence.n_frames
    v = sequence.linear_velocity_in_imu_mps + np.asarray(spec.velocity_bias_mps)
    w = sequence.angular_velocity_in_imu_radps + np.asarray(spec.angular_bias_radps)
    if spec.velocity_noise_mps:
        v = v + rng_v.normal(0.0, spec.velocity_noise_mps, (T, 3))
    if spec.angular_noise_radps:
        w = w + rng_w.normal(0.0, spec.angular_noise_radps, (T, 3))
    for name, samples in (("linear", v), ("angular", w)):
        far = first_sample_beyond(samples)
        if far is not None:
            k, i = far
            raise ConfigError(f"the added noise and bias take the {name} velocity of frame {k} to "
                              f"{samples[k, i]:.10g}, beyond ±{MAX_IMU_SAMPLE:g}")
    obs = sequence.observations
    pixels = obs.pixels.copy()
    if spec.pixel_noise_px and pixels.size:
        pixels += rng_px.normal(0.0, spec.pixel_noise_px, pixels.shape)
        # an exact repeat of the previous frame (a tracker artifact, see
        # StereoObservations.repeated_mask) stays an exact repeat of the noisy pixels
        rep = np.nonzero(obs.repeated_mask())[0]
        prev = obs.previous_index()
        for row in rep[np.argsort(obs.frame_index[rep], kind="stable")]:  # chains in frame order
            pixels[row] = pixels[prev[row]]
    n_out = int(round(spec.outlier_fraction * obs.n_observations))
    if n_out:
        rows = rng_out.choice(obs.n_observations, size=n_out, replace=False)
        lo = obs.pixels[:, :2].min(axis=0)
        hi = obs.pixels[:, :2].max(axis=0)
        uv = rng_out.uniform(lo, hi, size=(n_out, 2))
        disparity = rng_out.uniform(1.0, 60.0, size=n_out)
        pixels[rows] = np.column_stack([uv[:, 0], uv[:, 1], uv[:, 0] - disparity, uv[:, 1]])
        info["outliers_injected"] = n_out
    row = first_pixel_row_beyond(pixels)
    if row is not None:
        raise ConfigError(f"the added pixel noise ({spec.pixel_noise_px:g} px) takes an observation of frame "
                          f"{int(obs.frame_index[row])} to {pixels[row].tolist()}, beyond ±{MAX_PIXEL_COORD:g} px")
    noisy_obs = StereoObservations(obs.frame_offsets, obs.landmark_ids, pixels, obs.n_landmarks)
    out = sequence.replace(linear_velocity_in_imu_mps=v, angular_velocity_in_imu_radps=w, observations=noisy_obs,
                           name=sequence.name)
    return out, info
