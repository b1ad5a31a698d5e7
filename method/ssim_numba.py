"""The training SSIM (method/losses.py) as compiled CPU kernels, forward and backward.

Why: in torch the SSIM of a `small` stage-1 step is two depthwise convolutions over 15 stacked 128 x 128
planes (torch's pass along the rows, a 1 x 11 kernel, alone took 2-4 ms) and some forty element-wise ops
over (3, 128, 128) images forward and backward: about 9-11 ms of a ~100 ms step on one thread of an AVX2
box (BENCHMARKS.md, issue 23, session 40). Here the five blurs, the SSIM map and its mean are one pass, and
the backward blurs only the three maps the gradient needs; float64 inside. ``losses.ssim_torch`` stays the
reference (and the CUDA path), and tests hold this one to it.

Model (as the reference): mx = B x, my = B y, bxx = B x^2, byy = B y^2, bxy = B xy, with B the zero-padded
separable blur by the 11-tap Gaussian; s = (2 mx my + C1)(2 (bxy - mx my) + C2) / ((mx^2 + my^2 + C1)
(bxx - mx^2 + byy - my^2 + C2)) per pixel and channel; SSIM = mean s. With N1, N2, D1, D2 the four factors:
ds/dmx = 2 my (N2 - N1) / (D1 D2) - 2 mx s (D2 - D1) / (D1 D2), ds/dbxx = -s / D2, ds/dbxy = 2 N1 / (D1 D2).
B with zero padding and a symmetric window is a symmetric matrix, so g_x = (g / n) (B a1 + 2 x B a2 + y B a3)
for the three maps a = ds/d(mx, bxx, bxy).
"""
from __future__ import annotations

import numba
import numpy as np
import torch
from numba import njit, prange

from method.splat.raster_numba import as_f64, match_torch_threads

C1, C2 = 0.01 ** 2, 0.03 ** 2  # as losses.py


@njit(cache=True, error_model="numpy")
def _blur_plane(src, w, rows, pad, acc, dst):
    """dst (H, W) = the blur of src (H, W) by the 11 symmetric taps w along W, then along H (zero-padded);
    ``rows`` (H, W), ``pad`` (W + 10,) and ``acc`` (W,) are scratch. Along W each pixel's eleven products
    are one written-out sum over a zero-padded copy of its row (a loop over the taps there left the pass
    unvectorised: 0.25 against 0.02 ms a 128 x 128 plane); along H each tap is one pass along a row."""
    height, width = src.shape
    w0, w1, w2, w3, w4, w5, w6, w7, w8, w9, w10 = w[0], w[1], w[2], w[3], w[4], w[5], w[6], w[7], w[8], w[9], w[10]
    for x in range(width + 10):
        pad[x] = 0.0
    for y in range(height):
        for x in range(width):
            pad[x + 5] = src[y, x]
        for x in range(width):
            rows[y, x] = (w0 * pad[x] + w1 * pad[x + 1] + w2 * pad[x + 2] + w3 * pad[x + 3] + w4 * pad[x + 4]
                          + w5 * pad[x + 5] + w6 * pad[x + 6] + w7 * pad[x + 7] + w8 * pad[x + 8]
                          + w9 * pad[x + 9] + w10 * pad[x + 10])
    for y in range(height):
        for x in range(width):
            acc[x] = 0.0
        for k in range(max(0, 5 - y), min(11, height + 5 - y)):
            wk = w[k]
            yy = y + k - 5
            for x in range(width):
                acc[x] += wk * rows[yy, x]
        for x in range(width):
            dst[y, x] = acc[x]


