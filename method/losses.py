"""Stage-1 loss terms (paper "Training Loss", 2DGS), each a plain function of tensors.

Images are (H, W, C) in [0, 1]. SSIM here is the training loss: 11-tap Gaussian window (sigma 1.5),
zero padding, mean over the whole image, as 3DGS/2DGS train with (the benchmark's SSIM metric,
which crops borders like scikit-image, lives in benchmark/metrics).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

_C1, _C2 = 0.01 ** 2, 0.03 ** 2


def _window(dtype, device, size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    return g / g.sum()


def ssim(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two (H, W, C) images (zero-padded 11 x 11 Gaussian window), differentiable in ``img``
    (``ref`` is the target). By the compiled kernel (method/ssim_numba.py) where the splat backend resolves
    to Numba (CPU tensors), by the torch reference below otherwise."""
    from method.splat.backend import resolve

    if resolve(None, img.device) == "numba" and not ref.requires_grad:
        from method.ssim_numba import ssim_compiled

        return ssim_compiled(img, ref, _window(torch.float64, img.device))
    return ssim_torch(img, ref)


def ssim_torch(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """``ssim`` in torch (the blurs as grouped depthwise convolutions): the reference, and the CUDA path."""
    c = img.shape[-1]
    x = img.permute(2, 0, 1)[None]
    y = ref.permute(2, 0, 1)[None]
    g = _window(img.dtype, img.device)
    kx = g.view(1, 1, 1, -1).repeat(5 * c, 1, 1, 1)
    ky = g.view(1, 1, -1, 1).repeat(5 * c, 1, 1, 1)
    # the five blurred images as one grouped convolution pair over their stacked channels (each channel
    # is blurred on its own, as five separate calls would: one call instead of five, forward and backward)
    z = torch.cat([x, y, x * x, y * y, x * y], 1)
    z = F.conv2d(F.conv2d(z, kx, padding=(0, 5), groups=5 * c), ky, padding=(5, 0), groups=5 * c)
    mx, my, bxx, byy, bxy = z.split(c, 1)
    sxx = bxx - mx * mx
    syy = byy - my * my
    sxy = bxy - mx * my
    num = (2 * mx * my + _C1) * (2 * sxy + _C2)
    den = (mx * mx + my * my + _C1) * (sxx + syy + _C2)
    return (num / den).mean()


def colour_loss(img: torch.Tensor, ref: torch.Tensor, lambda_dssim: float) -> tuple[torch.Tensor, torch.Tensor]:
    """L_c = (1 - lambda) L1 + lambda (1 - SSIM); also returns the L1 term."""
    l1 = (img - ref).abs().mean()
    if lambda_dssim == 0:
        return l1, l1
    return (1 - lambda_dssim) * l1 + lambda_dssim * (1 - ssim(img, ref)), l1


def normal_consistency(rendered_normal: torch.Tensor, depth_normal: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """2DGS: mean over pixels of 1 - <n_rendered, n_from_depth * alpha> (alpha detached)."""
    surf = depth_normal * alpha.detach()[..., None]
    return (1.0 - (rendered_normal * surf).sum(-1)).mean()


def mask_bce(alpha: torch.Tensor, mask: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """L_o = -M log O - (1 - M) log(1 - O), mean over pixels."""
    o = alpha.clamp(eps, 1 - eps)
    return -(mask * torch.log(o) + (1 - mask) * torch.log(1 - o)).mean()


def p_l1(p: torch.Tensor) -> torch.Tensor:
    """L_P = mean |P|."""
    return p.abs().mean()


def mean_sq_norm(d: torch.Tensor) -> torch.Tensor:
    """L_dc and L_dmu: mean over Gaussians of the squared norm of the delta."""
    return (d * d).sum(-1).mean() if d.numel() else d.sum()


def psnr(img: torch.Tensor, ref: torch.Tensor) -> float:
    mse = float(((img - ref) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * float(torch.log10(torch.tensor(mse)))
