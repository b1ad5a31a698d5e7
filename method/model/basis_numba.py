"""The motion bases' blend (MotionBasis.offsets, method/model/motion_basis.py) as one compiled CPU kernel,
forward and backward.

Why: in torch the blend is some forty ops over (N, 10), (N, 3, 3) and (N, 4) tensors (the softmax of the
weights, three thin products with the bases' transforms, a batched 3 x 3 product, the quaternion blend, its
normalisation and the Hamilton product): 16-29 ms of forward and backward at 20k Gaussians on one thread of
the AVX2 EPYC (fastest and median of 60 rounds), against a ~120 ms `small` stage-1 step (BENCHMARKS.md,
issue 23, session 55), for ~400 flops per Gaussian; 14-19 ms with this kernel, the bases' own knots and the
softmax included. Here each Gaussian is one pass forward and one backward (float64 inside); the weights' softmax
stays in torch (its exponentials vectorised: one libm call per weight in the loop cost as much as the rest),
and the bases' gradients are one product of the weights with each Gaussian's share, not sums into 9 x 16
numbers from every row. MotionBasis.offsets_reference stays the reference (and the CUDA path), and tests
hold this one to it.

Model (as the reference), per Gaussian with canonical mean mu, rotation q, weight logits l (K bases, the
identity first, then the network's option when ``net``), the bases' A_k (3 x 3), b_k and Q_k at time t:
w = softmax(l), s = sum_{k<K} w_k, x = (sum_k w_k A_k) mu + sum_k w_k b_k, qb = sum_k w_k Q_k,
n = max(|qb|, 1e-12), d mu = x - s mu (+ w_K f_mu), d r = s ((qb / n) (x) q - q) (+ w_K f_r).
"""
from __future__ import annotations

import numpy as np
import numba
import torch
from numba import njit, prange

from method.model.nodes import row_softmax
from method.splat.raster_numba import as_f64, match_torch_threads

_NORM_FLOOR = 1e-12  # the reference's clamp_min on the blended quaternion's norm


@njit(cache=True, inline="always")
def _qmul(a0, a1, a2, a3, b0, b1, b2, b3):
    """Hamilton product of w-x-y-z quaternions a (x) b."""
    return (a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3,
            a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2,
            a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1,
            a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0)


@njit(cache=True, parallel=True, error_model="numpy")
def basis_forward(means, quats, w, f_mu, f_rot, a, b, q, net, nt):
    """means (N, 3), quats (N, 4), the blend weights w (N, L) (the logits' softmax, taken in torch: its
    exponentials vectorised), f_mu (N, 3), f_rot (N, 4) (read only when ``net``), the bases' a (K, 3, 3),
    b (K, 3), q (K, 4), L = K + net -> d_mu (N, 3), d_rot (N, 4). ``nt``: the thread count (rows dealt out
    in blocks)."""
    n = w.shape[0]
    k = a.shape[0]
    d_mu = np.empty((n, 3))
    d_rot = np.empty((n, 4))
    chunk = (n + nt - 1) // nt
    for ti in prange(nt):
        for i in range(ti * chunk, min(n, (ti + 1) * chunk)):
            m0, m1, m2 = means[i, 0], means[i, 1], means[i, 2]
            x0 = x1 = x2 = 0.0
            s = 0.0
            c0 = c1 = c2 = c3 = 0.0
            for j in range(k):
                wj = w[i, j]
                s += wj
                x0 += wj * (a[j, 0, 0] * m0 + a[j, 0, 1] * m1 + a[j, 0, 2] * m2 + b[j, 0])
                x1 += wj * (a[j, 1, 0] * m0 + a[j, 1, 1] * m1 + a[j, 1, 2] * m2 + b[j, 1])
                x2 += wj * (a[j, 2, 0] * m0 + a[j, 2, 1] * m1 + a[j, 2, 2] * m2 + b[j, 2])
                c0 += wj * q[j, 0]
                c1 += wj * q[j, 1]
                c2 += wj * q[j, 2]
                c3 += wj * q[j, 3]
            nrm = max(np.sqrt(c0 * c0 + c1 * c1 + c2 * c2 + c3 * c3), _NORM_FLOOR)
            p0, p1, p2, p3 = _qmul(c0 / nrm, c1 / nrm, c2 / nrm, c3 / nrm,
                                   quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3])
            d_mu[i, 0] = x0 - s * m0
            d_mu[i, 1] = x1 - s * m1
            d_mu[i, 2] = x2 - s * m2
            d_rot[i, 0] = s * (p0 - quats[i, 0])
            d_rot[i, 1] = s * (p1 - quats[i, 1])
            d_rot[i, 2] = s * (p2 - quats[i, 2])
            d_rot[i, 3] = s * (p3 - quats[i, 3])
            if net:
                wn = w[i, k]
                for c in range(3):
                    d_mu[i, c] += wn * f_mu[i, c]
                for c in range(4):
                    d_rot[i, c] += wn * f_rot[i, c]
    return d_mu, d_rot


