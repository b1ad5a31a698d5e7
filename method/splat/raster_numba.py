"""Compiled CPU kernels (Numba) for the rasterizer's pair selection, compositing and their backward.

The same model as the torch path (rasterize.py, composite.py), computed in float64 per image row:
splats are listed per image row in depth-rank order (a counting sort over the splats, not over the
pairs), so each row's pixels are composited front to back as the row's list is walked, with no pair list
and no global sort. Per splat and row, the closed-form x-span of the support bounds the pixels tested
(as _candidate_spans); each pixel then runs the exact alpha test, the T < 1e-4 stop and the
accumulation of features, depth, distortion moments and the median. Rows are independent, so the
forward is parallel over rows and writes each pixel once.

The backward walks the same rows again and recomputes every pair (cheaper than storing them). Per
pixel, the suffix sum the compositing gradient needs (sum over later pairs of g_w w) is the pixel's
total, known from the forward outputs, minus a running prefix:
    sum_k g_w_k w_k = sum_c gF_c F_c + gD D + 2 gDist (W M2 - M1^2).
Per-splat gradients go to one buffer per thread (rows dealt out round-robin), summed in thread order,
so results do not depend on scheduling (deterministic for a given thread count).
"""
from __future__ import annotations

import math

import numpy as np
from numba import get_num_threads, njit, prange

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
TINY = 1e-30
MARGIN = 0.01  # pixels: the span is widened by this much on each side, then every pixel is tested exactly


@njit(cache=True, error_model="numpy")
def row_lists(order, y0, y1, height):
    """Splat ids per image row, in the order given (depth rank): CSR (starts (H+1,), ids)."""
    counts = np.zeros(height + 1, np.int64)
    for i in range(order.shape[0]):
        s = order[i]
        for y in range(y0[s], y1[s] + 1):
            counts[y + 1] += 1
    for y in range(height):
        counts[y + 1] += counts[y]
    fill = counts[:height].copy()
    ids = np.empty(counts[height], np.int64)
    for i in range(order.shape[0]):
        s = order[i]
        for y in range(y0[s], y1[s] + 1):
            ids[fill[y]] = s
            fill[y] += 1
    return counts, ids


@njit(cache=True, inline="always", error_model="numpy")
def _span(r, s, kk, bounded, x0, x1, yc, cx, width):
    """Closed-form pixel interval [j0, j1] of splat s's support on the row at centred y = yc."""
    a0 = r[s, 0] + yc * r[s, 6]
    a1 = r[s, 1] + yc * r[s, 7]
    a2 = r[s, 2] + yc * r[s, 8]
    b0, b1, b2 = r[s, 3], r[s, 4], r[s, 5]
    k = kk[s]
    qa = b0 * b0 + b1 * b1 - k * b2 * b2
    if (not bounded[s]) or qa <= 0.0:
        return x0[s], x1[s]
    qb = a0 * b0 + a1 * b1 - k * a2 * b2
    qc = a0 * a0 + a1 * a1 - k * a2 * a2
    disc = qb * qb - qa * qc
    lo = math.inf
    hi = -math.inf
    if disc >= 0.0:
        sq = math.sqrt(disc)
        lo = (-qb - sq) / qa
        hi = (-qb + sq) / qa
    dy = yc - r[s, 11]
    dd = 0.5 * k - dy * dy
    if dd >= 0.0:
        sd = math.sqrt(dd)
        lo = min(lo, r[s, 10] - sd)
        hi = max(hi, r[s, 10] + sd)
    lim = float(width) + 2.0
    j0 = int(math.ceil(min(max(lo + (cx - 0.5 - MARGIN), -lim), lim)))
    j1 = int(math.floor(min(max(hi + (cx - 0.5 + MARGIN), -lim), lim)))
    return max(j0, x0[s]), min(j1, x1[s])


@njit(cache=True, inline="always", error_model="numpy")
def _pair(r, s, xc, yc):
    """alpha, hit depth and the terms the backward needs, for splat s at centred pixel (xc, yc)."""
    c0 = r[s, 0] + xc * r[s, 3] + yc * r[s, 6]
    c1 = r[s, 1] + xc * r[s, 4] + yc * r[s, 7]
    c2 = r[s, 2] + xc * r[s, 5] + yc * r[s, 8]
    grazing = abs(c2) <= TINY
    if grazing:
        c2 = TINY
    inv = 1.0 / c2
    u = c0 * inv
    v = c1 * inv
    rho3 = u * u + v * v
    dx = xc - r[s, 10]
    dy = yc - r[s, 11]
    rho2 = 2.0 * (dx * dx + dy * dy)
    use3 = (rho3 <= rho2) and not grazing
    rho = rho3 if use3 else rho2
    gauss = math.exp(-0.5 * rho)
    raw = r[s, 13] * gauss
    alpha = min(raw, ALPHA_MAX)
    depth = r[s, 9] * inv if use3 else r[s, 12]
    return alpha, depth, use3, u, v, inv, dx, dy, gauss, raw < ALPHA_MAX


