"""Differentiable 2D Gaussian splat rasterizer (2DGS, Huang et al. 2024), pure PyTorch, CPU and CUDA.

This is the reference path; raster_numba.py computes the same outputs and gradients with compiled CPU
kernels, chosen by ``backend`` (method.splat.backend: on the CPU by default when numba is installed).

Per splat, M = K [s_u t_u, s_v t_v, mean] (camera frame) maps local (u, v, 1) to homogeneous screen
coordinates. The pixel (x, y) is the intersection of the planes x w - X = 0 and y w - Y = 0; pulled back
into the splat frame they are h_u = M0 - x M2 and h_v = M1 - y M2, and the hit is (u, v, 1) ~ h_u x h_v.
Expanded, h_u x h_v = A + x B + y C with A = M0 x M1, B = M1 x M2, C = M2 x M0 (per splat), and the
camera depth of the hit is det(M) / c_2. Low-pass fallback (2DGS): rho = min(u^2 + v^2, 2 |pixel - centre|^2),
so tiny or edge-on splats still cover about one pixel; its depth is then the centre's.

Compositing: splats sorted by centre depth, alpha = min(0.99, o exp(-rho / 2)); pairs with alpha < 1/255
or hit depth < near are skipped; a pixel stops at the splat that would take its transmittance below 1e-4
(that splat is not composited, as in 3DGS/2DGS).

Scaling: (1) without gradients, per-splat screen bounds of the support (the ellipse where alpha can reach
1/255, union the fallback disc) and culling; (2) per splat and pixel row, the closed-form x-span of that
support, the exact alpha test on the pixels of the spans, a sort by (pixel, depth rank), transmittance by a
segmented log-sum, and the cut at the stop; (3) with gradients, only the surviving pairs are recomputed
(intersection and compositing each an autograd.Function with an analytic backward). Memory is linear in
the number of pairs. Pixel coordinates are centred on the principal point inside (float32 conditioning).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .backend import resolve
from .camera import Camera
from .composite import composite
from .segments import Segments, gather_cols
from .splats import check_splats, splat_frames

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_STOP = 1e-4
# Candidate rows are grouped by span length, exact up to this length and then by powers of two; each
# group costs ~25 kernel launches and a sync. CPU keeps the exact lengths up to 12 its targets were
# measured with (powers of two only: x0.99 and x1.07 in two A/B runs at 100 px / 20k, no gain); CUDA,
# where launches dominate, uses powers of two (x0.76 at 800 px / 300k, BENCHMARKS.md). Indexed by
# "is CUDA"; method.splat.bench_ab switches it.
EXACT_SPAN_MAX = {False: 12, True: 2}


@dataclass
class RasterOutput:
    """Per-pixel outputs (H, W, ...) plus per-splat visibility for densification.

    ``normal`` is the alpha-weighted sum of camera-facing world normals (length <= alpha, as in 2DGS);
    ``depth_expected`` is sum(w z) / alpha (0 where alpha = 0); ``depth_median`` is the depth of the splat
    at which transmittance crosses 0.5 (the last one if it never does; 0 where nothing is hit);
    ``distortion`` is sum_{i>j} w_i w_j (m_i - m_j)^2 with m the NDC-mapped depth;
    ``normal_from_depth`` is the unit normal of the surface unprojected from the rendered depth.
    """

    features: torch.Tensor
    alpha: torch.Tensor
    normal: torch.Tensor
    depth_expected: torch.Tensor
    depth_median: torch.Tensor
    distortion: torch.Tensor
    normal_from_depth: torch.Tensor
    visible: torch.Tensor  # (N,) bool: splat contributes to at least one pixel
    radii: torch.Tensor  # (N,) screen-space half extent of the support in pixels (0 if culled)
    num_pairs: int


def project_splats(means, quats, scales, opacities, camera: Camera):
    """Per-splat screen-space quantities (differentiable): A, B, C (N, 3 each), det(M), projected centre,
    centre depth, and the camera-facing world normal."""
    tu, tv, nrm = splat_frames(quats, scales)
    rot, trans = camera.w2c[:3, :3], camera.w2c[:3, 3]
    p = means @ rot.T + trans
    a = tu @ rot.T
    b = tv @ rot.T
    f = camera.focal
    # rows of M = K [a b p] with K = [[f, 0, 0], [0, f, 0], [0, 0, 1]] (centred pixels)
    m2 = torch.stack([a[:, 2], b[:, 2], p[:, 2]], -1)
    # pixel coordinates are centred on the principal point (x - cx, y - cy): better conditioned in float32
    m0 = f * torch.stack([a[:, 0], b[:, 0], p[:, 0]], -1)
    m1 = f * torch.stack([a[:, 1], b[:, 1], p[:, 1]], -1)
    A = torch.linalg.cross(m0, m1)
    B = torch.linalg.cross(m1, m2)
    C = torch.linalg.cross(m2, m0)
    det = (m2 * A).sum(-1)
    z = p[:, 2]
    zs = torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
    centre = torch.stack([f * p[:, 0] / zs, f * p[:, 1] / zs], -1)  # centred pixel coordinates
    view = camera.center - means
    facing = torch.where((nrm * view).sum(-1, keepdim=True) < 0, -nrm, nrm)
    return dict(A=A, B=B, C=C, det=det, centre=centre, z=z, normal=facing, m0=m0, m1=m1, m2=m2)


def _shift_rows(rows, shift):
    """Rows of footprints translated by ``shift`` pixels: evaluating at (x - sx, y - sy)."""
    sx, sy = shift[:, :1], shift[:, 1:2]
    a = rows[:, 0:3] - sx * rows[:, 3:6] - sy * rows[:, 6:9]
    return torch.cat([a, rows[:, 3:10], rows[:, 10:12] + shift, rows[:, 12:]], 1)


def _screen_bounds(proj, opacities, camera: Camera, near: float, shift=None):
    """No-grad pixel bounding boxes (inclusive) of each splat's support; also a validity mask and radii."""
    m0, m1, m2 = proj["m0"], proj["m1"], proj["m2"]
    o = opacities.detach()
    log_t = torch.log((o / ALPHA_MIN).clamp_min(1.0))  # G >= 1/(255 o)  <=>  rho <= 2 log(255 o)
    k2 = 2.0 * log_t
    # dual conic of the support ellipse: C* = M diag(k2, k2, -1) M^T; tangent lines x = X solve
    # C*00 - 2 X C*02 + X^2 C*22 = 0.
    def dual(r, s):
        return k2 * (r[:, 0] * s[:, 0] + r[:, 1] * s[:, 1]) - r[:, 2] * s[:, 2]

    c00, c11, c22 = dual(m0, m0), dual(m1, m1), dual(m2, m2)
    c02, c12 = dual(m0, m2), dual(m1, m2)
    bounded = c22 < -1e-12 * (m2[:, 2] ** 2).clamp_min(1e-30)
    c22s = torch.where(bounded, c22, torch.full_like(c22, -1.0))
    ex = torch.sqrt((c02 * c02 - c00 * c22s).clamp_min(0.0)) / (-c22s)
    ey = torch.sqrt((c12 * c12 - c11 * c22s).clamp_min(0.0)) / (-c22s)
    mx, my = c02 / c22s, c12 / c22s
    ctr = proj["centre"]
    rd = torch.sqrt(log_t)  # fallback disc: 2 d^2 <= 2 log(255 o)
    xmin = torch.minimum(mx - ex, ctr[:, 0] - rd)
    xmax = torch.maximum(mx + ex, ctr[:, 0] + rd)
    ymin = torch.minimum(my - ey, ctr[:, 1] - rd)
    ymax = torch.maximum(my + ey, ctr[:, 1] + rd)
    xmin, xmax, ymin, ymax = xmin + camera.cx, xmax + camera.cx, ymin + camera.cy, ymax + camera.cy
    if shift is not None:
        xmin, xmax, ymin, ymax = xmin + shift[:, 0], xmax + shift[:, 0], ymin + shift[:, 1], ymax + shift[:, 1]
    big = float(max(camera.width, camera.height)) * 4.0 + 10.0
    xmin = torch.where(bounded, xmin, torch.full_like(xmin, -big)).clamp(-big, big)
    xmax = torch.where(bounded, xmax, torch.full_like(xmax, big)).clamp(-big, big)
    ymin = torch.where(bounded, ymin, torch.full_like(ymin, -big)).clamp(-big, big)
    ymax = torch.where(bounded, ymax, torch.full_like(ymax, big)).clamp(-big, big)
    pad = 1e-3
    x0 = torch.ceil(xmin - 0.5 - pad).long().clamp_min(0)
    x1 = torch.floor(xmax - 0.5 + pad).long().clamp_max(camera.width - 1)
    y0 = torch.ceil(ymin - 0.5 - pad).long().clamp_min(0)
    y1 = torch.floor(ymax - 0.5 + pad).long().clamp_max(camera.height - 1)
    valid = (proj["z"] >= near) & (o >= ALPHA_MIN) & (x1 >= x0) & (y1 >= y0)
    radii = torch.where(valid, torch.maximum(xmax - xmin, ymax - ymin) * 0.5, torch.zeros_like(xmin))
    return x0, x1, y0, y1, valid, radii, bounded, k2


