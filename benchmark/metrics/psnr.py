"""PSNR for images in [0, 1], optionally over a mask, in either channel-averaging convention.

Two conventions exist in the literature and they differ on coloured errors: the PSNR of the mean squared
error over all channels (the usual one), and the mean of per-channel PSNRs, which is what the published
LumiMotion / 3DGS evaluation code computes (its ``psnr`` flattens each channel separately).
"""
from __future__ import annotations

import math

from ._common import as_mask, check_pair


def mse(pred, gt, mask=None, per_channel: bool = False):
    """Mean squared error over the (weighted) masked pixels; a float, or a list per channel."""
    p, g = check_pair(pred, gt)
    sq = (p - g) ** 2
    if mask is None:
        per = sq.mean(dim=(0, 1))
    else:
        w = as_mask(mask, p.shape, p.device)
        per = (sq * w).sum(dim=(0, 1)) / w.sum()
    if per_channel:
        return [float(v) for v in per]
    return float(per.mean())


def _psnr_of(m: float) -> float:
    # Identical images have no finite PSNR; inf is the honest answer (callers writing JSON must handle it).
    return math.inf if m <= 0.0 else -10.0 * math.log10(m)


def psnr(pred, gt, mask=None, per_channel: bool = False) -> float:
    """PSNR in dB with data range 1.

    ``mask`` (H x W or H x W x 1, binary or coverage weights) restricts the error to the masked pixels.
    ``per_channel=True`` averages the channels' PSNRs instead of taking the PSNR of the pooled MSE.
    """
    if per_channel:
        return float(sum(_psnr_of(m) for m in mse(pred, gt, mask, per_channel=True)) / _channels(pred))
    return _psnr_of(mse(pred, gt, mask))


def _channels(x) -> int:
    shape = tuple(x.shape)
    return 1 if len(shape) == 2 else int(shape[-1])
