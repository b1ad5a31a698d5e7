"""Dense brute-force reference rasterizer and tracer: every pixel/ray against every splat, sequential loop.

Used ONLY by tests (memory and time grow as pixels x splats). It is written independently of the fast
paths: the hit is a world-space ray-plane intersection projected on the splat's axes (not the homogeneous
cross-product form), and compositing is the literal front-to-back loop of 2DGS with its skip and stop rules.
"""
from __future__ import annotations

import torch

from .camera import Camera
from .rasterize import ALPHA_MAX, ALPHA_MIN, T_STOP, normal_from_depth_torch
from .splats import splat_frames


def _plane_hit(origin, dirs, mean, a, b, nrm):
    """Ray-plane hit: ray parameter t and local coordinates (u, v) (scaled axes a, b), for all rays."""
    denom = dirs @ nrm
    ok = denom.abs() > 1e-30
    denom_s = torch.where(ok, denom, torch.ones_like(denom))
    t = ((mean - origin) * nrm).sum(-1) / denom_s if origin.dim() > 1 else ((mean - origin) @ nrm) / denom_s
    hit = origin + t[:, None] * dirs
    rel = hit - mean
    u = rel @ a / (a @ a)
    v = rel @ b / (b @ b)
    return t, u, v, ok


def rasterize_dense(means, quats, scales, opacities, features, camera: Camera, background=None, *, near=0.01,
                    depth_ratio=0.0, distortion_near=0.2, distortion_far=100.0) -> dict:
    dev, dt = means.device, means.dtype
    cam = camera.to(dev, dt)
    H, W = cam.height, cam.width
    origin, _ = cam.pixel_rays()
    ys = torch.arange(H, device=dev, dtype=dt) + 0.5
    xs = torch.arange(W, device=dev, dtype=dt) + 0.5
    y, x = torch.meshgrid(ys, xs, indexing="ij")
    x, y = x.reshape(-1), y.reshape(-1)
    # camera-space direction with z = 1, so the ray parameter is the camera depth
    d_cam = torch.stack([(x - cam.cx) / cam.focal, (y - cam.cy) / cam.focal, torch.ones_like(x)], -1)
    dirs = d_cam @ cam.c2w[:3, :3].T
    eye = cam.center
    a_all, b_all, n_all = splat_frames(quats, scales)
    p_cam = means @ cam.w2c[:3, :3].T + cam.w2c[:3, 3]
    zc = p_cam[:, 2]
    order = torch.argsort(zc.detach(), stable=True)
    C = features.shape[1]
    P = H * W
    zeros = torch.zeros(P, dtype=dt, device=dev)
    T = torch.ones(P, dtype=dt, device=dev)
    done = torch.zeros(P, dtype=torch.bool, device=dev)
    feat = torch.zeros(P, C, dtype=dt, device=dev)
    nrm_img = torch.zeros(P, 3, dtype=dt, device=dev)
    dsum, med, dist, acc_w, m1, m2 = zeros, zeros, zeros, zeros, zeros, zeros
    scale_ndc = distortion_far / (distortion_far - distortion_near)
    for k in order.tolist():
        if float(zc[k].detach()) < near or float(opacities[k].detach()) < ALPHA_MIN:
            continue
        t, u, v, ok = _plane_hit(eye, dirs, means[k], a_all[k], b_all[k], n_all[k])
        rho3 = torch.where(ok, u * u + v * v, torch.full_like(u, float("inf")))
        cx = cam.focal * p_cam[k, 0] / zc[k] + cam.cx
        cy = cam.focal * p_cam[k, 1] / zc[k] + cam.cy
        rho2 = 2.0 * ((x - cx) ** 2 + (y - cy) ** 2)
        use3 = rho3 <= rho2
        rho = torch.where(use3, rho3, rho2)
        depth = torch.where(use3, t, zc[k].expand(P))
        alpha = torch.clamp(opacities[k] * torch.exp(-0.5 * rho), max=ALPHA_MAX)
        take = (~done) & (alpha >= ALPHA_MIN) & (depth >= near)
        test_T = T * (1.0 - alpha)
        stop = take & (test_T < T_STOP)
        done = done | stop
        take = take & ~stop
        w = torch.where(take, alpha * T, zeros)
        n_face = n_all[k] if float((n_all[k] * (eye - means[k])).sum().detach()) >= 0 else -n_all[k]
        feat = feat + w[:, None] * features[k]
        nrm_img = nrm_img + w[:, None] * n_face
        dsafe = torch.where(take, depth, torch.ones_like(depth))
        m = scale_ndc * (1.0 - distortion_near / dsafe)
        dist = dist + w * (m * m * acc_w + m2 - 2.0 * m * m1)
        acc_w, m1, m2 = acc_w + w, m1 + w * m, m2 + w * m * m
        dsum = dsum + w * dsafe
        med = torch.where(take & (T > 0.5), depth, med)
        T = torch.where(take, test_T, T)
    alpha_img = 1.0 - T
    if background is not None:
        feat = feat + T[:, None] * background.to(dev, dt)
    d_exp = torch.where(alpha_img > 0, dsum / alpha_img.clamp_min(1e-10), zeros)
    d_exp = d_exp.reshape(H, W)
    med = med.reshape(H, W)
    surf = d_exp * (1 - depth_ratio) + med * depth_ratio
    return dict(features=feat.reshape(H, W, C), alpha=alpha_img.reshape(H, W), normal=nrm_img.reshape(H, W, 3),
                depth_expected=d_exp, depth_median=med, distortion=dist.reshape(H, W),
                normal_from_depth=normal_from_depth_torch(surf, cam))


