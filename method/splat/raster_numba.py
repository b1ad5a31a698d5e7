"""Compiled CPU kernels (Numba) for the rasterizer's pair selection, compositing and their backward.

The same model as the torch path (rasterize.py, composite.py), computed in float64 per image row:
splats are listed per image row in depth-rank order (a counting sort over the splats, not over the
pairs), so each row's pixels are composited front to back as the row's list is walked, with no pair list
to build or sort first. Per splat and row, the closed-form x-span of the support bounds the pixels tested
(as _candidate_spans); each pixel then runs the exact alpha test, the T < 1e-4 stop and the
accumulation of features, depth, distortion moments and the median. Rows are independent, so the
forward is parallel over rows and writes each pixel once; rows are dealt to the threads round-robin, as in
the backward (prange's equal blocks of rows gave one of two threads 1.5-1.9x the mean pairs on real training
views, whose ground fills the lower half).

The forward keeps a record of the pairs it composited (each one's splat, pixel column and Gaussian factor,
row by row in compositing order; 16 bytes a pair, slots sized by pair_slots), and the backward walks that
record: no span, no alpha test, no exponential and no early-stop bookkeeping redone, only the pair's
cheap terms (_pair_terms). Recomputing every pair instead made the backward 1.48x slower on real `small`
views (19.1 against 12.9 ms on one thread), with the same gradients to the last bit (BENCHMARKS.md, issue
23, session 56). Per
pixel, the suffix sum the compositing gradient needs (sum over later pairs of g_w w) is the pixel's
total, known from the forward outputs, minus a running prefix:
    sum_k g_w_k w_k = sum_c gF_c F_c + gD D + 2 gDist (W M2 - M1^2).
Per-splat gradients go to one buffer per thread (rows dealt out round-robin), summed in thread order,
so results do not depend on scheduling (deterministic for a given thread count).
"""
from __future__ import annotations

import math
import threading

import numpy as np
import numba
import torch
from numba import njit, prange
from .backend import kernel_threads

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
TINY = 1e-30
SPLAT_BLOCK = 512  # splats per parallel task in the per-splat kernels (one set of scratch arrays each)
MARGIN = 0.01  # pixels: the span is widened by this much on each side, then every pixel is tested exactly


_SIGN = np.uint64(1 << 63)
_ALL = np.uint64(0xFFFFFFFFFFFFFFFF)
_BYTE = np.uint64(0xFF)


@njit(cache=True, error_model="numpy")
def depth_order(z, valid):
    """The indices of the valid splats by ascending z, ties in index order: what
    ``torch.argsort(z, stable=True)`` restricted to ``valid`` gives (-0.0 equal to +0.0, NaN last), in
    O(N). A least-significant-byte radix sort on z's float64 bit patterns made unsigned-sortable (float32
    widens exactly); the bytes every key shares are skipped (a float32 depth's low 29 bits are zero, its
    exponent byte mostly one value). torch's sort was ~2 ms of a `small` step at 20k splats (BENCHMARKS.md,
    issue 23, session 40)."""
    m = 0
    for i in range(z.shape[0]):
        if valid[i]:
            m += 1
    vals = np.empty(m)
    idx = np.empty(m, np.int64)
    j = 0
    for i in range(z.shape[0]):
        if valid[i]:
            v = np.float64(z[i])
            vals[j] = 0.0 if v == 0.0 else v
            idx[j] = i
            j += 1
    keys = vals.view(np.uint64).copy()
    for j in range(m):
        if vals[j] != vals[j]:
            keys[j] = _ALL  # NaN after everything, as torch sorts it
        elif keys[j] & _SIGN:
            keys[j] = ~keys[j]
        else:
            keys[j] = keys[j] | _SIGN
    counts = np.zeros((8, 257), np.int64)
    for j in range(m):
        k = keys[j]
        for b in range(8):
            counts[b, np.int64((k >> np.uint64(8 * b)) & _BYTE) + 1] += 1
    keys2 = np.empty_like(keys)
    idx2 = np.empty_like(idx)
    for b in range(8):
        cb = counts[b]
        if cb.max() == m:
            continue  # every key has the same byte here: the pass would not move anything
        for v in range(256):
            cb[v + 1] += cb[v]
        shift = np.uint64(8 * b)
        for j in range(m):
            d = np.int64((keys[j] >> shift) & _BYTE)
            pos = cb[d]
            cb[d] = pos + 1
            keys2[pos] = keys[j]
            idx2[pos] = idx[j]
        keys, keys2 = keys2, keys
        idx, idx2 = idx2, idx
    return idx


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