def _pair_terms(g, x, y):
    """Shared forward algebra of packed pairs, g = (14, P) gathered rows (structure of arrays)."""
    c0 = g[0] + x * g[3] + y * g[6]
    c1 = g[1] + x * g[4] + y * g[7]
    c2 = g[2] + x * g[5] + y * g[8]
    tiny = 1e-30 if c2.dtype == torch.float64 else 1e-20
    grazing = c2.abs() <= tiny  # the pixel ray lies in the splat's plane: no hit, only the fallback
    c2 = torch.where(grazing, torch.full_like(c2, tiny), c2)
    inv = 1.0 / c2
    u = c0 * inv
    v = c1 * inv
    rho3 = u * u + v * v
    dx = x - g[10]
    dy = y - g[11]
    rho2 = 2.0 * (dx * dx + dy * dy)
    use3 = (rho3 <= rho2) & ~grazing
    return u, v, inv, rho3, dx, dy, rho2, use3


class _PairAlpha(torch.autograd.Function):
    """alpha, hit depth of packed pairs from gathered per-splat rows g (14, P) (see _pack_rows), with a
    fused backward (autograd on slices would allocate a full zero tensor per slice). Rows are kept as a
    structure of arrays: gathers and scatter-adds of (14, P) run ~2x faster on CPU than of (P, 14)."""

    @staticmethod
    def forward(ctx, g, x, y):
        u, v, inv, rho3, dx, dy, rho2, use3 = _pair_terms(g, x, y)
        rho = torch.where(use3, rho3, rho2)
        gauss = torch.exp(-0.5 * rho)
        raw = g[13] * gauss
        alpha = torch.clamp_max(raw, ALPHA_MAX)
        depth = torch.where(use3, g[9] * inv, g[12])
        ctx.save_for_backward(g, x, y, u, v, inv, dx, dy, use3, gauss, raw < ALPHA_MAX, depth)
        return alpha, depth

    @staticmethod
    def backward(ctx, g_alpha, g_depth):
        g, x, y, u, v, inv, dx, dy, use3, gauss, unclamped, depth = ctx.saved_tensors
        ga = torch.where(unclamped, g_alpha, torch.zeros_like(g_alpha))
        g_o = ga * gauss
        g_rho = g_o * g[13] * -0.5
        g3 = torch.where(use3, g_rho, torch.zeros_like(g_rho))
        gd3 = torch.where(use3, g_depth, torch.zeros_like(g_depth))
        g2 = g_rho - g3
        # where the fallback is used (or the ray grazes the plane, c2 ~ 0) u, v and inv can overflow to inf:
        # select instead of multiplying by a zero gradient, which would give 0 * inf = NaN
        zero = torch.zeros_like(g3)
        gc0 = torch.where(use3, 2.0 * g3 * u * inv, zero)
        gc1 = torch.where(use3, 2.0 * g3 * v * inv, zero)
        gc2 = torch.where(use3, -(2.0 * g3 * (u * u + v * v) + gd3 * depth) * inv, zero)
        gcx = -4.0 * g2 * dx
        gcy = -4.0 * g2 * dy
        out = torch.stack([gc0, gc1, gc2, x * gc0, x * gc1, x * gc2, y * gc0, y * gc1, y * gc2, gd3 * inv,
                           gcx, gcy, g_depth - gd3, g_o], 0)
        gx = gy = None
        if ctx.needs_input_grad[1] or ctx.needs_input_grad[2]:
            gx = gc0 * g[3] + gc1 * g[4] + gc2 * g[5] - gcx
            gy = gc0 * g[6] + gc1 * g[7] + gc2 * g[8] - gcy
        return out, gx, gy


