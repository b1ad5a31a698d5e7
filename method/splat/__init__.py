"""Differentiable 2D Gaussian rasterizer and ray tracer, pure PyTorch (CPU and CUDA).

    from method.splat import Camera, rasterize, trace, TraceAccel

Public names are imported lazily so that importing the package does not load torch.
"""
from __future__ import annotations

_EXPORTS = {
    "Camera": "camera", "rasterize": "rasterize", "RasterOutput": "rasterize", "normal_from_depth": "rasterize",
    "trace": "trace", "TraceAccel": "trace", "quat_to_rotmat": "splats",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
