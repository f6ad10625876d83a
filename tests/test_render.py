"""The renderer's texture sampling: the same surface looks the same at every mip level.

Properties a tracker relies on: a surface's texture stays where the surface is when the
mip level of its pixels changes (the pyramid's levels are aligned and wrap with one period),
and the image changes continuously with the level (trilinear blending), so a drive's
images move only as its geometry does.
"""

from __future__ import annotations

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from vislam.core.render import _MIP_LEVELS, _pyramid, _sample_level, _sample_trilinear  # noqa: E402


def _smooth_texture(h: int, w: int) -> np.ndarray:
    """A periodic texture of long wavelength (64 texels: two pyrDowns barely change it) that
    tiles without a seam once cropped to a multiple of 64 texels."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    return (120 + 60 * np.sin(2 * np.pi * x / 64.0) * np.cos(2 * np.pi * y / 64.0)).astype(np.float32)


@pytest.mark.parametrize("shape", [(300, 451), (660, 550), (512, 512)])
def test_pyramid_levels_halve_exactly(shape):
    pyr = _pyramid(_smooth_texture(*shape))
    assert len(pyr) == _MIP_LEVELS
    for lower, upper in zip(pyr[:-1], pyr[1:]):
        assert upper.shape == (lower.shape[0] // 2, lower.shape[1] // 2)
        assert lower.shape[0] % 2 == 0 and lower.shape[1] % 2 == 0


def test_pyramid_refuses_a_texture_smaller_than_its_top_level():
    with pytest.raises(ValueError, match="smaller than 64"):
        _pyramid(np.zeros((40, 200), np.float32))


@pytest.mark.parametrize("shape", [(300, 451), (660, 550)])
def test_every_level_shows_the_texture_at_the_same_place_also_past_its_wrap(shape):
    """Level 0 and level 2 sampled at the same plane coordinates, over several periods of the
    texture (a quad is much longer than one texture tile): the values agree up to the
    attenuation of two pyrDowns. With the odd-sized levels of the uncropped pyramid the
    coarse levels wrapped with another period and showed another part of the texture."""
    pyr = _pyramid(_smooth_texture(*shape))
    texel_m, offset = 0.01, np.array([1234.5, 987.25])
    rng = np.random.default_rng(0)
    s1 = rng.uniform(0, 30.0, 4000).astype(np.float32)  # 30 m: several periods of every texture
    s2 = rng.uniform(0, 15.0, 4000).astype(np.float32)
    fine = _sample_level(pyr, 0, s1, s2, texel_m, offset, cv2)
    coarse = _sample_level(pyr, 2, s1, s2, texel_m, offset, cv2)
    # two pyrDowns attenuate the pattern by a few per cent: compare after the best gain about the mean
    f, c = fine - 120.0, coarse - 120.0
    gain = (f @ c) / (f @ f)
    assert 0.9 < gain <= 1.0
    assert np.percentile(np.abs(c - gain * f), 99) < 1.5  # grey levels, of a 120 +- 60 pattern


def test_trilinear_sampling_is_continuous_across_a_level_change():
    """Just below and just above an integer level the values agree (a surface whose distance
    crosses a level boundary does not pop); midway they are the blend of the two levels."""
    pyr = _pyramid(_smooth_texture(512, 512) + np.float32(30) * np.random.default_rng(1).standard_normal(
        (512, 512)).astype(np.float32))
    rng = np.random.default_rng(2)
    s1 = rng.uniform(0, 5.0, 2000).astype(np.float32)
    s2 = rng.uniform(0, 5.0, 2000).astype(np.float32)
    offset = np.array([10.0, 20.0])
    for level in range(1, _MIP_LEVELS - 1):
        below = _sample_trilinear(pyr, s1, s2, np.full(s1.size, level - 1e-4, np.float32), 0.01, offset, cv2)
        above = _sample_trilinear(pyr, s1, s2, np.full(s1.size, level + 1e-4, np.float32), 0.01, offset, cv2)
        assert np.max(np.abs(below - above)) < 0.05
    lo = _sample_level(pyr, 2, s1, s2, 0.01, offset, cv2)
    hi = _sample_level(pyr, 3, s1, s2, 0.01, offset, cv2)
    mid = _sample_trilinear(pyr, s1, s2, np.full(s1.size, 2.25, np.float32), 0.01, offset, cv2)
    np.testing.assert_allclose(mid, 0.75 * lo + 0.25 * hi, atol=1e-3)
