"""Image metrics of the benchmark: PSNR, SSIM and LPIPS (VGG, AlexNet), numpy or torch H x W x C in [0, 1].

Imports are lazy so that ``import benchmark.metrics`` stays cheap; torch loads on first use.
"""
from __future__ import annotations

from .psnr import mse, psnr
from .ssim import ssim, ssim_map


def lpips(pred, gt, net: str = "vgg", input_range: str = "[-1,1]") -> float:
    """LPIPS distance; see :func:`benchmark.metrics.lpips.lpips`."""
    from .lpips import lpips as _lpips

    return _lpips(pred, gt, net=net, input_range=input_range)


def lpips_weights_info(net: str = "vgg") -> dict:
    """Provenance of the LPIPS weights for result files; see :mod:`benchmark.metrics.lpips_weights`."""
    from .lpips_weights import lpips_weights_info as _info

    return _info(net)


def __getattr__(name):
    if name == "LPIPSModel":
        from .lpips import LPIPSModel

        return LPIPSModel
    raise AttributeError(name)


__all__ = ["mse", "psnr", "ssim", "ssim_map", "lpips", "lpips_weights_info", "LPIPSModel"]