@njit(cache=True, parallel=True, error_model="numpy")
def forward(r, attrs, kk, bounded, x0, x1, starts, ids, width, height, cx, cy, near, m_scale, m_near, t_stop):
    """Per pixel (H W): features (K), sum w z, distortion, log T, W, M1, M2, median depth and splat.
    Per splat: visible. Per row: pairs composited."""
    npix = width * height
    K = attrs.shape[1]
    feat = np.zeros((npix, K))
    dsum = np.zeros(npix)
    dist = np.zeros(npix)
    log_t = np.zeros(npix)
    trans = np.ones(npix)
    mom = np.zeros((npix, 3))
    med = np.zeros(npix)
    med_id = np.full(npix, -1, np.int64)
    visible = np.zeros(r.shape[0], np.bool_)
    pairs = np.zeros(height, np.int64)
    for y in prange(height):
        yc = y + 0.5 - cy
        done = np.zeros(width, np.bool_)
        base = y * width
        n_pairs = 0
        for li in range(starts[y], starts[y + 1]):
            s = ids[li]
            j0, j1 = _span(r, s, kk, bounded, x0, x1, yc, cx, width)
            for x in range(j0, j1 + 1):
                if done[x]:
                    continue
                alpha, depth, use3, u, v, inv, dx, dy, gauss, unclamped = _pair(r, s, x + 0.5 - cx, yc)
                if alpha < ALPHA_MIN or depth < near:
                    continue
                p = base + x
                t = trans[p]
                t_after = t * (1.0 - alpha)
                if t_after < t_stop:
                    done[x] = True
                    continue
                w = alpha * t
                m = m_scale * (1.0 - m_near / max(depth, 1e-6))
                dist[p] += w * (m * m * mom[p, 0] + mom[p, 2] - 2.0 * m * mom[p, 1])
                mom[p, 0] += w
                mom[p, 1] += w * m
                mom[p, 2] += w * m * m
                for c in range(K):
                    feat[p, c] += w * attrs[s, c]
                dsum[p] += w * depth
                if t > 0.5:
                    med[p] = depth
                    med_id[p] = s
                trans[p] = t_after
                visible[s] = True
                n_pairs += 1
        pairs[y] = n_pairs
        for x in range(width):
            log_t[base + x] = math.log(trans[base + x])
    return feat, dsum, dist, log_t, mom, med, med_id, visible, pairs


@njit(cache=True, parallel=True, error_model="numpy")
def backward(r, attrs, kk, bounded, x0, x1, starts, ids, width, height, cx, cy, near, m_scale, m_near, t_stop,
             feat, dsum, mom, med_id, g_feat, g_dsum, g_dist, g_logt, g_med, nt):
    """Gradients w.r.t. the rows r (N, 14) and attrs (N, K), given the upstream per-pixel gradients;
    ``nt`` per-thread buffers."""
    n = r.shape[0]
    K = attrs.shape[1]
    g_r = np.zeros((nt, n, 14))
    g_a = np.zeros((nt, n, K))
    for ti in prange(nt):
        gr = g_r[ti]
        ga = g_a[ti]
        trans = np.ones(width)
        prefix = np.zeros(width)
        total = np.zeros(width)
        done = np.zeros(width, np.bool_)
        for y in range(ti, height, nt):
            yc = y + 0.5 - cy
            base = y * width
            for x in range(width):
                p = base + x
                tot = g_dsum[p] * dsum[p] + 2.0 * g_dist[p] * (mom[p, 0] * mom[p, 2] - mom[p, 1] * mom[p, 1])
                for c in range(K):
                    tot += g_feat[p, c] * feat[p, c]
                total[x] = tot
                trans[x] = 1.0
                prefix[x] = 0.0
                done[x] = False
            for li in range(starts[y], starts[y + 1]):
                s = ids[li]
                j0, j1 = _span(r, s, kk, bounded, x0, x1, yc, cx, width)
                for x in range(j0, j1 + 1):
                    if done[x]:
                        continue
                    xc = x + 0.5 - cx
                    alpha, depth, use3, u, v, inv, dx, dy, gauss, unclamped = _pair(r, s, xc, yc)
                    if alpha < ALPHA_MIN or depth < near:
                        continue
                    p = base + x
                    t = trans[x]
                    t_after = t * (1.0 - alpha)
                    if t_after < t_stop:
                        done[x] = True
                        continue
                    w = alpha * t
                    dz = max(depth, 1e-6)
                    m = m_scale * (1.0 - m_near / dz)
                    gw = g_dsum[p] * depth + g_dist[p] * (m * m * mom[p, 0] - 2.0 * m * mom[p, 1] + mom[p, 2])
                    for c in range(K):
                        gw += g_feat[p, c] * attrs[s, c]
                        ga[s, c] += w * g_feat[p, c]
                    prefix[x] += gw * w
                    g_alpha = gw * t - (total[x] - prefix[x] + g_logt[p]) / (1.0 - alpha)
                    g_m = g_dist[p] * 2.0 * w * (m * mom[p, 0] - mom[p, 1])
                    g_depth = g_dsum[p] * w
                    if depth > 1e-6:
                        g_depth += g_m * (m_scale * m_near) / (dz * dz)
                    if med_id[p] == s:
                        g_depth += g_med[p]
                    trans[x] = t_after
                    # alpha and depth of the pair -> the splat's row (as _PairAlpha.backward)
                    g_o = g_alpha * gauss if unclamped else 0.0
                    gr[s, 13] += g_o
                    g_rho = g_o * r[s, 13] * -0.5
                    if use3:
                        gc0 = 2.0 * g_rho * u * inv
                        gc1 = 2.0 * g_rho * v * inv
                        gc2 = -(2.0 * g_rho * (u * u + v * v) + g_depth * depth) * inv
                        gr[s, 0] += gc0
                        gr[s, 1] += gc1
                        gr[s, 2] += gc2
                        gr[s, 3] += xc * gc0
                        gr[s, 4] += xc * gc1
                        gr[s, 5] += xc * gc2
                        gr[s, 6] += yc * gc0
                        gr[s, 7] += yc * gc1
                        gr[s, 8] += yc * gc2
                        gr[s, 9] += g_depth * inv
                    else:
                        gr[s, 10] += -4.0 * g_rho * dx
                        gr[s, 11] += -4.0 * g_rho * dy
                        gr[s, 12] += g_depth
    out_r = g_r[0].copy()
    out_a = g_a[0].copy()
    for ti in range(1, nt):
        out_r += g_r[ti]
        out_a += g_a[ti]
    return out_r, out_a


