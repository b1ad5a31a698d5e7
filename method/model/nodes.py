"""The deformation field read at a few sample points (nodes) and blended to every Gaussian.

Why: the network's forward and backward at every Gaussian is about two thirds of a `small` stage-1
iteration on the CPU (BENCHMARKS.md). The field it learns is smooth in space (a 6-frequency encoding of
the canonical position), so evaluating it at M nodes spread over the Gaussians and blending the K
nearest nodes' outputs at each Gaussian gives nearly the same field for a fifth of the products at
`small` (4,096 nodes for 20k Gaussians; the control-point idea of SC-GS, Huang et al. 2024, with the
paper's network as the field: the nodes are only where it is read, so re-choosing them does not change
what was learned).

Nodes: farthest-point sampling of the canonical means (a deterministic start), re-chosen whenever the
Gaussian count changes and every ``REFRESH_EVERY`` stage-1 iterations (the means drift). Each Gaussian's
K nearest nodes are fixed between re-choices; the blend weights are a softmax of -d^2 / (2 sigma_j^2) over
them, computed from the current means at every call, so positions keep a gradient through the weights as
they had one through the encoding. sigma_j: the mean distance from node j to its 3 nearest nodes.

The choice and the neighbours are taken in the joint space of position and motion (``DynamicScene`` passes
each Gaussian's offsets at five times about their mean, from the network as it stands): a small object that
moves unlike the ground it touches gets nodes of its own and blends only them, where by position alone its
Gaussians blended the ground's nodes and trailed along its path (BENCHMARKS.md, session 29: the benchmark's
moving-object gap smaller on all five scenes trained under city, by 0.2-0.6 dB; under sunrise, stage 1,
hook +1.1 dB and the mouse -0.6 dB on its moving objects; one seed each).
"""
from __future__ import annotations

import torch

K_NEIGHBOURS = 4      # nodes blended at each Gaussian (SC-GS: 4)
REFRESH_EVERY = 500   # stage-1 iterations between re-choices of the nodes (also at every count change)


@torch.no_grad()
def farthest_points(x: torch.Tensor, m: int) -> torch.Tensor:
    """Indices of ``m`` rows of ``x`` (N, D) by farthest-point sampling from row 0 (all rows if m >= N).
    Squared distances as |x|^2 - 2 x.x_last + |x_last|^2: one matrix-vector product per pick (at `small`,
    20k means and 4,096 picks, about a second on one core beside two trainings). Each pick is read on the
    host: keeping it a device tensor instead was timed on an idle H200 and gained nothing (0.43 s against
    0.40 s per 4,096 picks of 20k points; BENCHMARKS.md, session 30)."""
    n = x.shape[0]
    if m >= n:
        return torch.arange(n, device=x.device)
    idx = torch.empty(m, dtype=torch.long, device=x.device)
    sq = (x * x).sum(-1)
    dist = torch.full((n,), float("inf"), dtype=x.dtype, device=x.device)
    last = 0
    for i in range(m):
        idx[i] = last
        torch.minimum(dist, sq - 2.0 * (x @ x[last]) + sq[last], out=dist)
        last = int(dist.argmax())
    return idx


@torch.no_grad()
def nearest(x: torch.Tensor, nodes: torch.Tensor, k: int, chunk: int = 8192) -> tuple[torch.Tensor, torch.Tensor]:
    """(distances, indices) of the ``k`` nearest ``nodes`` to each row of ``x``, nearest first, chunked."""
    k = min(k, nodes.shape[0])
    ds, ix = [], []
    for i in range(0, x.shape[0], chunk):
        d = torch.cdist(x[i:i + chunk], nodes)
        v, j = d.topk(k, largest=False)
        ds.append(v)
        ix.append(j)
    return torch.cat(ds), torch.cat(ix)


class MotionNodes:
    """Where the deformation field is read (``count`` nodes) and how each Gaussian blends them."""

    def __init__(self, count: int):
        if count < 1:
            raise ValueError(f"MotionNodes needs at least one node (got {count})")
        self.count = int(count)
        self.nodes: torch.Tensor | None = None   # (M, 3) normalised canonical positions
        self.sigma: torch.Tensor | None = None   # (M,)
        self.index: torch.Tensor | None = None   # (N, K) each Gaussian's nearest nodes
        self.motion: torch.Tensor | None = None  # (N, D) each Gaussian's motion descriptor at the choice (or None)
        self.node_motion: torch.Tensor | None = None  # (M, D) the nodes' descriptors

    def stale(self, n: int) -> bool:
        return self.index is None or self.index.shape[0] != n

    @torch.no_grad()
    def choose(self, x: torch.Tensor, motion: torch.Tensor | None = None) -> None:
        """Nodes from the normalised canonical means ``x`` (N, 3); each row's nearest nodes. ``motion`` (N, D):
        each row's motion descriptor (its offsets at a few times about their mean, normalised like ``x``); the
        choice and the neighbours are then taken in the joint space of position and motion, so a small object
        that moves unlike the ground beside it gets nodes of its own and blends only them."""
        x = x.detach()
        feat = x if motion is None else torch.cat([x, motion.detach().to(x)], -1)
        pick = farthest_points(feat, self.count)
        nodes_f = feat[pick].clone()
        m = nodes_f.shape[0]
        if m > 1:
            d, _ = nearest(nodes_f, nodes_f, min(4, m))
            sigma = d[:, 1:].mean(-1)  # column 0 is the node itself
        else:
            sigma = torch.ones(1, dtype=x.dtype, device=x.device)
        self.nodes, self.sigma = nodes_f[:, :3].contiguous(), sigma.clamp_min(1e-6)
        self.motion = None if motion is None else motion.detach().to(x).clone()
        self.node_motion = None if motion is None else nodes_f[:, 3:].contiguous()
        self.index = nearest(feat, nodes_f, K_NEIGHBOURS)[1]

    def weights(self, x: torch.Tensor) -> torch.Tensor:
        """(N, K) blend weights of each row of ``x`` over its nearest nodes (rows sum to 1)."""
        nb = self.nodes[self.index]                       # (N, K, 3)
        d2 = ((x[:, None, :] - nb) ** 2).sum(-1)          # (N, K)
        if self.motion is not None:
            d2 = d2 + ((self.motion[:, None, :] - self.node_motion[self.index]) ** 2).sum(-1)
        s = self.sigma[self.index]
        return torch.softmax(-d2 / (2.0 * s * s), dim=-1)

    def blend(self, values: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        """(N, C): each row's weighted sum of its nodes' ``values`` (M, C)."""
        return (values[self.index] * w[..., None]).sum(1)

    def state(self) -> dict:
        return {"count": self.count, **{k: None if getattr(self, k) is None else getattr(self, k).cpu()
                                        for k in ("nodes", "sigma", "index", "motion", "node_motion")}}

    @staticmethod
    def from_state(st: dict, device) -> "MotionNodes":
        mn = MotionNodes(st["count"])
        for k in ("nodes", "sigma", "index", "motion", "node_motion"):
            if st.get(k) is not None:
                setattr(mn, k, st[k].to(device))
        return mn
