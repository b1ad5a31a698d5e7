"""Visibility V and indirect light for shade(), traced against the 2D Gaussians (method/splat/trace.py).

Rays start at x + offset * l (the paper: 0.05..0.1 scene units) so a surface point does not shadow
itself with the splats it lies on; hits with alpha < 0.01 are skipped and marching stops once the
transmittance is below 0.03 (DESIGN.md, Reference values). V is the transmittance along the ray.
Indirect light is what the blocking splats show: their colours composited front to back (stage-1
colours, sRGB-decoded, in training; relit colours at inference). shade() weights indirect by 1 - V, so
``indirect`` returns the composite divided by its coverage 1 - T, and V env + (1 - V) indirect is exactly
T env + sum_i alpha_i T_i c_i.
"""
from __future__ import annotations

import torch

from lumibench.color import srgb_to_linear
from method.splat.trace import TraceAccel, trace

ALPHA_MIN = 0.01
T_MIN = 0.03
OFFSET_FRACTION = 0.02  # of the splat centres' largest extent: 0.05 in the benchmark's 2.6-unit scene box


class GaussianTracer:
    """Callables ``visibility(origins, dirs) -> (R,)`` and ``indirect(origins, dirs) -> (R, 3)`` for shade().

    means (N, 3), quats (N, 4), scales (N, 2), opacities (N,) as for the rasterizer, at the frame's time.
    colors (N, 3) or None (visibility only); sRGB in [0, 1] when ``colors_srgb`` (stage-1 colours), else
    linear. ``offset``: ray start offset in scene units (default OFFSET_FRACTION of the scene's extent).
    ``accel``: a TraceAccel built from these splats with alpha_min (TraceAccel.build), to reuse between
    calls and iterations while the geometry and opacities do not change. A call to ``indirect`` with the
    very tensors of the preceding ``visibility`` call reuses that trace (shade() calls them in this order).
    """

    def __init__(self, means, quats, scales, opacities, colors=None, *, colors_srgb: bool = True,
                 offset: float | None = None, alpha_min: float = ALPHA_MIN, T_min: float = T_MIN,
                 accel: TraceAccel | None = None):
        self.means, self.quats, self.scales, self.opacities = means, quats, scales, opacities
        if colors is not None:
            colors = srgb_to_linear(colors.clamp(0.0, 1.0)) if colors_srgb else colors
        self.features = colors
        if offset is None:
            with torch.no_grad():
                ext = (means.max(0).values - means.min(0).values).max() if means.shape[0] else means.new_tensor(1.0)
            offset = OFFSET_FRACTION * max(float(ext), 1e-6)
        if not offset >= 0.0:
            raise ValueError(f"offset must be >= 0, got {offset}")
        self.offset = float(offset)
        self.alpha_min, self.T_min = float(alpha_min), float(T_min)
        self.accel = accel if accel is not None else TraceAccel.build(means, quats, scales, opacities,
                                                                      alpha_min=self.alpha_min)
        self._last = None  # (origins, dirs, transmittance, composite)

    def trace(self, origins: torch.Tensor, dirs: torch.Tensor):
        """(transmittance (R,), composited linear colours (R, 3) or None) of rays from origins + offset dirs."""
        last = self._last
        if last is not None and last[0] is origins and last[1] is dirs:
            return last[2], last[3]
        start = origins + self.offset * dirs
        T, comp = trace(self.means, self.quats, self.scales, self.opacities, self.features, start, dirs,
                        alpha_min=self.alpha_min, T_min=self.T_min, accel=self.accel)
        self._last = (origins, dirs, T, comp)
        return T, comp

    def visibility(self, origins: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        return self.trace(origins, dirs)[0]

    def indirect(self, origins: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        if self.features is None:
            raise ValueError("GaussianTracer was built without colors: no indirect light to trace")
        T, comp = self.trace(origins, dirs)
        self._last = None  # the pair is consumed: do not keep the rays (and their graph) alive
        cover = (1.0 - T)[:, None]
        return torch.where(cover > 1e-4, comp / cover.clamp_min(1e-4), torch.zeros_like(comp))
