"""The renderer's texture sampling: the same surface looks the same at every mip level.

Properties a tracker relies on: a surface's texture stays where the surface is when the
mip level of its pixels changes (the levels are aligned and wrap with one period, along
each axis), the image changes continuously with the levels (bilinear blending of the four
levels around a pixel's footprint), and a surface seen at a slant is filtered along the
slant only, as a camera pixel integrates its own stretched footprint — so a drive's images
move only as its geometry does.
"""

from __future__ import annotations

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from vislam.core.render import _MIP_LEVELS, _halve, _ripmap, _sample_anisotropic, _sample_level  # noqa: E402


def _smooth_texture(h: int, w: int) -> np.ndarray:
    """A periodic texture of long wavelength (64 texels: two pyrDowns barely change it) that
    tiles without a seam once cropped to a multiple of 64 texels."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    return (120 + 60 * np.sin(2 * np.pi * x / 64.0) * np.cos(2 * np.pi * y / 64.0)).astype(np.float32)


@pytest.mark.parametrize("shape", [(300, 451), (660, 550), (512, 512)])
def test_ripmap_levels_halve_exactly_along_each_axis(shape):
    rip = _ripmap(_smooth_texture(*shape))
    assert len(rip) == _MIP_LEVELS and all(len(row) == _MIP_LEVELS for row in rip)
    h, w = rip[0][0].shape
    assert h % 2 ** (_MIP_LEVELS - 1) == 0 and w % 2 ** (_MIP_LEVELS - 1) == 0
    for ly in range(_MIP_LEVELS):
        for lx in range(_MIP_LEVELS):
            assert rip[ly][lx].shape == (h >> ly, w >> lx)


def test_halving_both_axes_is_opencvs_pyrdown():
    """The per-axis halving uses pyrDown's kernel and keeps its texels: both axes halved give
    cv2.pyrDown's level (away from the border, where pyrDown reflects and the texture wraps)."""
    image = np.random.default_rng(3).uniform(0, 255, (128, 192)).astype(np.float32)
    ours = _halve(_halve(image, 0), 1)
    np.testing.assert_allclose(ours[2:-2, 2:-2], cv2.pyrDown(image)[2:-2, 2:-2], atol=1e-3)


def test_ripmap_refuses_a_texture_smaller_than_its_top_level():
    with pytest.raises(ValueError, match="smaller than 64"):
        _ripmap(np.zeros((40, 200), np.float32))


@pytest.mark.parametrize("shape", [(300, 451), (660, 550)])
@pytest.mark.parametrize("levels", [(2, 2), (2, 0), (0, 2)])
def test_every_level_shows_the_texture_at_the_same_place_also_past_its_wrap(shape, levels):
    """Level (0, 0) and a coarser level, also one coarser along one axis only, sampled at the
    same plane coordinates over several periods of the texture (a quad is much longer than
    one texture tile): the values agree up to the attenuation of the halvings. With odd-sized
    levels the coarse levels would wrap with another period and show another part of it."""
    rip = _ripmap(_smooth_texture(*shape))
    texel_m, offset = 0.01, np.array([1234.5, 987.25])
    rng = np.random.default_rng(0)
    s1 = rng.uniform(0, 30.0, 4000).astype(np.float32)  # 30 m: several periods of every texture
    s2 = rng.uniform(0, 15.0, 4000).astype(np.float32)
    fine = _sample_level(rip, 0, 0, s1, s2, texel_m, offset, cv2)
    coarse = _sample_level(rip, *levels, s1, s2, texel_m, offset, cv2)
    # halvings attenuate the pattern by a few per cent: compare after the best gain about the mean
    f, c = fine - 120.0, coarse - 120.0
    gain = (f @ c) / (f @ f)
    assert 0.9 < gain <= 1.0
    assert np.percentile(np.abs(c - gain * f), 99) < 1.5  # grey levels, of a 120 +- 60 pattern


def test_sampling_is_continuous_across_a_level_change_along_either_axis():
    """Just below and just above an integer level (along s1, along s2) the values agree (a
    surface whose distance or slant crosses a level boundary does not pop); between levels
    they are the bilinear blend of the four levels around."""
    rip = _ripmap(_smooth_texture(512, 512) + np.float32(30) * np.random.default_rng(1).standard_normal(
        (512, 512)).astype(np.float32))
    rng = np.random.default_rng(2)
    s1 = rng.uniform(0, 5.0, 2000).astype(np.float32)
    s2 = rng.uniform(0, 5.0, 2000).astype(np.float32)
    offset = np.array([10.0, 20.0])

    def sample(l1, l2):
        return _sample_anisotropic(rip, s1, s2, np.full(s1.size, l1, np.float32), np.full(s1.size, l2, np.float32),
                                   0.01, offset, cv2)

    for level in range(1, _MIP_LEVELS - 1):
        assert np.max(np.abs(sample(level - 1e-4, 1.5) - sample(level + 1e-4, 1.5))) < 0.05
        assert np.max(np.abs(sample(0.5, level - 1e-4) - sample(0.5, level + 1e-4))) < 0.05
    corners = {(a, b): _sample_level(rip, 2 + a, 3 + b, s1, s2, 0.01, offset, cv2) for a in (0, 1) for b in (0, 1)}
    expected = (0.75 * 0.5 * corners[0, 0] + 0.25 * 0.5 * corners[1, 0]
                + 0.75 * 0.5 * corners[0, 1] + 0.25 * 0.5 * corners[1, 1])
    np.testing.assert_allclose(sample(2.25, 3.5), expected, atol=1e-3)
    mixed = _sample_anisotropic(rip, s1, s2, np.where(s1 < 2.5, 0.0, 4.0).astype(np.float32),
                                np.full(s1.size, 1.0, np.float32), 0.01, offset, cv2)  # two level pairs at once
    np.testing.assert_allclose(mixed, np.where(s1 < 2.5, sample(0.0, 1.0), sample(4.0, 1.0)), atol=1e-4)


def test_a_slanted_surface_keeps_its_detail_across_the_slant():
    """Stripes of 8 texels across s2, sampled with a footprint of 16 texels along s1 and 1 along
    s2 (a façade far ahead: stretched along the street): the stripes keep their contrast; with
    the footprint's 16 texels along s2 instead they are filtered away."""
    y = np.arange(512, dtype=np.float32)[:, None]
    rip = _ripmap(np.broadcast_to(120 + 60 * np.sin(2 * np.pi * y / 8.0), (512, 512)).astype(np.float32))
    rng = np.random.default_rng(4)
    s1 = rng.uniform(0, 5.0, 4000).astype(np.float32)
    s2 = rng.uniform(0, 5.0, 4000).astype(np.float32)
    along = _sample_anisotropic(rip, s1, s2, np.full(s1.size, 4.0, np.float32), np.zeros(s1.size, np.float32),
                                0.01, np.zeros(2), cv2)
    across = _sample_anisotropic(rip, s1, s2, np.zeros(s1.size, np.float32), np.full(s1.size, 4.0, np.float32),
                                 0.01, np.zeros(2), cv2)
    assert np.std(along) > 0.8 * 60 / np.sqrt(2)  # bilinear sampling of an 8-texel period keeps most of it
    assert np.std(across) < 0.05 * 60
