"""Cast shadows of a height map towards a directional light: the compiled sweep that marches the
depth map towards the light (``shadow_margin``), soft visibility from its margins, and the cache of
sweeps a renderer reuses between nearby light directions (``ShadowCaster``)."""

from __future__ import annotations

from collections.abc import Iterator

import numba
import numpy as np

# An occluder must rise this far (pixels) above a shadow ray to count: it keeps interpolated height
# samples of a smooth surface from shadowing the surface itself.
SHADOW_BIAS_PX = 0.1


# Height (pixels) over which a shadow edge fades: a soft edge keeps V continuous in time, so frame
# integrals converge smoothly and events see a ramp instead of a jump.
PENUMBRA_PX = 0.25


# Columns a sweep gathers before writing them out (see ``_sweep``): 16 float32 fill a cache line
# (``docs/simulator-tuning.md``).
_TILE = 16


_NO_OCCLUDER = -1e9


_LOW_MARGIN = -1e3


@numba.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _sweep(
    occluder_t: np.ndarray, height_t: np.ndarray, inside_t: np.ndarray, k: np.ndarray, rise: np.ndarray,
    lights: np.ndarray, transpose: bool, flip: bool, column_major: bool, openness: tuple[float, float] | None,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Shadow margins for lights towards increasing column index of the oriented maps: how far
    (pixels of height) the highest occluder rises above each pixel's ray towards the light (negative:
    lit), written to ``out[lights[g]]`` (T, H, W) of the original maps, or — given ``openness``
    (bias, penumbra in pixels) — their unclipped V (``_openness``, in float32). ``occluder_t``, ``height_t``
    and ``inside_t`` (the mask) are the oriented maps transposed to (C, R), so a column is contiguous;
    the oriented maps are the originals transposed (``transpose``), then with their columns reversed
    (``flip``). Pixels outside the mask get ``_LOW_MARGIN``. With ``column_major`` the maps of an
    untransposed sweep are stored column by column: ``out[lights[g]]`` holds the (W, H) transpose.

    Light g's rays go one column per step and ``k[g]`` rows per column (|k| ≤ 1), climbing ``rise[g]``
    pixels of height per step. All rays of one light are parallel, so they lie on lines
    r = j + k·c; along each line a pixel is shadowed when the running maximum of occluder − rise·c
    over the columns after it exceeds its own height − rise·c. Lines sit at whole-row offsets; a pixel
    between two lines takes the linear mix of the two lines' margins (each measured against its own
    height, and floored so that an empty line cannot outweigh an occluded one). The mix is exact on
    smooth surfaces and continuous as the light (and with it the lines) moves, so a pixel does not
    flicker when a line sweeps past it; beside a wall parallel to the light it reads as shadowed
    up to one pixel early. The columns are walked from the light's side, so the running maximum of
    the columns after the current one is at hand for its pixels before the column joins it.
    Compiled, in parallel over the lights: one pass over the pixels per light, its inner loops over
    contiguous rows and lines (SIMD).
    """
    cols, rows = occluder_t.shape
    span = int(np.ceil(np.max(np.abs(k)) * (cols - 1))) if k.size else 0
    lines = rows + span + 2
    no_occluder = np.float32(_NO_OCCLUDER)
    low = np.float32(_LOW_MARGIN)
    one = np.float32(1.0)
    # V in float32, as stored: to within an ulp of ``_openness``, and faster sweeps than in float64
    bias, fade = (np.float32(openness[0]), np.float32(1.0 / openness[1])) if openness is not None else (one, one)
    # the oriented maps' columns are rows of ``target``: those of transposed maps, and of all with ``column_major``
    whole_rows = transpose or column_major
    for g in numba.prange(k.size):
        target = out[lights[g]] if not column_major or transpose else out[lights[g]].reshape((cols, rows))
        running = np.full(lines, no_occluder, dtype=np.float32)
        # the columns gather in a tile, written out every ``_TILE`` columns: as whole rows in ascending
        # order (one by one against the sweep, descending, they took up to twice as long), or else a
        # row of ``_TILE`` values (a cache line) at a time; the tile's rows are padded so they do not
        # all fall in the same cache sets
        tile = np.empty((_TILE, rows + 16), dtype=np.float32)
        first_base = np.floor(min(0.0, -k[g] * (cols - 1))) - 1.0
        for c in range(cols - 1, -1, -1):
            # line j crosses column c at row base + j
            base = first_base + k[g] * c
            ramp = np.float32(rise[g] * c)
            # pixel row r lies at (fractional) line r − base
            q0 = int(np.floor(-base))
            w = np.float32(-base - q0)
            lower_line, upper_line = running[q0: q0 + rows], running[q0 + 1: q0 + 1 + rows]
            own_height, inside = height_t[c], inside_t[c]
            column_out = tile[c % _TILE, :rows]
            for r in range(rows):
                own = own_height[r] - ramp
                margin = max(lower_line[r] - own, low) * (one - w) + max(upper_line[r] - own, low) * w
                column_out[r] = margin if inside[r] else low
            if openness is not None:
                for r in range(rows):
                    column_out[r] = one - (column_out[r] - bias) * fade
            if c % _TILE == 0:
                # the tile holds columns c … c + filled − 1 of the oriented maps
                filled = min(_TILE, cols - c)
                if whole_rows:
                    for i in range(filled):
                        j = filled - 1 - i if flip else i
                        target[cols - 1 - c - j if flip else c + j, :] = tile[j, :rows]
                else:
                    for r in range(rows):
                        line = target[r]
                        if flip:
                            for i in range(filled):
                                line[cols - 1 - c - i] = tile[i, r]
                        else:
                            for i in range(filled):
                                line[c + i] = tile[i, r]
            i0 = int(np.floor(base))
            f = np.float32(base - i0)
            occluder = occluder_t[c]
            # lines whose two rows lie in the map, then the two with one row outside (it counts as the
            # sentinel); a line with none stays at the sentinel, which its margins clip to ``low`` anyway
            inner_lo, inner_hi = max(0, -i0), min(lines, rows - 1 - i0)
            if inner_lo < inner_hi:
                a, b = occluder[i0 + inner_lo: i0 + inner_hi], occluder[i0 + inner_lo + 1: i0 + inner_hi + 1]
                line = running[inner_lo:inner_hi]
                for j in range(inner_hi - inner_lo):
                    # (1 − f)·a + f·b, not a + f·(b − a): the latter loses a real height against the sentinel
                    line[j] = max(line[j], a[j] * (one - f) + b[j] * f - ramp)
            for j in (inner_lo - 1, inner_hi):
                if 0 <= j < lines:
                    row = i0 + j
                    a_edge = occluder[row] if 0 <= row < rows else no_occluder
                    b_edge = occluder[row + 1] if 0 <= row + 1 < rows else no_occluder
                    running[j] = max(running[j], a_edge * (one - f) + b_edge * f - ramp)


class ShadowCaster:
    """Cast-shadow margins of one height map (``shadow_margin``), keeping what does not depend on the
    light: the maps in the four sweep orientations, made the first time a light needs each."""

    def __init__(self, depth: np.ndarray, mask: np.ndarray) -> None:
        depth = np.asarray(depth, dtype=np.float64)
        self.mask = np.asarray(mask, dtype=bool)
        self.occluder = np.where(self.mask, depth, _NO_OCCLUDER).astype(np.float32)
        self.height = depth.astype(np.float32)
        self._oriented: dict[tuple[bool, bool], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def _maps(self, transpose: bool, flip: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if (transpose, flip) not in self._oriented:
            oriented = [a.T if transpose else a for a in (self.occluder, self.height, self.mask)]
            if flip:
                oriented = [a[:, ::-1] for a in oriented]
            self._oriented[transpose, flip] = tuple(np.ascontiguousarray(a.T) for a in oriented)  # type: ignore[assignment]
        return self._oriented[transpose, flip]

    def margins(
        self, directions: np.ndarray, out: np.ndarray | None = None, *, openness: bool = False,
        column_major: bool = False,
    ) -> np.ndarray:
        """``shadow_margin`` for ``directions`` (T, 3), written into ``out`` ((T, H, W) float32) when
        given: a caller sweeping block after block reuses one buffer. With ``openness`` the unclipped V
        of them (``_openness``), made as they are written. With ``column_major`` the lights of
        ``column_major_lights`` are stored column-major, their (H, W) slot holding the (W, H)
        transpose: their sweeps walk the columns, and storing those whole took half the time of
        scattering them into rows."""
        l = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        t = l.shape[0]
        h, w = self.height.shape
        out = np.empty((t, h, w), dtype=np.float32) if out is None else out
        affine = (SHADOW_BIAS_PX, PENUMBRA_PX) if openness else None
        side = _sweep_axes(l)[2]
        out[~side] = _openness(np.float32(_LOW_MARGIN)) if openness else _LOW_MARGIN
        for transpose, flip, index, k, rise in sweep_groups(l):
            _sweep(*self._maps(transpose, flip), k, rise, index, transpose, flip, column_major, affine, out)
        return out

    @staticmethod
    def column_major_lights(directions: np.ndarray) -> np.ndarray:
        """(T,) bool: the lights ``margins(column_major=True)`` stores column-major (those whose rays
        run more along the image's rows than its columns)."""
        _, _, side, along_u = _sweep_axes(np.asarray(directions, dtype=np.float64).reshape(-1, 3))
        return side & along_u


def sweep_groups(l: np.ndarray) -> Iterator[tuple[bool, bool, np.ndarray, np.ndarray, np.ndarray]]:
    """The lights of unit directions ``l`` (T, 3) that cast shadows, by the orientation their sweep walks
    the maps in (``_sweep``): (transpose, flip, index (G,) of the lights, k (G,) rows per column of their
    rays, rise (G,) pixels of height their rays climb per column), for each orientation with any."""
    du, dv, side, along_u = _sweep_axes(l)
    tan_e = np.where(side, l[:, 2] / np.where(side, np.hypot(du, dv), 1.0), 0.0)
    for transpose in (False, True):
        for flip in (False, True):
            main, other = (dv, du) if transpose else (du, dv)
            index = np.flatnonzero(side & (along_u != transpose) & ((main < 0) == flip))
            if index.size == 0:
                continue
            k = other[index] / np.abs(main[index])
            yield transpose, flip, index, k, tan_e[index] * np.sqrt(1.0 + k * k)


def _sweep_axes(l: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For unit directions ``l`` (T, 3): their image components du, dv (v points down), whether they
    leave the vertical (lights straight overhead cast no shadows) and whether they run more along u."""
    du, dv = l[:, 0], -l[:, 1]
    side = np.hypot(du, dv) > 1e-9
    return du, dv, side, np.abs(du) >= np.abs(dv)


def shadow_margin(
    depth: np.ndarray,
    mask: np.ndarray,
    directions: np.ndarray,
) -> np.ndarray:
    """How far (pixels of height) occluders rise above each pixel's ray towards the light, (T, H, W)
    float32, for directional lights ``directions`` (T, 3) (unit, camera frame) coming from infinity;
    negative where the ray is clear.

    ``depth`` is the height towards the camera in pixels; only pixels inside ``mask`` occlude, and
    pixels outside it get a large negative margin. Work per light is linear in the pixel count (a
    running maximum along the parallel rays, see ``_sweep``, compiled and in parallel over the
    lights); memory is the output. Lights straight overhead cast no shadows. ``ShadowCaster`` keeps
    the light-independent part for many calls on one map.
    """
    return ShadowCaster(depth, mask).margins(directions)


def visibility_from_margin(margin: np.ndarray, bias_px: float = SHADOW_BIAS_PX, penumbra_px: float = PENUMBRA_PX) -> np.ndarray:
    """V in [0, 1] from ``shadow_margin``: 1 while occluders stay below ``bias_px`` above the ray, then
    a linear fade to 0 over ``penumbra_px`` (the soft edge of a light of finite size)."""
    return np.clip(_openness(margin, bias_px, penumbra_px), 0.0, 1.0)


def _openness(margin: np.ndarray, bias_px: float = SHADOW_BIAS_PX, penumbra_px: float = PENUMBRA_PX) -> np.ndarray:
    """V before clipping to [0, 1]: affine in the margin, so it interpolates like the margin."""
    return 1.0 - (margin - bias_px) / penumbra_px


def cast_shadow_mask(depth: np.ndarray, mask: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(T, H, W) bool: pixels more than half in a cast shadow (V < 0.5, see ``visibility_from_margin``)."""
    return shadow_margin(depth, mask, directions) > SHADOW_BIAS_PX + 0.5 * PENUMBRA_PX