def _pair_alpha(g, x, y):
    """Alpha and hit depth of packed pairs; differentiable w.r.t. the rows g and the pixel position."""
    if torch.is_grad_enabled() and (g.requires_grad or x.requires_grad or y.requires_grad):
        return _PairAlpha.apply(g, x, y)
    return _PairAlpha.forward(_NoCtx(), g, x, y)


class _NoCtx:
    def save_for_backward(self, *args):
        pass


def _pack_rows(proj, opacities):
    """(N, 14) per-splat rows: A, B, C, det, centre x, centre y, centre depth, opacity."""
    return torch.cat([proj["A"], proj["B"], proj["C"], proj["det"][:, None], proj["centre"],
                      proj["z"][:, None], opacities[:, None]], 1)


def _candidate_spans(rows, x0, x1, y0, y1, valid, bounded, k2, width: int, near: float, cx: float, cy: float,
                     margin: float = 0.01):
    """No-grad: (splat, pixel) pairs with alpha >= 1/255 and hit depth >= near, unordered.

    Per splat and pixel row, the x-interval of the support is solved in closed form: the ellipse
    c0^2 + c1^2 <= k^2 c2^2 with c = (A + y C) + x B is a quadratic in x, hulled with the fallback disc.
    Only pixels inside these spans (a few percent more than the final pairs) are gathered and tested.
    """
    dev, dt = rows.device, rows.dtype
    idx = torch.nonzero(valid).squeeze(1)
    h = (y1 - y0 + 1)[idx]
    n_rows = int(h.sum()) if idx.numel() else 0
    if n_rows == 0:
        e = torch.zeros(0, dtype=torch.long, device=dev)
        return e, e, torch.zeros(0, dtype=dt, device=dev)
    r_local = torch.repeat_interleave(torch.arange(idx.numel(), device=dev), h, output_size=n_rows)
    first = torch.cumsum(h, 0) - h
    r_sid = idx.index_select(0, r_local)
    r_y = y0.index_select(0, r_sid) + torch.arange(n_rows, device=dev) - first.index_select(0, r_local)
    # per-row splat parameters as 1-D gathers (structure of arrays: ~3x faster than 2-D row gathers)
    g = [col.index_select(0, r_sid) for col in rows.T.contiguous().unbind(0)]
    kk = k2.index_select(0, r_sid)
    yc = r_y.to(dt) + (0.5 - cy)
    a0, a1, a2 = g[0] + yc * g[6], g[1] + yc * g[7], g[2] + yc * g[8]
    b0, b1, b2 = g[3], g[4], g[5]
    qa = b0 * b0 + b1 * b1 - kk * b2 * b2
    qb = a0 * b0 + a1 * b1 - kk * a2 * b2
    qc = a0 * a0 + a1 * a1 - kk * a2 * a2
    disc = qb * qb - qa * qc
    ell = (qa > 0) & (disc >= 0)
    sq = torch.sqrt(disc.clamp_min(0.0))
    qa_s = torch.where(qa > 0, qa, torch.ones_like(qa))
    inf = torch.full_like(qa, float("inf"))
    lo = torch.where(ell, (-qb - sq) / qa_s, inf)
    hi = torch.where(ell, (-qb + sq) / qa_s, -inf)
    dy = yc - g[11]
    dd = 0.5 * kk - dy * dy
    disk = dd >= 0
    sd = torch.sqrt(dd.clamp_min(0.0))
    lo = torch.where(disk, torch.minimum(lo, g[10] - sd), lo)
    hi = torch.where(disk, torch.maximum(hi, g[10] + sd), hi)
    # unbounded footprints (support crossing the camera plane) and degenerate quadratics: whole box row
    full = ~bounded.index_select(0, r_sid) | (qa <= 0)
    bx0, bx1 = x0.index_select(0, r_sid), x1.index_select(0, r_sid)
    lim = float(width) + 2.0
    j0 = torch.ceil((lo + (cx - 0.5 - margin)).clamp(-lim, lim)).long()
    j1 = torch.floor((hi + (cx - 0.5 + margin)).clamp(-lim, lim)).long()
    j0 = torch.where(full, bx0, torch.maximum(j0, bx0))
    j1 = torch.where(full, bx1, torch.minimum(j1, bx1))
    cnt = (j1 - j0 + 1).clamp_min(0)
    # per-pixel exact test: rows grouped by span length (exact up to 12 on CPU, then powers of two) and each
    # group evaluated densely with broadcasting; rows are permuted once so that groups are contiguous
    # slices (no per-pixel and no per-group gathers of splat parameters)
    pow2 = torch.pow(2, torch.ceil(torch.log2(cnt.clamp_min(1).double()))).long()
    exact_max = EXACT_SPAN_MAX[dev.type == "cuda"]
    lw = torch.where(cnt <= exact_max, cnt, pow2)
    perm = torch.argsort(lw)
    lw_sorted = lw.index_select(0, perm)
    levels, sizes = torch.unique_consecutive(lw_sorted, return_counts=True)
    rowp = [v.index_select(0, perm) for v in (a0, a1, a2, b0, b1, b2, g[10], dy * dy, g[9], g[12], g[13])]
    j0p, cntp = j0.index_select(0, perm), cnt.index_select(0, perm)
    out_r, out_x, out_a = [], [], []
    tiny = 1e-30 if dt == torch.float64 else 1e-20
    lo_i = 0
    for lev, size in zip(levels.tolist(), sizes.tolist()):
        sl = slice(lo_i, lo_i + size)
        lo_i += size
        if lev <= 0:  # empty spans
            continue
        S = lev
        ar = torch.arange(S, device=dev)
        col = [v[sl, None] for v in rowp]
        xi = j0p[sl, None] + ar[None, :]
        x = xi.to(dt) + (0.5 - cx)
        c0 = col[0] + x * col[3]
        c1 = col[1] + x * col[4]
        c2 = col[2] + x * col[5]
        grazing = c2.abs() <= tiny
        c2 = torch.where(grazing, torch.full_like(c2, tiny), c2)
        inv = 1.0 / c2
        rho3 = (c0 * c0 + c1 * c1) * (inv * inv)
        ddx = x - col[6]
        rho2 = 2.0 * (ddx * ddx + col[7])
        use3 = (rho3 <= rho2) & ~grazing
        alpha = torch.clamp_max(col[10] * torch.exp(-0.5 * torch.where(use3, rho3, rho2)), ALPHA_MAX)
        depth = torch.where(use3, col[8] * inv, col[9])
        ok = (alpha >= ALPHA_MIN) & (depth >= near)
        if S > exact_max:  # padded group: mask the pixels past each row's span
            ok &= ar[None, :] < cntp[sl, None]
        flat = torch.nonzero(ok.reshape(-1)).squeeze(1)
        out_r.append(perm[sl].index_select(0, torch.div(flat, S, rounding_mode="floor")))
        out_x.append(xi.reshape(-1).index_select(0, flat))
        out_a.append(alpha.reshape(-1).index_select(0, flat))
    if not out_r:
        e = torch.zeros(0, dtype=torch.long, device=dev)
        return e, e, torch.zeros(0, dtype=dt, device=dev)
    r = torch.cat(out_r)
    return r_sid.index_select(0, r), r_y.index_select(0, r) * width + torch.cat(out_x), torch.cat(out_a)


