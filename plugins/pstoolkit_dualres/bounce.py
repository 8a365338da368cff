"""The one-bounce irradiance B/γ of a surface (``interreflection``'s module docstring) on a coarse grid
of cells: ``Cells`` pools the surface and its direct light onto at most ``WORK_SIDE`` cells a side (the
bounce is smooth at the scale of a pixel), the compiled ``_bounce`` sums each cell's neighbours within
``RADIUS_CELLS`` cells that it sees above the height field, and ``Bounce`` reads the result back at any
masked pixel and phase. ``bounce_device`` does all but the pooling onto the cells on a torch device.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from numba import prange

# Cells per side of the grid the bounce is summed on: the kernel's cost grows with the cells times
# the neighbours.
WORK_SIDE = 96
# Neighbours within this many cells contribute (a concavity narrower than a third of the frame).
RADIUS_CELLS = 32
# Smallest n_z taken for a patch's area (at most 1/MIN_NZ cells of surface per cell).
MIN_NZ = 0.1


@numba.njit(cache=True, parallel=True, nogil=True)
def _bounce(point: np.ndarray, normal: np.ndarray, albedo: np.ndarray, direct: np.ndarray, inside: np.ndarray,
            height: np.ndarray, radius: int, out: np.ndarray) -> None:
    """``out`` (Hc, Wc, T, 3) += the one-bounce sum of the module docstring (γ = 1) at every cell
    inside; ``point``, ``normal`` (Hc, Wc, 3) in cell units, ``albedo`` (Hc, Wc, 3), ``direct``
    (Hc, Wc, T), ``inside`` (Hc, Wc) bool, ``height`` (Hc, Wc) cell units."""
    hc, wc = inside.shape
    t_count = direct.shape[2]
    for v in prange(hc):
        for u in range(wc):
            if not inside[v, u]:
                continue
            px, py, pz = point[v, u, 0], point[v, u, 1], point[v, u, 2]
            nx, ny, nz = normal[v, u, 0], normal[v, u, 1], normal[v, u, 2]
            for dv in range(-radius, radius + 1):
                vy = v + dv
                if vy < 0 or vy >= hc:
                    continue
                for du in range(-radius, radius + 1):
                    uy = u + du
                    if uy < 0 or uy >= wc or (du == 0 and dv == 0) or du * du + dv * dv > radius * radius:
                        continue
                    if not inside[vy, uy]:
                        continue
                    dx, dy, dz = point[vy, uy, 0] - px, point[vy, uy, 1] - py, point[vy, uy, 2] - pz
                    r2 = dx * dx + dy * dy + dz * dz
                    r = math.sqrt(r2)
                    cos_x = (nx * dx + ny * dy + nz * dz) / r
                    cos_y = -(normal[vy, uy, 0] * dx + normal[vy, uy, 1] * dy + normal[vy, uy, 2] * dz) / r
                    if cos_x <= 0.0 or cos_y <= 0.0:
                        continue
                    # the segment between the two patches must pass above the height field
                    steps = max(abs(du), abs(dv))
                    blocked = False
                    for s in range(1, steps):
                        f = s / steps
                        su = int(round(u + f * du))
                        sv = int(round(v + f * dv))
                        if inside[sv, su] and height[sv, su] > pz + f * dz + 0.5:
                            blocked = True
                            break
                    if blocked:
                        continue
                    k = cos_x * cos_y / (math.pi * r2) / max(normal[vy, uy, 2], MIN_NZ)
                    for t in range(t_count):
                        d = direct[vy, uy, t]
                        if d > 0.0:
                            for c in range(3):
                                out[v, u, t, c] += k * albedo[vy, uy, c] * d


def _pool(values: np.ndarray, weight: np.ndarray, stride: int, shape: tuple[int, int]) -> np.ndarray:
    """Weighted mean of ``values`` (H, W, ...) over stride×stride blocks into ``shape`` cells."""
    h, w = weight.shape
    hc, wc = shape
    pad_h, pad_w = hc * stride - h, wc * stride - w
    vals = np.pad(values * weight.reshape(h, w, *([1] * (values.ndim - 2))),
                  [(0, pad_h), (0, pad_w)] + [(0, 0)] * (values.ndim - 2))
    wts = np.pad(weight, [(0, pad_h), (0, pad_w)])
    vals = vals.reshape(hc, stride, wc, stride, *values.shape[2:]).sum(axis=(1, 3))
    wts = wts.reshape(hc, stride, wc, stride).sum(axis=(1, 3))
    return vals / np.maximum(wts, 1e-12).reshape(hc, wc, *([1] * (values.ndim - 2)))


@dataclass
class Bounce:
    """B/γ of the module docstring on the cells it was summed on: ``value`` (T, C, 3) at the phases
    ``phase_us`` (T,) (µs since the phase origin, bin centres of one period ``period_us``), and
    ``cell`` (P,) the cell of each masked frame pixel (the bounce is smooth at the scale of a cell)."""

    value: np.ndarray
    cell: np.ndarray
    phase_us: np.ndarray
    period_us: float

    def _bracket(self, phase_us: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = len(self.phase_us)
        pos = np.mod(np.asarray(phase_us, dtype=np.float64) / self.period_us * t - 0.5, t)
        lo = np.floor(pos).astype(np.int64)
        return lo, (lo + 1) % t, pos - lo

    def at(self, phase_us: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """(N, 3) at the pixels ``rows`` (N,) (positions among the P) and phases ``phase_us`` (N,),
        linear in phase, cyclic."""
        lo, hi, frac = self._bracket(phase_us)
        cell = self.cell[rows]
        return self.value[lo, cell] * (1.0 - frac[:, None]) + self.value[hi, cell] * frac[:, None]

    def everywhere(self, phase_us: float) -> np.ndarray:
        """(P, 3) at every masked pixel at one phase."""
        lo, hi, frac = self._bracket(np.array([phase_us]))
        return (self.value[lo[0]] * (1.0 - frac[0]) + self.value[hi[0]] * frac[0])[self.cell]


@dataclass(frozen=True)
class Cells:
    """The grid the bounce is summed on, of a (H, W) bool ``mask``: ``stride`` frame pixels a cell
    side (at most ``WORK_SIDE`` cells a side), ``shape`` (Hc, Wc), ``cell`` (P,) the cell of each
    masked frame pixel (flat order)."""

    mask: np.ndarray
    stride: int
    shape: tuple[int, int]
    cell: np.ndarray

    @classmethod
    def of(cls, mask: np.ndarray) -> Cells:
        mask = np.asarray(mask, dtype=bool)
        h, w = mask.shape
        stride = max(1, math.ceil(max(h, w) / WORK_SIDE))
        shape = (math.ceil(h / stride), math.ceil(w / stride))
        pv, pu = np.divmod(np.flatnonzero(mask), w)
        return cls(mask, stride, shape, (pv // stride) * shape[1] + pu // stride)

    def pool(self, values: np.ndarray) -> np.ndarray:
        """(Hc, Wc, ...) the mean of ``values`` (H, W, ...) over each cell's masked pixels."""
        return _pool(values, self.mask.astype(np.float64), self.stride, self.shape)

    def direct(self, normal: np.ndarray, lit: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """(Hc, Wc, T) each cell's mean direct irradiance per unit light, [n·l]₊ where lit (``one_bounce``'s
        ``normal``, ``lit`` and ``directions``), a phase at a time: no (T, H·W) array at a large capture."""
        h, w = self.mask.shape
        pixels = np.flatnonzero(self.mask)
        out = np.zeros((*self.shape, len(directions)))
        plane = np.zeros(h * w)
        facing = normal.reshape(-1, 3)[pixels]
        for t in range(len(directions)):
            plane[pixels] = np.clip(facing @ directions[t], 0.0, None) * lit[t]
            out[..., t] = self.pool(plane.reshape(h, w))
        return out

    def surface(self, normal: np.ndarray, albedo: np.ndarray, height: np.ndarray) -> CellSurface:
        """The cells' surface of the frame pixels' ``normal`` (H, W, 3), ``albedo`` (H, W, 3) and ``height``
        (H, W, frame pixels), which ``_bounce`` sums over."""
        cell_normal = self.pool(normal)
        cell_normal /= np.maximum(np.linalg.norm(cell_normal, axis=-1, keepdims=True), 1e-12)
        cell_height = self.pool(height) / self.stride
        v, u = np.mgrid[0 : self.shape[0], 0 : self.shape[1]].astype(np.float64)
        inside = _pool(self.mask.astype(np.float64), np.ones(self.mask.shape), self.stride, self.shape) >= 0.5
        return CellSurface(np.stack([u, -v, cell_height], axis=-1), cell_normal, self.pool(albedo), inside, cell_height)

    def bounce(self, normal: np.ndarray, albedo: np.ndarray, height: np.ndarray, direct: np.ndarray, phase_us: np.ndarray,
               period_us: float) -> Bounce:
        """``one_bounce`` of the cells' mean direct irradiance ``direct`` (Hc, Wc, T) (``direct``)."""
        surface = self.surface(normal, albedo, height)
        t_count = direct.shape[-1]
        out = np.zeros((*self.shape, t_count, 3))
        _bounce(surface.point, surface.normal, surface.albedo, np.ascontiguousarray(direct, dtype=np.float64), surface.inside,
                surface.height, RADIUS_CELLS, out)
        value = np.ascontiguousarray(np.moveaxis(out.reshape(-1, t_count, 3), 1, 0)).astype(np.float32)
        return Bounce(value, self.cell, np.asarray(phase_us, dtype=np.float64), float(period_us))


@dataclass(frozen=True)
class CellSurface:
    """The surface on the cells (``Cells.surface``), each (Hc, Wc, ...) float64 in cell units: ``point``
    (u, −v, height) of each cell's centre, unit ``normal``, ``albedo`` (3 channels), ``inside`` bool
    (at least half its pixels on the object), ``height``."""

    point: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
    inside: np.ndarray
    height: np.ndarray


def one_bounce(normal: np.ndarray, albedo: np.ndarray, height: np.ndarray, mask: np.ndarray, lit: np.ndarray,
               directions: np.ndarray, phase_us: np.ndarray, period_us: float) -> Bounce:
    """The one-bounce irradiance B/γ (module docstring) of a surface.

    Parameters
    ----------
    normal
        (H, W, 3) unit normals (camera frame: x right, y up, z towards the camera).
    albedo
        (H, W, 3) diffuse albedo, relative units.
    height
        (H, W) height towards the camera, frame pixels (``pstoolkit.surface.integrate_normals``).
    mask
        (H, W) bool, the pixels on the object.
    lit
        (T, P) bool, whether each masked pixel (flat order) is out of cast shadow at each phase.
    directions
        (T, 3) unit light directions at the phases ``phase_us`` (T,), grid bin centres of one period.
    period_us
        The light period, µs.

    Returns
    -------
    Bounce
        On a grid of at most ``WORK_SIDE`` cells a side (``Cells``), with the cell of each masked pixel.
    """
    cells = Cells.of(mask)
    return cells.bounce(normal, albedo, height, cells.direct(normal, lit, directions), phase_us, period_us)
