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
Everything geometric runs without gradients; the surviving hits are recomputed with gradients
(opacities, features, and the splat geometry) and composited with segmented scans.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .rasterize import _gather_cols
from .segments import Segments
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
    plane: torch.Tensor  # (4, E) per-entry copy of the splat's plane (unit normal, offset), column-major
    uvo: torch.Tensor  # (9, E) per-entry copy of the maps to u, v (4 each) and the opacity
    alpha_min: float
    num_splats: int

    @staticmethod
    def build(means, quats, scales, opacities, alpha_min: float = 0.01, cell_size: float | None = None,
              max_cells: int = 1 << 21) -> "TraceAccel":
        """Register every splat whose opacity can reach ``alpha_min`` in the cells its support overlaps.

        ``cell_size`` defaults to half the median support radius (measured: finer cells multiply the
        entries and the build time, coarser cells the candidates per ray; see BENCHMARKS.md)."""
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
                                  (1, 1, 1), torch.zeros(2, dtype=torch.long, device=dev), z[:0],
                                  params[:0, 8:12].T.contiguous(),
                                  torch.cat([params[:0, 0:8], params[:0, 12:13]], 1).T.contiguous(), alpha_min,
                                  means.shape[0])
            bmin = (means - half)[live].min(0).values
            bmax = (means + half)[live].max(0).values
            ext = (bmax - bmin).clamp_min(1e-6)
            pad = 1e-4 * float(ext.max())
            bmin, bmax = bmin - pad, bmax + pad
            ext = bmax - bmin
            if cell_size is None:
                radius = (k[live] * torch.maximum(scales[live, 0], scales[live, 1]))
                cell_size = 0.5 * float(radius.median())
            h = max(float(cell_size), float(ext.max()) / 1024.0)
            while math.prod(max(1, math.ceil(float(e) / h)) for e in ext) > max_cells:
                h *= 1.25
            res = tuple(max(1, math.ceil(float(e) / h)) for e in ext)
            cell = ext / torch.tensor(res, dtype=dt, device=dev)
            res_t = torch.tensor(res, device=dev)
            c0 = torch.floor(((means - half)[live] - bmin) / cell).long().clamp_min(0)
            c1 = torch.minimum(torch.floor(((means + half)[live] - bmin) / cell).long(), res_t - 1)
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
            n_cells = res[0] * res[1] * res[2]
            counts = torch.bincount(flat, minlength=n_cells)
            cell_start = torch.cat([torch.zeros(1, dtype=torch.long, device=dev), torch.cumsum(counts, 0)])
            p = params.index_select(0, sid)
            return TraceAccel(bmin, cell, res, cell_start, sid, p[:, 8:12].T.contiguous(),
                              torch.cat([p[:, 0:8], p[:, 12:13]], 1).T.contiguous(), alpha_min, means.shape[0])


def _cols(mat, idx: torch.Tensor) -> list[torch.Tensor]:
    """Columns ``idx`` of a (K, M) structure-of-arrays tensor (or list of K rows), as K 1-D tensors
    (1-D index_select is ~3x faster on CPU than torch.gather over the rows)."""
    return [row.index_select(0, idx) for row in (mat.unbind(0) if torch.is_tensor(mat) else mat)]