@njit(cache=True, error_model="numpy")
def pair_slots(starts, ids, x0, x1, height):
    """Where each row's composited pairs go in the forward's pair record: row y writes from slot off[y]
    (off (H+1,), off[H] the record's size), with room for every pixel of its splats' boxes (an upper bound
    on its pairs: a pair is a pixel inside a splat's span, and the span inside its box)."""
    off = np.zeros(height + 1, np.int64)
    for y in range(height):
        room = 0
        for li in range(starts[y], starts[y + 1]):
            s = ids[li]
            room += x1[s] - x0[s] + 1
        off[y + 1] = off[y] + room
    return off


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
def forward(r, attrs, kk, bounded, x0, x1, starts, ids, width, height, cx, cy, near, m_scale, m_near, t_stop,
            off, pair_s, pair_x, pair_g, threads):
    """Per pixel (H W): features (K), sum w z, distortion, log T, W, M1, M2, median depth and splat.
    Per splat: visible. Per row: pairs composited. The pair record for the backward, when ``off`` (from
    pair_slots) is given (an empty ``off``: none kept), written into pair_s, pair_x, pair_g (at least
    off[H] long): each composited pair's splat, pixel column and Gaussian factor, row y's in compositing
    order from slot off[y]. ``threads``: numba's thread count, passed in (reading it here would make the
    kernel uncacheable: a ctypes global)."""
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
    keep = off.shape[0] == height + 1
    nt = max(1, min(threads, height))
    for ti in prange(nt):  # rows dealt out round-robin: prange's equal halves of a view are not equal work
        done = np.zeros(width, np.bool_)
        for y in range(ti, height, nt):
            yc = y + 0.5 - cy
            done[:] = False
            base = y * width
            n_pairs = 0
            slot = off[y] if keep else 0
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
                    if keep:
                        pair_s[slot] = s
                        pair_x[slot] = x
                        pair_g[slot] = gauss
                        slot += 1
            pairs[y] = n_pairs
            for x in range(width):
                log_t[base + x] = math.log(trans[base + x])
    return feat, dsum, dist, log_t, mom, med, med_id, visible, pairs


@njit(cache=True, inline="always", error_model="numpy")
def _pair_terms(r, s, xc, yc):
    """_pair's terms without the Gaussian factor (the pair record keeps it): hit depth, which of the two
    distances applies, u, v, 1 / c2, dx, dy. The same operations as _pair's, so the same values."""
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
    depth = r[s, 9] * inv if use3 else r[s, 12]
    return depth, use3, u, v, inv, dx, dy


