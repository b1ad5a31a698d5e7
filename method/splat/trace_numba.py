"""Compiled CPU traversal (Numba) of the tracer's uniform grid: the composited hits of each ray.

The same decisions as trace._march, one ray at a time instead of vectorised rounds: a 3D DDA from the
grid entry (or t_min) to the exit, and in each cell the plane hits of the cell's splats whose t lies in
the cell's t-interval and whose alpha reaches alpha_min, sorted by t (ties in splat-id order, the order
of a cell's entries); a hit is kept while the transmittance before it is >= T_min, and the ray stops at
the first hit that fails. Rays are independent, so the kernel is parallel over blocks of rays; each ray
writes at most ``cap`` hits into its own slots, and the rare ray with more is traced again with room
for the most hits the stop rule allows. Where the geometry is a constant (stage 2, relighting, the
predictions) the compositing of the kept hits is compiled too (composite_hits: each alpha from the opacity
given and the hit's Gaussian factor, returned by the traversal; forward and backward); where the geometry
takes a gradient, trace() recomputes the hits in torch and composites them there.
Where no gradient and no feature is asked for (visibility when relighting, writing predictions, the
diagnostic), the kernel's own transmittance is the answer and no hit list is kept (march_transmittance).
"""
from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba import njit, prange
from torch.autograd.function import once_differentiable

from .raster_numba import as_f64, as_i64, match_torch_threads

RAY_BLOCK = 256  # rays per parallel task (one set of scratch buffers each)
CAP = 32  # hit slots per ray in the first pass


