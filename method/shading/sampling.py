"""Sample directions for the per-pixel Monte Carlo of the rendering equation, with their pdfs.

Every strategy is stratified with the same Fibonacci lattice (point i of n: a "radial" coordinate
(i + 0.5) / n and an azimuth 2 pi frac(i / golden ratio)), rotated in azimuth by a random angle per pixel,
as in the paper (stratification removes most of the variance of smooth integrands; the rotation makes
the error of neighbouring pixels independent, so it averages out in the loss instead of biasing it).

    cosine: the lattice on the hemisphere with z = sqrt(1 - t): density cos / pi (diffuse term)
    uniform: z = 1 - t: density 1 / (2 pi) (the paper's estimator, kept for comparison)
    ggx:    half vectors from D(h) (n.h), reflected about h: density D (n.h) / (4 v.h) (specular lobe)
    env:    texels by luminance x solid angle (envmap.EnvSampler), for small bright suns; texel and
            position inside it from a 3D lattice (Roberts R3) shifted per pixel

Local frames are built around each normal (Duff et al. 2017, branchless); no gradients flow through
the sampled directions or pdfs (they define the estimator, not the model).
"""
from __future__ import annotations

import math

import torch

from .brdf import ggx_d

GOLDEN = (1.0 + math.sqrt(5.0)) / 2.0


def lattice(n: int, device=None, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """The n-point Fibonacci lattice in [0, 1)^2: (t_i, a_i) = ((i + 0.5) / n, frac(i / golden))."""
    i = torch.arange(n, device=device, dtype=torch.float64)
    t = (i + 0.5) / n
    a = torch.remainder(i / GOLDEN, 1.0)
    return t.to(dtype), a.to(dtype)


def random_offsets(shape, generator: torch.Generator | None, device=None, dtype=torch.float32) -> torch.Tensor:
    """Uniform [0, 1) numbers drawn on the generator's device (reproducible for a seed), then moved."""
    gdev = generator.device if generator is not None else torch.device(device or "cpu")
    return torch.rand(shape, generator=generator, device=gdev, dtype=torch.float64).to(device=device, dtype=dtype)


def orthonormal_basis(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Two unit tangents (t, b) with (t, b, n) right-handed, for unit normals (..., 3)."""
    x, y, z = n.unbind(-1)
    sign = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))
    a = -1.0 / (sign + z)
    b = x * y * a
    t = torch.stack([1.0 + sign * x * x * a, sign * b, -sign * x], -1)
    bb = torch.stack([b, sign + y * y * a, -y], -1)
    return t, bb


def to_world(local: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """Local (..., S, 3) directions with +z along each normal (..., 3) -> world (..., S, 3)."""
    t, b = orthonormal_basis(normals)
    return (local[..., 0:1] * t[..., None, :] + local[..., 1:2] * b[..., None, :]
            + local[..., 2:3] * normals[..., None, :])


def _rotation(P: int, generator, rotation, normals) -> torch.Tensor:
    if rotation is not None:
        return rotation.reshape(P, 1).to(normals.dtype)
    return random_offsets((P, 1), generator, normals.device, normals.dtype)


def sample_hemisphere(normals: torch.Tensor, n: int, generator: torch.Generator | None = None,
                      cosine: bool = True, rotation: torch.Tensor | None = None) -> torch.Tensor:
    """(P, n, 3) world directions: the lattice around each normal, rotated by a random azimuth per pixel
    (``rotation``: (P, 1) in [0, 1) turns, drawn from ``generator`` when not given)."""
    P = normals.shape[0]
    t, a = lattice(n, normals.device, normals.dtype)
    a = a[None, :] + _rotation(P, generator, rotation, normals)
    z = (torch.sqrt(1.0 - t) if cosine else 1.0 - t).expand(P, n)
    r = torch.sqrt((1.0 - z * z).clamp_min(0.0))
    phi = 2.0 * math.pi * a
    local = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)
    return to_world(local, normals)


def pdf_hemisphere(cos_theta: torch.Tensor, cosine: bool = True) -> torch.Tensor:
    if cosine:
        return cos_theta.clamp_min(0.0) / math.pi
    return torch.where(cos_theta > 0, torch.full_like(cos_theta, 0.5 / math.pi), torch.zeros_like(cos_theta))


def sample_ggx(normals: torch.Tensor, view_dirs: torch.Tensor, roughness: torch.Tensor, n: int,
               generator: torch.Generator | None = None, rotation: torch.Tensor | None = None) -> torch.Tensor:
    """(P, n, 3) directions l = reflect(v, h) with h drawn from D(h) (n.h) on the stratified lattice.

    ``roughness`` is (P,) or (P, 1); directions below the surface are returned as they are (their
    contribution is zero, but they still count as samples of this strategy).
    """
    P = normals.shape[0]
    t, a = lattice(n, normals.device, normals.dtype)
    a = a[None, :] + _rotation(P, generator, rotation, normals)
    a2 = roughness.reshape(P, 1).pow(4)
    cos_h = torch.sqrt((1.0 - t[None, :]) / (1.0 + (a2 - 1.0) * t[None, :]))
    sin_h = torch.sqrt((1.0 - cos_h * cos_h).clamp_min(0.0))
    phi = 2.0 * math.pi * a
    h = to_world(torch.stack([sin_h * torch.cos(phi), sin_h * torch.sin(phi), cos_h], -1), normals)
    v = view_dirs[:, None, :]
    vh = v[..., 0] * h[..., 0] + v[..., 1] * h[..., 1] + v[..., 2] * h[..., 2]
    return 2.0 * vh[..., None] * h - v


_R3 = 1.2207440846057596  # the plastic number: Roberts' R3 sequence, a 3D low-discrepancy lattice


def sample_env(sampler, n: int, offsets: torch.Tensor) -> torch.Tensor:
    """(P, n, 3) env-map directions: texel choice and position inside the texel from the 3D lattice
    ((i + 0.5) / n, frac(i / R3^2), frac(i / R3^3)), shifted per pixel by ``offsets`` (P, 3) in [0, 1)."""
    dev, dt = offsets.device, offsets.dtype
    i = torch.arange(n, device=dev, dtype=torch.float64)
    base = torch.stack([(i + 0.5) / n, torch.remainder(i / _R3 ** 2, 1.0), torch.remainder(i / _R3 ** 3, 1.0)], -1)
    u = torch.remainder(base.to(dt)[None] + offsets[:, None, :], 1.0)
    return sampler.sample(u[..., 0], u[..., 1], u[..., 2])


def pdf_ggx(n_dot_h: torch.Tensor, v_dot_h: torch.Tensor, roughness: torch.Tensor) -> torch.Tensor:
    """Solid-angle density of ``sample_ggx`` at l: D(h) (n.h) / (4 v.h)."""
    return ggx_d(n_dot_h, roughness) * n_dot_h.clamp_min(0.0) / (4.0 * v_dot_h.abs().clamp_min(1e-6))
