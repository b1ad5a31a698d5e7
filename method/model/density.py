"""Adaptive density control (3DGS / 2DGS): clone small Gaussians and split large ones where the
screen-space positional gradient is high, prune transparent or oversized ones, reset opacities.

A cap on the Gaussian count (``max_gaussians``) keeps the model no larger than the profile allows:
when the candidates would exceed it, those with the highest gradients are taken first.
"""
from __future__ import annotations

import torch

from method.splat.splats import quat_to_rotmat

from .gaussians import GaussianAdam, Gaussians, inverse_sigmoid


class DensityStats:
    """Running mean of the screen-space gradient norm per Gaussian (in NDC units, as the 3DGS threshold)."""

    def __init__(self, n: int, device="cpu"):
        self.grad = torch.zeros(n, device=device)
        self.count = torch.zeros(n, device=device)
        self.max_radii = torch.zeros(n, device=device)

    def add(self, offset_grad: torch.Tensor, visible: torch.Tensor, radii: torch.Tensor, width: int, height: int):
        g = offset_grad.detach() * torch.tensor([0.5 * width, 0.5 * height], device=offset_grad.device)
        self.grad[visible] += g[visible].norm(dim=-1)
        self.count[visible] += 1
        self.max_radii[visible] = torch.maximum(self.max_radii[visible], radii.detach()[visible].float())

    def mean(self) -> torch.Tensor:
        return self.grad / self.count.clamp_min(1)

    def reset(self, n: int):
        dev = self.grad.device
        self.grad, self.count, self.max_radii = (torch.zeros(n, device=dev), torch.zeros(n, device=dev),
                                                 torch.zeros(n, device=dev))

    def state(self) -> dict:
        return {"grad": self.grad.cpu(), "count": self.count.cpu(), "max_radii": self.max_radii.cpu()}

    def load(self, st: dict):
        dev = self.grad.device
        self.grad, self.count, self.max_radii = st["grad"].to(dev), st["count"].to(dev), st["max_radii"].to(dev)


def _rows(g: Gaussians, idx: torch.Tensor) -> dict[str, torch.Tensor]:
    return {k: v.detach()[idx].clone() for k, v in g.t.items()}


def densify_and_prune(g: Gaussians, opt: GaussianAdam, stats: DensityStats, *, grad_threshold: float,
                      percent_dense: float, extent: float, min_opacity: float, max_gaussians: int,
                      max_screen_radius: float | None, generator: torch.Generator) -> dict[str, int]:
    """One density-control step; returns the counts of cloned, split and pruned Gaussians."""
    n0 = len(g)
    grads = stats.mean()
    grads = torch.where(torch.isfinite(grads), grads, torch.zeros_like(grads))
    scales = g.scales.detach()
    big = scales.max(-1).values > percent_dense * extent
    cand = grads >= grad_threshold
    clone_idx = torch.nonzero(cand & ~big).squeeze(1)
    split_idx = torch.nonzero(cand & big).squeeze(1)
    # the cap: each clone adds one Gaussian, each split one net (two replace one); highest gradients first
    if max_gaussians > 0:
        room = max(0, max_gaussians - n0)
        if clone_idx.numel() + split_idx.numel() > room:
            idx = torch.cat([clone_idx, split_idx])
            order = torch.argsort(grads[idx], descending=True, stable=True)[:room]
            chosen = torch.zeros(n0, dtype=torch.bool, device=grads.device)
            chosen[idx[order]] = True
            clone_idx = torch.nonzero(chosen & ~big).squeeze(1)
            split_idx = torch.nonzero(chosen & big).squeeze(1)

    # clone: an identical copy (the two then separate under their own gradients)
    new_rows = [_rows(g, clone_idx)]
    # split: two samples inside the splat's disc, scales shrunk by 1.6 (3DGS's 0.8 * 2)
    if split_idx.numel():
        rows = _rows(g, split_idx)

        rot = quat_to_rotmat(rows["quats"])
        s = torch.exp(rows["log_scales"])
        for _ in range(2):
            z = torch.randn(s.shape, generator=generator).to(s.device) * s
            offs = rot[:, :, 0] * z[:, :1] + rot[:, :, 1] * z[:, 1:2]
            r = {k: v.clone() for k, v in rows.items()}
            r["means"] = rows["means"] + offs
            r["log_scales"] = rows["log_scales"] - torch.log(torch.tensor(1.6))
            new_rows.append(r)
    added = {k: torch.cat([r[k] for r in new_rows]) for k in g.t}
    n_new = int(added["means"].shape[0])
    if n_new:
        opt.append(added)
        stats.grad = torch.cat([stats.grad, torch.zeros(n_new, device=stats.grad.device)])
        stats.count = torch.cat([stats.count, torch.zeros(n_new, device=stats.count.device)])
        stats.max_radii = torch.cat([stats.max_radii, torch.zeros(n_new, device=stats.max_radii.device)])

    n1 = len(g)
    prune = torch.zeros(n1, dtype=torch.bool, device=grads.device)
    prune[split_idx] = True  # the split originals
    prune |= g.opacities.detach() < min_opacity
    if max_screen_radius is not None:
        prune |= stats.max_radii > max_screen_radius
        prune |= g.scales.detach().max(-1).values > 0.1 * extent
    if bool(prune.all()):  # never prune everything
        prune[:] = False
    keep = ~prune
    opt.keep(keep)
    stats.reset(len(g))
    return {"cloned": int(clone_idx.numel()), "split": int(split_idx.numel()), "pruned": int(prune.sum())}


def reset_opacity(g: Gaussians, opt: GaussianAdam, value: float = 0.01) -> None:
    """Clamp every opacity to at most ``value`` (3DGS): Gaussians that matter recover, floaters are pruned."""
    o = torch.minimum(g.opacities.detach(), torch.full_like(g.opacities.detach(), value))
    opt.reset_values("opacity_logit", inverse_sigmoid(o))