def trace_dense(means, quats, scales, opacities, features, origins, dirs, t_min=0.0, *, alpha_min=0.01,
                T_min=0.03, max_alpha=0.99):
    """Every ray against every splat; hits sorted by t per ray; sequential front-to-back loop."""
    R = origins.shape[0]
    dev, dt = means.device, means.dtype
    a, b, nrm = splat_frames(quats, scales)
    tmin = torch.as_tensor(t_min, dtype=dt, device=dev).expand(R)
    denom = dirs @ nrm.T  # (R, N)
    ok = denom.abs() > 1e-30
    denom = torch.where(ok, denom, torch.ones_like(denom))
    t = ((means[None] - origins[:, None]) * nrm[None]).sum(-1) / denom
    rel = origins[:, None] + t[..., None] * dirs[:, None] - means[None]
    u = (rel * a[None]).sum(-1) / (a * a).sum(-1)
    v = (rel * b[None]).sum(-1) / (b * b).sum(-1)
    alpha = torch.clamp(opacities[None] * torch.exp(-0.5 * (u * u + v * v)), max=max_alpha)
    hit = ok & (t >= tmin[:, None]) & (alpha >= alpha_min)
    t_key = torch.where(hit, t, torch.full_like(t, float("inf"))).detach()
    order = torch.argsort(t_key, dim=1, stable=True)
    T = torch.ones(R, dtype=dt, device=dev)
    C = 0 if features is None else features.shape[1]
    out = torch.zeros(R, C, dtype=dt, device=dev)
    alive = torch.ones(R, dtype=torch.bool, device=dev)
    rows = torch.arange(R, device=dev)
    for j in range(means.shape[0]):
        k = order[:, j]
        h = hit[rows, k] & alive
        if not bool(h.any()):
            if not bool((hit[rows, k]).any()):
                break
            continue
        al = alpha[rows, k]
        w = torch.where(h, al * T, torch.zeros_like(T))
        if features is not None:
            out = out + w[:, None] * features[k]
        T = torch.where(h, T * (1.0 - al), T)
        alive = alive & ~(h & (T < T_min))
    return T, out