@njit(cache=True, parallel=True, error_model="numpy")
def march(o, d, tmin, lo, cell, res, blk_start, blk_plane, slot_splat, rows, alpha_min, T_min, max_alpha, cap,
          max_cell, store=True):
    """Per ray up to ``cap`` kept hits (splat ids) with each hit's Gaussian factor exp(-rho / 2) (float64,
    the alpha without the opacity), and their count; a count of cap + 1 means the ray has more (trace it
    again with a larger cap). The alphas are not returned: trace() forms them from the opacities it is
    given. Also each ray's transmittance after its kept hits (float64). ``store`` False: no hits are
    written and ``cap`` does not apply (the transmittance alone, with the same decisions)."""
    R = o.shape[0]
    W = blk_plane.shape[1] // 4
    o_max = 1.0
    for s in range(rows.shape[0]):
        o_max = max(o_max, rows[s, 12])
    rho_max = 2.0 * math.log(o_max / alpha_min) + 1e-6  # o exp(-rho / 2) < alpha_min beyond it, any splat
    out_s = np.empty((R, cap if store else 0), np.int64)  # only the first count[i] slots of a row are written
    out_g = np.empty((R, cap if store else 0))
    count = np.zeros(R, np.int64)
    trans_out = np.ones(R)
    n_blocks = (R + RAY_BLOCK - 1) // RAY_BLOCK
    for b in prange(n_blocks):
        ht = np.empty(max_cell)
        hs = np.empty(max_cell, np.int64)
        ha = np.empty(max_cell)
        hg = np.empty(max_cell)
        ci = np.empty(3, np.int64)
        step = np.empty(3, np.int64)
        t_max = np.empty(3)
        t_delta = np.empty(3)
        iv = np.empty(3)
        tt = np.empty(W)
        for i in range(b * RAY_BLOCK, min(R, (b + 1) * RAY_BLOCK)):
            t_enter = tmin[i]
            t_exit = math.inf
            big = -math.inf
            for j in range(3):
                dj = d[i, j]
                iv[j] = 1.0 / (dj if abs(dj) > 1e-30 else 1e-30)
                ta = (lo[j] - o[i, j]) * iv[j]
                tb = (lo[j] + cell[j] * res[j] - o[i, j]) * iv[j]
                big = max(big, min(ta, tb))
                t_exit = min(t_exit, max(ta, tb))
            t_enter = max(big, t_enter)
            if not t_enter < t_exit:
                continue
            for j in range(3):
                p = o[i, j] + t_enter * d[i, j]
                c = int(math.floor((p - lo[j]) / cell[j]))
                c = min(max(c, 0), res[j] - 1)
                pos = d[i, j] > 0
                nxt = lo[j] + (c + (1 if pos else 0)) * cell[j]
                ci[j] = c
                step[j] = 1 if pos else -1
                t_max[j] = (nxt - o[i, j]) * iv[j] if abs(d[i, j]) > 1e-30 else math.inf
                t_delta[j] = abs(cell[j] * iv[j])
            t_cur = t_enter
            ox, oy, oz = o[i, 0], o[i, 1], o[i, 2]
            dx, dy, dz = d[i, 0], d[i, 1], d[i, 2]
            trans = 1.0
            n = 0
            stopped = False
            while not stopped:
                ax = 0
                if t_max[1] < t_max[ax]:
                    ax = 1
                if t_max[2] < t_max[ax]:
                    ax = 2
                t_next = t_max[ax]
                t_out = min(t_next, t_exit)
                flat = (ci[0] * res[1] + ci[1]) * res[2] + ci[2]
                m = 0
                for blk in range(blk_start[flat], blk_start[flat + 1]):
                    # the block's planes are contiguous (nx[W], ny[W], nz[W], offset[W]): the plane hits of
                    # all W slots in one branch-free loop (vectorised), then the tests
                    for w in range(W):
                        nx, ny, nz = blk_plane[blk, w], blk_plane[blk, W + w], blk_plane[blk, 2 * W + w]
                        tt[w] = -(nx * ox + ny * oy + nz * oz + blk_plane[blk, 3 * W + w]) / (nx * dx + ny * dy
                                                                                             + nz * dz)
                    for w in range(W):
                        t = tt[w]
                        if not (t >= t_cur and t < t_out):  # also rejects NaN (padding, ray in the plane)
                            continue
                        s = slot_splat[blk * W + w]
                        px = ox + t * dx
                        py = oy + t * dy
                        pz = oz + t * dz
                        pu = rows[s, 0] * px + rows[s, 1] * py + rows[s, 2] * pz + rows[s, 3]
                        pv = rows[s, 4] * px + rows[s, 5] * py + rows[s, 6] * pz + rows[s, 7]
                        rho = pu * pu + pv * pv
                        if rho > rho_max:  # alpha < alpha_min for any opacity: no exp (its underflow is slow)
                            continue
                        gauss = math.exp(-0.5 * rho)
                        a = min(rows[s, 12] * gauss, max_alpha)
                        if a < alpha_min:
                            continue
                        k = m  # insertion by t; equal t keeps entry (splat id) order
                        while k > 0 and ht[k - 1] > t:
                            ht[k] = ht[k - 1]
                            hs[k] = hs[k - 1]
                            ha[k] = ha[k - 1]
                            hg[k] = hg[k - 1]
                            k -= 1
                        ht[k] = t
                        hs[k] = s
                        ha[k] = a
                        hg[k] = gauss
                        m += 1
                for k in range(m):
                    if trans < T_min:
                        stopped = True
                        break
                    if store:
                        if n == cap:
                            n = cap + 1
                            stopped = True
                            break
                        out_s[i, n] = hs[k]
                        out_g[i, n] = hg[k]
                    n += 1
                    trans *= 1.0 - ha[k]
                if trans < T_min:
                    stopped = True
                ci[ax] += step[ax]
                t_max[ax] += t_delta[ax]
                t_cur = t_out
                if not t_next < t_exit or ci[ax] < 0 or ci[ax] >= res[ax]:
                    stopped = True
            count[i] = n
            trans_out[i] = trans
    return out_s, out_g, count, trans_out


@njit(cache=True, parallel=True, error_model="numpy")
def compact(out_s, out_g, count, over_row, s2, g2, c2):
    """Flat (ray, splat, Gaussian factor) from the per-ray slots; rays that overflowed (over_row[i] >= 0)
    take their hits from the second pass (s2, g2, c2)."""
    R = count.shape[0]
    n = np.empty(R, np.int64)
    for i in range(R):
        n[i] = c2[over_row[i]] if over_row[i] >= 0 else count[i]
    start = np.empty(R + 1, np.int64)
    start[0] = 0
    for i in range(R):
        start[i + 1] = start[i] + n[i]
    ray = np.empty(start[R], np.int64)
    spl = np.empty(start[R], np.int64)
    gau = np.empty(start[R])
    for i in prange(R):
        k = over_row[i]
        for j in range(n[i]):
            ray[start[i] + j] = i
            spl[start[i] + j] = s2[k, j] if k >= 0 else out_s[i, j]
            gau[start[i] + j] = g2[k, j] if k >= 0 else out_g[i, j]
    return ray, spl, gau


