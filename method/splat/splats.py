"""Splat parameters -> world-space frames, plus the input checks shared by the rasterizer and tracer.

A 2D Gaussian splat is the disc P(u, v) = mean + s_u t_u u + s_v t_v v, with (t_u, t_v, n) the columns of
the rotation of its (normalised, w-x-y-z) quaternion; G(u, v) = exp(-(u^2 + v^2) / 2).
"""
from __future__ import annotations

import torch


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """(N, 4) w-x-y-z quaternions (normalised here, so gradients see the normalisation) -> (N, 3, 3)."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(q.shape[:-1] + (3, 3))


def splat_frames(quats: torch.Tensor, scales: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Scaled tangent axes s_u t_u, s_v t_v and the unit normal t_u x t_v, each (N, 3)."""
    r = quat_to_rotmat(quats)
    return r[:, :, 0] * scales[:, :1], r[:, :, 1] * scales[:, 1:2], r[:, :, 2]


def check_splats(means, quats, scales, opacities, features=None) -> int:
    """Validate shapes/devices of the splat tensors; return N. Raises ValueError naming the argument."""
    if means.dim() != 2 or means.shape[1] != 3:
        raise ValueError(f"means must be (N, 3), got {tuple(means.shape)}")
    n = means.shape[0]
    expect = {"quats": (quats, (n, 4)), "scales": (scales, (n, 2)), "opacities": (opacities, (n,))}
    for name, (t, shape) in expect.items():
        if tuple(t.shape) != shape:
            raise ValueError(f"{name} must be {shape}, got {tuple(t.shape)}")
        if t.device != means.device:
            raise ValueError(f"{name} is on {t.device}, means on {means.device}")
    if features is not None:
        if features.dim() != 2 or features.shape[0] != n:
            raise ValueError(f"features must be (N, C) with N = {n}, got {tuple(features.shape)}")
        if features.device != means.device:
            raise ValueError(f"features is on {features.device}, means on {means.device}")
    return n
