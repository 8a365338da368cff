"""A start for glossy and metallic surfaces from the shape of each super pixel's irradiance over the turn.

The closed-form start (``closed_form``) reads the long exposures as Lambertian. On a surface whose light
is mostly specular (a metal) that reading is far off: a highlight's depth of modulation over the turn is
taken for a steep tilt, and the fit, started there, stays in that basin (path-traced rough copper: 39°
from the closed form, 19° from this start, 13° from the true normals). The events see the highlight's
shape, though: Î over one period (``irradiance``) at a super pixel has, up to cast shadows and scale, the
shape (1 − w)·D/ΣD + w·S/ΣS over the turn, D = [n·l(t)]₊ the diffuse shading and S(t) the GGX lobe
(``pstoolkit.optics.brdf.GGX`` with F0 = 1) of a roughness r, both under the ring's grey intensity, w the
share of the light the lobe reflects.

``specular_weight``: the w and r of a grid whose shapes, each profile at its best candidate normal and
scale, leave the least mean relative residual. One w and one r for the whole capture: with a free mixture
per pixel the lobe also fits profiles it did not make (a flat pixel's constant, a cast shadow's notch).
The simulator's plastics and path-traced rough plastic give w ≤ 0.1 (≤ 0.5 through the EVK4-like
sensor, whose refractory sharpens the profiles), path-traced copper 0.9–1.

``capture_start`` runs both for the solver: the weight from at most ``SELECT_PROFILES`` super pixels, the
normals ``BLOCK`` super pixels at a time. On a solver's torch device (``devices.on_host`` false) the
shapes and their residuals are computed there, in float64 as on the host, and only the choices come back:
the same choices but where two shapes fit a profile equally to rounding.

``profile_normals``: each super pixel's candidate normal (a Fibonacci grid of the hemisphere up to
``MAX_TILT_DEG``, ~3.5° apart) whose shape at that w and r fits its profile best. It is only a start, and
only worth it where the lobe carries the light: on a Lambertian surface a profile's shape fixes the
normal less well than the closed form's three exposures do.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from pstoolkit import LightModel
from pstoolkit._shared import devices
from pstoolkit.events.relation import grey_light
from pstoolkit.optics.brdf import GGX
from pstoolkit_dualres.irradiance import Irradiance

# Phases sampled over one light period.
PROFILE_SAMPLES = 96
# The grid of ``specular_weight``: roughnesses r (GGX α = r²) and specular weights w.
ROUGHNESSES = (0.2, 0.3, 0.4, 0.5, 0.6)
SPECULAR_WEIGHTS = (0.0, 0.1, 0.25, 0.5, 0.75, 0.9, 1.0)
# ``specular_weight`` compares the shapes at this many profiles and candidate normals (~6° apart).
SELECT_PROFILES = 1024
SELECT_CANDIDATES = 600
# Candidate normals of ``profile_normals``: a Fibonacci grid of the hemisphere up to this tilt.
CANDIDATES = 2000
MAX_TILT_DEG = 85.0
# The solver starts from ``profile_normals`` when ``specular_weight`` reaches this (module docstring).
PROFILE_START_WEIGHT = 0.75
# Profiles per block of the search: the (block, candidates) residual matrix stays under ~30 MB.
BLOCK = 2048


def profiles(irradiance: Irradiance, light: LightModel, t0_us: float, period_us: float, pixels: np.ndarray,
             samples: int = PROFILE_SAMPLES) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Î at event pixels ``pixels`` (P,) and ``samples`` phases mid-way in equal steps over the period,
    each profile scaled to peak 1: (P, samples) float64, the (P,) bool of the profiles that see light
    (the others are zero), and the grey light l(t)·luma (samples, 3)."""
    phase = (np.arange(samples) + 0.5) * (period_us / samples)
    values = np.asarray(irradiance.value(np.asarray(pixels, dtype=np.int64)[:, None], phase[None, :]), dtype=np.float64)
    peak = values.max(axis=1) if len(values) else np.zeros(0)
    lit = peak > 0
    values[lit] /= peak[lit, None]
    values[~lit] = 0.0
    return values, lit, grey_light(light, phase + t0_us).T


