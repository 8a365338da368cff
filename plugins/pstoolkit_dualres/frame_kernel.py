"""The frame term of eq. 24 on the shared time grid as one compiled pass, for the built-in ``ggx`` and
``lambertian`` BRDFs (``fused_frame_loss``).

Through torch, the term renders (P, K·S, 3) intermediates for every operation of the BRDF and again
for each one's backward: some sixty passes over memory per step, which is most of a step's time. The
kernel instead walks each pixel's K·S samples once and keeps in registers, per frame and channel, the
sums the prediction is linear in: with E = D·V·[n·l]₊ the specular factor of the sample,

    Ã_kc = ρ_d,c·Σ_s u_sc·[n·l]₊ + F0_c·Σ_s u_sc·E,      u_sc = e_c·Δt·lit share,

and the same sums of the derivatives of [n·l]₊ and E with respect to n and the roughness. The L1
residual of eq. 24 then gives the gradient with respect to the normal and every map from those sums,
in the same pass. The GGX formulas are ``ggx_kernel``'s, ``pstoolkit.optics.brdf.GGX.shade``
differentiated by hand (including the clamps and the |n × h|² form of 1 − (n·h)²); tests compare value
and gradients with torch's autograd of the BRDF itself.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from numba import prange
from torch import Tensor

from pstoolkit.optics.brdf import GGX, Lambertian
from pstoolkit_dualres.ggx_kernel import ggx_half, ggx_pixel, ggx_specular
from pstoolkit_dualres.reflectance import INDIRECT, FitModel

# Pixels a thread takes at once: the innermost loop's length (128 measured fastest at 512² pixels).
BLOCK = 128


# Fused multiply-adds only: with every fast-math flag the same solve gave different last bits from
# run to run on one machine (the determinism test failed about one process in three).
@numba.njit(cache=True, parallel=True, nogil=True, error_model="numpy", fastmath={"contract"})
def _frame_pass(normal: np.ndarray, albedo: np.ndarray, f0: np.ndarray, roughness: np.ndarray, light: np.ndarray,
                weight: np.ndarray, visible: np.ndarray, view: np.ndarray, indirect: np.ndarray, energy: np.ndarray,
                frames: int, measured: np.ndarray, saturated: np.ndarray, gradient: bool, loss: np.ndarray,
                grads: np.ndarray) -> None:
    """Per pixel i: ``loss[i]`` the summed residual of its K·3 frame values, and (``gradient``)
    ``grads[:, i]`` the derivatives of that sum with respect to its normal (rows 0–2), albedo (3–5),
    F0 (6–8), roughness (9) and indirect light (10).

    ``normal``, ``albedo``, ``f0`` (3, P) float32, ``roughness`` (P,), ``light`` (K·S, 3) unit light
    directions, ``weight`` (K·S, 3), ``visible`` (K·S, P) or (0, 0) when all is lit, ``view`` (3,)
    float64, ``indirect`` (P,) the indirect light b or (0,) without one, ``energy`` (K, 3) each frame's
    Σ weight without the mask (what b is reflected under: Ã_kc += ρ_c·b·energy_kc), ``measured``
    (K, P, 3), ``saturated`` (K, P). Pixels go in blocks of BLOCK, the innermost
    loop over a block's pixels, so the compiler vectorises it; the sums live in a (27, BLOCK) scratch."""
    p = normal.shape[1]
    per = light.shape[0] // frames
    shadows = visible.shape[0] > 0
    ambient = indirect.shape[0] > 0
    vx, vy, vz = np.float32(view[0]), np.float32(view[1]), np.float32(view[2])
    zero, one = np.float32(0.0), np.float32(1.0)
    for block in prange((p + BLOCK - 1) // BLOCK):
        i0 = block * BLOCK
        n = min(BLOCK, p - i0)
        # per pixel: ``ggx_pixel``'s α², k, b, n·v, r and its two clamp flags
        own = np.empty((7, BLOCK), dtype=np.float32)
        sums = np.empty((27, BLOCK), dtype=np.float32)
        out = np.zeros((12, BLOCK), dtype=np.float32)
        for j in range(n):
            i = i0 + j
            terms = ggx_pixel(normal[0, i], normal[1, i], normal[2, i], roughness[i], vx, vy, vz)
            for x in range(7):
                own[x, j] = terms[x]
        for fk in range(frames):
            sums[:, :n] = zero
            for s in range(fk * per, (fk + 1) * per):
                lx, ly, lz = light[s, 0], light[s, 1], light[s, 2]
                hx, hy, hz, he = ggx_half(lx, ly, lz, view)
                w0, w1, w2 = weight[s, 0], weight[s, 1], weight[s, 2]
                for j in range(n):
                    i = i0 + j
                    nx, ny, nz = normal[0, i], normal[1, i], normal[2, i]
                    nl_raw = nx * lx + ny * ly + nz * lz
                    # below the horizon a sample renders 0 with a zero gradient
                    lit = (visible[s, i] if shadows else one) if nl_raw >= zero else zero
                    nl = max(nl_raw, zero)
                    e, dx, dy, dz, dr = ggx_specular(nx, ny, nz, nl, lx, ly, lz, hx, hy, hz, he, vx, vy, vz, own[0, j],
                                                     own[1, j], own[2, j], own[3, j], own[4, j], own[5, j], own[6, j])
                    u0, u1, u2 = w0 * lit, w1 * lit, w2 * lit
                    sums[0, j] += u0 * nl
                    sums[1, j] += u1 * nl
                    sums[2, j] += u2 * nl
                    sums[3, j] += u0 * e
                    sums[4, j] += u1 * e
                    sums[5, j] += u2 * e
                    if gradient:
                        sums[6, j] += u0 * lx
                        sums[7, j] += u0 * ly
                        sums[8, j] += u0 * lz
                        sums[9, j] += u1 * lx
                        sums[10, j] += u1 * ly
                        sums[11, j] += u1 * lz
                        sums[12, j] += u2 * lx
                        sums[13, j] += u2 * ly
                        sums[14, j] += u2 * lz
                        sums[15, j] += u0 * dx
                        sums[16, j] += u0 * dy
                        sums[17, j] += u0 * dz
                        sums[18, j] += u1 * dx
                        sums[19, j] += u1 * dy
                        sums[20, j] += u1 * dz
                        sums[21, j] += u2 * dx
                        sums[22, j] += u2 * dy
                        sums[23, j] += u2 * dz
                        sums[24, j] += u0 * dr
                        sums[25, j] += u1 * dr
                        sums[26, j] += u2 * dr
            # eq. 24 per channel: L1, or for a clipped value only the shortfall below 1
            for c in range(3):
                for j in range(n):
                    i = i0 + j
                    # the light the diffuse albedo reflects: the direct sum and the indirect b·energy
                    diffuse = sums[c, j] + (indirect[i] * energy[fk, c] if ambient else zero)
                    pred = albedo[c, i] * diffuse + f0[c, i] * sums[3 + c, j]
                    if saturated[fk, i]:
                        residual = one - pred
                        g = -one if residual > zero else zero
                        out[11, j] += max(residual, zero)
                    else:
                        residual = pred - measured[fk, i, c]
                        g = one if residual > zero else (-one if residual < zero else zero)
                        out[11, j] += abs(residual)
                    if gradient:
                        out[3 + c, j] += g * diffuse
                        if ambient:
                            out[10, j] += g * albedo[c, i] * energy[fk, c]
                        out[6 + c, j] += g * sums[3 + c, j]
                        for x in range(3):
                            out[x, j] += g * (albedo[c, i] * sums[6 + 3 * c + x, j] + f0[c, i] * sums[15 + 3 * c + x, j])
                        out[9, j] += g * f0[c, i] * sums[24 + c, j]
        for j in range(n):
            loss[i0 + j] = out[11, j]
        if gradient:
            for x in range(11):
                for j in range(n):
                    grads[x, i0 + j] = out[x, j]


def supports(model: FitModel, normal: Tensor) -> bool:
    """True where ``fused_frame_loss`` computes the term: the built-in GGX or Lambertian (not a
    subclass, which may shade otherwise) on CPU tensors."""
    return type(model.brdf) in (GGX, Lambertian) and normal.device.type == "cpu"


def ggx_maps(model: FitModel, normal: Tensor, maps: dict[str, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
    """The (P, 3) albedo, (P, 3) F0 and (P, 1) roughness the kernels shade with: the GGX maps, or for
    the Lambertian GGX with F0 = 0 (finite D and V at r = 1, so the specular terms vanish exactly)."""
    albedo = maps["albedo"]
    if type(model.brdf) is GGX:
        return albedo, maps["f0"], maps["roughness"]
    return albedo, albedo.new_zeros((normal.shape[0], 3)), albedo.new_ones((normal.shape[0], 1))


def float32_array(x: Tensor) -> np.ndarray:
    """A C-contiguous float32 copy (or view) of ``x`` for the kernel."""
    return x.detach().to(torch.float32).contiguous().numpy()


class _FusedFrameLoss(torch.autograd.Function):
    @staticmethod
    def forward(ctx, normal: Tensor, albedo: Tensor, f0: Tensor, roughness: Tensor, indirect: Tensor, light: Tensor,
                weight: Tensor, visible: Tensor, view: Tensor, energy: Tensor, frames: int, measured: Tensor,
                saturated: Tensor) -> Tensor:
        p = normal.shape[0]
        gradient = any(ctx.needs_input_grad[:5])
        loss = np.empty(p, dtype=np.float32)
        grads = np.empty((11, p if gradient else 0), dtype=np.float32)
        shading = (float32_array(x) for x in (normal.T, albedo.T, f0.T, roughness.reshape(-1), light, weight, visible))
        _frame_pass(*shading, view.detach().double().numpy(), float32_array(indirect.reshape(-1)), float32_array(energy),
                    frames, float32_array(measured).reshape(frames, p, 3), saturated.reshape(frames, p).contiguous().numpy(),
                    gradient, loss, grads)
        count = frames * p * 3
        if gradient:
            ctx.grads = torch.from_numpy(grads)
            ctx.count = count
        return normal.new_tensor(loss.sum(dtype=np.float64) / max(count, 1))

    @staticmethod
    def backward(ctx, grad: Tensor):
        g = ctx.grads * (grad / max(ctx.count, 1))
        need = ctx.needs_input_grad
        parts = (g[0:3].T, g[3:6].T, g[6:9].T, g[9:10].T, g[10:11].T)
        return (*(part if wanted else None for part, wanted in zip(parts, need[:5])), *(None,) * 8)


def fused_frame_loss(model: FitModel, normal: Tensor, maps: dict[str, Tensor], light: Tensor, weight: Tensor,
                     visible: Tensor | None, view: Tensor, frames: int, measured: Tensor, saturated: Tensor,
                     energy: Tensor | None = None) -> Tensor:
    """``frame_loss(frame_prediction_grid(...), measured, saturated)`` in one compiled pass, with the
    gradient with respect to ``normal`` and the maps; only where ``supports(model, normal)``.

    Parameters
    ----------
    model
        A FitModel of the built-in GGX or Lambertian.
    normal
        (P, 3) unit normals.
    maps
        ``albedo`` (P, 3), and for GGX ``f0`` (P, 3) and ``roughness`` (P, 1).
    light, weight
        (K·S, 3) unit light directions and RGB weights of the shared time grid, in frame order.
    visible
        (K·S, P) lit share of each sample, or None.
    view
        (3,) unit direction to the camera.
    frames
        K; divides K·S.
    measured, saturated
        (K·P, 3) frame values and (K·P,) clipped flags, rows frame·P + pixel.
    energy
        (K, 3) each frame's light energy (``FrameTerms.energy``), under which a model with
        ``indirect`` reflects its indirect map; needed then.

    Returns
    -------
    Tensor
        The scalar mean of eq. 24's residual over the K·P·3 values, differentiable.
    """
    albedo, f0, roughness = ggx_maps(model, normal, maps)
    lit = visible if visible is not None else normal.new_zeros((0, 0))
    if model.indirect:
        assert energy is not None, "a model with indirect light needs the frames' energy"
        indirect = maps[INDIRECT.name]
    else:
        indirect, energy = normal.new_zeros((0, 1)), normal.new_zeros((frames, 3))
    return _FusedFrameLoss.apply(normal, albedo, f0, roughness, indirect, light, weight, lit, view, energy, frames, measured,
                                 saturated)
