"""Front-to-back compositing of packed (pixel, splat) pairs with an analytic backward pass.

Pairs are sorted by pixel, then front to back. With T_i = prod_{j<i} (1 - alpha_j) and w_i = alpha_i T_i,
per pixel: F = sum w_i f_i, D = sum w_i z_i, the 2DGS distortion sum_{i>j} w_i w_j (m_i - m_j)^2 with
m = s (1 - near / z), and log T_final = sum log(1 - alpha_i).

Backward (why it is cheap): every output depends on alpha only through the weights, so with
g_i = dL/dw_i,  dL/dalpha_i = g_i T_i - (sum_{k>i} g_k w_k + dL/dlogT) / (1 - alpha_i): one suffix sum.
For the distortion, dDist/dw_k = m_k^2 W - 2 m_k M1 + M2 and dDist/dm_k = 2 w_k (m_k W - M1) with the
pixel totals W = sum w, M1 = sum w m, M2 = sum w m^2. Autograd through the same scans was ~3x slower on CPU.
"""
from __future__ import annotations

import torch

from .segments import Segments


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, alpha, depth, attrs, segs: Segments, m_scale: float, m_near: float):
        la = torch.log1p(-alpha)
        trans = torch.exp(segs.exclusive_cumsum(la))
        w = alpha * trans
        m = m_scale * (1.0 - m_near / depth.clamp_min(1e-6))  # a degenerate hit at depth 0 must not give inf
        wm = w * m
        wmm = wm * m
        pre_w, pre_m1, pre_m2 = segs.exclusive_cumsum(w), segs.exclusive_cumsum(wm), segs.exclusive_cumsum(wmm)
        dist = w * (m * m * pre_w + pre_m2 - 2.0 * m * pre_m1)
        k = attrs.shape[1]
        # per-pixel sums of 1-D columns (no (P, K + 6) concatenation)
        feat = torch.stack([segs.sum(w * attrs[:, j]) for j in range(k)], 1)
        d_sum, dist_sum, log_t, W, M1, M2 = (segs.sum(v) for v in (w * depth, dist, la, w, wm, wmm))
        totals = torch.stack([W, M1, M2], 1)
        ctx.segs, ctx.m_scale, ctx.m_near = segs, m_scale, m_near
        ctx.save_for_backward(alpha, depth, attrs, trans, w, m, totals)
        ctx.mark_non_differentiable(trans)
        return feat, d_sum, dist_sum, log_t, trans

    @staticmethod
    def backward(ctx, g_feat, g_depth, g_dist, g_logt, _g_trans):
        alpha, depth, attrs, trans, w, m, totals = ctx.saved_tensors
        segs = ctx.segs
        zero = torch.zeros(segs.num, dtype=alpha.dtype, device=alpha.device)

        def per_pair(g):  # 1-D gathers: ~3x faster than gathering (S, K) rows on CPU
            return segs.gather(g if g is not None else zero)

        gd, gdist, glogt = per_pair(g_depth), per_pair(g_dist), per_pair(g_logt)
        W, M1, M2 = (per_pair(totals[:, j].contiguous()) for j in range(3))
        g_w = gd * depth + gdist * (m * m * W - 2.0 * m * M1 + M2)
        k = attrs.shape[1]
        if g_feat is not None:
            gf = [per_pair(g_feat[:, j].contiguous()) for j in range(k)]
            for j in range(k):
                g_w = g_w + gf[j] * attrs[:, j]
            g_attrs = torch.stack([w * gf[j] for j in range(k)], 1)
        else:
            g_attrs = torch.zeros_like(attrs)
        q = g_w * w
        suffix = segs.gather(segs.sum(q)) - segs.exclusive_cumsum(q) - q  # sum over k > i
        g_alpha = g_w * trans - (suffix + glogt) / (1.0 - alpha)
        g_m = gdist * 2.0 * w * (m * W - M1)
        dz = depth.clamp_min(1e-6)
        g_z = gd * w + torch.where(depth > 1e-6, g_m * (ctx.m_scale * ctx.m_near) / (dz * dz), torch.zeros_like(dz))
        return g_alpha, g_z, g_attrs, None, None, None


def composite(alpha: torch.Tensor, depth: torch.Tensor, attrs: torch.Tensor, segs: Segments,
              m_scale: float, m_near: float):
    """-> per-pixel (sum w f (S, K), sum w z (S,), distortion (S,), log T_final (S,)), and per-pair T_i."""
    return _Composite.apply(alpha, depth, attrs, segs, m_scale, m_near)
