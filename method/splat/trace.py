"""Ray tracing through 2D Gaussian splats: transmittance (visibility) and composited features per ray.

Hit: the ray meets the splat's plane at t, p = o + t d, local (u, v) on the scaled axes;
alpha = min(max_alpha, o exp(-(u^2 + v^2) / 2)); hits with t < t_min or alpha < alpha_min are skipped;
front to back along the ray, each hit is composited while the transmittance *before* it is >= T_min, so
the hit that takes it below T_min still counts (an opaque splat must give V ~ 0, not V = 1).

Acceleration (why a uniform grid): a splat's support (the ellipse where alpha can reach alpha_min) is
registered in every grid cell its bounding box overlaps and whose box its plane crosses; rays march cell
by cell (3D DDA, all rays vectorised, several cells per Python step), a hit counts only in the cell whose
t-interval contains it (no duplicates, no global sort), and rays drop out as soon as T < T_min. Unlike
binning per light direction it needs no shared directions (stage 2 rotates the directions per pixel),
and unlike a BVH its traversal is a fixed-size vector step that torch runs well on CPU and GPU.
Each cell's entries are padded to blocks of W slots holding the splats' planes, so a (ray, cell) record
costs one contiguous row gather per block, and the plane test runs on (blocks, W) tensors with the ray
broadcast (no per-candidate ray gathers); candidates are tested in chunks (see CANDIDATE_CHUNK).
Everything geometric runs without gradients; the surviving hits are recomputed with gradients
(opacities, features, and the splat geometry) and composited with segmented scans. Hits at equal t
(coplanar splats) are taken in splat-id order.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from .backend import resolve
from .segments import Segments, gather_cols
from .splats import check_splats, splat_frames


def _splat_local(means, quats, scales):
    """(N, 3, 4) affine maps world -> (u, v, w): w is the signed distance along the unit normal."""
    a, b, n = splat_frames(quats, scales)
    au = a / (a * a).sum(-1, keepdim=True)
    av = b / (b * b).sum(-1, keepdim=True)
    lin = torch.stack([au, av, n], 1)  # (N, 3, 3)
    off = -(lin @ means[:, :, None])  # (N, 3, 1)
    return torch.cat([lin, off], 2)


@dataclass
class TraceAccel:
    """Uniform grid over the splats' supports; build once per splat set (and opacity), reuse for any rays."""

    lo: torch.Tensor  # (3,) grid origin
    cell: torch.Tensor  # (3,) cell size
    res: tuple[int, int, int]
    cell_start: torch.Tensor  # (n_cells + 1,) CSR offsets into entries
    entries: torch.Tensor  # (E,) splat ids sorted by cell
    block: int  # W: each cell's entries are padded to whole blocks of W slots
    blk_start: torch.Tensor  # (n_cells + 1,) CSR offsets into blocks
    blk_plane: torch.Tensor  # (n_blocks, 4 * W) per block: unit normals x, y, z and offsets, W slots each
    splat_rows: torch.Tensor  # (N, 13) per splat: maps to u, v, w (4 each; w: the plane) and the opacity
    slot_splat: torch.Tensor  # (n_blocks * W,) splat id per slot (-1: padding, whose plane is all zero)
    alpha_min: float
    num_splats: int
    cache: dict = field(default_factory=dict, repr=False, compare=False)  # other backends' views of the grid

    @staticmethod
    def build(means, quats, scales, opacities, alpha_min: float = 0.01, cell_size: float | None = None,
              max_cells: int = 1 << 21, block: int = 8, cell_factor: float = 0.5,
              backend: str | None = None) -> "TraceAccel":
        """Register every splat whose opacity can reach ``alpha_min`` in the cells its support overlaps.

        ``cell_size`` defaults to ``cell_factor`` x the median support radius (measured: finer cells multiply
        the entries and the build time, coarser cells the candidates per ray; see BENCHMARKS.md). ``block``:
        slots per block (W); 4, 8 and 16 measured within noise of each other. ``backend`` (None: the process
        default): on the compiled one the (splat, cell) candidates are enumerated and tested in a kernel
        (trace_numba.grid_entries), the same tests in float64; in torch they are tensors of every candidate."""
        check_splats(means, quats, scales, opacities)
        dev, dt = means.device, means.dtype
        with torch.no_grad():
            means, quats, scales, o = means.detach(), quats.detach(), scales.detach(), opacities.detach()
            a, b, n = splat_frames(quats, scales)
            k = torch.sqrt(2.0 * torch.log((o / alpha_min).clamp_min(1.0)))
            live = torch.nonzero(o >= alpha_min).squeeze(1)
            half = k[:, None] * torch.sqrt(a * a + b * b)  # AABB half extents of the support ellipse
            local = _splat_local(means, quats, scales).reshape(-1, 12)
            params = torch.cat([local, o[:, None]], 1)
            if live.numel() == 0:
                z = torch.zeros(1, dtype=torch.long, device=dev)
                return TraceAccel(torch.zeros(3, dtype=dt, device=dev), torch.ones(3, dtype=dt, device=dev),
                                  (1, 1, 1), torch.zeros(2, dtype=torch.long, device=dev), z[:0], block,
                                  torch.zeros(2, dtype=torch.long, device=dev),
                                  params.new_zeros(0, 4 * block), params.contiguous(), z[:0], alpha_min,
                                  means.shape[0])
            bmin = (means - half)[live].min(0).values
            bmax = (means + half)[live].max(0).values
            ext = (bmax - bmin).clamp_min(1e-6)
            pad = 1e-4 * float(ext.max())
            bmin, bmax = bmin - pad, bmax + pad
            ext = bmax - bmin
            if cell_size is None:
                radius = (k[live] * torch.maximum(scales[live, 0], scales[live, 1]))
                cell_size = float(cell_factor) * float(radius.median())
            h = max(float(cell_size), float(ext.max()) / 1024.0)
            while math.prod(max(1, math.ceil(float(e) / h)) for e in ext) > max_cells:
                h *= 1.25
            res = tuple(max(1, math.ceil(float(e) / h)) for e in ext)
            cell = ext / torch.tensor(res, dtype=dt, device=dev)
            res_t = torch.tensor(res, device=dev)
            c0 = torch.floor(((means - half)[live] - bmin) / cell).long().clamp_min(0)
            c1 = torch.minimum(torch.floor(((means + half)[live] - bmin) / cell).long(), res_t - 1)
            if resolve(backend, dev) == "numba":
                from .trace_numba import grid_entries

                flat, sid = grid_entries(live, c0, c1, means, n, a, b, k, bmin, cell, pad, res)
            else:
                flat, sid = _grid_entries_torch(live, c0, c1, means, n, a, b, k, bmin, cell, pad, res)
            n_cells = res[0] * res[1] * res[2]
            counts = torch.bincount(flat, minlength=n_cells)
            cell_start = torch.cat([torch.zeros(1, dtype=torch.long, device=dev), torch.cumsum(counts, 0)])
            # blocks: W slots per block, a cell's entries padded to whole blocks; a query gathers one
            # contiguous row of 4 W plane values per (ray, block) instead of 4 scattered values per entry
            W = int(block)
            nblk = torch.div(counts + (W - 1), W, rounding_mode="floor")
            blk_start = torch.cat([torch.zeros(1, dtype=torch.long, device=dev), torch.cumsum(nblk, 0)])
            n_blk = int(blk_start[-1])
            slot = blk_start.index_select(0, flat) * W + torch.arange(flat.numel(), device=dev) \
                - cell_start.index_select(0, flat)
            p = params.index_select(0, sid)
            plane = params.new_zeros(4, n_blk * W)  # padding: zero plane, t = 0 / 0 fails every test
            plane[:, slot] = p[:, 8:12].T
            blk_plane = plane.view(4, n_blk, W).transpose(0, 1).reshape(n_blk, 4 * W)
            slot_splat = torch.full((n_blk * W,), -1, dtype=torch.long, device=dev)
            slot_splat[slot] = sid
            return TraceAccel(bmin, cell, res, cell_start, sid, W, blk_start, blk_plane, params.contiguous(), slot_splat,
                              alpha_min, means.shape[0])