@njit(cache=True, parallel=True, error_model="numpy")
def backward(r, attrs, width, height, cx, cy, m_scale, m_near, off, pairs, pair_s, pair_x, pair_g,
             feat, dsum, mom, med_id, g_feat, g_dsum, g_dist, g_logt, g_med, g_r, g_a, nt):
    """Gradients w.r.t. the rows r (N, 14) and attrs (N, K), given the upstream per-pixel gradients, over
    the forward's pair record (off, pairs per row, and each pair's splat, column and Gaussian factor): the
    composited pairs only, in the forward's order, with no span, alpha test or exponential to redo.
    ``nt`` per-thread buffers g_r (nt, N, 14) and g_a (nt, N, K), given (their contents are overwritten: each
    thread zeroes its own), rows dealt round-robin."""
    n = r.shape[0]
    K = attrs.shape[1]
    for ti in prange(nt):
        gr = g_r[ti]
        ga = g_a[ti]
        gr[:, :] = 0.0
        ga[:, :] = 0.0
        trans = np.ones(width)
        prefix = np.zeros(width)
        total = np.zeros(width)
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
            for k in range(off[y], off[y] + pairs[y]):
                s = pair_s[k]
                x = pair_x[k]
                gauss = pair_g[k]
                xc = x + 0.5 - cx
                depth, use3, u, v, inv, dx, dy = _pair_terms(r, s, xc, yc)
                raw = r[s, 13] * gauss
                alpha = min(raw, ALPHA_MAX)
                p = base + x
                t = trans[x]
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
                trans[x] = t * (1.0 - alpha)
                # alpha and depth of the pair -> the splat's row (as _PairAlpha.backward)
                g_o = g_alpha * gauss if raw < ALPHA_MAX else 0.0
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
    if nt == 1:  # views of the given buffers: the caller reads them before handing the buffers on
        return g_r[0], g_a[0]
    out_r = np.empty((n, 14))
    out_a = np.empty((n, K))
    for ch in prange((n + SPLAT_BLOCK - 1) // SPLAT_BLOCK):  # the buffers summed in thread order
        for i in range(ch * SPLAT_BLOCK, min(n, (ch + 1) * SPLAT_BLOCK)):
            for c in range(14):
                acc = g_r[0, i, c]
                for ti in range(1, nt):
                    acc += g_r[ti, i, c]
                out_r[i, c] = acc
            for c in range(K):
                acc = g_a[0, i, c]
                for ti in range(1, nt):
                    acc += g_a[ti, i, c]
                out_a[i, c] = acc
    return out_r, out_a


@njit(cache=True, parallel=True, error_model="numpy")
def project(means, quats, scales, opac, shift, rot, trans, cam_c, f, cx, cy, width, height, near, alpha_min):
    """Per splat (as rasterize.project_splats, _pack_rows, _shift_rows and _screen_bounds): the shifted rows
    (N, 14), the camera-facing unit normal (N, 3), the facing sign, and the pixel bounds of the support:
    x0, x1, y0, y1, valid, radii, bounded, k2."""
    n = means.shape[0]
    rows = np.empty((n, 14))
    nrm = np.empty((n, 3))
    sign = np.empty(n)
    x0 = np.zeros(n, np.int64)
    x1 = np.zeros(n, np.int64)
    y0 = np.zeros(n, np.int64)
    y1 = np.zeros(n, np.int64)
    valid = np.zeros(n, np.bool_)
    radii = np.zeros(n)
    bounded = np.zeros(n, np.bool_)
    k2 = np.zeros(n)
    big = float(max(width, height)) * 4.0 + 10.0
    for c in prange((n + SPLAT_BLOCK - 1) // SPLAT_BLOCK):
        m = np.empty((3, 3))  # rows m0, m1, m2 of M = K [a b p]
        for i in range(c * SPLAT_BLOCK, min(n, (c + 1) * SPLAT_BLOCK)):
            qn = math.sqrt(quats[i, 0] ** 2 + quats[i, 1] ** 2 + quats[i, 2] ** 2 + quats[i, 3] ** 2)
            qn = max(qn, 1e-12)
            w, x, y, z = quats[i, 0] / qn, quats[i, 1] / qn, quats[i, 2] / qn, quats[i, 3] / qn
            # columns of the rotation: t_u, t_v (scaled below) and the normal
            r00, r10, r20 = 1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)
            r01, r11, r21 = 2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)
            r02, r12, r22 = 2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)
            su, sv = scales[i, 0], scales[i, 1]
            for k in range(3):
                a_k = rot[k, 0] * r00 * su + rot[k, 1] * r10 * su + rot[k, 2] * r20 * su
                b_k = rot[k, 0] * r01 * sv + rot[k, 1] * r11 * sv + rot[k, 2] * r21 * sv
                p_k = rot[k, 0] * means[i, 0] + rot[k, 1] * means[i, 1] + rot[k, 2] * means[i, 2] + trans[k]
                scale = f if k < 2 else 1.0
                m[k, 0], m[k, 1], m[k, 2] = scale * a_k, scale * b_k, scale * p_k
            A0 = m[0, 1] * m[1, 2] - m[0, 2] * m[1, 1]
            A1 = m[0, 2] * m[1, 0] - m[0, 0] * m[1, 2]
            A2 = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
            B0 = m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1]
            B1 = m[1, 2] * m[2, 0] - m[1, 0] * m[2, 2]
            B2 = m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]
            C0 = m[2, 1] * m[0, 2] - m[2, 2] * m[0, 1]
            C1 = m[2, 2] * m[0, 0] - m[2, 0] * m[0, 2]
            C2 = m[2, 0] * m[0, 1] - m[2, 1] * m[0, 0]
            zc = m[2, 2]
            zs = zc if abs(zc) > 1e-12 else 1e-12
            ctr_x = m[0, 2] / zs  # m0 already carries f
            ctr_y = m[1, 2] / zs
            sx, sy = shift[i, 0], shift[i, 1]
            rows[i, 0] = A0 - sx * B0 - sy * C0
            rows[i, 1] = A1 - sx * B1 - sy * C1
            rows[i, 2] = A2 - sx * B2 - sy * C2
            rows[i, 3], rows[i, 4], rows[i, 5] = B0, B1, B2
            rows[i, 6], rows[i, 7], rows[i, 8] = C0, C1, C2
            rows[i, 9] = m[2, 0] * A0 + m[2, 1] * A1 + m[2, 2] * A2
            rows[i, 10] = ctr_x + sx
            rows[i, 11] = ctr_y + sy
            rows[i, 12] = zc
            rows[i, 13] = opac[i]
            view = (cam_c[0] - means[i, 0]) * r02 + (cam_c[1] - means[i, 1]) * r12 + (cam_c[2] - means[i, 2]) * r22
            sg = -1.0 if view < 0 else 1.0
            sign[i] = sg
            nrm[i, 0], nrm[i, 1], nrm[i, 2] = sg * r02, sg * r12, sg * r22
            # bounds of the support ellipse (dual conic) union the low-pass disc, as _screen_bounds
            o = opac[i]
            log_t = math.log(max(o / alpha_min, 1.0))
            kk = 2.0 * log_t
            k2[i] = kk
            c00 = kk * (m[0, 0] * m[0, 0] + m[0, 1] * m[0, 1]) - m[0, 2] * m[0, 2]
            c11 = kk * (m[1, 0] * m[1, 0] + m[1, 1] * m[1, 1]) - m[1, 2] * m[1, 2]
            c22 = kk * (m[2, 0] * m[2, 0] + m[2, 1] * m[2, 1]) - m[2, 2] * m[2, 2]
            c02 = kk * (m[0, 0] * m[2, 0] + m[0, 1] * m[2, 1]) - m[0, 2] * m[2, 2]
            c12 = kk * (m[1, 0] * m[2, 0] + m[1, 1] * m[2, 1]) - m[1, 2] * m[2, 2]
            bnd = c22 < -1e-12 * max(m[2, 2] * m[2, 2], 1e-30)
            bounded[i] = bnd
            c22s = c22 if bnd else -1.0
            ex = math.sqrt(max(c02 * c02 - c00 * c22s, 0.0)) / (-c22s)
            ey = math.sqrt(max(c12 * c12 - c11 * c22s, 0.0)) / (-c22s)
            mx, my = c02 / c22s, c12 / c22s
            rd = math.sqrt(log_t)
            if bnd:
                xmin = min(mx - ex, ctr_x - rd) + cx + sx
                xmax = max(mx + ex, ctr_x + rd) + cx + sx
                ymin = min(my - ey, ctr_y - rd) + cy + sy
                ymax = max(my + ey, ctr_y + rd) + cy + sy
                xmin, xmax = min(max(xmin, -big), big), min(max(xmax, -big), big)
                ymin, ymax = min(max(ymin, -big), big), min(max(ymax, -big), big)
            else:
                xmin, xmax, ymin, ymax = -big, big, -big, big
            pad = 1e-3
            x0[i] = max(int(math.ceil(xmin - 0.5 - pad)), 0)
            x1[i] = min(int(math.floor(xmax - 0.5 + pad)), width - 1)
            y0[i] = max(int(math.ceil(ymin - 0.5 - pad)), 0)
            y1[i] = min(int(math.floor(ymax - 0.5 + pad)), height - 1)
            ok = zc >= near and o >= alpha_min and x1[i] >= x0[i] and y1[i] >= y0[i]
            valid[i] = ok
            radii[i] = max(xmax - xmin, ymax - ymin) * 0.5 if ok else 0.0
    return rows, nrm, sign, x0, x1, y0, y1, valid, radii, bounded, k2


