"""The env map's exact cosine weights (envmap.cosine_weights) as a compiled CPU kernel, forward and backward.

Why: stage 2 sums the unshadowed diffuse term over every texel of the map, c[p, t] = sum_s max(0, n_p . m_ts)
for each shaded pixel p, texel t and sub-cell s (1,024 pixels x 512 texels x 16 cells at `small`). In torch
that is an (P, T, S) product, a clamp, a sum and their backward through masks, each writing 8.4 M floats:
the largest part of a `small` stage-2 step on the CPU (BENCHMARKS.md, issue 23, session 39). Here nothing of
size P T S is stored: the forward accumulates over s in registers, the backward recomputes the signs.
envmap._cosine_weights_torch stays the reference (and the CUDA path); tests hold this one to it.

Backward: d c[p, t] / d n_p = sum_s [n_p . m_ts > 0] m_ts, so g_n[p] = sum_t g[p, t] sum_s [...] m_ts.
"""
from __future__ import annotations

import numba
import numpy as np
import torch
from numba import njit, prange

from method.splat.raster_numba import as_f64, match_torch_threads


@njit(cache=True, parallel=True, error_model="numpy")
def cosine_forward(n, mom, nt):
    """n (P, 3), mom (T, S, 3) -> c (P, T) = sum_s max(0, n . m_ts); pixels dealt to ``nt`` threads in blocks."""
    p_count = n.shape[0]
    t_count, s_count = mom.shape[0], mom.shape[1]
    out = np.zeros((p_count, t_count))
    chunk = (p_count + nt - 1) // nt
    for ti in prange(nt):
        for p in range(ti * chunk, min(p_count, (ti + 1) * chunk)):
            n0, n1, n2 = n[p, 0], n[p, 1], n[p, 2]
            for t in range(t_count):
                acc = 0.0
                for s in range(s_count):
                    d = n0 * mom[t, s, 0] + n1 * mom[t, s, 1] + n2 * mom[t, s, 2]
                    acc += max(d, 0.0)
                out[p, t] = acc
    return out


@njit(cache=True, parallel=True, error_model="numpy")
def cosine_backward(n, mom, g, nt):
    """The gradient (P, 3) of sum_pt g[p, t] c[p, t] w.r.t. the normals."""
    p_count = n.shape[0]
    t_count, s_count = mom.shape[0], mom.shape[1]
    g_n = np.zeros((p_count, 3))
    chunk = (p_count + nt - 1) // nt
    for ti in prange(nt):
        for p in range(ti * chunk, min(p_count, (ti + 1) * chunk)):
            n0, n1, n2 = n[p, 0], n[p, 1], n[p, 2]
            a0 = a1 = a2 = 0.0
            for t in range(t_count):
                gp = g[p, t]
                if gp == 0.0:
                    continue
                b0 = b1 = b2 = 0.0
                for s in range(s_count):
                    m0, m1, m2 = mom[t, s, 0], mom[t, s, 1], mom[t, s, 2]
                    if n0 * m0 + n1 * m1 + n2 * m2 > 0.0:
                        b0 += m0
                        b1 += m1
                        b2 += m2
                a0 += gp * b0
                a1 += gp * b1
                a2 += gp * b2
            g_n[p, 0] = a0
            g_n[p, 1] = a1
            g_n[p, 2] = a2
    return g_n


class _CosineWeights(torch.autograd.Function):
    """normals (P, 3) -> (P, T) cosine weights; the moments are a constant of the map's size."""

    @staticmethod
    def forward(ctx, normals, mom):
        nf = as_f64(normals)
        ctx.state = (nf, mom)
        return torch.from_numpy(cosine_forward(nf, mom, numba.get_num_threads())).to(normals.dtype)

    @staticmethod
    def backward(ctx, g):
        nf, mom = ctx.state
        g_n = cosine_backward(nf, mom, as_f64(g), numba.get_num_threads())
        return torch.from_numpy(g_n).to(g.dtype), None


def cosine_weights_compiled(normals: torch.Tensor, moments: torch.Tensor) -> torch.Tensor:
    """(P, T) cosine weights of unit ``normals`` (P, 3) over ``moments`` (T, S, 3), compiled."""
    match_torch_threads()
    return _CosineWeights.apply(normals, as_f64(moments))
