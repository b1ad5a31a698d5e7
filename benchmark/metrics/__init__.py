"""Image metrics of the benchmark: PSNR, SSIM and LPIPS (VGG, AlexNet), numpy or torch H x W x C in [0, 1].

Importing this package does not import torch (it loads on first use). The submodules are imported here,
eagerly, so that the names ``lpips``, ``psnr`` and ``ssim`` below are always the functions: a later
``import benchmark.metrics.lpips`` would otherwise rebind the package attribute to the module. (To reach a submodule itself, use
``from benchmark.metrics.ssim import ...`` or ``sys.modules``; ``import benchmark.metrics.ssim as m`` yields
the function.)
"""
from __future__ import annotations

from .lpips import get_model, lpips, lpips_to_one
from .lpips_weights import lpips_weights_info
from .psnr import mse, psnr
from .ssim import ssim, ssim_map


def __getattr__(name):
    if name == "LPIPSModel":  # built on first use so that torch loads lazily
        import importlib

        return importlib.import_module(f"{__name__}.lpips").LPIPSModel
    raise AttributeError(name)


__all__ = ["mse", "psnr", "ssim", "ssim_map", "lpips", "lpips_to_one", "get_model", "lpips_weights_info", "LPIPSModel"]
