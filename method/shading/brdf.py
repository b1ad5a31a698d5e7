"""The simplified Disney BRDF of the paper: Lambert + GGX microfacet specular (DESIGN.md, Reference values).

    f(l, v) = w_d(v) rho / pi + D(h) F(v.h) G(l, v) / (4 (n.l) (n.v))
    alpha = r^2                 D = alpha^2 / (pi ((n.h)^2 (alpha^2 - 1) + 1)^2)
    F = F0 + (1 - F0)(1 - v.h)^5, F0 = 0.04      G = G1(n.l) G1(n.v), G1(x) = x / (x (1 - k) + k), k = (r + 1)^2 / 8

The diffuse weight w_d is the one choice the paper leaves open. Blender's Principled BSDF (which renders
the dataset) layers the diffuse base under the dielectric specular coat and scales it by one minus the
coat's directional albedo at the view angle (Cycles: closure_layering_weight of bsdf_albedo). We do the
same with our own specular lobe's albedo E_s(n.v, r) (DIFFUSE_WEIGHTING = "albedo", the default): that
matches Blender's renders best (measured in tests/test_shading.py, numbers in method/shading/__init__.py)
and keeps a white material under a white sky exactly white. "none" (the paper's literal formula) and
"fresnel" (1 - F(v.h) per sample) stay available for comparison.

Specular colour is achromatic (F0 = 0.04, metallic 0), so the specular term is one channel.
"""
from __future__ import annotations

import math

import torch

F0 = 0.04
MIN_ROUGHNESS = 0.04  # alpha = 1.6e-3: below that D is a spike no sampling budget of ours resolves
DIFFUSE_WEIGHTINGS = ("albedo", "fresnel", "none")
DIFFUSE_WEIGHTING = "albedo"
_EPS = 1e-6


def clamp_roughness(roughness: torch.Tensor) -> torch.Tensor:
    """Roughness in [MIN_ROUGHNESS, 1] (clamp passes gradients inside the range)."""
    return roughness.clamp(MIN_ROUGHNESS, 1.0)


def ggx_d(n_dot_h: torch.Tensor, roughness: torch.Tensor) -> torch.Tensor:
    """GGX normal distribution with alpha = r^2 (zero below the surface)."""
    a2 = roughness.pow(4)
    c2 = n_dot_h.clamp_min(0.0).square()
    return torch.where(n_dot_h > 0, a2 / (math.pi * (c2 * (a2 - 1.0) + 1.0).square()), torch.zeros_like(c2))


def fresnel_schlick(v_dot_h: torch.Tensor, f0: float = F0) -> torch.Tensor:
    return f0 + (1.0 - f0) * (1.0 - v_dot_h.clamp(0.0, 1.0)).pow(5)


def smith_g(n_dot_l: torch.Tensor, n_dot_v: torch.Tensor, roughness: torch.Tensor) -> torch.Tensor:
    """Separable Smith shadowing-masking with Schlick-GGX G1 and k = (r + 1)^2 / 8."""
    k = (roughness + 1.0).square() / 8.0
    nl, nv = n_dot_l.clamp_min(0.0), n_dot_v.clamp_min(0.0)
    return nl / (nl * (1.0 - k) + k) * nv / (nv * (1.0 - k) + k)


def specular(n_dot_l, n_dot_v, n_dot_h, v_dot_h, roughness) -> torch.Tensor:
    """The specular BRDF value D F G / (4 n.l n.v), zero where l or v is below the surface."""
    ok = (n_dot_l > 0) & (n_dot_v > 0)
    nl, nv = n_dot_l.clamp_min(_EPS), n_dot_v.clamp_min(_EPS)
    val = ggx_d(n_dot_h, roughness) * fresnel_schlick(v_dot_h) * smith_g(nl, nv, roughness) / (4.0 * nl * nv)
    return torch.where(ok, val, torch.zeros_like(val))


# ------------------------------------------------------------------ directional albedo of the specular lobe

_TABLE_N = 32  # (n.v, r) grid, both uniform on [0, 1]; E_s is smooth there (bilinear error < 1e-3)
_TABLE_SAMPLES = 4096
_TABLES: dict[tuple, torch.Tensor] = {}


