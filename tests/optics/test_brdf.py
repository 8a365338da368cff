"""BRDFs: Lambertian shading, GGX against an independent float64 numpy evaluation, reciprocity,
gradients; the ablation models (spherical Gaussians, learned bases, metallic) against their
definitions; every registered model's fit specification; the specular → metal-roughness conversion."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pstoolkit.optics.brdf import GGX, MIN_ROUGHNESS, SG_SHARPNESS, Lambertian, MetallicGGX, MLPBases, SphericalGaussians, pbr_from_specular
from pstoolkit.plugin.manager import get_registries


def _unit(a: np.ndarray) -> np.ndarray:
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def _upper_hemisphere(rng: np.random.Generator, n: int) -> np.ndarray:
    d = _unit(rng.normal(size=(n, 3)))
    d[:, 2] = np.abs(d[:, 2]) + 0.05
    return _unit(d)


def _ggx_reference(n, l, v, albedo, f0, r):
    """The Cook–Torrance GGX BRDF term by term: f_r = ρ_d + D·F0·G / (4 (n·l)(n·v)), shaded by n·l."""
    h = _unit(l + v)
    nl, nv, nh = (np.sum(n * x, -1, keepdims=True) for x in (l, v, h))
    alpha = r**2
    d = alpha**2 / (np.pi * (nh**2 * (alpha**2 - 1) + 1) ** 2)
    k = (r + 1) ** 2 / 8
    g1 = lambda x: x / (x * (1 - k) + k)  # noqa: E731
    spec = d * f0 * g1(nl) * g1(nv) / (4 * nl * nv)
    return (albedo + spec) * nl


def test_lambertian_is_albedo_times_cosine() -> None:
    n = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8], [0.0, 0.0, 1.0]], dtype=torch.float64)
    l = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
    albedo = torch.tensor([0.2, 0.4, 0.8], dtype=torch.float64)
    out = Lambertian().shade(n, l, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), albedo=albedo)
    np.testing.assert_allclose(out.numpy(), [[0.2, 0.4, 0.8], [0.16, 0.32, 0.64], [0, 0, 0]], atol=1e-15)


def test_ggx_matches_float64_reference() -> None:
    rng = np.random.default_rng(3)
    count = 2000
    n, l, v = (_upper_hemisphere(rng, count) for _ in range(3))
    keep = (np.sum(n * l, -1) > 0.02) & (np.sum(n * v, -1) > 0.02)
    n, l, v = n[keep], l[keep], v[keep]
    albedo = rng.uniform(0, 1, (len(n), 3))
    f0 = rng.uniform(0.02, 1, (len(n), 3))
    r = rng.uniform(0.1, 1, (len(n), 1))
    want = _ggx_reference(n, l, v, albedo, f0, r)
    got = GGX().shade(*(torch.from_numpy(a) for a in (n, l, v)), albedo=torch.from_numpy(albedo), f0=torch.from_numpy(f0), roughness=torch.from_numpy(r[:, 0]))
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-5, atol=1e-8)
    got32 = GGX().shade(*(torch.from_numpy(a).float() for a in (n, l, v)), albedo=torch.from_numpy(albedo).float(), f0=torch.from_numpy(f0).float(),
                        roughness=torch.from_numpy(r).float())
    assert got32.dtype == torch.float32
    np.testing.assert_allclose(got32.numpy(), want, rtol=1e-3, atol=1e-5)


def test_ggx_positive_and_zero_in_attached_shadow() -> None:
    rng = np.random.default_rng(4)
    n = torch.from_numpy(_unit(rng.normal(size=(500, 3))))
    l = torch.from_numpy(_unit(rng.normal(size=(500, 3))))
    v = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    out = GGX().shade(n, l, v, albedo=torch.full((3,), 0.5, dtype=torch.float64), f0=0.04, roughness=0.5)
    lit = (n * l).sum(-1) > 0
    assert torch.all(out[lit] > 0) and torch.all(out[~lit] == 0)


def test_ggx_specular_energy_bounded() -> None:
    """With a black albedo, the reflected energy ∫ f_s (n·l) dω over the hemisphere stays ≤ F0."""
    m = 400
    theta, phi = np.meshgrid((np.arange(m) + 0.5) * (np.pi / 2) / m, (np.arange(2 * m) + 0.5) * 2 * np.pi / (2 * m), indexing="ij")
    l = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1).reshape(-1, 3)
    d_omega = (np.sin(theta) * (np.pi / 2 / m) * (np.pi / m)).reshape(-1, 1)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    for view_deg in (0.0, 60.0):
        v = torch.tensor([np.sin(np.deg2rad(view_deg)), 0.0, np.cos(np.deg2rad(view_deg))], dtype=torch.float64)
        for r in (0.3, 0.6, 1.0):
            out = GGX().shade(n, torch.from_numpy(l), v, albedo=torch.zeros(3, dtype=torch.float64), f0=1.0, roughness=r)
            energy = float((out[:, 0].numpy()[:, None] * d_omega).sum())
            assert 0.2 < energy <= 1.0, (view_deg, r, energy)


def test_ggx_reciprocal_in_light_and_view() -> None:
    rng = np.random.default_rng(5)
    n, l, v = (torch.from_numpy(_upper_hemisphere(rng, 300)) for _ in range(3))
    maps = dict(albedo=torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64), f0=torch.tensor([0.9, 0.5, 0.04], dtype=torch.float64),
                roughness=torch.full((300, 1), 0.35, dtype=torch.float64))
    nl = torch.clamp((n * l).sum(-1, keepdim=True), min=0)
    nv = torch.clamp((n * v).sum(-1, keepdim=True), min=0)
    # shade = f_r·(n·l): f_r(l, v) = f_r(v, l) means shade(l, v)·(n·v) = shade(v, l)·(n·l).
    a = GGX().shade(n, l, v, **maps) * nv
    b = GGX().shade(n, v, l, **maps) * nl
    np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ggx_gradients_finite_at_grazing_and_smooth(dtype: torch.dtype) -> None:
    cases = [
        ([0, 0, 1], [1, 0, 0], [0, 0, 1], 0.5),  # n·l = 0
        ([0, 0, 1], [0, 0, 1], [1, 0, 0], 0.5),  # n·v = 0
        ([0, 0, 1], [0, 0, 1], [0, 0, 1], 0.0),  # mirror peak, roughness below the clamp
        ([0, 0, 1], [0, 0, 1], [0, 0, -1], 0.3),  # l = −v: no half vector
        ([0, 0, 1], [0.6, 0, 0.8], [-0.6, 0, 0.8], 1e-4),
        ([0, 0, 1], [0, 0, -1], [0, 0, 1], 0.5),  # light behind the surface
    ]
    for n_, l_, v_, r_ in cases:
        n = torch.tensor(n_, dtype=dtype, requires_grad=True)
        l = torch.tensor(l_, dtype=dtype, requires_grad=True)
        roughness = torch.tensor(r_, dtype=dtype, requires_grad=True)
        albedo = torch.tensor([0.5, 0.5, 0.5], dtype=dtype, requires_grad=True)
        f0 = torch.tensor([0.04, 0.04, 0.04], dtype=dtype, requires_grad=True)
        out = GGX().shade(n, l, torch.tensor(v_, dtype=dtype), albedo=albedo, f0=f0, roughness=roughness)
        out.sum().backward()
        for tensor in (out, n.grad, l.grad, roughness.grad, albedo.grad, f0.grad):
            assert torch.all(torch.isfinite(tensor)), (n_, l_, v_, r_)


def test_ggx_roughness_clamp_and_batch_shapes() -> None:
    n = torch.tensor([0.0, 0.0, 1.0])
    l = torch.tensor([0.0, 0.0, 1.0])
    at_zero = GGX().shade(n, l, l, albedo=torch.zeros(3), f0=torch.ones(3), roughness=torch.tensor(0.0))
    at_min = GGX().shade(n, l, l, albedo=torch.zeros(3), f0=torch.ones(3), roughness=torch.tensor(MIN_ROUGHNESS))
    # bit-equal: the clamp makes the inputs identical, and the same kernel runs on the same shapes
    assert torch.equal(at_zero, at_min)
    n_img = torch.nn.functional.normalize(torch.randn(4, 5, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    out = GGX().shade(n_img, l, l, albedo=torch.rand(4, 5, 3), f0=torch.full((3,), 0.04), roughness=torch.full((4, 5), 0.4))
    assert out.shape == (4, 5, 3)
    same = GGX().shade(n_img, l, l, albedo=torch.zeros(4, 5, 3), f0=torch.full((3,), 0.04), roughness=torch.full((4, 5, 1), 0.4))
    assert same.shape == (4, 5, 3)


@pytest.mark.cuda
def test_ggx_on_cuda_matches_cpu() -> None:
    rng = np.random.default_rng(6)
    n, l, v = (torch.from_numpy(_upper_hemisphere(rng, 100)) for _ in range(3))
    maps = dict(albedo=torch.full((3,), 0.3, dtype=torch.float64), f0=torch.full((3,), 0.5, dtype=torch.float64),
                roughness=torch.full((100,), 0.4, dtype=torch.float64))
    cpu = GGX().shade(n, l, v, **maps)
    gpu = GGX().shade(n.cuda(), l.cuda(), v.cuda(), **{k: m.cuda() for k, m in maps.items()})
    np.testing.assert_allclose(gpu.cpu().numpy(), cpu.numpy(), rtol=1e-10)


def test_every_registered_brdf_says_how_it_is_fitted() -> None:
    registry = get_registries().brdfs
    assert registry.names() == ["ggx", "lambertian", "metallic", "mlp-bases", "sg"]
    for name in registry.names():
        brdf = registry.get(name).obj
        assert tuple(p.name for p in brdf.fit) == brdf.params, name
        for p in brdf.fit:
            assert p.channels >= 1 and (p.high is None or p.high > p.low) and p.low <= p.init
            assert p.high is None or p.init <= p.high
        # one per-pixel RGB reflectance carries the frames' colour
        assert sum(1 for p in brdf.fit if not p.smooth and p.radiometric and p.channels == 3) == 1, name


def test_the_ablation_models_follow_their_definitions() -> None:
    rng = np.random.default_rng(2)
    n = torch.as_tensor(_upper_hemisphere(rng, 64))
    l = torch.as_tensor(_upper_hemisphere(rng, 64))
    v = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    albedo = torch.as_tensor(rng.random((64, 3)))
    weights = torch.as_tensor(rng.random((64, 9)))
    tint = torch.as_tensor(rng.random((64, 3)))
    nl = np.clip(np.sum(n.numpy() * l.numpy(), axis=-1, keepdims=True), 0.0, None)
    nh = np.sum(n.numpy() * _unit(l.numpy() + v.numpy()), axis=-1, keepdims=True)
    bases = np.exp(np.asarray(SG_SHARPNESS) * (nh - 1.0))
    expected = (albedo.numpy() + tint.numpy() * np.sum(weights.numpy() * bases, axis=-1, keepdims=True)) * nl
    out = SphericalGaussians().shade(n, l, v, albedo=albedo, basis_weights=weights, specular_tint=tint)
    # the half vector's guard ε (1e-12) moves the sharpest lobe (λ = 1000) by parts in 1e10
    np.testing.assert_allclose(out.numpy(), expected, rtol=1e-8)
    # metallic m mixes the diffuse (1 − m)·b and F0 = (1 − m)·0.04 + m·b into GGX
    base, metal, rough = torch.as_tensor(rng.random((64, 3))), torch.as_tensor(rng.random((64, 1))), torch.full((64, 1), 0.4, dtype=torch.float64)
    mixed = MetallicGGX().shade(n, l, v, base_color=base, metallic=metal, roughness=rough)
    ggx = GGX().shade(n, l, v, albedo=(1 - metal) * base, f0=(1 - metal) * 0.04 + metal * base, roughness=rough)
    torch.testing.assert_close(mixed, ggx)
    implied = MetallicGGX().derived_maps({"base_color": base.numpy(), "metallic": metal.numpy()})
    np.testing.assert_allclose(implied["albedo"], ((1 - metal) * base).numpy())
    # the learned bases are non-negative and carry gradients to their network
    torch.manual_seed(0)
    learned = MLPBases()
    out = learned.shade(n.float(), l.float(), v.float(), albedo=albedo.float(), basis_weights=weights.float(), specular_tint=tint.float())
    assert torch.all(out >= 0)
    out.sum().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in learned.parameters())


def test_pbr_conversion_of_a_dielectric_and_a_metal() -> None:
    metallic, base = pbr_from_specular(np.array([[0.5, 0.3, 0.2], [0.0, 0.0, 0.0]]), np.array([[0.04] * 3, [0.9, 0.6, 0.3]]))
    assert metallic[0] == pytest.approx(0.0, abs=1e-6) and metallic[1] == pytest.approx(1.0)
    assert np.allclose(base[0], [0.5, 0.3, 0.2], atol=0.02)
    assert np.allclose(base[1], [0.9, 0.6, 0.3], atol=1e-6)
    derived = GGX().derived_maps({"albedo": np.array([[0.5, 0.3, 0.2]]), "f0": np.array([[0.04] * 3]), "roughness": np.array([[0.5]])})
    assert set(derived) == {"metallic", "base_color"}
