"""What a block of the ring-light engine gives back: its events sorted by time (``gather``) and, at
a window's end, the exposure images of that window's sums (``window_exposures``)."""

from __future__ import annotations

import numba
import numpy as np

from pstoolkit.optics.lights import US_PER_S
from pstoolkit.sim.ring_kernels.inputs import ShadedScene
from pstoolkit.sim.ring_kernels.tuning import GATHER_RUNS


@numba.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def gather(out_t: np.ndarray, out_p: np.ndarray, count: np.ndarray, width: int, t_first: int, t_last: int,
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """The events of a block, at whole µs in [``t_first``, ``t_last``], sorted by (µs, pixel): a
    counting sort on the µs, in parallel over ``GATHER_RUNS`` runs of pixels. Slots are laid out µs
    by µs and, within one, run by run; each run visits its pixels in order, each pixel's events in
    time order, so ties keep pixel order and, within a pixel, emission order."""
    pixels = count.shape[0]
    total = 0
    for p in range(pixels):
        total += count[p]
    x = np.empty(total, np.uint16)
    y = np.empty(total, np.uint16)
    t_out = np.empty(total, np.int64)
    p_out = np.empty(total, np.int8)
    span = t_last - t_first + 1
    run_pixels = (pixels + GATHER_RUNS - 1) // GATHER_RUNS
    slots = np.zeros((GATHER_RUNS, span), np.int64)
    for run in numba.prange(GATHER_RUNS):
        mine = slots[run]
        for p in range(run * run_pixels, min((run + 1) * run_pixels, pixels)):
            for i in range(count[p]):
                mine[out_t[p, i] - t_first] += 1
    at = 0
    for k in range(span):
        for run in range(GATHER_RUNS):
            n = slots[run, k]
            slots[run, k] = at
            at += n
    for run in numba.prange(GATHER_RUNS):
        mine = slots[run]
        for p in range(run * run_pixels, min((run + 1) * run_pixels, pixels)):
            column, row = p % width, p // width
            for i in range(count[p]):
                t = out_t[p, i]
                j = mine[t - t_first]
                mine[t - t_first] += 1
                x[j] = column
                y[j] = row
                t_out[j] = t
                p_out[j] = out_p[p, i]
    return x, y, t_out, p_out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def exposure_images(
    sums: np.ndarray, albedo: np.ndarray, f0: np.ndarray, e_per_us: np.ndarray, index: np.ndarray, out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Into ``out`` (2, H·W, 3), zero outside the masked pixels ``index``: albedo·e·∫ V·[n·l]₊ dt, then that
    plus F0·e·∫ V·[n·l]₊·ratio dt (``sums`` (P, 2), dt in µs; ``e_per_us`` the RGB intensity per µs)."""
    for i in range(index.size):
        f = index[i]
        for c in range(3):
            diffuse = albedo[i, c] * sums[i, 0] * e_per_us[c]
            out[0, f, c] = diffuse
            out[1, f, c] = diffuse + f0[i, c] * sums[i, 1] * e_per_us[c]


def window_exposures(scene: ShadedScene, sums: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The (H, W, 3) float64 radiant exposures (dt in seconds) of a window from its ``pstoolkit.sim.ring_engine.Block.window_sums``:
    the diffuse part alone, and with the GGX specular part (as the renderer of ``scene`` shades them)."""
    rgb = scene.rgb
    e_per_us = scene.intensity / US_PER_S
    out = np.zeros((2, scene.height * scene.width, 3))
    exposure_images(sums, rgb["albedo"].cpu().numpy(), rgb["f0"].cpu().numpy(), e_per_us, scene.index, out)
    diffuse, gloss = out.reshape(2, scene.height, scene.width, 3)
    return diffuse, gloss
