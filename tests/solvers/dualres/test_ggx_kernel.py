"""Every copy of the GGX lobe held to the one numba kernel of dualres's compiled passes
(``pstoolkit_dualres.ggx_kernel``): the torch BRDF that autograd differentiates
(``pstoolkit.optics.brdf.GGX``), the simulator's closed form (``pstoolkit.sim.render.Renderer``) and
the viewer's JavaScript shader (``pstoolkit/view/static/shading.js``, run by node where installed).

The kernel computes in float32, the others in float64: values agree to a relative 1e-4 of the
largest; the shader's display bytes to one level.
"""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pytest
import torch
from helpers import REPO

from pstoolkit.optics.brdf import GGX, MIN_ROUGHNESS
from pstoolkit.optics.lights import RingLight
from pstoolkit.plugin.options import defaults
from pstoolkit.sim.render import Renderer
from pstoolkit.sim.scenes import Sphere
from pstoolkit_dualres.ggx_kernel import ggx_half, ggx_pixel, ggx_specular

LIGHTS = np.array([(0.3, 0.2, 0.93), (-0.55, 0.45, 0.7), (0.0, 0.0, 1.0), (0.95, -0.1, 0.3)])
LIGHTS /= np.linalg.norm(LIGHTS, axis=1, keepdims=True)
VIEW = np.array([0.0, 0.0, 1.0])
SHADING_JS = REPO / "pstoolkit" / "view" / "static" / "shading.js"


def kernel_specular(normal: np.ndarray, roughness: np.ndarray, light: np.ndarray) -> np.ndarray:
    """E = D·V·[n·l]₊ of each (P, 3) ``normal`` and (P,) ``roughness`` under the unit ``light`` (3,),
    from the kernel's own functions, as the compiled passes call them (float32 in, float64 out)."""
    lx, ly, lz = (np.float32(x) for x in light)
    vx, vy, vz = (np.float32(x) for x in VIEW)
    hx, hy, hz, he = ggx_half(lx, ly, lz, VIEW)
    out = np.empty(len(normal))
    for i, ((nx, ny, nz), r) in enumerate(zip(normal.astype(np.float32), roughness.astype(np.float32), strict=True)):
        nl = max(nx * lx + ny * ly + nz * lz, np.float32(0.0))
        terms = ggx_pixel(nx, ny, nz, r, vx, vy, vz)
        out[i] = ggx_specular(nx, ny, nz, nl, lx, ly, lz, hx, hy, hz, he, vx, vy, vz, *terms)[0]
    return out


def samples(seed: int, light: np.ndarray, count: int = 96) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals facing the camera, one of them on the half vector of ``light`` (the lobe's peak),
    and roughness from below the clamp to 1."""
    rng = np.random.default_rng(seed)
    normal = rng.normal(size=(count, 3))
    normal[:, 2] = np.abs(normal[:, 2]) + 0.1
    normal[4] = light + VIEW
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    roughness = rng.uniform(0.0, 1.0, count)
    roughness[:5] = (MIN_ROUGHNESS / 2, MIN_ROUGHNESS, 0.05, 1.0, 0.3)
    return normal.astype(np.float32), roughness.astype(np.float32)


@pytest.mark.parametrize("light", LIGHTS.tolist())
def test_the_torch_brdf_is_the_kernel(light: list[float]) -> None:
    normal, roughness = samples(0, np.array(light))
    expected = kernel_specular(normal, roughness, np.array(light))
    n = torch.from_numpy(normal.astype(np.float64))
    shaded = GGX().shade(n, torch.tensor(light, dtype=torch.float64), torch.tensor(VIEW), albedo=0.0, f0=1.0,
                         roughness=torch.from_numpy(roughness.astype(np.float64)))
    assert expected.max() > 1.0  # the lobe's peak is among the samples
    np.testing.assert_allclose(shaded[:, 0].numpy(), expected, rtol=1e-4, atol=1e-4 * expected.max())


def test_the_simulators_closed_form_is_the_kernel() -> None:
    maps = Sphere().build(24, 0, **defaults(Sphere.options))
    rng = np.random.default_rng(1)
    maps.albedo[:] = 0.0
    maps.f0[maps.mask] = 1.0
    maps.roughness[maps.mask] = rng.uniform(0.0, 1.0, maps.mask.sum()).astype(np.float32)
    light = RingLight(elevation_deg=55.0, period_us=1000.0)
    t_us = np.array([0.0, 250.0, 600.0])
    image = Renderer(maps, light, GGX()).image(t_us)
    directions, intensity = light.evaluate(t_us)
    for k, direction in enumerate(directions):
        expected = kernel_specular(maps.normal[maps.mask], maps.roughness[maps.mask], direction)
        np.testing.assert_allclose(image[k][maps.mask] / intensity[k], np.repeat(expected[:, None], 3, axis=1), rtol=1e-4,
                                   atol=1e-4 * expected.max())


def _to_byte(v: np.ndarray) -> np.ndarray:
    return np.where(v > 0, np.round(255 * np.clip(v, 0, 1) ** (1 / 2.2)), 0)


@pytest.mark.skipif(shutil.which("node") is None, reason="node is not installed")
@pytest.mark.parametrize("light", LIGHTS.tolist())
def test_the_viewers_javascript_shader_is_the_kernel(light: list[float]) -> None:
    normal, roughness = samples(2, np.array(light), 64)
    maps = {"normal": normal, "f0": np.ones((64, 1), np.float32), "roughness": roughness, "albedo": np.zeros((64, 1), np.float32)}
    script = (
        f"import {{ Shader }} from {SHADING_JS.as_uri()!r};\n"
        "const maps = JSON.parse(process.argv[1]);\n"
        "for (const m of Object.values(maps)) m.data = Float32Array.from(m.data);\n"
        "const shader = new Shader({ width: 64, height: 1, brdf: 'ggx' }, maps);\n"
        "const image = { data: new Uint8ClampedArray(4 * 64) };\n"
        "shader.render(image, JSON.parse(process.argv[2]), [0.5, 0.5, 0.5]);\n"
        "console.log(JSON.stringify(Array.from(image.data)));\n"
    )
    payload = {name: {"shape": [1, 64, value.reshape(64, -1).shape[1]], "data": value.reshape(-1).tolist()} for name, value in maps.items()}
    done = subprocess.run(["node", "--input-type=module", "-e", script, json.dumps(payload), json.dumps(light)],
                          capture_output=True, text=True, check=True)
    shown = np.array(json.loads(done.stdout)).reshape(64, 4)[:, 0]
    expected = _to_byte(0.5 * kernel_specular(normal, roughness, np.array(light)))
    assert np.abs(shown - expected).max() <= 1
    assert expected.max() == 255 and np.median(expected) > 0  # the peak and the flanks of the lobe