@njit(cache=True, parallel=True, error_model="numpy")
def composite_forward(start, splat, gauss, opac, feats, max_alpha, nt):
    """Front-to-back compositing of the kept hits, ray by ray: the hits of ray i are start[i]:start[i + 1],
    each with alpha = min(opacity x Gaussian factor, max_alpha). Per ray its transmittance after the hits and
    its composited features (R, C) (C may be 0). Float64 throughout; blocks of rays dealt to ``nt`` tasks."""
    R = start.shape[0] - 1
    C = feats.shape[1]
    trans = np.ones(R)
    out = np.zeros((R, C))
    n_blocks = (R + RAY_BLOCK - 1) // RAY_BLOCK
    for ti in prange(nt):
        for b in range(ti, n_blocks, nt):
            for i in range(b * RAY_BLOCK, min(R, (b + 1) * RAY_BLOCK)):
                t = 1.0
                for k in range(start[i], start[i + 1]):
                    s = splat[k]
                    a = min(opac[s] * gauss[k], max_alpha)
                    w = a * t
                    for c in range(C):
                        out[i, c] += w * feats[s, c]
                    t *= 1.0 - a
                trans[i] = t
    return trans, out


@njit(cache=True, parallel=True, error_model="numpy")
def composite_backward(start, splat, gauss, opac, feats, max_alpha, trans, out, g_t, g_f, nt):
    """Gradients of composite_forward w.r.t. the opacities (N,) and features (N, C), given the upstream
    gradients of the transmittance (R,) and the features (R, C). For hit k of a ray with weights w_j = a_j T_j:
    dL/da_k = gF.f_k T_k - (gT T_final + sum_{j>k} w_j gF.f_j) / (1 - a_k), the sum over later hits being the
    ray's total gF.out minus a running prefix. One gradient buffer per task (blocks of rays dealt
    round-robin), summed in task order: the result does not depend on scheduling."""
    R = start.shape[0] - 1
    N = opac.shape[0]
    C = feats.shape[1]
    g_o = np.zeros((nt, N))
    g_c = np.zeros((nt, N, C))
    n_blocks = (R + RAY_BLOCK - 1) // RAY_BLOCK
    for ti in prange(nt):
        go = g_o[ti]
        gc = g_c[ti]
        for b in range(ti, n_blocks, nt):
            for i in range(b * RAY_BLOCK, min(R, (b + 1) * RAY_BLOCK)):
                if start[i] == start[i + 1]:
                    continue
                total = g_t[i] * trans[i]
                for c in range(C):
                    total += g_f[i, c] * out[i, c]
                t = 1.0
                prefix = 0.0
                for k in range(start[i], start[i + 1]):
                    s = splat[k]
                    raw = opac[s] * gauss[k]
                    a = min(raw, max_alpha)
                    w = a * t
                    gw = 0.0
                    for c in range(C):
                        gw += g_f[i, c] * feats[s, c]
                        gc[s, c] += w * g_f[i, c]
                    prefix += gw * w
                    if raw < max_alpha:
                        go[s] += (gw * t - (total - prefix) / (1.0 - a)) * gauss[k]
                    t *= 1.0 - a
    out_o = g_o[0].copy()
    out_c = g_c[0].copy()
    for ti in range(1, nt):
        out_o += g_o[ti]
        out_c += g_c[ti]
    return out_o, out_c