# ---- torch glue ----------------------------------------------------------------------------------------

import torch  # noqa: E402


def _np64(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to("cpu", torch.float64).numpy())


def _npi(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to("cpu", torch.int64).numpy())


class _RasterRows(torch.autograd.Function):
    """rows (N, 14) [A, B, C, det, centre x, y, depth, opacity] and attrs (N, K) -> per-pixel sums."""

    @staticmethod
    def forward(ctx, rows, attrs, geom, width, height, cx, cy, near, m_scale, m_near, t_stop):
        x0, x1, starts, ids, kk, bounded = geom
        r, a = _np64(rows), _np64(attrs)
        feat, dsum, dist, log_t, mom, med, med_id, visible, pairs = forward(
            r, a, kk, bounded, x0, x1, starts, ids, width, height, cx, cy, near, m_scale, m_near, t_stop)
        ctx.state = (r, a, geom, width, height, cx, cy, near, m_scale, m_near, t_stop, feat, dsum, mom, med_id)
        ctx.dtype = rows.dtype
        outs = tuple(torch.from_numpy(v).to(rows.dtype) for v in (feat, dsum, dist, log_t, med))
        vis, n_pairs = torch.from_numpy(visible), torch.tensor(int(pairs.sum()))
        ctx.mark_non_differentiable(vis, n_pairs)
        return outs + (vis, n_pairs)

    @staticmethod
    def backward(ctx, g_feat, g_dsum, g_dist, g_logt, g_med, _g_vis, _g_pairs):
        r, a, geom, width, height, cx, cy, near, m_scale, m_near, t_stop, feat, dsum, mom, med_id = ctx.state
        x0, x1, starts, ids, kk, bounded = geom
        npix = width * height

        def grad(g, shape):
            return np.zeros(shape) if g is None else _np64(g).reshape(shape)

        gr, ga = backward(r, a, kk, bounded, x0, x1, starts, ids, width, height, cx, cy, near, m_scale, m_near,
                          t_stop, feat, dsum, mom, med_id, grad(g_feat, (npix, a.shape[1])), grad(g_dsum, npix),
                          grad(g_dist, npix), grad(g_logt, npix), grad(g_med, npix), get_num_threads())
        return (torch.from_numpy(gr).to(ctx.dtype), torch.from_numpy(ga).to(ctx.dtype)) + (None,) * 9


def composite_rows(rows, attrs, x0, x1, y0, y1, valid, bounded, k2, z, width: int, height: int, cx: float,
                   cy: float, near: float, m_scale: float, m_near: float, t_stop: float):
    """The compiled selection + compositing, rows and attrs on the CPU: per pixel (sum w f (HW, K), sum w z,
    distortion, log T final, median depth), per splat visibility (N,) and the number of composited pairs."""
    with torch.no_grad():
        order = torch.argsort(z.detach(), stable=True)
        order = order.index_select(0, torch.nonzero(valid.index_select(0, order)).squeeze(1))
        starts, ids = row_lists(_npi(order), _npi(y0), _npi(y1), height)
    geom = (_npi(x0), _npi(x1), starts, ids, _np64(k2), np.ascontiguousarray(bounded.detach().cpu().numpy()))
    args = (geom, width, height, float(cx), float(cy), float(near), float(m_scale), float(m_near), float(t_stop))
    if torch.is_grad_enabled() and (rows.requires_grad or attrs.requires_grad):
        *outs, vis, n_pairs = _RasterRows.apply(rows, attrs, *args)
    else:
        *outs, vis, n_pairs = _RasterRows.forward(_Ctx(), rows, attrs, *args)
    return tuple(outs), vis, int(n_pairs)


class _Ctx:
    """Stand-in for autograd's ctx when no gradient is needed."""

    def mark_non_differentiable(self, *args):
        pass
