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

By position alone. Session 29 chose the nodes and neighbours in position and motion (the network's offsets at
five times): the moving-object gap came out smaller on all five scenes under city (seed 0), but under
sunrise, three seeds each of hook and the mouse, it was even on average and cost hook albedo on two seeds
(mean -0.34 dB); taken out in session 30 (BENCHMARKS.md, "The nodes in position and motion over three seeds").
"""
from __future__ import annotations

import numpy as np
import torch

from lumibench.errors import UserError

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


def row_softmax(a: torch.Tensor) -> torch.Tensor:
    """Softmax along the last axis, written out: torch's own along a short last axis (4 nodes, 10 motion bases)
    took 2.3 ms (4 columns) and 5-9 ms (10) forward + backward at 20k rows on one thread, these ops 0.9 and 1.5
    (BENCHMARKS.md, issue 23). The max is a shift the result does not depend on."""
    e = torch.exp(a - a.detach().amax(-1, keepdim=True))
    return e / e.sum(-1, keepdim=True)


class MotionNodes:
    """Where the deformation field is read (``count`` nodes) and how each Gaussian blends them."""

    def __init__(self, count: int):
        if count < 1:
            raise ValueError(f"MotionNodes needs at least one node (got {count})")
        self.count = int(count)
        self.nodes: torch.Tensor | None = None   # (M, 3) normalised canonical positions
        self.sigma: torch.Tensor | None = None   # (M,)
        self.index: torch.Tensor | None = None   # (N, K) each Gaussian's nearest nodes
        self._near: tuple[torch.Tensor, torch.Tensor] | None = None  # nodes[index], sigma[index]: fixed per choice
        self._near_f64: tuple | None = None  # the same (and index) as numpy arrays for the compiled blend

    def stale(self, n: int) -> bool:
        return self.index is None or self.index.shape[0] != n

    @torch.no_grad()
    def choose(self, x: torch.Tensor) -> None:
        """Nodes from the normalised canonical means ``x`` (N, 3); each row's nearest nodes."""
        x = x.detach()
        nodes = x[farthest_points(x, self.count)].clone()
        m = nodes.shape[0]
        if m > 1:
            d, _ = nearest(nodes, nodes, min(4, m))
            sigma = d[:, 1:].mean(-1)  # column 0 is the node itself
        else:
            sigma = torch.ones(1, dtype=x.dtype, device=x.device)
        self.nodes, self.sigma = nodes, sigma.clamp_min(1e-6)
        self.index = nearest(x, nodes, K_NEIGHBOURS)[1]
        self._near = self._near_f64 = None

    def weights(self, x: torch.Tensor) -> torch.Tensor:
        """(N, K) blend weights of each row of ``x`` over its nearest nodes (rows sum to 1)."""
        nb, s = self.weights_constants()                  # (N, K, 3), (N, K): constants until the next choice
        d2 = ((x[:, None, :] - nb) ** 2).sum(-1)          # (N, K)
        return row_softmax(-d2 / (2.0 * s * s))

    def blend(self, values: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        """(N, C): each row's weighted sum of its nodes' ``values`` (M, C). One index_select of the
        flattened (N K) index: its backward is an index_add, where indexing with the (N, K) index
        accumulates through a sort (BENCHMARKS.md, issue 23, session 39)."""
        n, k = self.index.shape
        picked = values.index_select(0, self.index.reshape(-1)).view(n, k, values.shape[1])
        return (picked * w[..., None]).sum(1)

    def blend_all(self, values: tuple[torch.Tensor, ...], w: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """``blend`` of several (M, C_i) outputs at once: one gather and one product for all of them."""
        out = self.blend(torch.cat(values, 1), w)
        return out.split([v.shape[1] for v in values], 1)

    def blend_outputs(self, x: torch.Tensor, values: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, ...]:
        """``blend_all(values, weights(x))``: by the compiled kernel (method/model/blend_numba.py) where the
        splat backend resolves to Numba (CPU tensors), by the torch reference otherwise (CUDA)."""
        from method.splat.backend import resolve

        if resolve(None, x.device) != "numba":
            return self.blend_all(values, self.weights(x))
        from method.model.blend_numba import as_f64, blend_at_nodes

        if self._near_f64 is None:
            nb, s = self.weights_constants()
            self._near_f64 = (np.ascontiguousarray(self.index.cpu().numpy().astype(np.int64)), as_f64(nb), as_f64(s))
        out = blend_at_nodes(x, torch.cat(values, 1), *self._near_f64)
        return out.split([v.shape[1] for v in values], 1)

    def weights_constants(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(nodes[index] (N, K, 3), sigma[index] (N, K)): gathered once per choice."""
        if self._near is None:
            self._near = (self.nodes[self.index], self.sigma[self.index])
        return self._near

    def state(self) -> dict:
        return {"count": self.count, "nodes": None if self.nodes is None else self.nodes.cpu(),
                "sigma": None if self.sigma is None else self.sigma.cpu(),
                "index": None if self.index is None else self.index.cpu()}

    @staticmethod
    def from_state(st: dict, device) -> "MotionNodes":
        if st.get("motion") is not None:  # session 29's placement: its weights had a motion term this one lacks
            raise UserError("checkpoint: its nodes were chosen in position and motion (session 29's code), this "
                            "version chooses them by position; train the run again")
        mn = MotionNodes(st["count"])
        for k in ("nodes", "sigma", "index"):
            if st.get(k) is not None:
                setattr(mn, k, st[k].to(device))
        return mn
