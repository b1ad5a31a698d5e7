"""The sRGB transfer curves (IEC 61966-2-1), exact and piecewise, for numpy arrays and torch tensors.

One definition for the whole project: ground-truth PNGs, env-map previews, prediction reading and
albedo scoring must agree on the curve to the last bit.
"""
from __future__ import annotations

import numpy as np


def srgb_to_linear(x):
    """IEC 61966-2-1 decoding: c / 12.92 up to 0.04045, else ((c + 0.055) / 1.055) ** 2.4."""
    if hasattr(x, "detach"):
        import torch

        hi = ((x.clamp(min=0.04045) + 0.055) / 1.055) ** 2.4
        return torch.where(x <= 0.04045, x / 12.92, hi)
    x = np.asarray(x, dtype=np.float64) if not np.issubdtype(np.asarray(x).dtype, np.floating) else np.asarray(x)
    hi = ((np.maximum(x, 0.04045) + 0.055) / 1.055) ** 2.4
    return np.where(x <= 0.04045, x / 12.92, hi)


def linear_to_srgb(x):
    """IEC 61966-2-1 encoding: 12.92 l up to 0.0031308, else 1.055 l ** (1 / 2.4) - 0.055."""
    if hasattr(x, "detach"):
        import torch

        hi = 1.055 * x.clamp(min=0.0031308) ** (1.0 / 2.4) - 0.055
        return torch.where(x <= 0.0031308, 12.92 * x, hi)
    x = np.asarray(x, dtype=np.float64) if not np.issubdtype(np.asarray(x).dtype, np.floating) else np.asarray(x)
    hi = 1.055 * np.maximum(x, 0.0031308) ** (1.0 / 2.4) - 0.055
    return np.where(x <= 0.0031308, 12.92 * x, hi)
