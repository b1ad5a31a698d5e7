"""Rasterized buffers: which feature channel holds what, and the steps every reader of them takes.

The rasterizer composites per-Gaussian features premultiplied by coverage (alpha). Stage 1 renders
colour and P; stage 2 renders colour, albedo, roughness and P for deferred shading. Readers slice the
channels by name here, divide by alpha (un-premultiply) and composite their images on the background
with the helpers below, so a channel moved or added is changed in one place.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

ALPHA_EPS = 1e-4  # un-premultiply: alpha below this is treated as this (the pixel is background anyway)


@dataclass(frozen=True)
class Layout:
    """Named channel ranges of a feature buffer (``features[..., layout.albedo]``)."""

    colour: slice
    p: slice
    albedo: slice | None = None
    roughness: slice | None = None

    @property
    def width(self) -> int:
        return max(s.stop for s in (self.colour, self.p, self.albedo, self.roughness) if s is not None)


# stage 1: [colour (3, display), P (1)]
STAGE1 = Layout(colour=slice(0, 3), p=slice(3, 4))
# stage 2 (deferred shading): [colour (3, display), albedo (3, display), roughness (1), P (1)]
MATERIALS = Layout(colour=slice(0, 3), albedo=slice(3, 6), roughness=slice(6, 7), p=slice(7, 8))


def pack(layout: Layout, **channels: torch.Tensor) -> torch.Tensor:
    """(N, layout.width) per-Gaussian features from named (N, k) or (N,) tensors, one per channel range."""
    names = [n for n in ("colour", "albedo", "roughness", "p") if getattr(layout, n) is not None]
    if set(channels) != set(names):
        raise ValueError(f"pack needs exactly {names}, got {sorted(channels)}")
    parts = sorted(((getattr(layout, n).start, n) for n in names))
    cols = []
    for _, n in parts:
        x = channels[n]
        cols.append(x[:, None] if x.dim() == 1 else x)
    return torch.cat(cols, 1)


def background_for(layout: Layout, background: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """The rasterizer's background vector: the image background in the colour channels, zeros elsewhere."""
    bg = like.new_zeros(layout.width)
    bg[layout.colour] = background.to(like)
    return bg


def unpremultiply(x: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """A premultiplied channel divided by coverage, clamped to [0, 1] (``x`` (..., k) or (...,) with
    ``alpha`` (...,))."""
    a = alpha.clamp_min(ALPHA_EPS)
    return (x / (a[..., None] if x.dim() > a.dim() else a)).clamp(0, 1)


def channel(features: torch.Tensor, alpha: torch.Tensor, rng: slice) -> torch.Tensor:
    """Un-premultiplied channel ``rng`` of a feature buffer; a single channel comes back without its last axis."""
    x = features[..., rng]
    if rng.stop - rng.start == 1:
        x = x[..., 0]
    return unpremultiply(x, alpha)


def unit(v: torch.Tensor) -> torch.Tensor:
    """Vectors (..., 3) normalised (rasterized normals are coverage-weighted sums)."""
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-8)


def over_background(img: torch.Tensor, alpha: torch.Tensor, background) -> torch.Tensor:
    """A straight (not premultiplied) image composited on the background: img a + bg (1 - a) (torch or numpy)."""
    a = alpha[..., None] if alpha.ndim == img.ndim - 1 else alpha
    return img * a + background * (1 - a)
