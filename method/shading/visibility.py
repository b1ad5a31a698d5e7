"""Visibility V and indirect light for shade(), traced against the 2D Gaussians (method/splat/trace.py).

Rays start at x + offset * l (the paper: 0.05..0.1 scene units) so a surface point does not shadow
itself with the splats it lies on; hits with alpha < 0.01 are skipped and marching stops once the
transmittance is below 0.03 (DESIGN.md, Reference values; trace()'s defaults). V is the transmittance
along the ray. Indirect light is what the blocking splats show: their colours composited front to back
(stage-1 colours, sRGB-decoded). shade() weights indirect by 1 - V, so ``indirect`` returns the
composite divided by its coverage 1 - T, and V env + (1 - V) indirect is T env + sum_i alpha_i T_i c_i.
"""
from __future__ import annotations

import torch

from lumibench.color import srgb_to_linear
from method.splat.trace import TraceAccel, trace

ALPHA_MIN = 0.01  # the tracer's alpha cut (trace()'s default; the grid is built with it)


def build_accel(means, quats, scales, opacities, cell_factor: float = 1.0) -> TraceAccel:
    """The tracer grid of splats at one time; cells of ``cell_factor`` x the median support radius
    (stage2.trace_cell: trained scenes mix a few large splats with many small ones, and at 0.5 those
    large splats fill so many cells that one build cost 7 s, BENCHMARKS.md)."""
    with torch.no_grad():
        return TraceAccel.build(means, quats, scales, opacities, alpha_min=ALPHA_MIN, cell_factor=cell_factor)


class GaussianTracer:
    """Callables ``visibility(origins, dirs) -> (R,)`` and ``indirect(origins, dirs) -> (R, 3)`` for shade(),
    sharing one traversal per batch of rays (shade() asks for V, then for the indirect light of the same rays).

    means (N, 3), quats (N, 4), scales (N, 2), opacities (N,) as for the rasterizer, at the frame's time;
    gradients flow to the opacities and colours, not to the geometry. ``colours_srgb`` (N, 3) in [0, 1] or
    None (visibility only); or ``radiance`` (N, 3k) linear, what each Gaussian sends out (relighting: the
    Gaussians relit under k maps, deferred.relit_radiance). ``offset``: ray start offset in scene units;
    ``extent``: the scene's size, which the caller's normal lift scales with (both default from the splat
    centres' largest extent: 0.02 x it for the offset). ``accel``: a grid from ``build_accel`` over these
    splats, reused while the geometry is fixed. ``replay``: rays of a second pass that repeat an earlier pass's rays in the same order (one view
    relit under several maps with the same directions) reuse its traversals (call ``rewind`` between passes).
    """

    def __init__(self, means, quats, scales, opacities, colours_srgb=None, *, offset: float | None = None,
                 extent: float | None = None, accel: TraceAccel | None = None, replay: bool = False,
                 radiance: torch.Tensor | None = None):
        self.means, self.quats, self.scales = means.detach(), quats.detach(), scales.detach()
        self.opacities = opacities
        if colours_srgb is not None and radiance is not None:
            raise ValueError("give the Gaussians' colours_srgb or their radiance, not both")
        self.colours_linear = radiance if colours_srgb is None else srgb_to_linear(colours_srgb.clamp(0, 1))
        if extent is None or offset is None:
            with torch.no_grad():
                ext = (means.max(0).values - means.min(0).values).max() if means.shape[0] else means.new_tensor(1.0)
            extent = max(float(ext), 1e-6) if extent is None else extent
            offset = 0.02 * extent if offset is None else offset
        if not offset >= 0.0:
            raise ValueError(f"offset must be >= 0, got {offset}")
        self.offset, self.extent = float(offset), float(extent)
        self.accel = accel if accel is not None else build_accel(self.means, self.quats, self.scales, opacities)
        self.rays = 0
        self.replay = replay
        self._key = None
        self._val = None
        self._log: list = []
        self._pos = 0

    @property
    def use_indirect(self) -> bool:
        return self.colours_linear is not None

    def rewind(self) -> None:
        self._pos = 0

    def _trace(self, o, dirs):
        if self._key is not None and self._key[0] is o and self._key[1] is dirs:
            return self._val
        if self.replay and self._pos < len(self._log):
            po, pd, val = self._log[self._pos]
            if po.shape == o.shape and torch.equal(po, o) and torch.equal(pd, dirs):
                self._pos += 1
                self._key, self._val = (o, dirs), val
                return val
        T, comp = trace(self.means, self.quats, self.scales, self.opacities, self.colours_linear,
                        o + self.offset * dirs, dirs, accel=self.accel)
        self.rays += o.shape[0]
        self._key, self._val = (o, dirs), (T, comp)
        if self.replay:
            self._log.append((o, dirs, (T, comp)))
            self._pos = len(self._log)
        return T, comp

    def visibility(self, o: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        return self._trace(o, dirs)[0]

    def indirect(self, o: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        if self.colours_linear is None:
            raise ValueError("GaussianTracer was built without colours: no indirect light to trace")
        T, comp = self._trace(o, dirs)
        return comp / (1.0 - T).clamp_min(1e-4)[:, None]  # shade() weights it by (1 - V)


def lifted_points(pts: torch.Tensor, n: torch.Tensor, view: torch.Tensor, distance: float) -> torch.Tensor:
    """``pts`` moved ``distance`` along the normal turned to face the camera (``view`` points from the surface
    to the camera): shadow rays then start off the surface, so a flat splat floor does not shadow itself
    at grazing angles (stage2.normal_offset). ``distance`` 0: unchanged."""
    if distance <= 0.0:
        return pts
    facing = torch.where((n * view).sum(-1, keepdim=True) < 0, -n, n)
    return pts + distance * facing