@njit(cache=True, parallel=True, error_model="numpy")
def basis_backward(means, quats, w, f_mu, f_rot, a, b, q, net, g_mu, g_rot, nt):
    """Gradients of the blend w.r.t. means, quats, w, f_mu, f_rot (per Gaussian), and each Gaussian's share
    of the bases' gradients before its weight: o (N, 16) = [g_x mu^T (9), g_x (3), g_qb (4)], so that the
    gradients of a, b and q are w[:, :K]^T o (one product, basis_offsets' backward), not sums into the bases
    from every row of the loop."""
    n, nl = w.shape
    k = a.shape[0]
    gm = np.empty((n, 3))
    gq = np.empty((n, 4))
    gw = np.empty((n, nl))
    gfm = np.zeros((n, 3))
    gfr = np.zeros((n, 4))
    o = np.empty((n, 16))
    chunk = (n + nt - 1) // nt
    for ti in prange(nt):
        for i in range(ti * chunk, min(n, (ti + 1) * chunk)):
            m0, m1, m2 = means[i, 0], means[i, 1], means[i, 2]
            r0, r1, r2, r3 = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
            # the forward's blend again (cheaper than keeping it)
            s = 0.0
            c0 = c1 = c2 = c3 = 0.0
            for j in range(k):
                wj = w[i, j]
                s += wj
                c0 += wj * q[j, 0]
                c1 += wj * q[j, 1]
                c2 += wj * q[j, 2]
                c3 += wj * q[j, 3]
            raw = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2 + c3 * c3)
            nrm = max(raw, _NORM_FLOOR)
            u0, u1, u2, u3 = c0 / nrm, c1 / nrm, c2 / nrm, c3 / nrm
            p0, p1, p2, p3 = _qmul(u0, u1, u2, u3, r0, r1, r2, r3)
            gx0, gx1, gx2 = g_mu[i, 0], g_mu[i, 1], g_mu[i, 2]
            h0, h1, h2, h3 = g_rot[i, 0], g_rot[i, 1], g_rot[i, 2], g_rot[i, 3]
            # d mu = x - s mu; d r = s (p - r)
            g_s = -(gx0 * m0 + gx1 * m1 + gx2 * m2) + h0 * (p0 - r0) + h1 * (p1 - r1) + h2 * (p2 - r2) + h3 * (p3 - r3)
            gp0, gp1, gp2, gp3 = s * h0, s * h1, s * h2, s * h3
            # p = u (x) r: d/du = g_p (x) conj(r), d/dr = conj(u) (x) g_p
            gu0, gu1, gu2, gu3 = _qmul(gp0, gp1, gp2, gp3, r0, -r1, -r2, -r3)
            gr0, gr1, gr2, gr3 = _qmul(u0, -u1, -u2, -u3, gp0, gp1, gp2, gp3)
            gq[i, 0] = gr0 - s * h0
            gq[i, 1] = gr1 - s * h1
            gq[i, 2] = gr2 - s * h2
            gq[i, 3] = gr3 - s * h3
            # u = c / max(|c|, floor)
            if raw > _NORM_FLOOR:
                dot = gu0 * u0 + gu1 * u1 + gu2 * u2 + gu3 * u3
                gc0, gc1, gc2, gc3 = (gu0 - u0 * dot) / nrm, (gu1 - u1 * dot) / nrm, (gu2 - u2 * dot) / nrm, (gu3 - u3 * dot) / nrm
            else:
                gc0, gc1, gc2, gc3 = gu0 / nrm, gu1 / nrm, gu2 / nrm, gu3 / nrm
            # x = sum_j w_j (A_j mu + b_j): the mean's gradient -s g_x + sum_j w_j A_j^T g_x
            gmx0, gmx1, gmx2 = -s * gx0, -s * gx1, -s * gx2
            for j in range(k):
                wj = w[i, j]
                y0 = a[j, 0, 0] * m0 + a[j, 0, 1] * m1 + a[j, 0, 2] * m2 + b[j, 0]
                y1 = a[j, 1, 0] * m0 + a[j, 1, 1] * m1 + a[j, 1, 2] * m2 + b[j, 1]
                y2 = a[j, 2, 0] * m0 + a[j, 2, 1] * m1 + a[j, 2, 2] * m2 + b[j, 2]
                gw[i, j] = gx0 * y0 + gx1 * y1 + gx2 * y2 + g_s + \
                    gc0 * q[j, 0] + gc1 * q[j, 1] + gc2 * q[j, 2] + gc3 * q[j, 3]
                gmx0 += wj * (a[j, 0, 0] * gx0 + a[j, 1, 0] * gx1 + a[j, 2, 0] * gx2)
                gmx1 += wj * (a[j, 0, 1] * gx0 + a[j, 1, 1] * gx1 + a[j, 2, 1] * gx2)
                gmx2 += wj * (a[j, 0, 2] * gx0 + a[j, 1, 2] * gx1 + a[j, 2, 2] * gx2)
            gm[i, 0], gm[i, 1], gm[i, 2] = gmx0, gmx1, gmx2
            o[i, 0], o[i, 1], o[i, 2] = gx0 * m0, gx0 * m1, gx0 * m2
            o[i, 3], o[i, 4], o[i, 5] = gx1 * m0, gx1 * m1, gx1 * m2
            o[i, 6], o[i, 7], o[i, 8] = gx2 * m0, gx2 * m1, gx2 * m2
            o[i, 9], o[i, 10], o[i, 11] = gx0, gx1, gx2
            o[i, 12], o[i, 13], o[i, 14], o[i, 15] = gc0, gc1, gc2, gc3
            if net:
                wn = w[i, k]
                acc = 0.0
                for c in range(3):
                    acc += g_mu[i, c] * f_mu[i, c]
                    gfm[i, c] = wn * g_mu[i, c]
                for c in range(4):
                    acc += g_rot[i, c] * f_rot[i, c]
                    gfr[i, c] = wn * g_rot[i, c]
                gw[i, k] = acc
    return gm, gq, gw, gfm, gfr, o


