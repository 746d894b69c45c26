"""Snell, Fresnel and TIR against closed-form values."""

import math

import pytest
import torch

from lookingglass.physics.optics import (IOR_AIR, IOR_GLASS, face_forward, fresnel_dielectric, interface,
                                         reflect, refract)

ETA_IN = IOR_AIR / IOR_GLASS  # entering glass
ETA_OUT = IOR_GLASS / IOR_AIR  # leaving glass


def _random_rays(n=4096, seed=0):
    g = torch.Generator().manual_seed(seed)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)
    nrm = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)
    return d, face_forward(nrm, d)


def test_normal_incidence_reflectance():
    f = fresnel_dielectric(torch.tensor([1.0], dtype=torch.float64), ETA_IN)
    expected = ((IOR_AIR - IOR_GLASS) / (IOR_AIR + IOR_GLASS)) ** 2
    assert f.item() == pytest.approx(expected, rel=1e-12)
    # Symmetric from inside at normal incidence.
    assert fresnel_dielectric(torch.tensor([1.0], dtype=torch.float64), ETA_OUT).item() == pytest.approx(expected, rel=1e-12)


def test_critical_angle_and_tir():
    theta_c = math.asin(IOR_AIR / IOR_GLASS)
    eps = 1e-6
    cos_below, cos_above = math.cos(theta_c - eps), math.cos(theta_c + eps)
    d = lambda c: torch.tensor([[math.sqrt(1 - c * c), -c, 0.0]], dtype=torch.float64)  # noqa: E731
    n = torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64)
    t, tir = refract(d(cos_below), n, ETA_OUT)
    assert not tir.item()
    # Just below the critical angle the transmitted ray grazes the surface.
    assert abs(t[0, 1].item()) < 2e-3
    _, tir = refract(d(cos_above), n, ETA_OUT)
    assert tir.item()
    f = fresnel_dielectric(torch.tensor([cos_above], dtype=torch.float64), ETA_OUT)
    assert f.item() == 1.0
    # Reflectance rises continuously to 1 at the critical angle.
    assert fresnel_dielectric(torch.tensor([cos_below], dtype=torch.float64), ETA_OUT).item() > 0.98


def test_snell_law_and_unit_length():
    d, n = _random_rays()
    t, tir = refract(d, n, ETA_IN)
    assert not tir.any()  # never TIR entering the denser medium
    sin_i = torch.linalg.cross(d, n).norm(dim=-1)
    sin_t = torch.linalg.cross(t, n).norm(dim=-1)
    torch.testing.assert_close(IOR_AIR * sin_i, IOR_GLASS * sin_t, rtol=0, atol=1e-12)
    torch.testing.assert_close(t.norm(dim=-1), torch.ones(len(t), dtype=torch.float64))
    # Transmitted ray stays in the plane of incidence and crosses the surface.
    plane = torch.linalg.cross(d, n)
    assert (t * plane).sum(-1).abs().max() < 1e-12
    assert ((t * n).sum(-1) < 0).all()


def test_reflection_law():
    d, n = _random_rays()
    r = reflect(d, n)
    torch.testing.assert_close((r * n).sum(-1), -(d * n).sum(-1))
    torch.testing.assert_close(r.norm(dim=-1), torch.ones(len(r), dtype=torch.float64))


def test_fresnel_matches_paper_formula_and_reciprocity():
    d, n = _random_rays()
    _, t, f, tir = interface(d, n, ETA_IN)
    # The paper's Eq.: with eta = n_t / n_i written in terms of the dot products.
    li, lt = (d * n).sum(-1), (t * n).sum(-1)
    e = IOR_GLASS / IOR_AIR
    paper = 0.5 * ((li - e * lt) / (li + e * lt)) ** 2 + 0.5 * ((e * li - lt) / (e * li + lt)) ** 2
    torch.testing.assert_close(f, paper, rtol=1e-10, atol=1e-12)
    # Reciprocity: the reverse path through the interface has the same reflectance.
    f_back = fresnel_dielectric((-(t * n).sum(-1)).abs(), ETA_OUT)
    torch.testing.assert_close(f, f_back, rtol=1e-9, atol=1e-12)


def test_energy_conservation_and_tir_fraction():
    d, n = _random_rays(20000, seed=1)
    for eta in (ETA_IN, ETA_OUT):
        _, t, f, tir = interface(d, n, eta)
        assert ((f >= 0) & (f <= 1)).all()
        assert (f[tir] == 1).all() and (t[tir] == 0).all()
    # From inside glass, rays beyond the critical angle are TIR: for isotropic directions
    # the fraction of the hemisphere with cos_i < cos(theta_c) is cos(theta_c).
    _, _, _, tir = interface(d, n, ETA_OUT)
    expected = math.cos(math.asin(IOR_AIR / IOR_GLASS))
    assert tir.double().mean().item() == pytest.approx(expected, abs=4 * math.sqrt(expected * (1 - expected) / len(d)))


def test_gradients_flow():
    d, n = _random_rays(64)
    n = n.clone().requires_grad_(True)
    _, t, f, _ = interface(d, n, ETA_IN)
    (t.sum() + f.sum()).backward()
    assert torch.isfinite(n.grad).all() and n.grad.abs().sum() > 0
    assert torch.autograd.gradcheck(lambda nn: interface(d[:8], nn, ETA_IN)[1], (n[:8].detach().clone().requires_grad_(True),))
