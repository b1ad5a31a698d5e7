"""LumiMotion stage 1: loss terms, Binary Concrete, the deformation rules, the loader, and the training
loop (a ci run, resume equality, the NaN guard, bad input)."""
from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from method import losses
from method.model.deform import DeformNet, binary_concrete
from method.model.gaussians import Gaussians
from method.splat.camera import Camera
from method.stage1 import DynamicScene, render, stage1_loss


# ----------------------------------------------------------------------------------------- loss terms

def _ssim_brute(x: np.ndarray, y: np.ndarray) -> float:
    """SSIM with an explicit 11 x 11 Gaussian window over zero-padded images, pixel by pixel."""
    r = 5
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / 1.5) ** 2)
    k /= k.sum()
    w2 = np.outer(k, k)
    h, w, c = x.shape
    xp = np.pad(x, ((r, r), (r, r), (0, 0)))
    yp = np.pad(y, ((r, r), (r, r), (0, 0)))
    vals = []
    for i in range(h):
        for j in range(w):
            for ch in range(c):
                px, py = xp[i:i + 11, j:j + 11, ch], yp[i:i + 11, j:j + 11, ch]
                mx, my = (w2 * px).sum(), (w2 * py).sum()
                sxx = (w2 * px * px).sum() - mx * mx
                syy = (w2 * py * py).sum() - my * my
                sxy = (w2 * px * py).sum() - mx * my
                c1, c2 = 0.01 ** 2, 0.03 ** 2
                vals.append((2 * mx * my + c1) * (2 * sxy + c2) / ((mx * mx + my * my + c1) * (sxx + syy + c2)))
    return float(np.mean(vals))


def test_ssim_loss_matches_brute_force_window():
    rng = np.random.default_rng(0)
    x = rng.random((9, 13, 3))
    y = np.clip(x + 0.2 * rng.standard_normal(x.shape) * np.array([1.0, 0.3, 0.0]), 0, 1)
    got = float(losses.ssim(torch.tensor(x), torch.tensor(y)))
    assert got == pytest.approx(_ssim_brute(x, y), abs=1e-9)
    assert float(losses.ssim(torch.tensor(x), torch.tensor(x))) == pytest.approx(1.0, abs=1e-12)


def test_colour_loss_weights_l1_and_dssim():
    rng = np.random.default_rng(1)
    x = torch.tensor(rng.random((8, 8, 3)))
    y = torch.tensor(rng.random((8, 8, 3)))
    l1 = float((x - y).abs().mean())
    lc, l1_out = losses.colour_loss(x, y, 0.2)
    assert float(l1_out) == pytest.approx(l1)
    assert float(lc) == pytest.approx(0.8 * l1 + 0.2 * (1 - _ssim_brute(x.numpy(), y.numpy())), abs=1e-9)


def test_normal_consistency_mask_bce_and_regularisers_by_hand():
    up = torch.tensor([[[0.0, 0.0, 1.0]]])
    side = torch.tensor([[[1.0, 0.0, 0.0]]])
    one = torch.ones(1, 1)
    assert float(losses.normal_consistency(up, up, one)) == pytest.approx(0.0)
    assert float(losses.normal_consistency(up, side, one)) == pytest.approx(1.0)
    assert float(losses.normal_consistency(up, up, 0.5 * one)) == pytest.approx(0.5)  # surface normal x alpha
    o = torch.tensor([[0.8, 0.3]])
    m = torch.tensor([[1.0, 0.0]])
    assert float(losses.mask_bce(o, m)) == pytest.approx(-(math.log(0.8) + math.log(0.7)) / 2)
    assert float(losses.p_l1(torch.tensor([0.2, 0.6]))) == pytest.approx(0.4)
    d = torch.tensor([[1.0, 2.0, 2.0], [0.0, 0.0, 1.0]])
    assert float(losses.mean_sq_norm(d)) == pytest.approx((9 + 1) / 2)


def _tiny_scene(n=40, seed=0, dynamic=True, dtype=torch.float64):
    gen = torch.Generator().manual_seed(seed)
    pts = (torch.rand(n, 3, generator=gen) * 2 - 1) * 0.6
    g = Gaussians.from_points(pts, 0.6, -0.01, gen, colours=torch.rand(n, 3, generator=gen))
    g = Gaussians({k: v.to(dtype) for k, v in g.t.items()})
    net = DeformNet(3, 16, 1, 3, 2, 8, 6).to(dtype) if dynamic else None
    return DynamicScene(g, net, torch.zeros(3, dtype=dtype), 1.0)


def _randomise_heads(net: DeformNet, seed=3):
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for head in (net.d_mu, net.d_rot, net.d_col):
            head.weight.copy_(0.3 * torch.randn(head.weight.shape, generator=gen, dtype=head.weight.dtype))
            head.bias.copy_(0.1 * torch.randn(head.bias.shape, generator=gen, dtype=head.bias.dtype))