class _CompositeHits(torch.autograd.Function):
    """(opacities (N,), features (N, C)) -> (transmittance (R,), composited features (R, C)) over a fixed list
    of hits with their Gaussian factors: trace()'s compositing where the geometry is a constant (stage 2,
    relighting, predictions), one compiled pass each way instead of a dozen segmented torch ops and their
    backward (BENCHMARKS.md, issue 23, session 44)."""

    @staticmethod
    def forward(ctx, opacities, features, start, splat, gauss, max_alpha):
        match_torch_threads()
        nt = max(1, numba.get_num_threads())
        op, ft = as_f64(opacities), as_f64(features)
        trans, out = composite_forward(start, splat, gauss, op, ft, max_alpha, nt)
        ctx.kernel_args = (start, splat, gauss, op, ft, max_alpha, trans, out, nt)
        ctx.dtype = opacities.dtype
        return torch.from_numpy(trans).to(opacities.dtype), torch.from_numpy(out).to(opacities.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_trans, g_out):
        start, splat, gauss, op, ft, max_alpha, trans, out, nt = ctx.kernel_args
        g_t = np.zeros(trans.shape[0]) if g_trans is None else as_f64(g_trans)
        g_f = np.zeros(out.shape) if g_out is None else as_f64(g_out)
        match_torch_threads()
        g_o, g_c = composite_backward(start, splat, gauss, op, ft, max_alpha, trans, out, g_t, g_f, nt)
        need_o, need_f = ctx.needs_input_grad[:2]
        return (torch.from_numpy(g_o).to(ctx.dtype) if need_o else None,
                torch.from_numpy(g_c).to(ctx.dtype) if need_f else None, None, None, None, None)


def composite_hits(opacities, features, ray, splat, gauss, num_rays: int, max_alpha: float):
    """Transmittance (R,) and composited features (R, C), or None without features, of the hits (ray sorted,
    each ray's hits front to back) with alpha = min(opacity x gauss, max_alpha); differentiable w.r.t. the
    opacities and features."""
    counts = torch.bincount(ray, minlength=num_rays)
    start = np.zeros(num_rays + 1, np.int64)
    np.cumsum(counts.numpy(), out=start[1:])
    feats = features if features is not None else opacities.new_zeros(opacities.shape[0], 0)
    T, out = _CompositeHits.apply(opacities, feats, start, as_i64(splat), as_f64(gauss), float(max_alpha))
    return T, (out if features is not None else None)


@njit(cache=True, error_model="numpy")
def grid_counts(live, c0, c1, means, nrm, ax_a, ax_b, k, bmin, cell, pad, res, out_flat, out_sid, fill):
    """The candidate tests of trace._grid_entries_torch, one (splat, cell) at a time in float64: the cell's
    box crossed by the splat's plane (slab test), and a disc of the cell's half-diagonal meeting the support
    ellipse in the splat's (u, v) units. Without ``fill`` (a zero-length one) it counts the kept pairs per cell
    (returned in out_flat's place: counts (n_cells + 1,), shifted by one); with it it writes each kept splat
    at its cell's cursor (fill), in the order of ``live``."""
    rho = 0.5 * math.sqrt(cell[0] * cell[0] + cell[1] * cell[1] + cell[2] * cell[2]) * 1.001 + pad
    writing = fill.shape[0] > 0
    for j in range(live.shape[0]):
        s = live[j]
        n0, n1, n2 = nrm[s, 0], nrm[s, 1], nrm[s, 2]
        reach = 0.5 * (abs(n0) * cell[0] + abs(n1) * cell[1] + abs(n2) * cell[2]) * 1.001 + pad
        a0, a1, a2 = ax_a[s, 0], ax_a[s, 1], ax_a[s, 2]
        b0, b1, b2 = ax_b[s, 0], ax_b[s, 1], ax_b[s, 2]
        la = a0 * a0 + a1 * a1 + a2 * a2
        lb = b0 * b0 + b1 * b1 + b2 * b2
        ra, rb = rho / math.sqrt(la), rho / math.sqrt(lb)
        kk = k[s] * k[s]
        for ix in range(c0[j, 0], c1[j, 0] + 1):
            rx = bmin[0] + (ix + 0.5) * cell[0] - means[s, 0]
            for iy in range(c0[j, 1], c1[j, 1] + 1):
                ry = bmin[1] + (iy + 0.5) * cell[1] - means[s, 1]
                for iz in range(c0[j, 2], c1[j, 2] + 1):
                    rz = bmin[2] + (iz + 0.5) * cell[2] - means[s, 2]
                    if abs(rx * n0 + ry * n1 + rz * n2) > reach:
                        continue
                    du = max(abs(rx * a0 + ry * a1 + rz * a2) / la - ra, 0.0)
                    dv = max(abs(rx * b0 + ry * b1 + rz * b2) / lb - rb, 0.0)
                    if du * du + dv * dv > kk:
                        continue
                    flat = (ix * res[1] + iy) * res[2] + iz
                    if writing:
                        out_sid[fill[flat]] = s
                        out_flat[fill[flat]] = flat
                        fill[flat] += 1
                    else:
                        out_flat[flat + 1] += 1