@njit(cache=True, parallel=True, error_model="numpy")
def project_backward(means, quats, scales, shift, rot, trans, f, sign, g_rows, g_nrm):
    """Gradients of project()'s rows and normals w.r.t. means, quats, scales, opacities and shift."""
    n = means.shape[0]
    g_means = np.zeros((n, 3))
    g_quats = np.zeros((n, 4))
    g_scales = np.zeros((n, 2))
    g_opac = np.zeros(n)
    g_shift = np.zeros((n, 2))
    for ch in prange((n + SPLAT_BLOCK - 1) // SPLAT_BLOCK):
        R = np.empty((3, 3))
        m = np.empty((3, 3))
        gm = np.empty((3, 3))
        gR = np.empty((3, 3))
        A = np.empty(3)
        B = np.empty(3)
        C = np.empty(3)
        gA = np.empty(3)
        gB = np.empty(3)
        gC = np.empty(3)
        gtu = np.empty(3)
        gtv = np.empty(3)
        for i in range(ch * SPLAT_BLOCK, min(n, (ch + 1) * SPLAT_BLOCK)):
            qn = max(math.sqrt(quats[i, 0] ** 2 + quats[i, 1] ** 2 + quats[i, 2] ** 2 + quats[i, 3] ** 2), 1e-12)
            w, x, y, z = quats[i, 0] / qn, quats[i, 1] / qn, quats[i, 2] / qn, quats[i, 3] / qn
            R[0, 0], R[1, 0], R[2, 0] = 1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)
            R[0, 1], R[1, 1], R[2, 1] = 2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)
            R[0, 2], R[1, 2], R[2, 2] = 2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)
            su, sv = scales[i, 0], scales[i, 1]
            for k in range(3):
                a_k = (rot[k, 0] * R[0, 0] + rot[k, 1] * R[1, 0] + rot[k, 2] * R[2, 0]) * su
                b_k = (rot[k, 0] * R[0, 1] + rot[k, 1] * R[1, 1] + rot[k, 2] * R[2, 1]) * sv
                p_k = rot[k, 0] * means[i, 0] + rot[k, 1] * means[i, 1] + rot[k, 2] * means[i, 2] + trans[k]
                scale = f if k < 2 else 1.0
                m[k, 0], m[k, 1], m[k, 2] = scale * a_k, scale * b_k, scale * p_k
            g = g_rows[i]
            sx, sy = shift[i, 0], shift[i, 1]
            for k in range(3):  # rows 0:3 hold A - sx B - sy C
                gA[k] = g[k]
                gB[k] = g[3 + k] - sx * g[k]
                gC[k] = g[6 + k] - sy * g[k]
                gm[k, 0] = 0.0
                gm[k, 1] = 0.0
                gm[k, 2] = 0.0
            g_opac[i] = g[13]
            A[0] = m[0, 1] * m[1, 2] - m[0, 2] * m[1, 1]
            A[1] = m[0, 2] * m[1, 0] - m[0, 0] * m[1, 2]
            A[2] = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
            B[0] = m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1]
            B[1] = m[1, 2] * m[2, 0] - m[1, 0] * m[2, 2]
            B[2] = m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]
            C[0] = m[2, 1] * m[0, 2] - m[2, 2] * m[0, 1]
            C[1] = m[2, 2] * m[0, 0] - m[2, 0] * m[0, 2]
            C[2] = m[2, 0] * m[0, 1] - m[2, 1] * m[0, 0]
            g_shift[i, 0] = g[10] - (g[0] * B[0] + g[1] * B[1] + g[2] * B[2])
            g_shift[i, 1] = g[11] - (g[0] * C[0] + g[1] * C[1] + g[2] * C[2])
            for k in range(3):  # det = m2 . A
                gm[2, k] += g[9] * A[k]
                gA[k] += g[9] * m[2, k]
            _cross_back(m, 0, 1, gA, gm)  # A = m0 x m1
            _cross_back(m, 1, 2, gB, gm)  # B = m1 x m2
            _cross_back(m, 2, 0, gC, gm)  # C = m2 x m0
            zc = m[2, 2]
            if abs(zc) > 1e-12:
                gm[0, 2] += g[10] / zc
                gm[1, 2] += g[11] / zc
                gm[2, 2] -= (g[10] * m[0, 2] + g[11] * m[1, 2]) / (zc * zc)
            gm[2, 2] += g[12]
            # m0 = f (a0, b0, p0), m1 = f (a1, b1, p1), m2 = (a2, b2, p2); a = rot t_u, b = rot t_v, p = rot mean + t
            for j in range(3):
                gtu[j] = 0.0
                gtv[j] = 0.0
            for k in range(3):
                scale = f if k < 2 else 1.0
                for j in range(3):
                    gtu[j] += rot[k, j] * gm[k, 0] * scale
                    gtv[j] += rot[k, j] * gm[k, 1] * scale
                    g_means[i, j] += rot[k, j] * gm[k, 2] * scale
            for j in range(3):
                gR[j, 0] = gtu[j] * su
                gR[j, 1] = gtv[j] * sv
                gR[j, 2] = sign[i] * g_nrm[i, j]
            g_scales[i, 0] = R[0, 0] * gtu[0] + R[1, 0] * gtu[1] + R[2, 0] * gtu[2]
            g_scales[i, 1] = R[0, 1] * gtv[0] + R[1, 1] * gtv[1] + R[2, 1] * gtv[2]
            gw = 2 * (-z * gR[0, 1] + y * gR[0, 2] + z * gR[1, 0] - x * gR[1, 2] - y * gR[2, 0] + x * gR[2, 1])
            gx = 2 * (y * gR[0, 1] + z * gR[0, 2] + y * gR[1, 0] - 2 * x * gR[1, 1] - w * gR[1, 2] + z * gR[2, 0]
                      + w * gR[2, 1] - 2 * x * gR[2, 2])
            gy = 2 * (-2 * y * gR[0, 0] + x * gR[0, 1] + w * gR[0, 2] + x * gR[1, 0] + z * gR[1, 2] - w * gR[2, 0]
                      + z * gR[2, 1] - 2 * y * gR[2, 2])
            gz = 2 * (-2 * z * gR[0, 0] - w * gR[0, 1] + x * gR[0, 2] + w * gR[1, 0] - 2 * z * gR[1, 1] + y * gR[1, 2]
                      + x * gR[2, 0] + y * gR[2, 1])
            dot = w * gw + x * gx + y * gy + z * gz  # through the normalisation q = q_raw / |q_raw|
            g_quats[i, 0] = (gw - w * dot) / qn
            g_quats[i, 1] = (gx - x * dot) / qn
            g_quats[i, 2] = (gy - y * dot) / qn
            g_quats[i, 3] = (gz - z * dot) / qn
    return g_means, g_quats, g_scales, g_opac, g_shift