def test_stage1_loss_is_the_weighted_sum_and_respects_start_iterations():
    sc = _tiny_scene()
    _randomise_heads(sc.net)
    cam = Camera.look_at((0, -3, 1), (0, 0, 0), 24, 24, dtype=torch.float64)
    d = sc.deform(0.4, p_mode="sample", generator=torch.Generator().manual_seed(0))
    out = render(d, cam, torch.ones(3, dtype=torch.float64))
    gen = torch.Generator().manual_seed(5)
    gt = torch.rand(24, 24, 3, generator=gen, dtype=torch.float64)
    mask = (torch.rand(24, 24, generator=gen, dtype=torch.float64) > 0.5).double()
    cfg = dict(lambda_dssim=0.2, lambda_normal=0.05, normal_from=10, lambda_distortion=100.0, distortion_from=20,
               lambda_mask=0.1, lambda_p=0.01, lambda_dc=0.02, lambda_dmu=0.003)
    total, terms = stage1_loss(out, d, gt, mask, cfg, iteration=15, warmup=False)
    assert "distortion" not in terms and "normal" in terms  # 15: normal on (from 10), distortion off (from 20)
    expect = (terms["l_c"] + 0.05 * terms["normal"] + 0.1 * terms["mask"] + 0.01 * terms["p"]
              + 0.02 * terms["dc"] + 0.003 * terms["dmu"])
    assert float(total) == pytest.approx(float(expect))
    assert float(terms["p"]) == pytest.approx(float(d.p.mean()))
    assert float(terms["dmu"]) == pytest.approx(float((d.d_mu ** 2).sum(-1).mean()))
    total_w, terms_w = stage1_loss(out, d, gt, mask, cfg, iteration=25, warmup=True)
    assert "p" not in terms_w and "distortion" in terms_w  # no L_P in warm-up (P = 1 there)


# ------------------------------------------------------------------------------- Binary Concrete, P

def test_binary_concrete_statistics():
    gen = torch.Generator().manual_seed(0)
    n = 200_000
    logit = torch.zeros(n)
    p = binary_concrete(logit, 0.5, gen)
    # logit 0, T = 0.5: symmetric (mean 1/2); P > 0.9 iff logistic noise > T logit(0.9), prob 1 / (1 + 0.9/0.1)^T...
    assert float(p.mean()) == pytest.approx(0.5, abs=0.005)
    thr = 0.5 * math.log(9.0)  # L > T * logit(0.9)
    near_binary = 2.0 / (1.0 + math.exp(thr))  # P < 0.1 or P > 0.9
    assert float(((p < 0.1) | (p > 0.9)).float().mean()) == pytest.approx(near_binary, abs=0.005)
    # P(P > 0.5) = sigmoid(logit) whatever the temperature
    for lg, t in ((1.0, 0.5), (-2.0, 0.2)):
        q = binary_concrete(torch.full((n,), lg), t, gen)
        assert float((q > 0.5).float().mean()) == pytest.approx(1 / (1 + math.exp(-lg)), abs=0.005)
    # inference (u = 0.5): deterministic sigmoid(logit / T)
    assert float(binary_concrete(torch.tensor([1.0]), 0.5, training=False)) == pytest.approx(1 / (1 + math.exp(-2.0)))


def test_p_zero_makes_geometry_time_independent():
    sc = _tiny_scene()
    _randomise_heads(sc.net)
    cam = Camera.look_at((0.3, -3, 1), (0, 0, 0), 24, 24, dtype=torch.float64)
    bg = torch.zeros(3, dtype=torch.float64)
    a = sc.deform(0.1, fixed_p=0.0)
    b = sc.deform(0.8, fixed_p=0.0)
    ra, rb = render(a, cam, bg), render(b, cam, bg)
    torch.testing.assert_close(ra.alpha, rb.alpha, rtol=0, atol=0)
    torch.testing.assert_close(ra.depth_expected, rb.depth_expected, rtol=0, atol=0)
    # P = 1 moves them (so the test above is not vacuous), and colour changes with time even at P = 0 (by
    # design: moving shadows darken static surfaces)
    assert not torch.allclose(render(sc.deform(0.1, fixed_p=1.0), cam, bg).alpha,
                              render(sc.deform(0.8, fixed_p=1.0), cam, bg).alpha)
    assert not torch.allclose(a.colours, b.colours)


def test_zeroed_network_equals_the_static_model():
    dyn = _tiny_scene(dynamic=True)  # heads are zero-initialised
    sta = DynamicScene(dyn.g, None, dyn.center, dyn.extent)
    cam = Camera.look_at((0.5, -3, 1.2), (0, 0, 0), 24, 24, dtype=torch.float64)
    bg = torch.ones(3, dtype=torch.float64)
    for t in (0.0, 0.6):
        r1 = render(dyn.deform(t, p_mode="sample", generator=torch.Generator().manual_seed(1)), cam, bg)
        r0 = render(sta.deform(t), cam, bg)
        torch.testing.assert_close(r1.features[..., :3], r0.features[..., :3], rtol=0, atol=1e-12)
        torch.testing.assert_close(r1.alpha, r0.alpha, rtol=0, atol=1e-12)
    _randomise_heads(dyn.net)
    r1 = render(dyn.deform(0.6, fixed_p=1.0), cam, bg)
    assert not torch.allclose(r1.features[..., :3], render(sta.deform(0.6), cam, bg).features[..., :3])