def grid_entries(live, c0, c1, means, nrm, ax_a, ax_b, k, bmin, cell, pad: float, res):
    """trace._grid_entries_torch compiled: (cell id, splat id) of the kept candidates sorted by cell, a
    cell's splats in the order of ``live``, as int64 tensors; two passes (count, then fill), nothing of the
    size of all candidates is stored. The tests run in float64 on the float32 inputs training passes, so a
    candidate on a test's boundary may fall the other way than in torch's float32; both tests are
    conservative (a margin beyond the support), so the hits a ray finds are the same."""
    args = [as_i64(t) for t in (live, c0, c1)] + [as_f64(t) for t in (means, nrm, ax_a, ax_b, k, bmin, cell)]
    res_np = np.asarray(res, np.int64)
    n_cells = int(res_np.prod())
    counts = np.zeros(n_cells + 1, np.int64)
    grid_counts(*args, float(pad), res_np, counts, np.zeros(0, np.int64), np.zeros(0, np.int64))
    start = np.cumsum(counts)  # counts[c + 1] held cell c's count: start[c] is cell c's first entry
    flat = np.empty(start[-1], np.int64)
    sid = np.empty(start[-1], np.int64)
    grid_counts(*args, float(pad), res_np, flat, sid, start[:-1].copy())
    return torch.from_numpy(flat), torch.from_numpy(sid)


def _grid(accel):
    """The grid as the kernel reads it, converted once per TraceAccel (stage 2 reuses each frame's grid)."""
    g = accel.cache.get("numba")
    if g is None:
        counts = accel.cell_start[1:] - accel.cell_start[:-1]
        max_cell = max(1, int(counts.max())) if counts.numel() else 1
        g = ((as_f64(accel.lo), as_f64(accel.cell), np.asarray(accel.res, np.int64),
              np.ascontiguousarray(accel.blk_start.cpu().numpy()), as_f64(accel.blk_plane),
              np.ascontiguousarray(accel.slot_splat.cpu().numpy()), as_f64(accel.splat_rows)), max_cell)
        accel.cache["numba"] = g
    return g


def march_hits(accel, origins, dirs, tmin, T_min: float, max_alpha: float):
    """(ray, splat, Gaussian factor (float64)) of the composited hits, rays in order and each ray's hits
    front to back."""
    match_torch_threads()
    o, d, tm = as_f64(origins), as_f64(dirs), as_f64(tmin)
    grid, max_cell = _grid(accel)
    args = (float(accel.alpha_min), float(T_min), float(max_alpha))
    out_s, out_g, count, _ = march(o, d, tm, *grid, *args, CAP, max_cell)
    over = np.nonzero(count > CAP)[0]
    over_row = np.full(o.shape[0], -1, np.int64)
    if over.size:  # the stop rule bounds the hits: T_min > (1 - alpha_min)^n
        most = int(math.ceil(math.log(T_min) / math.log1p(-accel.alpha_min))) + 1
        s2, g2, c2, _ = march(o[over], d[over], tm[over], *grid, *args, most, max_cell)
        over_row[over] = np.arange(over.size)
    else:
        s2, g2, c2 = np.zeros((1, 1), np.int64), np.zeros((1, 1)), np.zeros(1, np.int64)
    ray, spl, gau = compact(out_s, out_g, count, over_row, s2, g2, c2)
    return torch.from_numpy(ray), torch.from_numpy(spl), torch.from_numpy(gau)


def march_transmittance(accel, origins, dirs, tmin, T_min: float, max_alpha: float) -> torch.Tensor:
    """Each ray's transmittance (float64, (R,)) with no hit list: the traversal's own alphas, from the
    opacities the grid was built with (trace() takes this path only where those are the current ones and
    no gradient is asked for: relighting, predictions, the diagnostic)."""
    match_torch_threads()
    o, d, tm = as_f64(origins), as_f64(dirs), as_f64(tmin)
    grid, max_cell = _grid(accel)
    _, _, _, trans = march(o, d, tm, *grid, float(accel.alpha_min), float(T_min), float(max_alpha), 0, max_cell,
                        False)
    return torch.from_numpy(trans)