@njit(cache=True, inline="always", error_model="numpy")
def _cross_back(m, i, j, g, gm):
    """Accumulate the gradients of c = m_i x m_j (upstream g) into gm's rows i and j."""
    # dc/dm_i: g_mi = m_j x g ; dc/dm_j: g_mj = g x m_i
    gm[i, 0] += m[j, 1] * g[2] - m[j, 2] * g[1]
    gm[i, 1] += m[j, 2] * g[0] - m[j, 0] * g[2]
    gm[i, 2] += m[j, 0] * g[1] - m[j, 1] * g[0]
    gm[j, 0] += g[1] * m[i, 2] - g[2] * m[i, 1]
    gm[j, 1] += g[2] * m[i, 0] - g[0] * m[i, 2]
    gm[j, 2] += g[0] * m[i, 1] - g[1] * m[i, 0]


# ---- torch glue ----------------------------------------------------------------------------------------


def match_torch_threads() -> None:
    """Run the kernels on as many threads as torch uses (torch.set_num_threads, JOBS=N workers), or on
    the count backend.kernels_take_the_threads() set (a training alone: torch on one, the kernels on all).

    Numba's OpenMP pool, started on first use, sets the process's OpenMP thread count to
    NUMBA_NUM_THREADS, and torch reads the same count: a grid worker set to one thread ran torch on two
    from its first kernel on (two such workers on 2 cores: stage 2 ~3x slower, BENCHMARKS.md). So torch's
    count is read before and put back after."""
    want = torch.get_num_threads()
    n = max(1, min(kernel_threads() or want, numba.config.NUMBA_NUM_THREADS))
    if numba.get_num_threads() != n:  # the first call starts the pool
        numba.set_num_threads(n)
    if torch.get_num_threads() != want:
        torch.set_num_threads(want)