def _march(accel: TraceAccel, origins, dirs, t_min, T_min: float, max_alpha: float, steps_per_round: int):
    """No-grad traversal: returns the composited hits (ray, splat) in front-to-back order per ray."""
    dev, dt = origins.device, origins.dtype
    R = origins.shape[0]
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
    log_t = torch.zeros(active.numel(), dtype=torch.float64, device=dev)
    ray_id = active
    log_tmin = math.log(T_min)
    out_ray, out_splat = [], []
    m0, m1 = accel.res[1] * accel.res[2], accel.res[2]
    while ray_id.numel():
        # -- up to K cells per ray: (ray, cell, t_in, t_out) records, ray-major
        recs_c, recs_in, recs_out, recs_ok = [], [], [], []
        alive = torch.ones(ray_id.numel(), dtype=torch.bool, device=dev)
        for _ in range(steps_per_round):
            sx = (t_max[0] <= t_max[1]) & (t_max[0] <= t_max[2])  # ties: x before y before z
            sy = ~sx & (t_max[1] <= t_max[2])
            sz = ~(sx | sy)
            t_next = torch.where(sx, t_max[0], torch.where(sy, t_max[1], t_max[2]))
            t_out = torch.minimum(t_next, t_end)
            recs_c.append(ci[0] * m0 + ci[1] * m1 + ci[2])
            recs_in.append(t_cur)
            recs_out.append(t_out)
            recs_ok.append(alive)
            for j, sj in enumerate((sx, sy, sz)):
                ci[j] = torch.where(sj, ci[j] + step[j], ci[j])
                t_max[j] = torch.where(sj, t_max[j] + t_delta[j], t_max[j])
            t_cur = t_out
            alive = alive & (t_next < t_end) & (ci[0] >= 0) & (ci[0] < accel.res[0]) & (ci[1] >= 0) \
                & (ci[1] < accel.res[1]) & (ci[2] >= 0) & (ci[2] < accel.res[2])
        cells = torch.stack(recs_c, 1).reshape(-1)
        r_in = torch.stack(recs_in, 1).reshape(-1)
        r_out = torch.stack(recs_out, 1).reshape(-1)
        ok = torch.stack(recs_ok, 1).reshape(-1)
        rec = torch.nonzero(ok).squeeze(1)
        cells = cells.index_select(0, rec).clamp(0, accel.cell_start.numel() - 2)
        start = accel.cell_start.index_select(0, cells)
        cnt = accel.cell_start.index_select(0, cells + 1) - start
        total = int(cnt.sum())
        rec_of = torch.repeat_interleave(torch.arange(rec.numel(), device=dev), cnt, output_size=total)
        ent = start.index_select(0, rec_of) + torch.arange(total, device=dev) \
            - (torch.cumsum(cnt, 0) - cnt).index_select(0, rec_of)
        ray_rec = torch.div(rec, steps_per_round, rounding_mode="floor")
        # structure-of-arrays: gathers of (K, P) rows are ~2x faster on CPU than of (P, K) rows
        recd = _cols(o + d, ray_rec) + _cols([r_in, r_out], rec)
        # phase A (4 floats per candidate): plane hit inside this cell's t-interval
        qa = _cols(accel.plane, ent)
        r = _cols(recd, rec_of)
        ow = qa[0] * r[0] + qa[1] * r[1] + qa[2] * r[2] + qa[3]
        dw = qa[0] * r[3] + qa[1] * r[4] + qa[2] * r[5]
        t = -ow / dw  # dw = 0 gives inf/nan, which fails the interval test
        sel = torch.nonzero((t >= r[6]) & (t < r[7])).squeeze(1)
        # phase B (9 floats): local coordinates and alpha of the in-cell hits
        ent_s, t_s, r_s = ent.index_select(0, sel), t.index_select(0, sel), _cols(r, sel)
        qb = _cols(accel.uvo, ent_s)
        px, py, pz = r_s[0] + t_s * r_s[3], r_s[1] + t_s * r_s[4], r_s[2] + t_s * r_s[5]
        pu = qb[0] * px + qb[1] * py + qb[2] * pz + qb[3]
        pv = qb[4] * px + qb[5] * py + qb[6] * pz + qb[7]
        alpha = torch.clamp_max(qb[8] * torch.exp(-0.5 * (pu * pu + pv * pv)), max_alpha)
        hs = torch.nonzero(alpha >= accel.alpha_min).squeeze(1)
        hidx = sel.index_select(0, hs)
        h_rec, h_t = rec_of.index_select(0, hidx), t_s.index_select(0, hs)
        rin, rout = r_s[6].index_select(0, hs), r_s[7].index_select(0, hs)
        ray_local = ray_rec.index_select(0, h_rec)
        # order: record (ray-major, cells front to back), then t within the cell
        frac = (h_t - rin) / (rout - rin).clamp_min(1e-30)
        order = torch.argsort(h_rec.double() + frac.double().clamp(0.0, 0.999999))
        hidx = hidx.index_select(0, order)
        h_ray = ray_local.index_select(0, order)
        h_alpha = alpha.index_select(0, hs).index_select(0, order)
        segs = Segments(h_ray, ray_id.numel())
        la = torch.log1p(-h_alpha).double()
        before = log_t.index_select(0, h_ray) + segs.exclusive_cumsum(la)
        inc = torch.nonzero(before >= log_tmin).squeeze(1)
        out_ray.append(ray_id.index_select(0, h_ray.index_select(0, inc)))
        out_splat.append(accel.entries.index_select(0, ent.index_select(0, hidx.index_select(0, inc))))
        log_t = log_t + torch.zeros_like(log_t).index_add(0, h_ray.index_select(0, inc), la.index_select(0, inc))
        keep = torch.nonzero(alive & (log_t >= log_tmin)).squeeze(1)
        ray_id, t_cur, t_end, log_t = (v.index_select(0, keep) for v in (ray_id, t_cur, t_end, log_t))
        o, d, ci, step, t_max, t_delta = ([v.index_select(0, keep) for v in lst] for lst in (o, d, ci, step, t_max, t_delta))
    if not out_ray:
        e = torch.zeros(0, dtype=torch.long, device=dev)
        return e, e
    ray = torch.cat(out_ray)
    splat = torch.cat(out_splat)
    order = torch.argsort(ray, stable=True)  # rounds are in front-to-back order already
    return ray.index_select(0, order), splat.index_select(0, order)


