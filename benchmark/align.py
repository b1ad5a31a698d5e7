"""Albedo alignment and sRGB transfer curves.

Albedo is only recoverable up to a per-channel scale (light intensity and surface colour trade off), so
predictions are aligned to ground truth before scoring, as IRGS and TensoIR do: the per-channel median of
gt / pred over the foreground pixels of all test views, in linear space. A median (not a least-squares fit)
keeps a few wrong pixels from moving the scale.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from lumibench.color import linear_to_srgb, srgb_to_linear  # noqa: F401  (re-exported: part of this API)
from lumibench.errors import UserError

PRED_EPS = 1e-6  # predicted values at or below this carry no ratio information


def _np(x, name: str) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3:
        raise UserError(f"{name}: expected an H x W x C array, got shape {arr.shape}")
    return arr


def albedo_scale(preds: Sequence, gts: Sequence, masks: Sequence, eps: float = PRED_EPS) -> np.ndarray:
    """Per-channel median of gt / pred over the foreground of all views -> (3,) float64.

    ``preds`` and ``gts`` are lists of H x W x 3 linear albedo images (numpy or torch), ``masks`` a list of
    H x W (or H x W x 1) foreground masks; coverage values count as foreground above 0.5. Pixels whose
    predicted channel is <= ``eps`` are skipped for that channel.
    """
    if not (len(preds) == len(gts) == len(masks)):
        raise UserError(f"albedo alignment needs as many predictions, ground truths and masks; got "
                        f"{len(preds)}, {len(gts)}, {len(masks)}")
    if len(preds) == 0:
        raise UserError("albedo alignment needs at least one view")
    ratios: list[list[np.ndarray]] = [[], [], []]
    for v, (p, g, m) in enumerate(zip(preds, gts, masks)):
        p, g, m = _np(p, f"prediction {v}"), _np(g, f"ground truth {v}"), _np(m, f"mask {v}")
        if p.shape != g.shape or p.shape[-1] != 3:
            raise UserError(f"view {v}: prediction {p.shape} and ground truth {g.shape} must both be H x W x 3")
        if m.shape != p.shape[:2] + (1,):
            raise UserError(f"view {v}: mask {m.shape} does not fit image {p.shape}")
        fg = m[..., 0] > 0.5
        for c in range(3):
            pc, gc = p[..., c][fg], g[..., c][fg]
            ok = (pc > eps) & np.isfinite(pc) & np.isfinite(gc)
            ratios[c].append(gc[ok] / pc[ok])
    scale = np.empty(3)
    for c in range(3):
        r = np.concatenate(ratios[c])
        if r.size == 0:
            raise UserError(f"albedo alignment: channel {'RGB'[c]} has no foreground pixel with a non-zero prediction")
        scale[c] = np.median(r)
    return scale


def apply_scale(pred, scale):
    """``pred * scale`` per channel, clipped to [0, 1]; numpy or torch (same kind and device out)."""
    if hasattr(pred, "detach"):
        import torch

        s = torch.as_tensor(np.asarray(scale), dtype=pred.dtype, device=pred.device)
        return (pred * s).clamp(0.0, 1.0)
    return np.clip(np.asarray(pred) * np.asarray(scale, dtype=np.float64), 0.0, 1.0)
