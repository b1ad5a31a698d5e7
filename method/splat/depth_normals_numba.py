"""``rasterize.normal_from_depth`` as compiled CPU kernels, forward and backward.

Why: in torch the depth map's normals are a dozen ops over (H, W, 3) images (the rays, the points, two
central differences, a cross product, a norm, a division, a pad) and their backward; with the stage-1
normal-consistency loss that took ~4-5 ms of a `small` step at 128 px on an AVX2 box, and the forward
runs at every step (BENCHMARKS.md, issue 23, session 40). Here each pixel is one pass, float64 inside;
``rasterize.normal_from_depth_torch`` stays the reference (and the CUDA path), and tests hold this one to it.

Model (as the reference): p = c + z d with d = R (x', y', 1) the pixel's ray (R the camera-to-world
rotation), a = p[i+1, j] - p[i-1, j], b = p[i, j+1] - p[i, j-1], n = a x b, out = n / max(|n|, 1e-12) on
the interior, zero on the one-pixel border. Backward: g_n = (g - out (out . g)) / |n| (g / 1e-12 where
the clamp holds), g_a = b x g_n, g_b = g_n x a, and each point's gradient gathered from its four
neighbours' differences (no two threads write one pixel), g_z = d . g_p.
"""
from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba import njit, prange

from .raster_numba import as_f64, match_torch_threads

TINY = 1e-12  # as the reference's clamp_min


@njit(cache=True, inline="always", error_model="numpy")
def _ray(rot, f, cx, cy, i, j):
    """The world-space ray (not normalised; camera z = 1) through pixel (row i, column j)'s centre."""
    u = (j + 0.5 - cx) / f
    v = (i + 0.5 - cy) / f
    return (rot[0, 0] * u + rot[0, 1] * v + rot[0, 2], rot[1, 0] * u + rot[1, 1] * v + rot[1, 2],
            rot[2, 0] * u + rot[2, 1] * v + rot[2, 2])


@njit(cache=True, inline="always", error_model="numpy")
def _point(z, rot, centre, f, cx, cy, i, j):
    d0, d1, d2 = _ray(rot, f, cx, cy, i, j)
    zz = z[i, j]
    return centre[0] + zz * d0, centre[1] + zz * d1, centre[2] + zz * d2


@njit(cache=True, inline="always", error_model="numpy")
def _differences(z, rot, centre, f, cx, cy, i, j):
    """a = p[i+1, j] - p[i-1, j] and b = p[i, j+1] - p[i, j-1] at an interior pixel."""
    u0, u1, u2 = _point(z, rot, centre, f, cx, cy, i + 1, j)
    w0, w1, w2 = _point(z, rot, centre, f, cx, cy, i - 1, j)
    r0, r1, r2 = _point(z, rot, centre, f, cx, cy, i, j + 1)
    l0, l1, l2 = _point(z, rot, centre, f, cx, cy, i, j - 1)
    return u0 - w0, u1 - w1, u2 - w2, r0 - l0, r1 - l1, r2 - l2


@njit(cache=True, inline="always", error_model="numpy")
def _cross(a0, a1, a2, b0, b1, b2):
    """a x b."""
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@njit(cache=True, parallel=True, error_model="numpy")
def normals_forward(z, rot, centre, f, cx, cy):
    """z (H, W) camera-z depth -> unit normals (H, W, 3), zero on the border."""
    height, width = z.shape
    out = np.zeros((height, width, 3))
    if height < 3 or width < 3:
        return out
    for i in prange(1, height - 1):
        for j in range(1, width - 1):
            a0, a1, a2, b0, b1, b2 = _differences(z, rot, centre, f, cx, cy, i, j)
            n0, n1, n2 = _cross(a0, a1, a2, b0, b1, b2)
            norm = max(math.sqrt(n0 * n0 + n1 * n1 + n2 * n2), TINY)
            out[i, j, 0] = n0 / norm
            out[i, j, 1] = n1 / norm
            out[i, j, 2] = n2 / norm
    return out