def _select_pairs(proj, opacities, cam: Camera, near: float, screen_offsets):
    """No-grad selection of the composited (pixel, splat) pairs, sorted by pixel then front to back."""
    n = opacities.shape[0]
    H, W = cam.height, cam.width
    dev = opacities.device
    detached = {k: v.detach() for k, v in proj.items()}
    shift = None if screen_offsets is None else screen_offsets.detach()
    x0, x1, y0, y1, valid, radii, bounded, k2 = _screen_bounds(detached, opacities, cam, near, shift)
    rows = _pack_rows(detached, opacities.detach())
    if shift is not None:
        rows = _shift_rows(rows, shift)
    with torch.profiler.record_function("splat:candidates"):
        sid, pix, alpha = _candidate_spans(rows, x0, x1, y0, y1, valid, bounded, k2, W, near, cam.cx, cam.cy)
    with torch.profiler.record_function("splat:sort_and_stop"):
        rank = torch.empty(n, dtype=torch.long, device=dev)
        rank[torch.argsort(detached["z"], stable=True)] = torch.arange(n, device=dev)
        key = pix * n + rank.index_select(0, sid)  # unique: (pixel, depth rank)
        order = torch.argsort(key.int() if H * W * n < 2 ** 31 else key)
        sid, pix, alpha = sid.index_select(0, order), pix.index_select(0, order), alpha.index_select(0, order)
        la = torch.log1p(-alpha).double()
        log_after = Segments(pix, H * W).exclusive_cumsum(la) + la
        live = torch.nonzero(log_after >= math.log(T_STOP)).squeeze(1)  # T after the pair >= 1e-4
        sid, pix = sid.index_select(0, live), pix.index_select(0, live)
        visible = torch.zeros(n, dtype=torch.bool, device=dev)
        visible[sid] = True
    return sid, pix, Segments(pix, H * W), visible, radii