def _albedo_table_f64() -> torch.Tensor:
    """E_s(mu, r) = integral of the specular BRDF times n.l over the hemisphere, on a 32 x 32 grid.

    Deterministic quadrature: a Fibonacci lattice of half vectors drawn from D (n.h) (so the integrand's
    peak is sampled densely at any roughness), estimator F G (v.h) / ((n.h)(n.v)).
    """
    mu = torch.linspace(0.0, 1.0, _TABLE_N, dtype=torch.float64).clamp_min(1e-3)
    r = torch.linspace(0.0, 1.0, _TABLE_N, dtype=torch.float64).clamp_min(MIN_ROUGHNESS)
    i = torch.arange(_TABLE_SAMPLES, dtype=torch.float64)
    u1 = (i + 0.5) / _TABLE_SAMPLES
    u2 = torch.remainder(i * (math.sqrt(5.0) - 1.0) / 2.0, 1.0)
    a2 = r.pow(4)[None, :, None]  # (1, R, S)
    cos_h = torch.sqrt((1.0 - u1) / (1.0 + (a2 - 1.0) * u1))  # GGX NDF inversion
    sin_h = torch.sqrt((1.0 - cos_h.square()).clamp_min(0.0))
    phi = 2.0 * math.pi * u2
    v = torch.stack([torch.sqrt(1.0 - mu.square()), torch.zeros_like(mu), mu], -1)[:, None, None, :]  # (M,1,1,3)
    h = torch.stack([sin_h * torch.cos(phi), sin_h * torch.sin(phi), cos_h.expand_as(sin_h)], -1)  # (1,R,S,3)
    v_dot_h = (v * h).sum(-1)
    l_z = 2.0 * v_dot_h * h[..., 2] - v[..., 2]
    rr = r[None, :, None]
    w = fresnel_schlick(v_dot_h) * smith_g(l_z, v[..., 2].expand_as(l_z), rr) * v_dot_h / (h[..., 2] * v[..., 2])
    w = torch.where((l_z > 0) & (v_dot_h > 0), w, torch.zeros_like(w))
    return w.mean(-1)  # (M, R)


def specular_albedo(n_dot_v: torch.Tensor, roughness: torch.Tensor) -> torch.Tensor:
    """E_s(n.v, r): the fraction of light the specular lobe reflects towards v under a white sky.

    Bilinear in a table computed once per device and dtype; differentiable w.r.t. both arguments.
    """
    key = (n_dot_v.device, n_dot_v.dtype)
    table = _TABLES.get(key)
    if table is None:
        if (torch.device("cpu"), torch.float64) not in _TABLES:
            _TABLES[(torch.device("cpu"), torch.float64)] = _albedo_table_f64()
        table = _TABLES[(torch.device("cpu"), torch.float64)].to(device=n_dot_v.device, dtype=n_dot_v.dtype)
        _TABLES[key] = table
    n = _TABLE_N - 1
    x = n_dot_v.clamp(0.0, 1.0) * n
    y = roughness.clamp(0.0, 1.0) * n
    x0 = x.detach().floor().clamp(0, n - 1)
    y0 = y.detach().floor().clamp(0, n - 1)
    fx, fy = x - x0, y - y0
    i0, j0 = x0.long(), y0.long()
    t00, t01 = table[i0, j0], table[i0, j0 + 1]
    t10, t11 = table[i0 + 1, j0], table[i0 + 1, j0 + 1]
    return (t00 * (1 - fx) + t10 * fx) * (1 - fy) + (t01 * (1 - fx) + t11 * fx) * fy


def diffuse_weight(n_dot_v, v_dot_h, roughness, weighting: str = DIFFUSE_WEIGHTING) -> torch.Tensor | float:
    """The factor on rho / pi: 1 - E_s(n.v, r) ("albedo"), 1 - F(v.h) ("fresnel") or 1 ("none")."""
    if weighting == "albedo":
        return 1.0 - specular_albedo(n_dot_v, roughness)
    if weighting == "fresnel":
        return 1.0 - fresnel_schlick(v_dot_h)
    if weighting == "none":
        return 1.0
    raise ValueError(f"unknown diffuse weighting {weighting!r} (one of {', '.join(DIFFUSE_WEIGHTINGS)})")