def as_f64(t: torch.Tensor) -> np.ndarray:
    """A contiguous float64 numpy copy (or view) of a tensor, for the kernels."""
    return np.ascontiguousarray(t.detach().to("cpu", torch.float64).numpy())


def as_i64(t: torch.Tensor) -> np.ndarray:
    """A contiguous int64 numpy copy (or view) of a tensor, for the kernels."""
    return np.ascontiguousarray(t.detach().to("cpu", torch.int64).numpy())


class _ScratchPool:
    """Scratch arrays reused from one call to the next: the pair records (taken by a forward, given back by its
    backward) and the backward's per-thread gradient buffers. Why: arrays of a few MB come fresh from the
    system on most calls, every page faulted in on first write, and on two threads the faults serialise. On
    the AVX2 EPYC (BENCHMARKS.md, issue 23, session 56): the forward took 14.1 ms with a reused record and
    19.1 ms with a fresh one, on one thread; the backward 7.2 ms with reused gradient buffers and 12.4 ms with
    fresh ones, on two. ``dtypes``: one flat array of each per set; a set whose caller never gives it back
    (a forward whose backward never runs) is just let go."""

    def __init__(self, dtypes: tuple, keep: int = 2):
        self.dtypes = dtypes
        self.keep = keep
        self.free: list[tuple[np.ndarray, ...]] = []
        self.lock = threading.Lock()

    def take(self, sizes: tuple[int, ...]) -> tuple[np.ndarray, ...]:
        """A set of flat arrays, the i-th at least sizes[i] long (uninitialised)."""
        if not any(sizes):
            return tuple(np.zeros(0, dt) for dt in self.dtypes)
        with self.lock:
            for i, arrays in enumerate(self.free):
                if all(a.shape[0] >= n for a, n in zip(arrays, sizes)):
                    return self.free.pop(i)
            if len(self.free) >= self.keep:
                self.free.pop(0)  # none fits: let the oldest go
        return tuple(np.empty(int(n * 1.25), dt) for n, dt in zip(sizes, self.dtypes))  # room for larger views

    def give(self, arrays: tuple[np.ndarray, ...]) -> None:
        with self.lock:
            if arrays[0].shape[0] and len(self.free) < self.keep:
                self.free.append(arrays)


_records = _ScratchPool((np.int32, np.int32, np.float64))
_grad_buffers = _ScratchPool((np.float64, np.float64), keep=1)