def rasterize(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
              features: torch.Tensor, camera: Camera, background: torch.Tensor | None = None, *,
              near: float = 0.01, depth_ratio: float = 0.0, distortion_near: float = 0.2,
              distortion_far: float = 100.0, screen_offsets: torch.Tensor | None = None,
              backend: str | None = None) -> RasterOutput:
    """Render N splats with C-channel ``features`` into ``camera``.

    ``screen_offsets`` (N, 2), optional, is added to each splat's footprint position in pixels; pass zeros
    with requires_grad to read the screen-space positional gradient (densification statistic).
    ``depth_ratio`` blends expected (0) and median (1) depth for ``normal_from_depth``.
    ``backend``: 'auto', 'torch' or 'numba' (method.splat.backend; None: the process default).
    """
    check_splats(means, quats, scales, opacities, features)
    H, W = camera.height, camera.width
    dev, dt = means.device, means.dtype
    cam = camera if (camera.device == dev and camera.dtype == dt) else camera.to(dev, dt)
    m_scale = distortion_far / (distortion_far - distortion_near)
    C = features.shape[1]
    if resolve(backend, dev) == "numba":
        from .raster_numba import rasterize_compiled  # numba is optional: imported only when this backend runs

        with torch.profiler.record_function("splat:compiled"):
            acc, dsum, dist, log_t, med, visible, radii, num_pairs = rasterize_compiled(
                means, quats, scales, opacities, features, cam, near, screen_offsets, m_scale, distortion_near,
                ALPHA_MIN, T_STOP)
    else:
        with torch.profiler.record_function("splat:project"):
            proj = project_splats(means, quats, scales, opacities, cam)
        acc, dsum, dist, log_t, med, visible, radii, num_pairs = _composite_torch(
            proj, opacities, features, cam, near, screen_offsets, m_scale, distortion_near)
    t_final = torch.exp(log_t)
    alpha_img = 1.0 - t_final
    feat = acc[:, :C]
    if background is not None:
        feat = feat + t_final[:, None] * background.to(dev, dt)[None, :]
    depth_exp = dsum / alpha_img.clamp_min(1e-10)
    out_depth_exp = depth_exp.reshape(H, W)
    out_med = med.reshape(H, W)
    surf = out_depth_exp * (1.0 - depth_ratio) + out_med * depth_ratio if depth_ratio else out_depth_exp
    return RasterOutput(
        features=feat.reshape(H, W, C), alpha=alpha_img.reshape(H, W), normal=acc[:, C:C + 3].reshape(H, W, 3),
        depth_expected=out_depth_exp, depth_median=out_med, distortion=dist.reshape(H, W),
        normal_from_depth=normal_from_depth(surf, cam, backend), visible=visible, radii=radii, num_pairs=num_pairs)