def trace(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
          features: torch.Tensor | None, origins: torch.Tensor, dirs: torch.Tensor,
          t_min: torch.Tensor | float = 0.0, *, alpha_min: float = 0.01, T_min: float = 0.03,
          max_alpha: float = 0.99, accel: TraceAccel | None = None, steps_per_round: int = 8,
          ray_chunk: int = 1 << 17):
    """Trace R rays; returns (transmittance (R,), composited features (R, C) or None).

    ``dirs`` need not be unit length (t is in units of |d|). Pass ``accel`` (TraceAccel.build) to reuse
    the grid across calls; it must have been built from the same splats and opacities with the same
    ``alpha_min``. Differentiable w.r.t. opacities, features and the splat geometry (not the rays).
    ``ray_chunk`` rays are traversed at a time (peak memory of the traversal scales with it).
    """
    check_splats(means, quats, scales, opacities, features)
    if origins.dim() != 2 or origins.shape[1] != 3 or dirs.shape != origins.shape:
        raise ValueError(f"origins and dirs must both be (R, 3), got {tuple(origins.shape)}, {tuple(dirs.shape)}")
    R = origins.shape[0]
    dev, dt = means.device, means.dtype
    origins, dirs = origins.to(dev, dt), dirs.to(dev, dt)
    tmin = torch.as_tensor(t_min, dtype=dt, device=dev).detach().expand(R).contiguous()
    if accel is None:
        accel = TraceAccel.build(means, quats, scales, opacities, alpha_min=alpha_min)
    elif accel.num_splats != means.shape[0] or abs(accel.alpha_min - alpha_min) > 0:
        raise ValueError("accel was built for a different splat set or alpha_min; rebuild it")
    with torch.no_grad():  # rays in chunks bound the candidate buffers (memory linear in the chunk)
        parts = [_march(accel, origins[i:i + ray_chunk].detach(), dirs[i:i + ray_chunk].detach(),
                        tmin[i:i + ray_chunk], T_min, max_alpha, steps_per_round)
                 for i in range(0, R, ray_chunk)]
        ray = torch.cat([p[0] + i * ray_chunk for i, p in enumerate(parts)]) if parts else tmin.new_zeros(0).long()
        splat = torch.cat([p[1] for p in parts]) if parts else ray
    # differentiable recomputation on the composited hits only (rays are treated as constants)
    q = _gather_cols(torch.cat([_splat_local(means, quats, scales).reshape(-1, 12), opacities[:, None]], 1).T, splat)
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
    out = segs.sum(((alpha * trans_before)[None, :] * _gather_cols(features.T, splat)).T)
    return transmittance, out