def _grid_entries_torch(live, c0, c1, means, n, a, b, k, bmin, cell, pad: float, res):
    """(cell id, splat id) of every splat in every cell of its support's bounding box [c0, c1] whose box its
    plane crosses and whose in-plane footprint meets the support ellipse, sorted by cell (stably: a cell's
    splats in the order of ``live``)."""
    dev, dt = means.device, means.dtype
    span = c1 - c0 + 1
    cnt = span.prod(1)
    total = int(cnt.sum())
    which = torch.repeat_interleave(torch.arange(live.numel(), device=dev), cnt, output_size=total)
    off = torch.arange(total, device=dev) - (torch.cumsum(cnt, 0) - cnt).index_select(0, which)
    sp = span.index_select(0, which)
    iz = off % sp[:, 2]
    iy = torch.div(off, sp[:, 2], rounding_mode="floor") % sp[:, 1]
    ix = torch.div(off, sp[:, 2] * sp[:, 1], rounding_mode="floor")
    cidx = c0.index_select(0, which) + torch.stack([ix, iy, iz], 1)
    sid = live.index_select(0, which)
    # keep only cells the splat's plane crosses (conservative slab test with a small margin)
    centre = bmin + (cidx.to(dt) + 0.5) * cell
    nn = n.index_select(0, sid)
    dist = ((centre - means.index_select(0, sid)) * nn).sum(1).abs()
    reach = 0.5 * (nn.abs() * cell).sum(1) * 1.001 + pad
    # and whose in-plane footprint (a disc of the cell's half-diagonal) meets the support ellipse:
    # box-vs-circle test in the splat's (u, v) units, conservative
    rel = centre - means.index_select(0, sid)
    a_s, b_s = a.index_select(0, sid), b.index_select(0, sid)
    la, lb = (a_s * a_s).sum(1), (b_s * b_s).sum(1)
    rho = 0.5 * float(cell.norm()) * 1.001 + pad
    du = ((rel * a_s).sum(1).abs() / la - rho / la.sqrt()).clamp_min(0.0)
    dv = ((rel * b_s).sum(1).abs() / lb - rho / lb.sqrt()).clamp_min(0.0)
    kk = k.index_select(0, sid)
    keep = torch.nonzero((dist <= reach) & (du * du + dv * dv <= kk * kk)).squeeze(1)
    sid, cidx = sid.index_select(0, keep), cidx.index_select(0, keep)
    flat = (cidx[:, 0] * res[1] + cidx[:, 1]) * res[2] + cidx[:, 2]
    order = torch.argsort(flat, stable=True)
    flat, sid = flat.index_select(0, order), sid.index_select(0, order)
    return flat, sid


