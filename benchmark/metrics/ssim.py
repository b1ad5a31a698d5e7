"""SSIM with an 11-tap Gaussian window (sigma 1.5), population covariance, data range 1.

Matches scikit-image's ``structural_similarity(..., gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=1, channel_axis=-1)``: scikit-image filters with reflect padding but
then crops ``(win - 1) // 2`` = 5 pixels from every border before averaging, so only windows lying wholly
inside the image count. We compute exactly those windows (a 'valid' convolution), in float64.
"""
from __future__ import annotations

import math

from lumibench.errors import UserError

from ._common import as_mask, check_pair

SIGMA = 1.5
TRUNCATE = 3.5  # scipy.ndimage's default; radius int(3.5 * 1.5 + 0.5) = 5 gives the 11-tap window
RADIUS = int(TRUNCATE * SIGMA + 0.5)
WIN = 2 * RADIUS + 1
K1, K2 = 0.01, 0.03
DATA_RANGE = 1.0


def _kernel(dtype, device):
    import torch

    x = torch.arange(-RADIUS, RADIUS + 1, dtype=dtype, device=device)
    k = torch.exp(-0.5 * (x / SIGMA) ** 2)
    return k / k.sum()


def _blur_valid(x, k):
    """Separable Gaussian blur of (N, H, W) without padding -> (N, H - 10, W - 10).

    On the CPU scipy's 1-D correlation is used (about 10x faster than torch's float64 conv2d); on other
    devices, conv2d. Only windows wholly inside the image are kept, so the padding mode never matters.
    """
    if x.device.type != "cpu":
        return _blur_valid_conv(x, k)
    import torch
    from scipy.ndimage import correlate1d

    kk = k.numpy()
    y = correlate1d(x.numpy(), kk, axis=-2, mode="constant")
    y = correlate1d(y, kk, axis=-1, mode="constant")
    return torch.from_numpy(y[:, RADIUS:-RADIUS, RADIUS:-RADIUS])


def _blur_valid_conv(x, k):
    import torch.nn.functional as F

    y = F.conv2d(x.unsqueeze(1), k.view(1, 1, 1, -1))
    return F.conv2d(y, k.view(1, 1, -1, 1)).squeeze(1)


def _ssim_map_t(p, g):
    """SSIM map of H x W x C tensors over the valid region, as (H - 10) x (W - 10) x C."""
    import torch

    h, w, _ = p.shape
    if h < WIN or w < WIN:
        raise UserError(f"image of {h} x {w} pixels is too small for SSIM; it needs at least {WIN} x {WIN}")
    k = _kernel(p.dtype, p.device)
    x = p.permute(2, 0, 1)
    y = g.permute(2, 0, 1)
    ux, uy, uxx, uyy, uxy = _blur_valid(torch.stack([x, y, x * x, y * y, x * y]).flatten(0, 1), k).unflatten(0, (5, -1))
    vx = uxx - ux * ux
    vy = uyy - uy * uy
    vxy = uxy - ux * uy
    c1 = (K1 * DATA_RANGE) ** 2
    c2 = (K2 * DATA_RANGE) ** 2
    s = ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2))
    return s.permute(1, 2, 0)


def ssim_map(pred, gt):
    """Per-pixel, per-channel SSIM over the valid region: (H - 10) x (W - 10) x C.

    Pixel (i, j) of the map is the window centred on image pixel (i + 5, j + 5). Returns a torch tensor
    for torch inputs (on their device) and a float64 numpy array otherwise.
    """
    import torch

    p, g = check_pair(pred, gt)
    s = _ssim_map_t(p, g)
    return s if isinstance(pred, torch.Tensor) else s.cpu().numpy()


def ssim(pred, gt, mask=None) -> float:
    """Mean SSIM (over pixels and channels). With ``mask`` (H x W or H x W x 1, binary or coverage weights),
    the weighted mean of the SSIM map over the masked pixels of the valid region (the same 5-pixel border is
    dropped, so an all-ones mask gives exactly the unmasked value)."""
    p, g = check_pair(pred, gt)
    s = _ssim_map_t(p, g)
    if mask is None:
        return float(s.mean())
    w = as_mask(mask, p.shape, p.device)[RADIUS:-RADIUS, RADIUS:-RADIUS]
    total = float(w.sum())
    if total <= 0.0:
        raise UserError(f"mask covers only the {RADIUS}-pixel border, where SSIM is undefined")
    value = float((s * w).sum()) / (total * s.shape[-1])
    return value if math.isfinite(value) else float("nan")