def capture_start(irradiance: Irradiance, light: LightModel, view: np.ndarray, t0_us: float, period_us: float,
                  pixels: np.ndarray, rule: str, device: str = "cpu") -> tuple[float | None, np.ndarray | None]:
    """The specular weight of the event pixels ``pixels`` (P,) (``specular_weight`` on at most
    ``SELECT_PROFILES`` of them, evenly spread) and, by ``rule`` ("auto": where the weight reaches
    ``PROFILE_START_WEIGHT``; "profile": always), their profile normals (P, 3) (zero where a profile
    sees no light), else None. The weight is None where no profile sees light. Profiles are made
    ``BLOCK`` pixels at a time, so memory does not grow with the capture; their fits run on the torch
    ``device`` (module docstring)."""
    chosen = pixels[np.unique(np.linspace(0, len(pixels) - 1, min(len(pixels), SELECT_PROFILES)).astype(np.int64))]
    y, lit, grey = profiles(irradiance, light, t0_us, period_us, chosen)
    if not lit.any():
        return None, None
    weight, roughness = specular_weight(y[lit], grey, view, device)
    if rule == "auto" and weight < PROFILE_START_WEIGHT:
        return weight, None
    normal = np.zeros((len(pixels), 3))
    for start in range(0, len(pixels), BLOCK):
        y, lit, grey = profiles(irradiance, light, t0_us, period_us, pixels[start:start + BLOCK])
        if lit.any():
            normal[start:start + BLOCK][lit] = profile_normals(y[lit], grey, view, weight, roughness, device)
    return weight, normal


def _bases(normal: np.ndarray, light: np.ndarray, view: np.ndarray, roughness: float, device: str = "cpu"
           ) -> tuple[Tensor, Tensor]:
    """Diffuse D = [n·l]₊|l| and lobe S (GGX, F0 = 1) × |l|, each (N, T) float64 on the torch ``device``,
    of unit normals (N, 3) under grey lights ``light`` (T, 3) (direction × luma)."""
    strength = np.linalg.norm(light, axis=1)
    direction = light / np.maximum(strength, 1e-12)[:, None]
    n = torch.as_tensor(normal, dtype=torch.float64, device=device)[:, None, :]
    l = torch.as_tensor(direction, dtype=torch.float64, device=device)[None, :, :]
    v = torch.as_tensor(view, dtype=torch.float64, device=device).expand(1, 1, 3)
    zero, one = torch.zeros(1, dtype=torch.float64, device=device), torch.ones(1, dtype=torch.float64, device=device)
    r = torch.tensor(roughness, dtype=torch.float64, device=device)
    strength_there = torch.as_tensor(strength, device=device)
    with torch.no_grad():
        lobe = GGX().shade(n, l, v, albedo=zero, f0=one, roughness=r)[..., 0]
        diffuse = GGX().shade(n, l, v, albedo=one, f0=zero, roughness=r)[..., 0]
    return diffuse * strength_there, lobe * strength_there


def _mixtures(normal: np.ndarray, light: np.ndarray, view: np.ndarray, roughness: float,
              weights: tuple[float, ...], device: str = "cpu") -> np.ndarray | Tensor:
    """(len(weights), N, T): the profiles (1 − w)·D/ΣD + w·S/ΣS of unit normals (N, 3) for each specular
    weight w (``_bases``' D, S, each scaled to sum to one over the turn); a tensor on ``device`` where
    that is not the host."""
    diffuse, lobe = _bases(normal, light, view, roughness, device)
    if devices.on_host(device):
        diffuse, lobe = diffuse.numpy(), lobe.numpy()
        stack = np.stack
    else:
        stack = torch.stack
    diffuse = diffuse / diffuse.sum(axis=1, keepdims=True).clip(min=1e-30)
    lobe = lobe / lobe.sum(axis=1, keepdims=True).clip(min=1e-30)
    return stack([(1.0 - w) * diffuse + w * lobe for w in weights])


