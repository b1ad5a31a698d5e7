"""The nodes' blend (method/model/nodes.py) as one compiled CPU kernel, forward and backward.

Why: in torch the blend is a dozen broadcast ops over (N, K, C) tensors with trailing dimensions of 3, 4
and 10 (the distances to the K = 4 nodes, their softmax, the gather, the weighted sum), which torch runs far
below memory speed: about 9 ms of a ~80 ms `small` stage-1 step at 20k Gaussians (BENCHMARKS.md, issue 23,
session 39). Per Gaussian they are ~100 flops. Here each Gaussian's weights and blended values are computed
in one pass (float64 inside), the backward in another; MotionNodes.weights + blend_all stay the reference
(and the CUDA path), and tests hold this one to it.

Model (as the reference): a = -|x - node_k|^2 / (2 sigma_k^2), w = softmax_k(a), out_c = sum_k w_k v[idx_k, c].
Backward: g_w_k = sum_c g_c v[idx_k, c]; g_v[idx_k, c] += w_k g_c (one buffer per thread, summed in
thread order: deterministic); g_a_k = w_k (g_w_k - sum_j w_j g_w_j); g_x = sum_k g_a_k (node_k - x) / sigma_k^2.
"""
from __future__ import annotations

import math

import numpy as np
import numba
import torch
from numba import njit, prange

from method.splat.raster_numba import as_f64, match_torch_threads


@njit(cache=True, parallel=True, error_model="numpy")
def blend_forward(x, values, index, near, sigma, nt):
    """x (N, 3), values (M, C), index (N, K), near (N, K, 3) = nodes[index], sigma (N, K) -> out (N, C),
    w (N, K). ``nt``: the thread count (rows dealt out in blocks; each row is written by one thread)."""
    n, k = index.shape
    c = values.shape[1]
    out = np.zeros((n, c))
    w = np.zeros((n, k))
    chunk = (n + nt - 1) // nt
    for ti in prange(nt):
        a = np.empty(k)
        for i in range(ti * chunk, min(n, (ti + 1) * chunk)):
            top = -math.inf
            for j in range(k):
                d2 = 0.0
                for q in range(3):
                    d = x[i, q] - near[i, j, q]
                    d2 += d * d
                s = sigma[i, j]
                a[j] = -d2 / (2.0 * s * s)
                top = max(top, a[j])
            tot = 0.0
            for j in range(k):
                a[j] = math.exp(a[j] - top)
                tot += a[j]
            for j in range(k):
                wj = a[j] / tot
                w[i, j] = wj
                row = index[i, j]
                for q in range(c):
                    out[i, q] += wj * values[row, q]
    return out, w


@njit(cache=True, parallel=True, error_model="numpy")
def blend_backward(x, values, index, near, sigma, w, g_out, nt):
    """Gradients of the blend w.r.t. x (N, 3) and values (M, C), given g_out (N, C) and the forward's w."""
    n, k = index.shape
    m, c = values.shape
    g_x = np.zeros((n, 3))
    g_v = np.zeros((nt, m, c))
    chunk = (n + nt - 1) // nt
    for ti in prange(nt):
        gw = np.empty(k)
        gv = g_v[ti]
        for i in range(ti * chunk, min(n, (ti + 1) * chunk)):
            dot = 0.0
            for j in range(k):
                row = index[i, j]
                wj = w[i, j]
                acc = 0.0
                for q in range(c):
                    g = g_out[i, q]
                    acc += g * values[row, q]
                    gv[row, q] += wj * g
                gw[j] = acc
                dot += wj * acc
            for j in range(k):
                ga = w[i, j] * (gw[j] - dot)
                s = sigma[i, j]
                f = ga / (s * s)
                for q in range(3):
                    g_x[i, q] += f * (near[i, j, q] - x[i, q])
    out = g_v[0].copy()
    for ti in range(1, nt):
        out += g_v[ti]
    return g_x, out


class _BlendAtNodes(torch.autograd.Function):
    """(x (N, 3), values (M, C)) -> the blend (N, C); index, near and sigma are constants of the choice."""

    @staticmethod
    def forward(ctx, x, values, index, near, sigma):
        xf, vf = as_f64(x), as_f64(values)
        nt = numba.get_num_threads()
        out, w = blend_forward(xf, vf, index, near, sigma, nt)
        ctx.state = (xf, vf, index, near, sigma, w)
        return torch.from_numpy(out).to(values.dtype)

    @staticmethod
    def backward(ctx, g_out):
        xf, vf, index, near, sigma, w = ctx.state
        g_x, g_v = blend_backward(xf, vf, index, near, sigma, w, as_f64(g_out), numba.get_num_threads())
        return torch.from_numpy(g_x).to(g_out.dtype), torch.from_numpy(g_v).to(g_out.dtype), None, None, None


def blend_at_nodes(x: torch.Tensor, values: torch.Tensor, index: np.ndarray, near: np.ndarray,
                   sigma: np.ndarray) -> torch.Tensor:
    """The compiled blend of ``values`` (M, C) at the rows of ``x`` (N, 3): index (N, K) int64, near
    (N, K, 3) and sigma (N, K) float64 numpy arrays (MotionNodes keeps them per choice)."""
    match_torch_threads()
    return _BlendAtNodes.apply(x, values, index, near, sigma)
