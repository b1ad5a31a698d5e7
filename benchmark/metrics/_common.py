"""Input handling shared by the metrics: numpy or torch H x W x C images and optional masks, as torch."""
from __future__ import annotations

from typing import Any

from lumibench.errors import UserError


def as_image(x: Any, name: str, dtype=None):
    """Return ``x`` (numpy array or torch tensor, H x W x C or H x W) as a torch tensor H x W x C.

    Torch inputs keep their device; numpy inputs land on the CPU. ``dtype`` defaults to float64 so that
    the reference comparisons (scikit-image works in float64) hold to 1e-6.
    """
    import numpy as np
    import torch

    dtype = dtype or torch.float64
    if isinstance(x, torch.Tensor):
        t = x.detach().to(dtype)
    else:
        try:
            t = torch.from_numpy(np.asarray(x, dtype=np.float64)).to(dtype)
        except (TypeError, ValueError) as exc:
            raise UserError(f"{name}: not a numeric image ({exc})") from None
    if t.ndim == 2:
        t = t[..., None]
    if t.ndim != 3:
        raise UserError(f"{name}: expected an H x W x C image, got shape {tuple(t.shape)}")
    return t


def check_pair(pred, gt, dtype=None):
    """Convert a prediction/ground-truth pair, requiring equal shapes and finite values; gt moves to pred's device."""
    import torch

    p = as_image(pred, "prediction", dtype)
    g = as_image(gt, "ground truth", dtype).to(p.device)
    if p.shape != g.shape:
        raise UserError(f"image sizes differ: prediction {tuple(p.shape)} vs ground truth {tuple(g.shape)}")
    # A NaN would silently poison every mean downstream; name it instead.
    for t, name in ((p, "prediction"), (g, "ground truth")):
        if not bool(torch.isfinite(t).all()):
            raise UserError(f"{name} image contains NaN or infinite values")
    return p, g


def as_mask(mask: Any, shape, device, dtype=None):
    """Return a mask as H x W x 1 weights (values in {0,1} or coverage in [0,1]), validated against ``shape``."""
    import numpy as np
    import torch

    dtype = dtype or torch.float64
    if isinstance(mask, torch.Tensor):
        m = mask.detach().to(device=device, dtype=dtype)
    else:
        m = torch.from_numpy(np.asarray(mask, dtype=np.float64)).to(device=device, dtype=dtype)
    if m.ndim == 2:
        m = m[..., None]
    if m.ndim != 3 or m.shape[-1] != 1 or tuple(m.shape[:2]) != tuple(shape[:2]):
        raise UserError(f"mask shape {tuple(m.shape)} does not fit image shape {tuple(shape)}; expected H x W or H x W x 1")
    if not bool(torch.isfinite(m).all()) or float(m.min()) < 0.0:
        raise UserError("mask has negative or non-finite values; expected {0,1} or coverage weights in [0,1]")
    if float(m.sum()) <= 0.0:
        raise UserError("mask is empty: no pixel to score")
    return m
