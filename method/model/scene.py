"""The dynamic scene: canonical 2D Gaussians, the deformation network (None for the static pipeline)
and the scene box that normalises positions for the network's encoding; ``deform`` gives the Gaussians
at one time (paper: mu' = mu + P dmu, r' = r + P dr, c' = c (1 - dc))."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from method import buffers
from method.buffers import STAGE1
from method.model.deform import DeformNet, binary_concrete
from method.model.gaussians import Gaussians
from method.model.motion_basis import MotionBasis
from method.model.nodes import MotionNodes
from method.splat.backend import on_the_kernels_threads
from method.splat.camera import Camera
from method.splat.rasterize import RasterOutput, rasterize


@dataclass
class Deformed:
    """The Gaussians at one time: what the rasterizer and the tracer consume, plus the deltas."""

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colours: torch.Tensor
    p: torch.Tensor          # the P used (sampled in training, u = 0.5 at inference; ones in warm-up)
    d_mu: torch.Tensor
    d_col: torch.Tensor


class DynamicScene:
    def __init__(self, gaussians: Gaussians, net: DeformNet | None, center: torch.Tensor, extent: float,
                 temperature: float = 0.5, delta_colour: bool = True, separation: bool = True):
        self.g = gaussians
        self.net = net
        self.center = center
        self.extent = float(extent)
        self.temperature = float(temperature)
        self.delta_colour = bool(delta_colour)  # False: the wo_dc ablation
        self.separation = bool(separation)      # False: the wo_P ablation (P = 1 always)
        self.model_cfg: dict = {}                # the config's model section, saved in checkpoints
        self.nodes: MotionNodes | None = None    # where the network is read (model.deform_nodes; None: every Gaussian)
        self.basis: MotionBasis | None = None    # rigid motion bases blended with the network's offset from the
                                                 # warm-up's end (model.motion_bases; None: the network alone)

    @property
    def static(self) -> bool:
        return self.net is None

    def normalised(self, means: torch.Tensor) -> torch.Tensor:
        """Positions as the network reads them: the scene box mapped to about [-1, 1]."""
        return (means - self.center.to(means)) / self.extent

    def refresh_nodes(self) -> None:
        """Re-choose the nodes from the current canonical means (no-op without nodes)."""
        if self.nodes is not None:
            self.nodes.choose(self.normalised(self.g.means))

    def field(self, x: torch.Tensor, t: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(d mu, d r, d c) at the normalised positions ``x`` (one row per Gaussian) and time ``t``: the
        network at every row, or at the nodes blended to every row (method/model/nodes.py)."""
        if self.nodes is None:
            return on_the_kernels_threads(self.net, x, t)
        if self.nodes.stale(x.shape[0]):
            self.nodes.choose(x)
        return self.nodes.blend_outputs(x, on_the_kernels_threads(self.net, self.nodes.nodes, t))

    def p_inference(self) -> torch.Tensor:
        return binary_concrete(self.g.t["p_logit"], self.temperature, training=False)

    def deform(self, t: float, *, p_mode: str = "inference", generator: torch.Generator | None = None,
               fixed_p: float | None = None, trunk_cache: dict | None = None) -> Deformed:
        """Gaussians at time ``t``. ``p_mode``: "sample" (training), "inference" (u = 0.5), "ones" (warm-up).

        ``trunk_cache`` (stage 2, where the canonical means, the network's trunk and its motion heads are
        frozen): the trunk's features and the motion per time are computed once and kept there; only the
        colour head runs each call. The same values as without it (the same operations, once)."""
        g = self.g
        means, quats, colours = g.means, g.quats, g.colours
        n = len(g)
        if self.net is None:
            zero = means.new_zeros(n, 3)
            return Deformed(means, quats, g.scales, g.opacities, colours, means.new_zeros(n), zero, zero)
        if fixed_p is not None:
            p = means.new_full((n,), float(fixed_p))
        elif not self.separation:
            p = means.new_ones(n)
        elif p_mode == "sample":
            p = binary_concrete(g.t["p_logit"], self.temperature, generator, training=True)
        elif p_mode == "ones":
            p = means.new_ones(n)
        else:
            p = self.p_inference()
        x = self.normalised(means)
        if trunk_cache is None:
            d_mu, d_rot, d_col = self.field(x, t)
        else:
            trainable = [n for n, q in self.net.named_parameters() if q.requires_grad and not n.startswith("d_col.")]
            if means.requires_grad or trainable:
                raise ValueError("trunk_cache needs frozen means, trunk and motion heads "
                                 f"(trainable: {', '.join(trainable + (['means'] if means.requires_grad else []))})")
            key = float(t)
            if key not in trunk_cache:
                with torch.no_grad():
                    if self.nodes is None:
                        h = self.net.trunk(x, t)
                        trunk_cache[key] = (h, *self.net.heads(h)[:2])
                    else:
                        if self.nodes.stale(n):
                            self.nodes.choose(x)
                        h = self.net.trunk(self.nodes.nodes, t)
                        trunk_cache[key] = (h, *self.nodes.blend_outputs(x, self.net.heads(h)[:2]))
            h, d_mu, d_rot = trunk_cache[key]
            d_col = self.net.heads(h)[2]  # the heads' one product, as uncached (the frozen ones cost nothing)
            if self.nodes is not None:  # blended as uncached: each output channel is blended on its own
                d_col = self.nodes.blend_outputs(x, (d_col,))[0]
        if self.basis is not None:
            d_mu, d_rot = self.basis.offsets(means, quats, g.t["basis_logit"], t, (d_mu, d_rot))
        if not self.delta_colour:
            d_col = torch.zeros_like(d_col)
        pc = p[:, None]
        return Deformed(means + pc * d_mu, quats + pc * d_rot, g.scales, g.opacities, colours * (1.0 - d_col),
                        p, d_mu, d_col)

    def num_parameters(self) -> int:
        return self.g.num_parameters() + (self.net.num_parameters() if self.net is not None else 0) + \
            (sum(q.numel() for q in self.basis.parameters()) if self.basis is not None else 0)


def render(d: Deformed, camera: Camera, background: torch.Tensor,
           screen_offsets: torch.Tensor | None = None, depth_ratio: float = 0.0) -> RasterOutput:
    """Rasterize the STAGE1 layout (colour, P); the background fills colour only. ``depth_ratio``: the depth
    of ``normal_from_depth``, expected (0) to median (1) (stage1.depth_ratio)."""
    f = buffers.pack(STAGE1, colour=d.colours, p=d.p)
    return rasterize(d.means, d.quats, d.scales, d.opacities, f, camera, buffers.background_for(STAGE1, background, f),
                     screen_offsets=screen_offsets, depth_ratio=depth_ratio)