@njit(cache=True, parallel=True, error_model="numpy")
def normals_backward(z, rot, centre, f, cx, cy, g):
    """The gradient (H, W) of sum(g * normals) w.r.t. z, for g (H, W, 3)."""
    height, width = z.shape
    g_z = np.zeros((height, width))
    if height < 3 or width < 3:
        return g_z
    g_a = np.zeros((height, width, 3))  # d loss / d a and d loss / d b at each interior pixel
    g_b = np.zeros((height, width, 3))
    for i in prange(1, height - 1):
        for j in range(1, width - 1):
            a0, a1, a2, b0, b1, b2 = _differences(z, rot, centre, f, cx, cy, i, j)
            n0, n1, n2 = _cross(a0, a1, a2, b0, b1, b2)
            length = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            q0, q1, q2 = g[i, j, 0], g[i, j, 1], g[i, j, 2]
            if length > TINY:
                o0, o1, o2 = n0 / length, n1 / length, n2 / length
                dot = o0 * q0 + o1 * q1 + o2 * q2
                m0, m1, m2 = (q0 - o0 * dot) / length, (q1 - o1 * dot) / length, (q2 - o2 * dot) / length
            else:
                m0, m1, m2 = q0 / TINY, q1 / TINY, q2 / TINY
            g_a[i, j, 0], g_a[i, j, 1], g_a[i, j, 2] = _cross(b0, b1, b2, m0, m1, m2)  # b x g_n
            g_b[i, j, 0], g_b[i, j, 1], g_b[i, j, 2] = _cross(m0, m1, m2, a0, a1, a2)  # g_n x a
    for i in prange(height):
        for j in range(width):
            p0 = p1 = p2 = 0.0
            # g_a and g_b are zero off the interior, so only the image's edges need a test
            if i >= 1:  # a at (i-1, j) has +p[i, j]
                p0 += g_a[i - 1, j, 0]
                p1 += g_a[i - 1, j, 1]
                p2 += g_a[i - 1, j, 2]
            if i + 1 < height:  # a at (i+1, j) has -p[i, j]
                p0 -= g_a[i + 1, j, 0]
                p1 -= g_a[i + 1, j, 1]
                p2 -= g_a[i + 1, j, 2]
            if j >= 1:  # b at (i, j-1) has +p[i, j]
                p0 += g_b[i, j - 1, 0]
                p1 += g_b[i, j - 1, 1]
                p2 += g_b[i, j - 1, 2]
            if j + 1 < width:  # b at (i, j+1) has -p[i, j]
                p0 -= g_b[i, j + 1, 0]
                p1 -= g_b[i, j + 1, 1]
                p2 -= g_b[i, j + 1, 2]
            d0, d1, d2 = _ray(rot, f, cx, cy, i, j)
            g_z[i, j] = d0 * p0 + d1 * p1 + d2 * p2
    return g_z


class _DepthNormals(torch.autograd.Function):
    """depth (H, W) -> normals (H, W, 3) for one camera (its rotation, centre and intrinsics as arrays)."""

    @staticmethod
    def forward(ctx, depth, rot, centre, f, cx, cy):
        z = as_f64(depth)
        ctx.state = (z, rot, centre, f, cx, cy)
        return torch.from_numpy(normals_forward(z, rot, centre, f, cx, cy)).to(depth.dtype)

    @staticmethod
    def backward(ctx, g):
        z, rot, centre, f, cx, cy = ctx.state
        g_z = normals_backward(z, rot, centre, f, cx, cy, as_f64(g))
        return torch.from_numpy(g_z).to(g.dtype), None, None, None, None, None


def normal_from_depth_compiled(depth: torch.Tensor, camera) -> torch.Tensor:
    """``rasterize.normal_from_depth``, compiled (CPU tensors)."""
    match_torch_threads()
    return _DepthNormals.apply(depth, as_f64(camera.c2w[:3, :3]), as_f64(camera.center), float(camera.focal),
                               float(camera.cx), float(camera.cy))