def _residuals(y: np.ndarray | Tensor, shapes: np.ndarray | Tensor) -> np.ndarray | Tensor:
    """(P, N) relative squared residual |y − a·m|²/|y|² of each profile of ``y`` (P, T) under its best
    scale a ≥ 0 for each shape m of ``shapes`` (N, T): arrays, or tensors on one device."""
    yy = (y * y).sum(axis=1).clip(min=1e-30)
    projection = (y @ shapes.T).clip(min=0.0)
    return 1.0 - projection**2 / (shapes * shapes).sum(axis=1).clip(min=1e-30) / yy[:, None]


def specular_weight(y: np.ndarray, light: np.ndarray, view: np.ndarray, device: str = "cpu") -> tuple[float, float]:
    """The weight w of ``SPECULAR_WEIGHTS`` and roughness of ``ROUGHNESSES`` whose profile family fits
    the profiles ``y`` (P, T) best, each profile at its best normal among ``SELECT_CANDIDATES`` (the mean
    relative residual over the profiles; ``capture_start`` gives it at most ``SELECT_PROFILES``),
    computed on the torch ``device``."""
    candidates = candidate_normals(SELECT_CANDIDATES)
    there = not devices.on_host(device)
    profiles_y = torch.as_tensor(y, device=device) if there else y
    fits = []
    for r in ROUGHNESSES:
        for shapes in _mixtures(candidates, light, view, r, SPECULAR_WEIGHTS, device):
            residual = _residuals(profiles_y, shapes)
            fits.append(residual.amin(dim=1).mean() if there else residual.min(axis=1).mean())
    # one read back of them all on a device
    residuals = torch.stack(fits).cpu().tolist() if there else [float(fit) for fit in fits]
    best = (np.inf, 0.0, ROUGHNESSES[0])
    for (r, w), residual in zip(((r, w) for r in ROUGHNESSES for w in SPECULAR_WEIGHTS), residuals, strict=True):
        if residual < best[0]:
            best = (residual, w, r)
    return best[1], best[2]


def candidate_normals(count: int = CANDIDATES, max_tilt_deg: float = MAX_TILT_DEG) -> np.ndarray:
    """Unit normals (N, 3) of a Fibonacci grid of the hemisphere n_z ≥ cos ``max_tilt_deg``, ``count``
    points over the whole hemisphere."""
    i = np.arange(count) + 0.5
    z = 1.0 - i / count
    ring = np.sqrt(1.0 - z * z)
    angle = np.pi * (1.0 + np.sqrt(5.0)) * i
    grid = np.stack([ring * np.cos(angle), ring * np.sin(angle), z], axis=1)
    return grid[z >= np.cos(np.radians(max_tilt_deg))]


def profile_normals(y: np.ndarray, light: np.ndarray, view: np.ndarray, weight: float, roughness: float,
                    device: str = "cpu") -> np.ndarray:
    """Per profile of ``y`` (P, T) the candidate normal (``candidate_normals``) whose profile of specular
    ``weight`` and ``roughness`` (``specular_weight``) fits it best up to scale: (P, 3) unit normals,
    the fits computed on the torch ``device``."""
    candidates = candidate_normals()
    shapes = _mixtures(candidates, light, view, roughness, (weight,), device)[0]
    best = np.zeros(len(y), dtype=np.int64)
    for start in range(0, len(y), BLOCK):
        if devices.on_host(device):
            best[start:start + BLOCK] = np.argmin(_residuals(y[start:start + BLOCK], shapes), axis=1)
        else:
            block = torch.as_tensor(y[start:start + BLOCK], device=device)
            best[start:start + BLOCK] = torch.argmin(_residuals(block, shapes), dim=1).cpu().numpy()
    return candidates[best]
