"""dualres's normals for the pixels no light reached (``unlit``): only regions the lit object encloses
and that are small beside it are filled, the harmonic continuation reproduces a plane exactly, and the
solver marks what it filled."""

from __future__ import annotations

import numpy as np

from pstoolkit_dualres.unlit import MAX_UNLIT_SHARE, fill_unlit, harmonic_fill, unlit_pixels


def _disc(size: int, radius: float) -> np.ndarray:
    y, x = np.mgrid[0:size, 0:size] - (size - 1) / 2
    return np.hypot(x, y) <= radius


def test_only_small_enclosed_dark_regions_count() -> None:
    lit = _disc(64, 28)
    hole = _disc(64, 4)
    lit &= ~hole
    found = unlit_pixels(lit)
    # the background outside the disc touches the border: not enclosed
    assert np.array_equal(found, hole)
    # a dark region larger than MAX_UNLIT_SHARE of the lit pixels is taken for background seen through
    big = _disc(64, 16)
    assert np.count_nonzero(big) > MAX_UNLIT_SHARE * np.count_nonzero(_disc(64, 28) & ~big)
    assert not unlit_pixels(_disc(64, 28) & ~big).any()


def test_the_harmonic_fill_continues_a_plane_exactly() -> None:
    y, x = np.mgrid[0:32, 0:32].astype(np.float64)
    values = np.stack([0.3 * x - 0.1 * y + 2.0, 0.05 * y], axis=-1)
    region = np.zeros((32, 32), dtype=bool)
    region[10:20, 12:25] = True
    damaged = values.copy()
    damaged[region] = 7.0
    np.testing.assert_allclose(harmonic_fill(damaged, region), values, atol=1e-9)


def test_a_tilted_plane_keeps_its_normal_through_a_dark_pocket() -> None:
    normal = np.broadcast_to(np.array([0.3, -0.2, 0.0]) + np.array([0.0, 0.0, 1.0]), (48, 48, 3)).copy()
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    lit = _disc(48, 20)
    unlit = _disc(48, 5)
    lit &= ~unlit
    damaged = normal.copy()
    damaged[unlit] = 0.0
    filled = fill_unlit(damaged.astype(np.float32), lit, unlit)
    cosine = np.sum(filled[unlit] * normal[unlit], axis=-1)
    # float32 normals: arccos near 1 resolves ~0.01°
    assert np.degrees(np.arccos(np.clip(cosine.min(), -1.0, 1.0))) < 0.05
    assert np.array_equal(filled[~unlit], damaged[~unlit].astype(np.float32))