def _composite_torch(proj, opacities, features, cam: Camera, near, screen_offsets, m_scale, m_near):
    """The reference path: per-pixel sums (HW, C + 3), sum w z, distortion, log T, median depth; visible,
    radii and the pair count. No-grad selection of the pairs, then the survivors with gradients."""
    H, W = cam.height, cam.width
    dev, dt = features.device, features.dtype
    with torch.no_grad():
        sid, pix, segs, visible, radii = _select_pairs(proj, opacities, cam, near, screen_offsets)
    rows = _pack_rows(proj, opacities)
    if screen_offsets is not None:
        rows = _shift_rows(rows, screen_offsets)
    g = gather_cols(rows.T, sid)
    px = (pix % W).to(dt) + (0.5 - cam.cx)  # centred pixel coordinates
    py = torch.div(pix, W, rounding_mode="floor").to(dt) + (0.5 - cam.cy)
    with torch.profiler.record_function("splat:pair_alpha"):
        alpha, depth = _pair_alpha(g, px, py)
    attrs = gather_cols(torch.cat([features, proj["normal"]], 1).T, sid).T
    with torch.profiler.record_function("splat:composite"):
        acc, dsum, dist, log_t, trans = composite(alpha, depth, attrs, segs, m_scale, m_near)
    with torch.no_grad():
        cand = torch.where(trans > 0.5, torch.arange(sid.numel(), device=dev), torch.full_like(sid, -1))
        last = torch.full((H * W,), -1, dtype=torch.long, device=dev).scatter_reduce(0, pix, cand, "amax")
        # never crossing 0.5 still has a last contributor: T > 0.5 holds for the first pair of each pixel
        has = last >= 0
    if sid.numel():
        med = torch.where(has, depth[last.clamp_min(0)], torch.zeros((), dtype=dt, device=dev))
    else:
        med = torch.zeros(H * W, dtype=dt, device=dev) + 0.0 * depth.sum()
    return acc, dsum, dist, log_t, med, visible, radii, int(sid.numel())