class _RasterRows(torch.autograd.Function):
    """rows (N, 14) [A, B, C, det, centre x, y, depth, opacity] and attrs (N, K) -> per-pixel sums. The
    kernels see only the valid splats, gathered in depth order (geom's ``order``), so a row's splat list
    ascends through memory; visibility and the gradients are put back in the callers' numbering."""

    @staticmethod
    def forward(ctx, rows, attrs, geom, width, height, cx, cy, near, m_scale, m_near, t_stop, keep):
        x0, x1, starts, ids, kk, bounded, order = geom
        idx = torch.from_numpy(order)
        r, a = as_f64(rows.detach().index_select(0, idx)), as_f64(attrs.detach().index_select(0, idx))
        # the backward's pair record, kept only when a backward will run (``keep``)
        off = pair_slots(starts, ids, x0, x1, height) if keep else np.zeros(0, np.int64)
        size = int(off[-1]) if keep else 0
        record = _records.take((size, size, size))
        feat, dsum, dist, log_t, mom, med, med_id, visible, pairs = forward(
            r, a, kk, bounded, x0, x1, starts, ids, width, height, cx, cy, near, m_scale, m_near, t_stop, off,
            *record, numba.get_num_threads())
        ctx.state = (r, a, order, width, height, cx, cy, m_scale, m_near, off, pairs, feat, dsum, mom, med_id)
        ctx.record = record
        ctx.redo = (kk, bounded, x0, x1, starts, ids, near, t_stop)  # to write the record again (below)
        ctx.dtype = rows.dtype
        ctx.n = rows.shape[0]
        outs = tuple(torch.from_numpy(v).to(rows.dtype) for v in (feat, dsum, dist, log_t, med))
        vis = torch.zeros(rows.shape[0], dtype=torch.bool)
        vis[idx] = torch.from_numpy(visible)
        n_pairs = torch.tensor(int(pairs.sum()))
        ctx.mark_non_differentiable(vis, n_pairs)
        return outs + (vis, n_pairs)

    @staticmethod
    def backward(ctx, g_feat, g_dsum, g_dist, g_logt, g_med, _g_vis, _g_pairs):
        r, a, order, width, height, cx, cy, m_scale, m_near, off, pairs, feat, dsum, mom, med_id = ctx.state
        if ctx.record is None:  # a second backward through one forward (retain_graph, gradcheck): the
            # record went back to the pool after the first, so the forward writes it again
            kk, bounded, x0, x1, starts, ids, near, t_stop = ctx.redo
            size = int(off[-1])
            ctx.record = _records.take((size, size, size))
            forward(r, a, kk, bounded, x0, x1, starts, ids, width, height, cx, cy, near, m_scale, m_near, t_stop,
                    off, *ctx.record, numba.get_num_threads())
        pair_s, pair_x, pair_g = ctx.record
        npix = width * height

        def grad(g, shape):
            return np.zeros(shape) if g is None else as_f64(g).reshape(shape)

        nt, n, k = numba.get_num_threads(), r.shape[0], a.shape[1]
        bufs = _grad_buffers.take((nt * n * 14, nt * n * k))
        gr, ga = backward(r, a, width, height, cx, cy, m_scale, m_near, off, pairs, pair_s, pair_x, pair_g,
                          feat, dsum, mom, med_id, grad(g_feat, (npix, k)), grad(g_dsum, npix),
                          grad(g_dist, npix), grad(g_logt, npix), grad(g_med, npix),
                          bufs[0][:nt * n * 14].reshape(nt, n, 14), bufs[1][:nt * n * k].reshape(nt, n, k), nt)
        _records.give(ctx.record)
        ctx.record = None
        idx = torch.from_numpy(order)
        # index_copy_ copies even where .to() is a no-op (float64), so gr and ga (on one thread, views of the
        # buffers) are read before the buffers go back to the pool
        g_rows = torch.zeros((ctx.n, gr.shape[1]), dtype=ctx.dtype).index_copy_(0, idx, torch.from_numpy(gr).to(ctx.dtype))
        g_attrs = torch.zeros((ctx.n, ga.shape[1]), dtype=ctx.dtype).index_copy_(0, idx, torch.from_numpy(ga).to(ctx.dtype))
        _grad_buffers.give(bufs)
        return (g_rows, g_attrs) + (None,) * 10


