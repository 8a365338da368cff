"""Forward rendering of a scene under a moving light: I(x, t) = e(t)·f_r·V·[l(t)·n]₊ with an
orthographic view along (0, 0, 1), attached shadows from the clamp and cast shadows V from marching
the depth map towards the light.

    renderer = Renderer(maps, light, brdf)
    rgb = renderer.image(t_us)                  # (T, H, W, 3) linear irradiance at frame resolution
    grey = renderer.event_grey(t_us, 0.5)       # (T, H/2, W/2) grey, area-averaged to the event grid
    exposure = integrate(renderer, 0, 11111)    # (H, W, 3) ∫ I dt over a window, dt in seconds

    fast = Renderer(maps, light, brdf, shadow_step_us=65.0)   # cast shadows on a time grid
    grey = fast.event_pixels(t_us, pixel, 0.5)  # (M,) single event pixels at single times

The simulator's speed comes from ``shadow_step_us`` (one shadow sweep serves every render near it),
the closed-form shading of the built-in BRDFs and ``event_pixels`` (see ``Renderer``).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Sequence

import numpy as np
import torch

from pstoolkit.errors import UserError
from pstoolkit.grid import event_shape, footprints
from pstoolkit.optics.brdf import BRDF, GGX, HALF_EPS, MIN_ROUGHNESS, Lambertian
from pstoolkit.optics.grey import GREY_WEIGHTS
from pstoolkit.optics.lights import LightModel
from pstoolkit.optics.shadow_sweep import (
    ShadowCaster,
    visibility_from_margin,
)
from pstoolkit.sim.scenes import SceneMaps

# Work is chunked so one (T, P, 3) float tensor holds about this many values.
CHUNK_VALUES = 1 << 21
# Shadow margins kept for reuse on the shadow grid (``Renderer(shadow_step_us=…)``), in values.
MARGIN_CACHE_VALUES = 1 << 22
















def _event_footprints(height: int, width: int, event_scale: float, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which masked frame pixels each event pixel averages: (E, K) positions into the masked pixels
    ``index`` (0 where unused) and (E, K) area weights (0 for unused slots and unmasked pixels)."""
    frame, weight = footprints(event_shape(height, width, event_scale), (height, width), event_scale)
    position = np.full(height * width, -1, dtype=np.int64)
    position[index] = np.arange(index.size)
    masked = position[frame]
    return np.maximum(masked, 0), np.where(masked >= 0, weight, 0.0)