def normal_from_depth(depth: torch.Tensor, camera: Camera, backend: str | None = None) -> torch.Tensor:
    """World-space unit normals (facing the camera) from a camera-z depth map by central differences;
    the one-pixel border is zero. By the compiled kernel (depth_normals_numba.py) where ``backend``
    resolves to Numba (CPU tensors), by the torch reference below otherwise."""
    if resolve(backend, depth.device) == "numba":
        from .depth_normals_numba import normal_from_depth_compiled

        cam = camera if (camera.device == depth.device and camera.dtype == depth.dtype) else camera.to(
            depth.device, depth.dtype)
        return normal_from_depth_compiled(depth, cam)
    return normal_from_depth_torch(depth, camera)


def normal_from_depth_torch(depth: torch.Tensor, camera: Camera) -> torch.Tensor:
    """``normal_from_depth`` in torch: the reference, and the CUDA path."""
    H, W = depth.shape
    dev, dt = depth.device, depth.dtype
    ys = torch.arange(H, device=dev, dtype=dt) + 0.5
    xs = torch.arange(W, device=dev, dtype=dt) + 0.5
    y, x = torch.meshgrid(ys, xs, indexing="ij")
    d_cam = torch.stack([(x - camera.cx) / camera.focal, (y - camera.cy) / camera.focal, torch.ones_like(x)], -1)
    d_world = d_cam @ camera.c2w[:3, :3].to(dev, dt).T
    pts = camera.center.to(dev, dt) + depth[..., None] * d_world
    out = torch.zeros(H, W, 3, dtype=dt, device=dev)
    if H < 3 or W < 3:
        return out
    dy = pts[2:, 1:-1] - pts[:-2, 1:-1]  # along image rows (down)
    dx = pts[1:-1, 2:] - pts[1:-1, :-2]  # along columns (right)
    n = torch.linalg.cross(dy, dx)  # down x right = towards the camera
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return torch.nn.functional.pad(n.permute(2, 0, 1), (1, 1, 1, 1)).permute(1, 2, 0)