class _BasisOffsets(torch.autograd.Function):
    """(means, quats, w, f_mu, f_rot, a, b, q) -> (d_mu, d_rot); ``net`` says whether w's last column is the
    network's option (f_mu, f_rot read) or a basis."""

    @staticmethod
    def forward(ctx, means, quats, w, f_mu, f_rot, a, b, q, net):
        arrays = [as_f64(t) for t in (means, quats, w, f_mu, f_rot, a, b, q)]
        d_mu, d_rot = basis_forward(*arrays, bool(net), numba.get_num_threads())
        ctx.state = (arrays, bool(net))
        ctx.dtype = means.dtype
        return torch.from_numpy(d_mu).to(means.dtype), torch.from_numpy(d_rot).to(means.dtype)

    @staticmethod
    def backward(ctx, g_mu, g_rot):
        (means, quats, w, f_mu, f_rot, a, b, q), net = ctx.state
        gm, gq, gw, gfm, gfr, o = basis_backward(means, quats, w, f_mu, f_rot, a, b, q, net, as_f64(g_mu),
                                                 as_f64(g_rot), numba.get_num_threads())
        k = a.shape[0]
        # (K, 16): the bases' a, b and q gradients, in the inputs' precision (float64's product of this thin
        # shape was 1.1-1.8 ms on one thread of the AVX2 EPYC, float32's 0.24-0.42 with the casts)
        dt = ctx.dtype
        bases = (torch.from_numpy(w).to(dt).T @ torch.from_numpy(o).to(dt))[:k]
        out = [torch.from_numpy(g).to(ctx.dtype) for g in (gm, gq, gw, gfm, gfr)]
        out += [bases[:, :9].reshape(k, 3, 3), bases[:, 9:12], bases[:, 12:]]
        if not net:  # f_mu, f_rot were placeholders
            out[3] = out[4] = None
        return (*out, None)


def basis_offsets(means: torch.Tensor, quats: torch.Tensor, logits: torch.Tensor, a: torch.Tensor,
                  b: torch.Tensor, q: torch.Tensor,
                  field: tuple[torch.Tensor, torch.Tensor] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The compiled MotionBasis.offsets: (d mu (N, 3), d r (N, 4)) from the Gaussians' means (N, 3), quats
    (N, 4) and weight logits (N, K [+ 1]), the bases' (a (K, 3, 3), b (K, 3), q (K, 4)) at the time, and
    ``field``, the network's (d mu, d r), when the logits have its column."""
    match_torch_threads()
    net = field is not None
    if net:
        f_mu, f_rot = field
    else:
        f_mu, f_rot = means.new_zeros(1, 3), means.new_zeros(1, 4)
    if logits.shape[1] != a.shape[0] + int(net):
        raise ValueError(f"basis_offsets: {logits.shape[1]} weight columns for {a.shape[0]} bases "
                         f"{'and the network' if net else 'without the network'}")
    return _BasisOffsets.apply(means, quats, row_softmax(logits), f_mu, f_rot, a, b, q, net)