def _cols(mat, idx: torch.Tensor) -> list[torch.Tensor]:
    """Columns ``idx`` of a (K, M) structure-of-arrays tensor (or list of K rows), as K 1-D tensors
    (1-D index_select is ~3x faster on CPU than torch.gather over the rows)."""
    return [row.index_select(0, idx) for row in (mat.unbind(0) if torch.is_tensor(mat) else mat)]


# Candidates are tested in chunks of about this many (ray, slot) pairs: every temporary then stays small
# enough for the allocator to reuse (fresh multi-megabyte tensors page-fault on every op: measured ~4x
# slower for the same arithmetic), while each op stays big enough to be worth waking a second thread
# (measured on 2 cores, passive OpenMP waiting: 2^18 ~25 % slower than 2^20, 2^22 and unchunked ~10 %).
CANDIDATE_CHUNK = 1 << 20
# On CUDA, launches and syncs per chunk and per round dominate instead: larger chunks, more DDA steps per
# round and more rays per traversal (H100, 20k splats, 1M rays: 756-887 ms with the CPU values, 130-170 ms
# with these; 65k rays: 73 -> 38 ms; `python -m method.splat.bench_ab --trace-sweep`, BENCHMARKS.md). Peak
# memory grows with the ray chunk: 2^19 rays took 2.6 GiB at 20k splats and 12 GiB at 300k (2^20: 23 GiB).
CUDA_CANDIDATE_CHUNK = 1 << 24
STEPS_PER_ROUND = {False: 8, True: 16}  # indexed by "is CUDA"
RAY_CHUNK = {False: 1 << 17, True: 1 << 19}