@njit(cache=True, parallel=True, error_model="numpy")
def ssim_forward(x, y, w, nt):
    """x, y (C, H, W) float64 -> (the sum of the SSIM map over every pixel and channel, the maps
    a (3, C, H, W) = ds/d(mx, bxx, bxy) the backward blurs). ``nt``: the thread count (planes dealt out
    round-robin; each plane written by one thread, the sum taken in a fixed order)."""
    c_count, height, width = x.shape
    blurred = np.empty((5, c_count, height, width))
    for ti in prange(nt):
        src = np.empty((height, width))
        rows = np.empty((height, width))
        pad = np.empty(width + 10)
        acc = np.empty(width)
        for q in range(ti, 5 * c_count, nt):
            kind = q // c_count
            c = q % c_count
            for i in range(height):
                for j in range(width):
                    a = x[c, i, j]
                    b = y[c, i, j]
                    if kind == 0:
                        src[i, j] = a
                    elif kind == 1:
                        src[i, j] = b
                    elif kind == 2:
                        src[i, j] = a * a
                    elif kind == 3:
                        src[i, j] = b * b
                    else:
                        src[i, j] = a * b
            _blur_plane(src, w, rows, pad, acc, blurred[kind, c])
    maps = np.empty((3, c_count, height, width))
    sums = np.zeros(c_count)
    for c in prange(c_count):
        tot = 0.0
        for i in range(height):
            for j in range(width):
                mx = blurred[0, c, i, j]
                my = blurred[1, c, i, j]
                sxx = blurred[2, c, i, j] - mx * mx
                syy = blurred[3, c, i, j] - my * my
                sxy = blurred[4, c, i, j] - mx * my
                n1 = 2.0 * mx * my + C1
                n2 = 2.0 * sxy + C2
                d1 = mx * mx + my * my + C1
                d2 = sxx + syy + C2
                dd = d1 * d2
                s = n1 * n2 / dd
                tot += s
                maps[0, c, i, j] = 2.0 * my * (n2 - n1) / dd - 2.0 * mx * s * (d2 - d1) / dd
                maps[1, c, i, j] = -s / d2
                maps[2, c, i, j] = 2.0 * n1 / dd
        sums[c] = tot
    total = 0.0
    for c in range(c_count):
        total += sums[c]
    return total, maps


@njit(cache=True, parallel=True, error_model="numpy")
def ssim_backward(x, y, maps, w, scale, nt):
    """The gradient (C, H, W) of ``scale`` * (the sum of the SSIM map) w.r.t. x, from ssim_forward's maps."""
    c_count, height, width = x.shape
    blurred = np.empty((3, c_count, height, width))
    for ti in prange(nt):
        rows = np.empty((height, width))
        pad = np.empty(width + 10)
        acc = np.empty(width)
        for q in range(ti, 3 * c_count, nt):
            _blur_plane(maps[q // c_count, q % c_count], w, rows, pad, acc, blurred[q // c_count, q % c_count])
    g = np.empty((c_count, height, width))
    for c in prange(c_count):
        for i in range(height):
            for j in range(width):
                g[c, i, j] = scale * (blurred[0, c, i, j] + 2.0 * x[c, i, j] * blurred[1, c, i, j]
                                      + y[c, i, j] * blurred[2, c, i, j])
    return g


def _planes(img: torch.Tensor) -> np.ndarray:
    """(H, W, C) tensor -> a contiguous (C, H, W) float64 array."""
    return as_f64(img.permute(2, 0, 1))


class _SSIM(torch.autograd.Function):
    """img, ref (H, W, C) -> the mean SSIM (a 0-d tensor of img's dtype), differentiable in img."""

    @staticmethod
    def forward(ctx, img, ref, w):
        x, y = _planes(img), _planes(ref)
        total, maps = ssim_forward(x, y, w, numba.get_num_threads())
        ctx.state = (x, y, maps, w)
        ctx.shape = img.shape
        return torch.tensor(total / x.size, dtype=img.dtype)

    @staticmethod
    def backward(ctx, g):
        x, y, maps, w = ctx.state
        grad = ssim_backward(x, y, maps, w, float(g) / x.size, numba.get_num_threads())
        return torch.from_numpy(grad).permute(1, 2, 0).to(g.dtype), None, None


def ssim_compiled(img: torch.Tensor, ref: torch.Tensor, window: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of (H, W, C) images with the symmetric 1-D ``window`` of 11 taps, compiled; the gradient
    flows to ``img`` only."""
    if window.shape != (11,) or not torch.equal(window, window.flip(0)):
        raise ValueError("ssim_compiled needs a symmetric 1-D window of 11 taps (its backward is the same blur)")
    if img.shape != ref.shape or img.dim() != 3:
        raise ValueError(f"ssim_compiled takes two (H, W, C) images of one shape; got {tuple(img.shape)} "
                         f"and {tuple(ref.shape)}")
    match_torch_threads()
    return _SSIM.apply(img, ref, as_f64(window))