class Renderer:
    """Renders one scene under one light model and BRDF at any times, on ``device``.

    The masked pixels' maps are held as tensors once; ``irradiance`` shades them for a batch of
    times. Near lights (``light.near``) are evaluated at each pixel's surface point, which the model
    provides through ``light.pixel_points(height, width, depth_mm)`` (depth in mm = depth in pixels ×
    the model's ``pixel_pitch_mm``); their cast shadows march towards the light direction seen from the
    middle of the mask, as if the light were far.

    Speed (the simulator renders thousands of times per light turn):

    - A scene without self-shadowing (``SceneMaps.self_shadowing``, a convex surface) has no cast
      shadows to compute: ``shadows`` is then False whatever is asked.
    - ``shadow_step_us`` (optional) puts the cast-shadow sweeps on a time grid of that step: the
      margin of ``shadow_margin`` (continuous in the light direction by design) is computed at the
      grid times, kept in a bounded cache, and interpolated linearly in between. One sweep then serves
      every render, single pixels included (``event_pixels``); without it each time is swept exactly.
    - Directional lights with the ``ggx`` or ``lambertian`` BRDF are shaded in closed form from
      precomputed per-pixel constants (n·v's G1 term, α², |n|²) with the dot products as matrix
      products, as ``e_c · n·l · (albedo_c + ratio · f0_c)``; grey and exposure sums are then matrix
      products with the light's RGB intensity, never (T, P, 3) temporaries. The result is
      ``brdf.shade``'s (in float64; ``tests/sim/test_render_fast.py`` compares them).
    """

    def __init__(
        self,
        maps: SceneMaps,
        light: LightModel,
        brdf: BRDF,
        *,
        shadows: bool = True,
        device: str | torch.device = "cpu",
        dtype: torch.dtype = torch.float32,
        shadow_step_us: float | None = None,
    ) -> None:
        self.maps = maps
        self.light = light
        self.brdf = brdf
        # a surface that cannot shadow itself needs no sweeps: its V is 1 wherever it faces the light
        self.shadows = shadows and maps.self_shadowing
        self.device = torch.device(device)
        self.dtype = dtype
        self.shadow_step_us = shadow_step_us
        self.index = np.flatnonzero(maps.mask.ravel())
        flat = {
            "normal": maps.normal.reshape(-1, 3),
            "albedo": maps.albedo.reshape(-1, 3),
            "f0": maps.f0.reshape(-1, 3),
            "roughness": maps.roughness.reshape(-1, 1),
        }
        self._t = {k: self._tensor(np.take(v, self.index, axis=0)) for k, v in flat.items()}
        self._view = self._tensor(np.array([0.0, 0.0, 1.0]))
        self._points: np.ndarray | None = None
        if light.near:
            pitch = float(light.pixel_pitch_mm)  # type: ignore[attr-defined]
            points = light.pixel_points(maps.height, maps.width, maps.depth * pitch)  # type: ignore[attr-defined]
            self._points = points[self.index]
        self._margins: OrderedDict[int, np.ndarray] = OrderedDict()
        self._caster: ShadowCaster | None = None
        # sweeps of ``frame_openness``, kept so the next call does not allocate anew
        self._sweep_buffer = np.empty((0, maps.height, maps.width), dtype=np.float32)
        self._footprints: dict[float, tuple[np.ndarray, np.ndarray]] = {}
        self._constants: dict[str, torch.Tensor] | None = None
        self._rgb64: dict[str, torch.Tensor] = {}

    def _tensor(self, array: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(array), dtype=self.dtype, device=self.device)

    @property
    def pixels(self) -> int:
        return int(self.index.size)

    def _maps(self, brdf: BRDF) -> dict[str, torch.Tensor]:
        missing = [k for k in brdf.params if k not in self._t or k == "normal"]
        if missing:
            raise UserError(f"BRDF {brdf.name!r} needs map(s) {', '.join(missing)} that scenes do not provide")
        return {k: self._t[k] for k in brdf.params}

    @staticmethod
    def _shadow_directions(direction: np.ndarray) -> np.ndarray:
        """(T, 3) directions to march shadows towards: a near light's (T, P, 3) directions averaged."""
        if direction.ndim == 3:
            direction = direction.mean(axis=1)
            direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
        return direction

    def _grid_margins(self, t_us: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Unclipped V (``_openness`` of the margins) on the shadow grid around ``t_us``: a (K, P)
        table of the grid times needed, the rows of the grid times before and after each time, and
        the weight of the one after."""
        step = float(self.shadow_step_us)  # type: ignore[arg-type]
        x = np.asarray(t_us, dtype=np.float64) / step
        j0 = np.floor(x)
        after = (x - j0).astype(np.float32)
        period = self.light.period_us
        turn = round(period / step) if period else 0
        wrap = turn > 0 and abs(turn * step - period) < 1e-9 * period  # type: ignore[operator]
        key0 = j0.astype(np.int64)
        key0, key1 = (key0 % turn, (key0 + 1) % turn) if wrap else (key0, key0 + 1)
        keys, inverse = np.unique(np.concatenate((key0, key1)), return_inverse=True)
        missing = [int(k) for k in keys if int(k) not in self._margins]
        if missing:
            for key, row in zip(missing, self.grid_openness(np.array(missing))):
                self._margins[key] = row
        table = np.stack([self._margins[int(k)] for k in keys])
        for key in keys:
            self._margins.move_to_end(int(key))
        while len(self._margins) > max(2, MARGIN_CACHE_VALUES // max(1, self.pixels)):
            self._margins.popitem(last=False)
        n = len(key0)
        return table, inverse[:n], inverse[n:], after

    def grid_openness(self, keys: np.ndarray) -> np.ndarray:
        """(N, P) float32 unclipped V (``_openness`` of the margins) of the masked pixels at the shadow
        grid times ``keys`` × ``shadow_step_us``, swept anew into fresh arrays (the bounded cache of
        ``_grid_margins`` keeps its rows)."""
        keys = np.asarray(keys)
        margin = self.shadow_caster.margins(self._grid_directions(keys), openness=True)
        return margin.reshape(len(keys), -1)[:, self.index]

    def frame_openness(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``grid_openness`` of every frame pixel, (N, H·W) (those outside the mask open, V > 1),
        each row row-major (H, W) or, where the (N,) bool it comes with says so, column-major (W, H)
        (``ShadowCaster.margins(column_major=True)``, the faster sweeps). The table is a view of the
        buffer the renderer keeps for its sweeps, valid until its next call, so a caller walking time
        in blocks allocates nothing block after block."""
        keys = np.asarray(keys)
        if self._sweep_buffer.shape[0] < len(keys):
            self._sweep_buffer = np.empty((len(keys), self.maps.height, self.maps.width), dtype=np.float32)
        directions = self._grid_directions(keys)
        table = self.shadow_caster.margins(directions, self._sweep_buffer[: len(keys)], openness=True, column_major=True)
        return table.reshape(len(keys), -1), ShadowCaster.column_major_lights(directions)

    @property
    def column_major_index(self) -> np.ndarray:
        """The masked pixels' flat positions in the column-major rows of ``frame_openness`` (``index``
        is theirs in the row-major ones)."""
        return (self.index % self.maps.width) * self.maps.height + self.index // self.maps.width

    def _grid_directions(self, keys: np.ndarray) -> np.ndarray:
        direction, _ = self.light.evaluate(keys * float(self.shadow_step_us), self._points)  # type: ignore[arg-type]
        return self._shadow_directions(direction)

    @property
    def shadow_caster(self) -> ShadowCaster:
        if self._caster is None:
            self._caster = ShadowCaster(self.maps.depth, self.maps.mask)
        return self._caster

    def visibility(self, t_us: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """(T, P) float32 V in [0, 1]: how much of each masked pixel is out of cast shadow at ``t_us``."""
        if not self.shadows:
            return np.ones((len(t_us), self.pixels), dtype=np.float32)
        if self.shadow_step_us is not None:
            table, row0, row1, after = self._grid_margins(t_us)
            visible = table[row0]
            visible *= 1.0 - after[:, None]
            visible += table[row1] * after[:, None]
            return np.clip(visible, 0.0, 1.0, out=visible)
        margin = self.shadow_caster.margins(self._shadow_directions(directions))
        return visibility_from_margin(margin.reshape(len(t_us), -1)[:, self.index])

    def _pixel_visibility(self, t_us: np.ndarray, pixel: np.ndarray) -> np.ndarray:
        """(M,) V of masked pixels ``pixel`` at times ``t_us`` (M,), from the shadow grid."""
        if not self.shadows:
            return np.ones(len(t_us), dtype=np.float32)
        table, row0, row1, after = self._grid_margins(t_us)
        return np.clip(table[row0, pixel] * (1.0 - after) + table[row1, pixel] * after, 0.0, 1.0)

    def _fast(self, brdfs: Sequence[BRDF]) -> bool:
        return not self.light.near and all(type(b) in (GGX, Lambertian) for b in brdfs)

    def _closed_form(self, specular: bool, l: torch.Tensor, pixel: torch.Tensor | None = None,
                     ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``ggx`` (``specular``) or ``lambertian`` shading in closed form as
        ``nl · (albedo + ratio · f0)`` per channel: returns [n·l]₊ and the GGX specular ratio
        D·G/(4 n·l n·v) (None for Lambertian). ``l`` is (T, 3) float64
        unit directions; both results are (T, P) for all masked pixels, or (M,) for ``pixel`` (M,)
        with ``l`` (M, 3) one direction per pixel. In-place float64 arithmetic: one pass per
        operation over (T, P), no (T, P, 3) temporaries."""
        c = self._closed_form_constants()
        if pixel is None:
            nl = l @ c["nT"]
        else:
            normal = c["nT"].T[pixel]
            nl = torch.sum(normal * l, dim=-1)
        nl.clamp_(min=0.0)
        if not specular:
            return nl, None
        constant = c if pixel is None else {name: value[pixel] for name, value in c.items() if name != "nT"}
        s = l + torch.tensor([0.0, 0.0, 1.0], dtype=l.dtype, device=l.device)
        ss = torch.sum(s * s, dim=-1, keepdim=True)
        h = s / torch.sqrt(ss + HALF_EPS)
        hh, lift = ss / (ss + HALF_EPS), HALF_EPS / (ss + HALF_EPS)
        if pixel is None:
            q = h @ c["nT"]
        else:
            q = torch.sum(normal * h, dim=-1)
            hh, lift = hh[:, 0], lift[:, 0]
        # D's denominator sin² + (n·h)²α² with sin² = |n × h|² = |n|²|h|² − (n·h)² (+ the term that keeps
        # l = −v finite), as in brdf.GGX; float64 keeps the peak of a smooth surface finite.
        q.mul_(q).mul_(constant["alpha2_1"]).add_(lift).addcmul_(hh, constant["nn"])
        q.mul_(q)
        q.mul_(torch.addcmul(constant["k"], nl, constant["1_k"]))
        return nl, torch.div(constant["dv"], q, out=q)

    def closed_form_constants(self) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """Per masked pixel: normals ``nT`` (3, P), |n|² ``nn``, α² − 1 ``alpha2_1``, ``k``, 1 − k ``1_k``
        and α²·(1/(4 G1-denominator of n·v))/π ``dv``; and (P, 3) ``albedo`` and ``f0``; float64."""
        return self._closed_form_constants(), self._rgb64

    def _closed_form_constants(self) -> dict[str, torch.Tensor]:
        """Per masked pixel: normals (3, P), |n|², α² − 1, k, 1 − k and α²·(1/(4 G1-denominator of
        n·v))/π, float64 (and float64 albedo and F0 in ``_rgb64``)."""
        if self._constants is None:
            n = self._t["normal"].double()
            r = torch.clamp(self._t["roughness"][:, 0].double(), min=MIN_ROUGHNESS)
            alpha2, k = r**4, (r + 1.0) ** 2 / 8.0
            view = 1.0 / (4.0 * (torch.clamp(n[:, 2], min=0.0) * (1.0 - k) + k))
            self._constants = {
                # |n|² summed column by column: the same sums as torch.sum over the last axis, 8× faster
                "nT": n.T.contiguous(), "nn": n[:, 0] * n[:, 0] + n[:, 1] * n[:, 1] + n[:, 2] * n[:, 2],
                "alpha2_1": alpha2 - 1.0, "k": k,
                "1_k": 1.0 - k, "dv": alpha2 * view / math.pi,
            }
            self._rgb64 = {name: self._t[name].double() for name in ("albedo", "f0")}
        return self._constants

    def _light(self, t_us: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        direction, intensity = self.light.evaluate(t_us)
        return (torch.as_tensor(direction, dtype=torch.float64, device=self.device),
                torch.as_tensor(intensity, dtype=torch.float64, device=self.device))

    def _visible_tensor(self, t_us: np.ndarray, l: torch.Tensor) -> torch.Tensor:
        return torch.as_tensor(self.visibility(t_us, l.cpu().numpy()), device=self.device)

    def shade(self, t_us: np.ndarray, brdfs: Sequence[BRDF]) -> list[torch.Tensor]:
        """(T, P, 3) linear RGB irradiance of the masked pixels at times ``t_us`` (µs), one tensor per
        BRDF; the lights and cast shadows are computed once for all of them."""
        t_us = np.asarray(t_us, dtype=np.float64).reshape(-1)
        outs = [torch.empty((t_us.size, self.pixels, 3), dtype=self.dtype, device=self.device) for _ in brdfs]
        step = max(1, CHUNK_VALUES // max(1, 3 * self.pixels))
        fast = self._fast(brdfs)
        for start in range(0, t_us.size, step):
            t = t_us[start : start + step]
            direction, intensity = self.light.evaluate(t, self._points)
            visible = self._tensor(self.visibility(t, direction))[..., None]
            if fast:
                l, e = self._light(t)
                for brdf, out in zip(brdfs, outs):
                    nl, ratio = self._closed_form(type(brdf) is GGX, l)
                    rgb = self._rgb64["albedo"]
                    if ratio is not None:
                        rgb = rgb + ratio[..., None] * self._rgb64["f0"]
                    out[start : start + t.size] = (e[:, None, :] * nl[..., None] * rgb).to(self.dtype) * visible
                continue
            l = self._tensor(direction)
            e = self._tensor(intensity)
            if l.dim() == 2:
                l, e = l[:, None, :], e[:, None, :]
            for brdf, out in zip(brdfs, outs):
                shaded = brdf.shade(self._t["normal"], l, self._view, **self._maps(brdf))
                out[start : start + t.size] = e * shaded * visible
        return outs

    def shade_sum(self, t_us: np.ndarray, brdfs: Sequence[BRDF]) -> list[torch.Tensor]:
        """(P, 3) float64 Σ_t of the irradiance of the masked pixels over times ``t_us``, one per BRDF
        (``shade`` summed over time; on the closed-form path a matrix product with the light's RGB
        intensity, without (T, P, 3) tensors)."""
        return self._render(t_us, None, brdfs)[1]

    def irradiance(self, t_us: np.ndarray) -> torch.Tensor:
        """(T, P, 3) linear RGB irradiance of the masked pixels at times ``t_us`` (µs)."""
        return self.shade(t_us, [self.brdf])[0]

    def scatter(self, values: torch.Tensor) -> torch.Tensor:
        """(T, P, C) values of the masked pixels → (T, H, W, C) images, 0 outside the mask."""
        t, _, c = values.shape
        full = torch.zeros((t, self.maps.height * self.maps.width, c), dtype=values.dtype, device=values.device)
        full[:, torch.as_tensor(self.index, device=values.device)] = values
        return full.reshape(t, self.maps.height, self.maps.width, c)

    def image(self, t_us: np.ndarray) -> np.ndarray:
        """(T, H, W, 3) float32 linear RGB irradiance at frame resolution."""
        return self.scatter(self.irradiance(t_us)).cpu().numpy().astype(np.float32, copy=False)

    def footprint(self, event_scale: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Which masked frame pixels each event pixel averages: (E, K) positions into the masked pixels
        and (E, K) float64 area weights (0 for unused slots and unmasked pixels)."""
        if event_scale not in self._footprints:
            self._footprints[event_scale] = _event_footprints(self.maps.height, self.maps.width, event_scale, self.index)
        position, weight = self._footprints[event_scale]
        return torch.as_tensor(position, device=self.device), torch.as_tensor(weight, dtype=torch.float64, device=self.device)

    def _closed_form_sample(self, t: np.ndarray, grey: bool, brdfs: Sequence[BRDF],
                            ) -> tuple[torch.Tensor | None, list[torch.Tensor]]:
        """Closed-form path of ``_render`` for one chunk of times: (T, P) grey of the renderer's BRDF
        (if ``grey``) and the (P, 3) sums over ``t`` of each BRDF of ``brdfs``, from one n·l, one
        specular ratio and one V: the Lambertian sum is the GGX sum's albedo term."""
        l, e = self._light(t)
        gloss_sum = any(type(b) is GGX for b in brdfs)
        nl, ratio = self._closed_form(gloss_sum or (grey and type(self.brdf) is GGX), l)
        nl.mul_(self._visible_tensor(t, l))
        out = None
        if grey:
            e_grey = e * torch.tensor(GREY_WEIGHTS, dtype=torch.float64, device=self.device)
            out = e_grey @ self._rgb64["albedo"].T
            if type(self.brdf) is GGX and ratio is not None:
                out.addcmul_(ratio, e_grey @ self._rgb64["f0"].T)
            out.mul_(nl)
        sums = []
        if brdfs:
            diffuse = self._rgb64["albedo"] * (nl.T @ e)
            gloss = self._rgb64["f0"] * (ratio.mul_(nl).T @ e) if gloss_sum and ratio is not None else None
            sums = [diffuse + gloss if type(b) is GGX and gloss is not None else diffuse.clone() for b in brdfs]
        return out, sums

    def _render(self, t_us: np.ndarray, event_scale: float | None, brdfs: Sequence[BRDF],
                ) -> tuple[np.ndarray | None, list[torch.Tensor]]:
        """``event_grey`` at ``event_scale`` (None: skipped) and ``shade_sum`` over ``brdfs`` of the
        same times, chunked; on the closed-form path both come from one shading of each time."""
        t_us = np.asarray(t_us, dtype=np.float64).reshape(-1)
        totals = [torch.zeros((self.pixels, 3), dtype=torch.float64, device=self.device) for _ in brdfs]
        out = None
        if event_scale is not None:
            he, we = event_shape(self.maps.height, self.maps.width, event_scale)
            position, weight = self.footprint(event_scale)
            out = np.empty((t_us.size, he, we), dtype=np.float64)
        grey_w = torch.tensor(GREY_WEIGHTS, dtype=torch.float64, device=self.device)
        fast = self._fast([self.brdf, *brdfs])
        step = max(1, CHUNK_VALUES // max(1, 3 * self.pixels))
        for start in range(0, t_us.size, step):
            t = t_us[start : start + step]
            if fast:
                grey, sums = self._closed_form_sample(t, out is not None, brdfs)
            else:
                grey = None if out is None else self.irradiance(t).double() @ grey_w
                sums = [part.sum(dim=0, dtype=torch.float64) for part in self.shade(t, brdfs)] if brdfs else []
            for total, part in zip(totals, sums):
                total += part
            if out is not None and grey is not None:
                out[start : start + t.size] = (grey[:, position] * weight).sum(dim=-1).reshape(-1, he, we).cpu().numpy()
        return out, totals

    def event_grey(self, t_us: np.ndarray, event_scale: float) -> np.ndarray:
        """(T, He, We) float64 grey irradiance (0.299 R + 0.587 G + 0.114 B) area-averaged from the frame
        grid to the event grid of ``psfmt.scale_affine(event_scale)``: each event pixel is the weighted
        sum of the few masked frame pixels it covers (a gather, not a dense matrix product)."""
        grey, _ = self._render(t_us, event_scale, ())
        assert grey is not None
        return grey

    def event_grey_and_sums(self, t_us: np.ndarray, event_scale: float, brdfs: Sequence[BRDF],
                            ) -> tuple[np.ndarray, list[torch.Tensor]]:
        """``event_grey(t_us, event_scale)`` and ``shade_sum(t_us, brdfs)`` together: on the
        closed-form path each time is shaded once for both (the simulator's shared time grid)."""
        grey, sums = self._render(t_us, event_scale, brdfs)
        assert grey is not None
        return grey, sums

    def event_pixels(self, t_us: np.ndarray, pixel: np.ndarray, event_scale: float) -> np.ndarray:
        """(M,) float64 ``event_grey`` of single event pixels ``pixel`` (y·We + x) at single times
        ``t_us`` (M,): only the frame pixels under them are shaded. Needs ``shadow_step_us`` (or no
        shadows), a directional light and the ``ggx`` or ``lambertian`` BRDF (``event_pixels_supported``)."""
        if not self.event_pixels_supported:
            raise UserError("Renderer.event_pixels needs a directional light, the ggx or lambertian BRDF and a shadow grid")
        t_us = np.asarray(t_us, dtype=np.float64).reshape(-1)
        position, weight = self.footprint(event_scale)
        pixel_t = torch.as_tensor(np.asarray(pixel, dtype=np.int64), device=self.device)
        frame = position[pixel_t].reshape(-1)
        w = weight[pixel_t]
        taps = w.shape[1]
        l, e = self._light(t_us)
        l, e = l.repeat_interleave(taps, dim=0), e.repeat_interleave(taps, dim=0)
        grey_w = torch.tensor(GREY_WEIGHTS, dtype=torch.float64, device=self.device)
        nl, ratio = self._closed_form(type(self.brdf) is GGX, l, frame)
        grey = torch.sum(self._rgb64["albedo"][frame] * e * grey_w, dim=-1)
        if ratio is not None:
            grey += ratio * torch.sum(self._rgb64["f0"][frame] * e * grey_w, dim=-1)
        grey *= nl
        visible = self._pixel_visibility(np.repeat(t_us, taps), frame.cpu().numpy())
        grey *= torch.as_tensor(visible, dtype=torch.float64, device=self.device)
        return (grey.reshape(-1, taps) * w).sum(dim=-1).cpu().numpy()

    @property
    def event_pixels_supported(self) -> bool:
        """Whether ``event_pixels`` can render this scene (else render whole event frames)."""
        return self._fast([self.brdf]) and (self.shadow_step_us is not None or not self.shadows)