def _candidates(accel: TraceAccel, b0, nb, recd, max_alpha: float, chunk: int):
    """Test every slot of each record's cell blocks: (record, slot) pairs whose plane hit lies inside the
    record's t-interval and whose alpha reaches alpha_min. ``b0``, ``nb``: first block and block count per
    record; ``recd``: per record o (3), d (3), t_in, t_out. Returns (record, slot, alpha, fraction of the
    interval at the hit) or None."""
    dev = b0.device
    n = b0.numel()
    if n == 0:
        return None
    W = accel.block
    cum = torch.cumsum(nb, 0)
    total = int(cum[-1])
    shift = b0 - (cum - nb)  # block = block index in the round + shift of its record
    per = max(1, chunk // W)  # blocks per chunk
    # record boundaries of the chunks (whole records per chunk) and their block offsets
    marks = torch.arange(per, total, per, device=dev) if total > per else cum[:0]
    cuts = torch.searchsorted(cum, marks, right=True)
    bounds = torch.unique_consecutive(torch.cat([cuts.new_zeros(1), cuts, cuts.new_full((1,), n)]))
    offs = torch.cat([cum.new_zeros(1), cum]).index_select(0, bounds).tolist()
    bounds = bounds.tolist()
    ox, oy, oz, dx, dy, dz, r_in, r_out = recd
    n_in, n_out = -r_in, -r_out
    out = []
    for a, b, base, end in zip(bounds[:-1], bounds[1:], offs[:-1], offs[1:]):
        if end == base:
            continue
        brec = torch.repeat_interleave(torch.arange(a, b, device=dev), nb[a:b], output_size=end - base)
        blk = torch.arange(base, end, device=dev) + shift.index_select(0, brec)
        # phase A (one row of 4 W floats per block): plane hit inside this cell's t-interval;
        # t = -ow / dw, so t >= t_in <=> ow / dw <= -t_in (negation is exact)
        g = accel.blk_plane.index_select(0, blk).view(-1, 4, W)
        r = [v.index_select(0, brec)[:, None] for v in (ox, oy, oz, dx, dy, dz, n_in, n_out)]
        # (addcmul: fused multiply-adds, ~2x fewer passes; the same pair gives the same q in every block)
        ow = torch.addcmul(torch.addcmul(torch.addcmul(g[:, 3], g[:, 0], r[0]), g[:, 1], r[1]), g[:, 2], r[2])
        dw = torch.addcmul(torch.addcmul(g[:, 0] * r[3], g[:, 1], r[4]), g[:, 2], r[5])
        q = ow.div_(dw)  # dw = 0 gives inf/nan, which fails the interval test
        sel = torch.nonzero(((q <= r[6]) & (q > r[7])).view(-1)).squeeze(1)
        # phase B (9 floats per hit): local coordinates and alpha of the in-cell hits
        bsel = torch.div(sel, W, rounding_mode="floor")
        slot = blk.index_select(0, bsel) * W + (sel - bsel * W)
        rec_s = brec.index_select(0, bsel)
        o_s = _cols([ox, oy, oz, dx, dy, dz], rec_s)
        sid = accel.slot_splat.index_select(0, slot)
        qb = accel.splat_rows.index_select(0, sid).T  # one row per hit from a small, cache-resident table
        # t again with unfused operations and then u, v, alpha exactly as trace() recomputes them: the
        # alpha_min and T_min decisions here agree bit for bit with the composited values
        t_s = -(qb[8] * o_s[0] + qb[9] * o_s[1] + qb[10] * o_s[2] + qb[11]) / (qb[8] * o_s[3] + qb[9] * o_s[4]
                                                                                + qb[10] * o_s[5])
        px, py, pz = o_s[0] + t_s * o_s[3], o_s[1] + t_s * o_s[4], o_s[2] + t_s * o_s[5]
        pu = qb[0] * px + qb[1] * py + qb[2] * pz + qb[3]
        pv = qb[4] * px + qb[5] * py + qb[6] * pz + qb[7]
        alpha = torch.clamp_max(qb[12] * torch.exp(-0.5 * (pu * pu + pv * pv)), max_alpha)
        hs = torch.nonzero(alpha >= accel.alpha_min).squeeze(1)
        rec_h = rec_s.index_select(0, hs)
        rin, rout = r_in.index_select(0, rec_h), r_out.index_select(0, rec_h)
        frac = (t_s.index_select(0, hs) - rin) / (rout - rin).clamp_min(1e-30)
        out.append((rec_h, sid.index_select(0, hs), alpha.index_select(0, hs), frac))
    if not out:
        return None
    return tuple(torch.cat(c) for c in zip(*out)) if len(out) > 1 else out[0]


def _march(accel: TraceAccel, origins, dirs, t_min, T_min: float, max_alpha: float, steps_per_round: int,
           chunk: int | None = None):
    """No-grad traversal: returns the composited hits (ray, splat, alpha) in front-to-back order per ray."""
    dev, dt = origins.device, origins.dtype
    R = origins.shape[0]
    if chunk is None:
        chunk = CUDA_CANDIDATE_CHUNK if dev.type == "cuda" else CANDIDATE_CHUNK
    res = torch.tensor(accel.res, device=dev)
    lo, cell = accel.lo, accel.cell
    hi = lo + cell * res.to(dt)
    inv = 1.0 / torch.where(dirs.abs() > 1e-30, dirs, torch.full_like(dirs, 1e-30))
    ta, tb = (lo - origins) * inv, (hi - origins) * inv
    t_enter = torch.maximum(torch.minimum(ta, tb).max(1).values, t_min)
    t_exit = torch.maximum(ta, tb).min(1).values
    active = torch.nonzero(t_enter < t_exit).squeeze(1)
    # per-ray state as 1-D tensors per axis (structure of arrays: cheap vector steps on CPU)
    o = [v.index_select(0, active) for v in origins.T.contiguous().unbind(0)]
    d = [v.index_select(0, active) for v in dirs.T.contiguous().unbind(0)]
    iv = [v.index_select(0, active) for v in inv.T.contiguous().unbind(0)]
    t_cur, t_end = t_enter.index_select(0, active), t_exit.index_select(0, active)
    ci, step, t_max, t_delta = [], [], [], []
    for j in range(3):
        p_j = o[j] + t_cur * d[j]
        c_j = torch.floor((p_j - lo[j]) / cell[j]).long().clamp(0, accel.res[j] - 1)
        pos = d[j] > 0
        nxt = lo[j] + (c_j + pos.long()).to(dt) * cell[j]
        ci.append(c_j)
        step.append(torch.where(pos, 1, -1))
        t_max.append(torch.where(d[j].abs() > 1e-30, (nxt - o[j]) * iv[j], torch.full_like(p_j, float("inf"))))
        t_delta.append((cell[j] * iv[j]).abs())
    # the stepping state as (3, n) tensors: one argmin, gather and scatter per step instead of per axis
    ci, step, t_max, t_delta = (torch.stack(v, 0) for v in (ci, step, t_max, t_delta))
    mult = torch.tensor([accel.res[1] * accel.res[2], accel.res[2], 1], device=dev)[:, None]
    res_col = torch.tensor(accel.res, device=dev)[:, None]
    log_t = torch.zeros(active.numel(), dtype=torch.float64, device=dev)
    ray_id = active
    log_tmin = math.log(T_min)
    out_ray, out_splat, out_pos, out_alpha = [], [], [], []
    n_done = torch.zeros(R, dtype=torch.long, device=dev)  # hits kept so far per ray
    while ray_id.numel():
        # -- up to K cells per ray: (ray, cell, t_in, t_out) records, ray-major
        recs_c, recs_in, recs_out, recs_ok = [], [], [], []
        alive = torch.ones(ray_id.numel(), dtype=torch.bool, device=dev)
        for _ in range(steps_per_round):
            t_next, ax = t_max.min(0)  # ties: the first axis (x before y before z)
            t_out = torch.minimum(t_next, t_end)
            recs_c.append((ci * mult).sum(0))
            recs_in.append(t_cur)
            recs_out.append(t_out)
            recs_ok.append(alive)
            ax = ax[None]
            ci.scatter_add_(0, ax, step.gather(0, ax))
            t_max.scatter_add_(0, ax, t_delta.gather(0, ax))
            t_cur = t_out
            alive = alive & (t_next < t_end) & ((ci >= 0) & (ci < res_col)).all(0)
        cells = torch.stack(recs_c, 1).reshape(-1)
        ok = torch.stack(recs_ok, 1).reshape(-1)
        cells = cells.clamp(0, accel.blk_start.numel() - 2)
        b0 = accel.blk_start.index_select(0, cells)
        nb = accel.blk_start.index_select(0, cells + 1) - b0
        rec = torch.nonzero(ok & (nb > 0)).squeeze(1)  # records of cells with entries only
        b0, nb = b0.index_select(0, rec), nb.index_select(0, rec)
        ray_rec = torch.div(rec, steps_per_round, rounding_mode="floor")
        # structure-of-arrays: gathers of (K, P) rows are ~2x faster on CPU than of (P, K) rows
        recd = _cols(o + d, ray_rec) + _cols([torch.stack(recs_in, 1).reshape(-1),
                                               torch.stack(recs_out, 1).reshape(-1)], rec)
        hits = _candidates(accel, b0, nb, recd, max_alpha, chunk)
        if hits is None:
            h_rec = ray_rec.new_zeros(0)
            h_ent, h_alpha, frac = h_rec, recd[0][:0], recd[0][:0]
        else:
            h_rec, h_ent, h_alpha, frac = hits
        ray_local = ray_rec.index_select(0, h_rec)
        # order: record (ray-major, cells front to back), then t within the cell
        order = torch.argsort(h_rec.double() + frac.double().clamp(0.0, 0.999999), stable=True)
        h_ent = h_ent.index_select(0, order)
        h_ray = ray_local.index_select(0, order)
        h_alpha = h_alpha.index_select(0, order)
        segs = Segments(h_ray, ray_id.numel())
        la = torch.log1p(-h_alpha).double()
        before = log_t.index_select(0, h_ray) + segs.exclusive_cumsum(la)
        inc = torch.nonzero(before >= log_tmin).squeeze(1)
        # place of each kept hit among its ray's hits of all rounds (kept hits are a prefix of each ray's
        # segment here): the final ray-major order is then a scatter, not a sort
        g_ray = ray_id.index_select(0, h_ray.index_select(0, inc))
        out_ray.append(g_ray)
        out_pos.append(n_done.index_select(0, g_ray) + inc - segs.start_of.index_select(0, inc))
        out_splat.append(h_ent.index_select(0, inc))
        out_alpha.append(h_alpha.index_select(0, inc))
        n_done.index_add_(0, g_ray, torch.ones_like(g_ray))
        log_t = log_t + torch.zeros_like(log_t).index_add(0, h_ray.index_select(0, inc), la.index_select(0, inc))
        keep = torch.nonzero(alive & (log_t >= log_tmin)).squeeze(1)
        ray_id, t_cur, t_end, log_t = (v.index_select(0, keep) for v in (ray_id, t_cur, t_end, log_t))
        o, d = ([v.index_select(0, keep) for v in lst] for lst in (o, d))
        ci, step, t_max, t_delta = (v.index_select(1, keep) for v in (ci, step, t_max, t_delta))
    if not out_ray:
        e = torch.zeros(0, dtype=torch.long, device=dev)
        return e, e, origins.new_zeros(0)
    ray = torch.cat(out_ray)
    first = torch.cumsum(n_done, 0) - n_done
    pos = first.index_select(0, ray) + torch.cat(out_pos)
    splat = torch.empty_like(ray).index_copy_(0, pos, torch.cat(out_splat))
    alpha = torch.empty(ray.numel(), dtype=dt, device=dev).index_copy_(0, pos, torch.cat(out_alpha))
    return torch.repeat_interleave(torch.arange(R, device=dev), n_done, output_size=ray.numel()), splat, alpha


def trace(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
          features: torch.Tensor | None, origins: torch.Tensor, dirs: torch.Tensor,
          t_min: torch.Tensor | float = 0.0, *, alpha_min: float = 0.01, T_min: float = 0.03,
          max_alpha: float = 0.99, accel: TraceAccel | None = None, steps_per_round: int | None = None,
          ray_chunk: int | None = None, backend: str | None = None):
    """Trace R rays; returns (transmittance (R,), composited features (R, C) or None).

    ``dirs`` need not be unit length (t is in units of |d|). Pass ``accel`` (TraceAccel.build) to reuse
    the grid across calls; it must have been built from the same splats and opacities with the same
    ``alpha_min``. Differentiable w.r.t. opacities, features and the splat geometry (not the rays).
    ``ray_chunk`` rays are traversed at a time (peak memory of the traversal scales with it); it and
    ``steps_per_round`` (DDA cells per ray per round) default per device (RAY_CHUNK, STEPS_PER_ROUND).
    ``backend``: 'auto', 'torch' or 'numba' (method.splat.backend; None: the process default); the
    compiled traversal returns the same hits (trace_numba); with the geometry constant (no gradient to it:
    stage 2, relighting, the predictions) it composites them too (trace_numba.composite_hits), otherwise the
    compositing below is shared. Visibility alone without gradients (``features`` None, the grid built from
    these opacities) takes the compiled traversal's own float64 transmittance instead.
    """
    check_splats(means, quats, scales, opacities, features)
    if origins.dim() != 2 or origins.shape[1] != 3 or dirs.shape != origins.shape:
        raise ValueError(f"origins and dirs must both be (R, 3), got {tuple(origins.shape)}, {tuple(dirs.shape)}")
    R = origins.shape[0]
    dev, dt = means.device, means.dtype
    steps_per_round = STEPS_PER_ROUND[dev.type == "cuda"] if steps_per_round is None else steps_per_round
    ray_chunk = RAY_CHUNK[dev.type == "cuda"] if ray_chunk is None else ray_chunk
    if steps_per_round < 1 or ray_chunk < 1:
        raise ValueError(f"steps_per_round and ray_chunk must be >= 1, got {steps_per_round}, {ray_chunk}")
    origins, dirs = origins.to(dev, dt), dirs.to(dev, dt)
    tmin = torch.as_tensor(t_min, dtype=dt, device=dev).detach().expand(R).contiguous()
    if accel is None:
        accel = TraceAccel.build(means, quats, scales, opacities, alpha_min=alpha_min)
    elif accel.num_splats != means.shape[0] or abs(accel.alpha_min - alpha_min) > 0:
        raise ValueError("accel was built for a different splat set or alpha_min; rebuild it")
    compiled = resolve(backend, dev) == "numba"
    geometry_grad = torch.is_grad_enabled() and any(v.requires_grad for v in (means, quats, scales))
    needs_grad = geometry_grad or (torch.is_grad_enabled() and opacities.requires_grad)
    # the torch traversal's alphas use the opacities the grid was built with: reused only when those are the
    # opacities given (a grid kept while opacities are fine-tuned, as stage 2 does, selects the hits, and
    # the alphas come from the current opacities, as with gradients or the compiled traversal)
    stale = not torch.equal(accel.splat_rows[:, 12], opacities.detach().to(accel.splat_rows))
    if compiled and features is None and not needs_grad and not stale:
        # visibility only, no gradient: the compiled traversal's transmittance (float64, the same kept hits)
        # is the answer; the hit list and its recomputation below are skipped
        from .trace_numba import march_transmittance

        with torch.no_grad():
            T = torch.cat([march_transmittance(accel, origins[i:i + ray_chunk].detach(), dirs[i:i + ray_chunk].detach(),
                                               tmin[i:i + ray_chunk], T_min, max_alpha)
                           for i in range(0, R, ray_chunk)]) if R else tmin.new_ones(0)
        return T.to(device=dev, dtype=dt), None
    if compiled:
        from .trace_numba import march_hits  # numba is optional: imported only when this backend runs

        def march(o, d, tm):  # (ray, splat, Gaussian factor): the alphas are formed below
            return march_hits(accel, o, d, tm, T_min, max_alpha)
    else:
        def march(o, d, tm):  # (ray, splat, alpha)
            return _march(accel, o, d, tm, T_min, max_alpha, steps_per_round)
    with torch.no_grad():  # rays in chunks bound the candidate buffers (memory linear in the chunk)
        parts = [march(origins[i:i + ray_chunk].detach(), dirs[i:i + ray_chunk].detach(), tmin[i:i + ray_chunk])
                 for i in range(0, R, ray_chunk)]
        ray = torch.cat([p[0] + i * ray_chunk for i, p in enumerate(parts)]) if parts else tmin.new_zeros(0).long()
        splat = torch.cat([p[1] for p in parts]) if parts else ray
        third = torch.cat([p[2] for p in parts]) if parts else tmin[:0]
        alpha = None if compiled else third  # the torch traversal's alphas (the grid's opacities)
    if compiled and not geometry_grad:
        # the geometry is a constant here (stage 2 freezes it; relighting and predictions take no gradient):
        # each hit's Gaussian factor comes from the traversal (float64), and the compositing over the opacities
        # and features is one compiled pass each way, where the recomputation below gathers 13 splat rows and 6
        # ray rows per hit and differentiates it all (stage 2: BENCHMARKS.md, issue 23, sessions 43-44)
        from .trace_numba import composite_hits

        return composite_hits(opacities, features, ray, splat, third, R, max_alpha)
    if compiled or stale or needs_grad:
        # differentiable recomputation on the composited hits only (rays are treated as constants); the torch
        # traversal computed the same alphas with the same operations, so without gradients they are reused
        # (the compiled one returns no alphas: with a gradient to the geometry they are computed here)
        q = gather_cols(torch.cat([_splat_local(means, quats, scales).reshape(-1, 12), opacities[:, None]], 1).T,
                         splat)
        oT, dT = origins.detach().T.contiguous(), dirs.detach().T.contiguous()
        ox, oy, oz = _cols(oT, ray)
        dx, dy, dz = _cols(dT, ray)
        ow = q[8] * ox + q[9] * oy + q[10] * oz + q[11]
        dw = q[8] * dx + q[9] * dy + q[10] * dz
        t = -ow / dw
        px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
        pu = q[0] * px + q[1] * py + q[2] * pz + q[3]
        pv = q[4] * px + q[5] * py + q[6] * pz + q[7]
        alpha = torch.clamp_max(q[12] * torch.exp(-0.5 * (pu * pu + pv * pv)), max_alpha)
    segs = Segments(ray, R)
    la = torch.log1p(-alpha)
    trans_before = torch.exp(segs.exclusive_cumsum(la))
    transmittance = torch.exp(segs.sum(la))
    if features is None:
        return transmittance, None
    out = segs.sum(((alpha * trans_before)[None, :] * gather_cols(features.T, splat)).T)
    return transmittance, out
