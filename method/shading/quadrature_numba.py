"""The env map's exact cosine weights (envmap.cosine_weights) as a compiled CPU kernel, forward and backward.

Why: stage 2 sums the unshadowed diffuse term over every texel of the map, c[p, t] = sum_s max(0, n_p . m_ts)
for each shaded pixel p, texel t and sub-cell s (1,024 pixels x 512 texels x 16 cells at `small`). In torch
that is an (P, T, S) product, a clamp, a sum and their backward through masks, each writing 8.4 M floats:
the largest part of a `small` stage-2 step on the CPU (BENCHMARKS.md, issue 23, session 39). Here nothing of
size P T S is stored: the forward accumulates over s in registers, the backward recomputes the signs.
envmap._cosine_weights_torch stays the reference (and the CUDA path); tests hold this one to it.

Backward: d c[p, t] / d n_p = sum_s [n_p . m_ts > 0] m_ts, so g_n[p] = sum_t g[p, t] sum_s [...] m_ts.

Most texels lie wholly on one side of a normal's horizon: a texel's cell moments all point within a cone of
half-angle theta_t around their sum's direction c_t, so n . c_t > |n| sin(theta_t) (+ a margin) puts every cell
above the horizon and n . c_t < -(...) every cell below it (texel_cones). Below: the weight is 0 and the
gradient term too, with no loop over the cells; above: the backward's sum of the cells' moments is the texel's
precomputed sum (the same additions in the same order), and the forward still sums its cells, so both are
bit-identical to the loop over every cell. Only the texels that straddle the horizon take the loop, the
backward's written without a branch per cell (a 0 / 1 weight: its sign tests are unpredictable there).
"""
from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba import njit, prange

from method.splat.raster_numba import as_f64, match_torch_threads


CONE_MARGIN = 1e-9  # of n . c_t beyond |n| sin(theta_t): every cell's computed n . m then has the cone's sign


@njit(cache=True, error_model="numpy")
def texel_cones(mom):
    """Per texel t of mom (T, S, 3): the unit direction c_t of its cells' summed moments, the bound
    lim_t = sin(theta_t) of the largest angle between c_t and a cell's moment, and the summed moments (T, 3),
    added over the cells in order (as the backward's loop adds them)."""
    t_count, s_count = mom.shape[0], mom.shape[1]
    centre = np.zeros((t_count, 3))
    lim = np.ones(t_count)
    total = np.zeros((t_count, 3))
    for t in range(t_count):
        b0 = b1 = b2 = 0.0
        for s in range(s_count):
            b0 += mom[t, s, 0]
            b1 += mom[t, s, 1]
            b2 += mom[t, s, 2]
        total[t, 0], total[t, 1], total[t, 2] = b0, b1, b2
        nb = math.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
        if nb == 0.0:
            continue  # lim 1: never classified, the loop decides
        c0, c1, c2 = b0 / nb, b1 / nb, b2 / nb
        cos_min = 1.0
        for s in range(s_count):
            m0, m1, m2 = mom[t, s, 0], mom[t, s, 1], mom[t, s, 2]
            nm = math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
            cos_min = min(cos_min, (c0 * m0 + c1 * m1 + c2 * m2) / nm if nm > 0.0 else -1.0)
        centre[t, 0], centre[t, 1], centre[t, 2] = c0, c1, c2
        lim[t] = math.sqrt(max(0.0, 1.0 - cos_min * cos_min)) if cos_min > 0.0 else 1.0
    return centre, lim, total


@njit(cache=True, parallel=True, error_model="numpy")
def cosine_forward(n, mom, centre, lim, nt):
    """n (P, 3), mom (T, S, 3) -> c (P, T) = sum_s max(0, n . m_ts); pixels dealt to ``nt`` threads in blocks;
    texels wholly below the horizon are 0 without their loop (texel_cones)."""
    p_count = n.shape[0]
    t_count, s_count = mom.shape[0], mom.shape[1]
    out = np.zeros((p_count, t_count))
    chunk = (p_count + nt - 1) // nt
    for ti in prange(nt):
        for p in range(ti * chunk, min(p_count, (ti + 1) * chunk)):
            n0, n1, n2 = n[p, 0], n[p, 1], n[p, 2]
            nn = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            for t in range(t_count):
                if n0 * centre[t, 0] + n1 * centre[t, 1] + n2 * centre[t, 2] < -(nn * lim[t] + CONE_MARGIN):
                    continue  # every cell below the horizon: 0 (out starts at 0)
                acc = 0.0
                for s in range(s_count):
                    d = n0 * mom[t, s, 0] + n1 * mom[t, s, 1] + n2 * mom[t, s, 2]
                    acc += max(d, 0.0)
                out[p, t] = acc
    return out


@njit(cache=True, parallel=True, error_model="numpy")
def cosine_backward(n, mom, centre, lim, total, g, nt):
    """The gradient (P, 3) of sum_pt g[p, t] c[p, t] w.r.t. the normals."""
    p_count = n.shape[0]
    t_count, s_count = mom.shape[0], mom.shape[1]
    g_n = np.zeros((p_count, 3))
    chunk = (p_count + nt - 1) // nt
    for ti in prange(nt):
        for p in range(ti * chunk, min(p_count, (ti + 1) * chunk)):
            n0, n1, n2 = n[p, 0], n[p, 1], n[p, 2]
            nn = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            a0 = a1 = a2 = 0.0
            for t in range(t_count):
                gp = g[p, t]
                if gp == 0.0:
                    continue
                dc = n0 * centre[t, 0] + n1 * centre[t, 1] + n2 * centre[t, 2]
                bound = nn * lim[t] + CONE_MARGIN
                if dc < -bound:
                    continue  # every cell below the horizon: no gradient
                if dc > bound:  # every cell above it: the sum of all the cells' moments
                    b0, b1, b2 = total[t, 0], total[t, 1], total[t, 2]
                else:
                    b0 = b1 = b2 = 0.0
                    for s in range(s_count):
                        m0, m1, m2 = mom[t, s, 0], mom[t, s, 1], mom[t, s, 2]
                        w = 1.0 if n0 * m0 + n1 * m1 + n2 * m2 > 0.0 else 0.0
                        b0 += w * m0
                        b1 += w * m1
                        b2 += w * m2
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
        centre, lim, total = texel_cones(mom)
        ctx.state = (nf, mom, centre, lim, total)
        return torch.from_numpy(cosine_forward(nf, mom, centre, lim, numba.get_num_threads())).to(normals.dtype)

    @staticmethod
    def backward(ctx, g):
        nf, mom, centre, lim, total = ctx.state
        g_n = cosine_backward(nf, mom, centre, lim, total, as_f64(g), numba.get_num_threads())
        return torch.from_numpy(g_n).to(g.dtype), None


def cosine_weights_compiled(normals: torch.Tensor, moments: torch.Tensor) -> torch.Tensor:
    """(P, T) cosine weights of unit ``normals`` (P, 3) over ``moments`` (T, S, 3), compiled."""
    match_torch_threads()
    return _CosineWeights.apply(normals, as_f64(moments))