class _ProjectRows(torch.autograd.Function):
    """means, quats, scales, opacities, screen shift -> rows (N, 14) and facing normals (N, 3), plus the
    no-grad pixel bounds of each splat's support (project())."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, shift, cam, near, alpha_min):
        rot = as_f64(cam.w2c[:3, :3])
        trans = as_f64(cam.w2c[:3, 3])
        mq, qq, sq, sh = as_f64(means), as_f64(quats), as_f64(scales), as_f64(shift)
        rows, nrm, sign, x0, x1, y0, y1, valid, radii, bounded, k2 = project(
            mq, qq, sq, as_f64(opacities), sh, rot, trans, as_f64(cam.center), float(cam.focal), float(cam.cx),
            float(cam.cy), cam.width, cam.height, float(near), float(alpha_min))
        ctx.state = (mq, qq, sq, sh, rot, trans, float(cam.focal), sign)
        ctx.dtype = means.dtype
        dt = means.dtype
        bounds = (x0, x1, y0, y1, valid, radii, bounded, k2)
        return torch.from_numpy(rows).to(dt), torch.from_numpy(nrm).to(dt), bounds

    @staticmethod
    def backward(ctx, g_rows, g_nrm, _g_bounds):
        mq, qq, sq, sh, rot, trans, f, sign = ctx.state
        n = mq.shape[0]
        gr = np.zeros((n, 14)) if g_rows is None else as_f64(g_rows)
        gn = np.zeros((n, 3)) if g_nrm is None else as_f64(g_nrm)
        grads = project_backward(mq, qq, sq, sh, rot, trans, f, sign, gr, gn)
        return tuple(torch.from_numpy(g).to(ctx.dtype) for g in grads) + (None, None, None)


def rasterize_compiled(means, quats, scales, opacities, features, cam, near: float, screen_offsets, m_scale: float,
                       m_near: float, alpha_min: float, t_stop: float):
    """The whole compiled path from the splat parameters: per pixel (sum w [features, normal] (HW, C + 3),
    sum w z, distortion, log T final, median depth), per splat visibility and radii, the pair count."""
    match_torch_threads()
    shift = screen_offsets if screen_offsets is not None else means.new_zeros((means.shape[0], 2))
    args = (means, quats, scales, opacities, shift, cam, near, alpha_min)
    if torch.is_grad_enabled() and any(t.requires_grad for t in args[:5]):
        rows, nrm, bounds = _ProjectRows.apply(*args)
    else:
        rows, nrm, bounds = _ProjectRows.forward(_Ctx(), *args)
    x0, x1, y0, y1, valid, radii, bounded, k2 = bounds
    attrs = torch.cat([features, nrm], 1)
    with torch.no_grad():
        zs = rows[:, 12].detach()
    (acc, dsum, dist, log_t, med), visible, num_pairs = composite_rows(
        rows, attrs, torch.from_numpy(x0), torch.from_numpy(x1), torch.from_numpy(y0), torch.from_numpy(y1),
        torch.from_numpy(valid), torch.from_numpy(bounded), torch.from_numpy(k2), zs, cam.width, cam.height,
        cam.cx, cam.cy, near, m_scale, m_near, t_stop)
    return acc, dsum, dist, log_t, med, visible, torch.from_numpy(radii).to(means.dtype), num_pairs


def composite_rows(rows, attrs, x0, x1, y0, y1, valid, bounded, k2, z, width: int, height: int, cx: float,
                   cy: float, near: float, m_scale: float, m_near: float, t_stop: float):
    """The compiled selection + compositing, rows and attrs on the CPU: per pixel (sum w f (HW, K), sum w z,
    distortion, log T final, median depth), per splat visibility (N,) and the number of composited pairs."""
    with torch.no_grad():
        order = depth_order(np.ascontiguousarray(z.detach().cpu().numpy()),
                            np.ascontiguousarray(valid.detach().cpu().numpy()))
        # the valid splats renumbered by depth rank: each row's list then ascends through the per-splat
        # arrays, where the depth order scattered it over them (forward 1.4x, backward 1.7x on `small`'s
        # views; BENCHMARKS.md, issue 23, session 41)
        starts, ids = row_lists(np.arange(order.shape[0]), as_i64(y0)[order], as_i64(y1)[order], height)
    geom = (as_i64(x0)[order], as_i64(x1)[order], starts, ids, as_f64(k2)[order],
            np.ascontiguousarray(bounded.detach().cpu().numpy())[order], order)
    args = (geom, width, height, float(cx), float(cy), float(near), float(m_scale), float(m_near), float(t_stop))
    if torch.is_grad_enabled() and (rows.requires_grad or attrs.requires_grad):
        *outs, vis, n_pairs = _RasterRows.apply(rows, attrs, *args, True)
    else:
        *outs, vis, n_pairs = _RasterRows.forward(_Ctx(), rows, attrs, *args, False)
    return tuple(outs), vis, int(n_pairs)


class _Ctx:
    """Stand-in for autograd's ctx when no gradient is needed."""

    def mark_non_differentiable(self, *args):
        pass

    def save_for_backward(self, *args):
        pass
