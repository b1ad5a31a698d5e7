"""LumiMotion stage 1: loss terms, Binary Concrete, the deformation rules, the loader, and the training
loop (a ci run, resume equality, the NaN guard, bad input)."""
from __future__ import annotations

import json
import math
import shutil
import warnings
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


def test_bf16_trunk_follows_the_fp32_network_and_keeps_fp32_outputs():
    """model.mlp_precision=bf16 runs the trunk's products in bfloat16: the same network within bf16's
    rounding (values and gradients), outputs and gradients in fp32, and not bit-equal (it is on)."""
    torch.manual_seed(3)
    ref = DeformNet(4, 64, 2, 6, 6, 32, 30)
    for head in (ref.d_mu, ref.d_rot, ref.d_col):
        torch.nn.init.normal_(head.weight, std=0.1)
    low = DeformNet(4, 64, 2, 6, 6, 32, 30, precision="bf16")
    low.load_state_dict(ref.state_dict())
    x = torch.rand(500, 3) * 2 - 1
    outs, grads = [], []
    for net in (ref, low):
        xi = x.clone().requires_grad_()
        out = net(xi, 0.37)
        sum(o.square().sum() for o in out).backward()
        outs.append(out)
        grads.append([xi.grad] + [q.grad for q in net.parameters()])
    for a, b in zip(*outs):
        assert b.dtype == torch.float32
        scale = float(a.detach().abs().max())
        assert float((a - b).detach().abs().max()) < 0.02 * scale and not torch.equal(a, b)
    # relative to the gradient's norm: the weights' within 2 %; the input's within 10 % (it sums the high
    # positional-encoding frequencies' terms, which cancel, so bf16's rounding shows most there)
    for i, (a, b) in enumerate(zip(*grads)):
        assert b.dtype == torch.float32
        assert float((a - b).norm()) <= (0.10 if i == 0 else 0.02) * float(a.norm()), i
    with pytest.raises(ValueError, match="precision"):
        DeformNet(precision="fp16")


def test_the_blocked_encoding_is_the_encoding_reordered_with_its_gradient():
    """blocked_encoding (two transcendental calls, a backward from the saved sines and cosines) gives
    positional_encoding's columns in blocked_order, and the same gradient for any upstream gradient."""
    from method.model.deform import blocked_encoding, blocked_order, positional_encoding

    torch.manual_seed(3)
    for n, d, freqs in [(50, 3, 6), (7, 1, 3), (4, 3, 1), (5, 2, 0)]:
        x = (torch.randn(n, d, dtype=torch.float64) * 2).requires_grad_()
        ours, ref = blocked_encoding(x, freqs), positional_encoding(x, freqs)[:, blocked_order(d, freqs)]
        assert sorted(blocked_order(d, freqs)) == list(range(d * (1 + 2 * freqs)))
        torch.testing.assert_close(ours, ref, rtol=0, atol=0)
        g = torch.randn_like(ref)
        g_ours, = torch.autograd.grad(ours, x, g, allow_unused=True)
        g_ref, = torch.autograd.grad(ref, x, g)
        torch.testing.assert_close(g_ours, g_ref, rtol=1e-12, atol=1e-12)


def test_the_trunk_equals_the_mlp_on_the_concatenated_position_and_time_features():
    """The trunk takes the time features' share of the first and the skip layer once per call, and the heads
    are one product: the same network as the textbook one, every layer on [enc(mu), timenet(enc(t))] (and
    the skip's [h, that]), each head its own layer, in values and in the gradients of the positions and of
    every weight."""
    from method.model.deform import positional_encoding

    torch.manual_seed(5)
    net = DeformNet(4, 32, 2, 6, 6, 16, 10).double()
    for q in net.parameters():
        torch.nn.init.normal_(q, std=0.3)
    x = (torch.rand(200, 3, dtype=torch.float64) * 2 - 1)

    def textbook(xi, t):
        tt = torch.full((1, 1), t, dtype=xi.dtype)
        inp = torch.cat([positional_encoding(xi, 6), net.time_net(positional_encoding(tt, 6)).expand(len(xi), -1)], -1)
        h = inp
        for i, layer in enumerate(net.layers):
            h = torch.relu(layer(torch.cat([h, inp], -1) if i == 2 else h))
        return net.d_mu(h), net.d_rot(h), torch.clamp_max(net.d_col(h), 1.0)  # each head its own product

    res = []
    for f in (textbook, net):
        xi = x.clone().requires_grad_()
        out = f(xi, 0.63)
        net.zero_grad()
        sum((o * (k + 1)).sum() for k, o in enumerate(out)).backward()
        res.append(([o.detach() for o in out], [xi.grad] + [q.grad.clone() for q in net.parameters()]))
    for a, b in zip(res[0][0] + res[0][1], res[1][0] + res[1][1]):
        torch.testing.assert_close(b, a, rtol=1e-10, atol=1e-12)
    assert float(res[0][0][0].abs().max()) > 0.1  # the heads say something


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


class _ScriptedNet(torch.nn.Module):
    """A deformation 'network' with known motion: Gaussians with x > 0 oscillate along x with time, every
    Gaussian carries the same time-independent offset and rotation delta."""

    offset = torch.tensor([0.05, -0.02, 0.03], dtype=torch.float64)
    rot = torch.tensor([0.01, 0.02, 0.0, -0.01], dtype=torch.float64)

    def forward(self, x, t):
        n = x.shape[0]
        d_mu = self.offset.expand(n, 3).clone()
        d_mu[:, 0] += (x[:, 0] > 0).double() * 0.2 * math.sin(2 * math.pi * t)
        return d_mu, self.rot.expand(n, 4).clone(), torch.zeros(n, 3, dtype=torch.float64)


def test_otsu_threshold_matches_brute_force_and_splits_two_modes():
    from method.stage1 import otsu_threshold

    gen = torch.Generator().manual_seed(0)
    v = torch.rand(37, generator=gen, dtype=torch.float64) ** 3

    def between(t):
        lo, hi = v[v < t], v[v >= t]
        w0 = lo.numel() / v.numel()
        return w0 * (1 - w0) * float(lo.mean() - hi.mean()) ** 2

    s = v.sort().values
    cands = [float(s[i] + s[i + 1]) / 2 for i in range(len(s) - 1)]
    assert otsu_threshold(v) == pytest.approx(max(cands, key=between))
    # two modes in log motion (static wobble ~0.004, movers ~0.1) are split between them
    logm = torch.cat([math.log(0.004) + 0.3 * torch.randn(900, generator=gen),
                      math.log(0.1) + 0.5 * torch.randn(100, generator=gen)])
    t = math.exp(otsu_threshold(logm))
    assert 0.012 < t < 0.04, t


def test_p_from_motion_bakes_static_offsets_and_splits_by_motion():
    from method.stage1 import assign_p_from_motion

    sc = _tiny_scene(n=60)
    sc.net = _ScriptedNet()
    times = [k / 9 for k in range(10)]
    moving = sc.g.means[:, 0].detach() > 0
    assert 0 < int(moving.sum()) < 60
    before = {t: sc.deform(t, fixed_p=1.0) for t in (0.0, 0.3)}
    means0 = sc.g.means.detach().clone()
    info = assign_p_from_motion(sc, times, threshold=0.01, logit=2.0)
    assert info["threshold"] == 0.01
    # the split follows the motion (RMS of 0.2 sin: 0.14 x extent), not the constant offset (0.06)
    assert torch.equal(sc.g.t["p_logit"].detach() > 0, moving)
    assert set(sc.g.t["p_logit"].detach().abs().tolist()) == {2.0}
    assert info["static_share"] == pytest.approx(float((~moving).float().mean()))
    # static Gaussians keep where the warm-up put them, now with P = 0 at every time (offset baked in) ...
    for t, d in before.items():
        after = sc.deform(t, fixed_p=0.0)
        torch.testing.assert_close(after.means[~moving], d.means[~moving], rtol=0, atol=1e-12)
        torch.testing.assert_close(after.quats[~moving], d.quats[~moving], rtol=0, atol=1e-12)
    # ... and dynamic ones are untouched
    torch.testing.assert_close(sc.g.means.detach()[moving], means0[moving], rtol=0, atol=0)
    # Otsu's threshold (None) finds the same split (on a fresh copy: baking moved some static x across 0)
    sc2 = _tiny_scene(n=60)
    sc2.net = _ScriptedNet()
    info = assign_p_from_motion(sc2, times, threshold=None, logit=2.0)
    assert torch.equal(sc2.g.t["p_logit"].detach() > 0, moving), info


def test_p_from_motion_relative_measures_motion_in_each_gaussians_size():
    """stage1.p_motion_relative: the same motion (RMS 0.14 x extent) is a wobble for a splat of size 1 and
    motion for one of size 0.1; the largest of the two scales is the size."""
    from method.stage1 import assign_p_from_motion

    sc = _tiny_scene(n=60)
    sc.net = _ScriptedNet()
    times = [k / 9 for k in range(10)]
    moving = sc.g.means[:, 0].detach() > 0
    big = torch.arange(60) % 2 == 0
    with torch.no_grad():
        sc.g.t["log_scales"][:, 0] = torch.where(big, math.log(1.0), math.log(0.1)).double()
        sc.g.t["log_scales"][:, 1] = math.log(0.01)
    assign_p_from_motion(sc, times, threshold=0.5, logit=2.0, relative=True)
    assert torch.equal(sc.g.t["p_logit"].detach() > 0, moving & ~big)
    sc2 = _tiny_scene(n=60)
    sc2.net = _ScriptedNet()
    with torch.no_grad():
        sc2.g.t["log_scales"].copy_(sc.g.t["log_scales"].detach())
    assign_p_from_motion(sc2, times, threshold=0.01, logit=2.0)  # in extent units: every mover
    assert torch.equal(sc2.g.t["p_logit"].detach() > 0, moving)



class _ThreeSpeedNet(torch.nn.Module):
    """x < -0.4: a nearly motionless tail (amplitude 1e-9); x > 0.2: moving (0.2); between: a static wobble (0.01)."""

    def forward(self, x, t):
        amp = torch.where(x[:, 0] < -0.4, 1e-9, torch.where(x[:, 0] > 0.2, 0.2, 0.01)).to(x.dtype)
        d_mu = torch.zeros_like(x)
        d_mu[:, 0] = amp * math.sin(2 * math.pi * t)
        return d_mu, torch.zeros(x.shape[0], 4, dtype=x.dtype), torch.zeros_like(x)


def test_p_motion_floor_keeps_a_motionless_tail_out_of_the_split():
    """Without a floor, Otsu on the log motion makes the far tail (1e-9) one group and marks the wobble dynamic
    with the movers; with stage1.p_motion_floor at 1e-3 the tail joins the static side and only movers move."""
    from method.stage1 import assign_p_from_motion

    times = [k / 9 for k in range(10)]
    sc = _tiny_scene(n=60)
    x = sc.g.means[:, 0].detach()
    tail, movers = x < -0.4, x > 0.2
    assert int(tail.sum()) >= 3 and int(movers.sum()) >= 3 and int((~tail & ~movers).sum()) >= 3
    sc.net = _ThreeSpeedNet()
    assign_p_from_motion(sc, times, threshold=None, logit=2.0)
    assert torch.equal(sc.g.t["p_logit"].detach() > 0, ~tail)
    sc = _tiny_scene(n=60)
    sc.net = _ThreeSpeedNet()
    info = assign_p_from_motion(sc, times, threshold=None, logit=2.0, floor=1e-3)
    assert torch.equal(sc.g.t["p_logit"].detach() > 0, movers), info


class _MirrorNet(torch.nn.Module):
    """Before time 0.5, carries every Gaussian with x > 0 to -x; from 0.5 on, moves nothing."""

    def forward(self, x, t):
        d_mu = torch.zeros_like(x)
        if t < 0.5:
            d_mu[:, 0] = -2 * x[:, 0] * (x[:, 0] > 0).to(x.dtype)
        return d_mu, torch.zeros(x.shape[0], 4, dtype=x.dtype), torch.zeros_like(x)


@pytest.mark.parametrize("early,late", [(3, 2), (2, 3)])
def test_on_moving_objects_follows_the_network_and_takes_the_majority_of_views(early, late):
    """The log's check of the P split: a Gaussian is on the moving objects when its centre, carried to each
    view's time, lands on the view's mask in most views. Mask: the image's right half (world x > 0 for a
    camera on the -y axis). Gaussians with x > 0 sit on it only at the late times, so they count as on the
    moving objects exactly when the late views are the majority; those with x < 0 never do."""
    from types import SimpleNamespace

    from method.stage1 import on_moving_objects, split_check

    sc = _tiny_scene(n=60)
    sc.net = _MirrorNet()
    cam = Camera.look_at((0, -3, 0), (0, 0, 0), 32, 32, dtype=torch.float64)
    mask = torch.zeros(32, 32)
    mask[:, 16:] = 1
    views = [SimpleNamespace(camera=cam, time=0.1 * k, dynamic_mask=mask) for k in range(early)]
    views += [SimpleNamespace(camera=cam, time=0.6 + 0.1 * k, dynamic_mask=mask) for k in range(late)]
    right = sc.g.means[:, 0].detach() > 0
    assert 0 < int(right.sum()) < 60
    moving = on_moving_objects(sc, views)
    assert torch.equal(moving, right if late > early else torch.zeros_like(right))
    views[0].dynamic_mask = None
    assert on_moving_objects(sc, views) is None  # no masks, no check
    check = split_check(right, static=~right)
    assert check == {"moving_gaussians": int(right.sum()), "moving_marked_dynamic": 1.0, "rest_marked_static": 1.0}
    check = split_check(right, static=torch.ones_like(right))
    assert check["moving_marked_dynamic"] == 0.0 and check["rest_marked_static"] == 1.0


# ------------------------------------------------------------------------------------------- loader

def _write_rgba(path: Path, rgb, alpha):
    from lumibench.io import write_png

    img = np.concatenate([np.broadcast_to(np.asarray(rgb, np.float32), alpha.shape + (3,)), alpha[..., None]], -1)
    write_png(path, img)


def test_loader_reads_the_authors_layout(tmp_path):
    """Their released scenes: './train/r_N' unpadded paths listed out of order, no dataset.json."""
    from method.data import load_scene

    scene = tmp_path / "theirs"
    c2w = np.eye(4)
    c2w[2, 3] = 4.0  # OpenGL camera at +z looking down -z
    frames = []
    for i in (10, 2, 0):  # r_10 after r_2 numerically, not lexically
        frames.append({"file_path": f"./train/r_{i}", "time": i / 10, "transform_matrix": c2w.tolist()})
        alpha = np.zeros((8, 8), np.float32)
        alpha[2:6, 2:6] = 1.0
        _write_rgba(scene / "golden_bay" / "train" / f"r_{i}.png", [i / 10, 0.5, 0.25], alpha)
    (scene / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.69, "frames": frames}))
    data = load_scene(scene, "golden_bay", background=(0.0, 0.0, 1.0))
    assert [v.stem for v in data.train] == ["r_0", "r_2", "r_10"]
    assert [v.time for v in data.train] == [0.0, 0.2, 1.0]
    v = data.train[2]
    np.testing.assert_allclose(v.rgb[3, 3].numpy(), [1.0, 0.5, 0.25], atol=1 / 255)  # foreground
    np.testing.assert_allclose(v.rgb[0, 0].numpy(), [0.0, 0.0, 1.0], atol=1e-6)      # on the background
    assert float(v.alpha.sum()) == 16.0
    assert not data.static and data.test == []


def test_static_variant_is_detected(ci_dataset):
    from method.data import load_scene

    static_dir = next(ci_dataset.parent.glob(f"{ci_dataset.name}_statictimestep*"))
    assert load_scene(static_dir, "city", load_test=False).static
    assert not load_scene(ci_dataset, "city", load_test=False).static


# ------------------------------------------------------------------------------------ training loop

TINY = ["stage1.iterations=24", "stage1.init_points=400", "stage1.max_gaussians=700", "stage1.warmup=6",
        "stage1.densify_from=4", "stage1.densify_until=20", "stage1.densify_every=4", "stage1.checkpoint_every=12",
        "stage1.eval_every=0", "stage1.log_every=4", "stage1.normal_from=8", "stage1.distortion_from=8",
        "stage1.opacity_reset_every=16", "stage1.densify_grad_threshold=1.0e-5"]


def _cfg(extra=()):
    from method.config import load_method_config

    return load_method_config("ci", TINY + list(extra))


@pytest.mark.parametrize("backend,threads", [("numba", 1), ("torch", 1), ("numba", 2)])
def test_resume_equals_an_uninterrupted_run(ci_dataset, tmp_path, monkeypatch, backend, threads):
    """Also with two threads, where a training alone runs torch on one and the kernels on two
    (method.splat.backend.kernels_take_the_threads): their sums split over threads come back the same."""
    import method.splat.backend as backend_mod
    from method.checkpoints import checkpoint_paths, load_checkpoint
    from method.train import train_stage1

    if backend == "numba" and not backend_mod.numba_available():
        pytest.skip("numba is not installed")
    monkeypatch.setattr(backend_mod, "_default", backend)
    torch.set_num_threads(threads)
    full = tmp_path / "full"
    train_stage1(ci_dataset, "city", full, _cfg(), seed=3, progress=False, write_outputs=False)
    timings = json.loads((full / "timings.json").read_text())
    assert (timings["threads"], timings["torch_threads"]) == (threads, 1)
    assert torch.get_num_threads() == threads  # put back after the training
    cks = checkpoint_paths(full)
    assert [i for i, _ in cks] == [12, 24]
    # the interrupted run: the same directory as it was at iteration 12, then --resume
    part = tmp_path / "part"
    shutil.copytree(full, part)
    (part / "checkpoints" / "stage1_000024.pt").unlink()
    train_stage1(ci_dataset, "city", part, _cfg(), seed=3, resume=True, progress=False, write_outputs=False)
    a = load_checkpoint(full / "checkpoints" / "stage1_000024.pt", "cpu")
    b = load_checkpoint(part / "checkpoints" / "stage1_000024.pt", "cpu")
    assert a["gaussians"]["means"].shape == b["gaussians"]["means"].shape
    assert a["gaussians"]["means"].shape[0] != 400  # density control ran (the state it carries matters)
    for k in a["gaussians"]:
        assert torch.equal(a["gaussians"][k], b["gaussians"][k]), k
    for k in a["net"]:
        assert torch.equal(a["net"][k], b["net"][k]), k
    # a fresh run with another seed differs (so equality above is not vacuous)
    other = tmp_path / "other"
    train_stage1(ci_dataset, "city", other, _cfg(), seed=4, progress=False, write_outputs=False)
    c = load_checkpoint(other / "checkpoints" / "stage1_000024.pt", "cpu")
    assert not torch.equal(a["gaussians"]["colour_logit"][:100], c["gaussians"]["colour_logit"][:100])


def _denormal_survives() -> bool:
    """True when a float32 denormal survives arithmetic on this thread (flush-to-zero off)."""
    return (torch.tensor([1e-39], dtype=torch.float32) * 1.5).item() != 0.0


def test_a_stage_flushes_float32_denormals_and_puts_the_mode_back(ci_dataset, tmp_path, monkeypatch):
    """Adam's moments of the bases' logits decay into denormals, on which the CPU's slow path made the
    optimiser step 2.4x slower: every optimiser step of a CPU stage runs with them flushed to zero
    (method.train.denormals_flushed), and the process's default comes back after the stage."""
    from method.stage1 import Stage1
    from method.train import train_stage1

    if not torch.set_flush_denormal(False):
        pytest.skip("this CPU cannot flush denormals")
    assert _denormal_survives()
    seen = []
    step = Stage1.optimiser_step

    def spy(self, *args, **kwargs):
        seen.append(_denormal_survives())
        return step(self, *args, **kwargs)

    monkeypatch.setattr(Stage1, "optimiser_step", spy)
    # numpy works its float limits out on first use, and warns when that use falls inside the mode
    monkeypatch.setattr(np.finfo, "_finfo_cache", {})
    torch.set_num_threads(1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        train_stage1(ci_dataset, "city", tmp_path / "run", _cfg(["stage1.iterations=4"]), seed=0, progress=False,
                     write_outputs=True)
    assert len(seen) == 4 and not any(seen)
    assert _denormal_survives()
    assert not [w for w in caught if "subnormal" in str(w.message)]


def test_p_from_motion_runs_at_the_warmup_end_and_resumes_across_it(ci_dataset, tmp_path):
    """stage1.p_from_motion splits P (Otsu) at iteration warmup + 1 (logged, logits at +-p_from_motion_logit
    moved by at most two Adam steps), and a run resumed from the warm-up's last checkpoint equals the
    uninterrupted one."""
    from method.checkpoints import checkpoint_paths, load_checkpoint
    from method.train import train_stage1

    torch.set_num_threads(1)
    extra = ["stage1.iterations=8", "stage1.checkpoint_every=6", "stage1.p_from_motion=true",
             "stage1.p_from_motion_logit=3.0"]  # the threshold by Otsu
    full = tmp_path / "full"
    train_stage1(ci_dataset, "city", full, _cfg(extra), seed=2, progress=False, write_outputs=False)
    assert [i for i, _ in checkpoint_paths(full)] == [6, 8]
    log = [json.loads(line) for line in (full / "log_stage1.jsonl").read_text().splitlines()]
    rec = [r for r in log if "p_from_motion" in r]
    assert len(rec) == 1 and rec[0]["iteration"] == 7  # warm-up 6
    info = rec[0]["p_from_motion"]
    assert 0.0 < info["static_share"] < 1.0, rec
    assert info["motion_static_median"] < info["threshold"] < info["motion_dynamic_median"]
    before = load_checkpoint(full / "checkpoints" / "stage1_000006.pt", "cpu")["gaussians"]["p_logit"]
    after = load_checkpoint(full / "checkpoints" / "stage1_000008.pt", "cpu")["gaussians"]["p_logit"]
    assert float((before + 0.01).abs().max()) < 1e-6  # untouched in the warm-up (init -0.01)
    assert float((after.abs() - 3.0).abs().max()) < 0.1  # two Adam steps of lr_p 0.02 at most
    part = tmp_path / "part"
    shutil.copytree(full, part)
    (part / "checkpoints" / "stage1_000008.pt").unlink()
    train_stage1(ci_dataset, "city", part, _cfg(extra), seed=2, resume=True, progress=False, write_outputs=False)
    a = load_checkpoint(full / "checkpoints" / "stage1_000008.pt", "cpu")
    b = load_checkpoint(part / "checkpoints" / "stage1_000008.pt", "cpu")
    for k in a["gaussians"]:
        assert torch.equal(a["gaussians"][k], b["gaussians"][k]), k


def test_network_rate_decays_exponentially(ci_dataset, tmp_path):
    """The network's rate in the checkpoints: lr_mlp decaying exponentially to lr_mlp * lr_mlp_final."""
    from method.checkpoints import checkpoint_paths, load_checkpoint
    from method.schedules import expon_lr
    from method.train import train_stage1

    torch.set_num_threads(1)
    run = tmp_path / "run"
    train_stage1(ci_dataset, "city", run, _cfg(["stage1.iterations=8", "stage1.checkpoint_every=6",
                                                "stage1.lr_mlp=4e-3", "stage1.lr_mlp_final=0.1"]),
                 seed=0, progress=False, write_outputs=False)
    lrs = {i: load_checkpoint(p, "cpu")["nopt"]["param_groups"][0]["lr"] for i, p in checkpoint_paths(run)}
    assert lrs[6] == pytest.approx(expon_lr(6, 8, 4e-3, 4e-4)) and lrs[8] == pytest.approx(4e-4)
    assert expon_lr(4, 8, 4e-3, 4e-4) == pytest.approx(4e-3 * 0.1 ** 0.5)  # the geometric midpoint


def test_nan_guard_stops_names_the_term_and_keeps_the_checkpoint(ci_dataset, tmp_path, monkeypatch, capsys):
    from method.__main__ import main

    calls = {"n": 0}
    real = losses.mask_bce

    def poisoned(alpha, mask, eps=1e-6):
        calls["n"] += 1
        out = real(alpha, mask, eps)
        return out * float("nan") if calls["n"] == 15 else out

    monkeypatch.setattr(losses, "mask_bce", poisoned)
    run = tmp_path / "run"
    rc = main(["train", "--scene", str(ci_dataset), "--run-dir", str(run), "--no-progress"] + TINY)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 3
    assert len(err) == 1 and "iteration 15" in err[0] and "'mask'" in err[0], err
    record = json.loads((run / "failure.json").read_text())
    assert record["status"] == "failed" and record["iteration"] == 15 and "mask" in record["term"]
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["stage1_000012.pt"]


@pytest.mark.parametrize("argv, needle", [
    (["--scene", "no_such_scene"], "unknown scene 'no_such_scene'"),
    (["--light", "moonlight"], "unknown light 'moonlight'"),
    (["stage1.iterationz=5"], "unknown key 'stage1.iterationz'"),
    (["stage1.iterations=many"], "key 'stage1.iterations' must be an integer"),
    (["--profile", "huge"], "unknown profile 'huge'"),
    (["--resume"], "no stage-1 checkpoint to resume"),
])
def test_bad_input_is_one_line_exit_2(ci_dataset, tmp_path, capsys, argv, needle):
    from method.__main__ import main

    base = {"--scene": str(ci_dataset), "--light": "city", "--profile": "ci"}
    args = ["train", "--run-dir", str(tmp_path / "r"), "--data", str(ci_dataset.parent.parent), "--no-progress"]
    for k, v in base.items():
        if k not in argv:
            args += [k, v]
    rc = main(args + argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and needle in err[0], err


def test_coarse_to_fine_schedule_and_downsampled_views(ci_dataset):
    from method.data import load_scene
    from method.splat.rasterize import rasterize
    from method.stage1 import c2f_factor, downsampled

    # 2 levels reaching full resolution after 600: 1/4 for 1..300, 1/2 for 301..600, then full
    assert [c2f_factor(i, 2, 600) for i in (1, 300, 301, 600, 601, 5000)] == [4, 4, 2, 2, 1, 1]
    assert {c2f_factor(i, 0, 600) for i in (1, 300)} == {1} and c2f_factor(1, 2, 0) == 1
    data = load_scene(ci_dataset, "city", [1.0, 1.0, 1.0], torch.device("cpu"))
    v = data.train[0]
    small = downsampled(v, 2)
    H, W = v.camera.height, v.camera.width
    assert small.camera.width == W // 2 and small.rgb.shape == (H // 2, W // 2, 3)
    assert torch.allclose(small.rgb.mean((0, 1)), v.rgb.mean((0, 1)), atol=1e-5)
    assert torch.allclose(small.alpha[3, 5], v.alpha[6:8, 10:12].mean())
    # the same splats rendered into the halved camera land where the full render, area-averaged, has them
    g = torch.Generator().manual_seed(0)
    n = 400
    means = data.center + (torch.rand(n, 3, generator=g) - 0.5) * data.extent
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
    scales = torch.full((n, 2), 0.08 * data.extent)
    opac = torch.full((n,), 0.8)
    feats = torch.rand(n, 3, generator=g)
    full = rasterize(means, quats, scales, opac, feats, v.camera).features
    half = rasterize(means, quats, scales, opac, feats, small.camera).features
    pooled = torch.nn.functional.avg_pool2d(full.permute(2, 0, 1)[None], 2)[0].permute(1, 2, 0)
    # (measured: 0.045 of the spread; a half-pixel shift of the principal point gives 0.17, focal x 1.1 0.28)
    assert (half - pooled).abs().mean() < 0.1 * (pooled - pooled.mean((0, 1))).abs().mean()


def test_time_window_curriculum_opens_the_times_in_order(ci_dataset, tmp_path, monkeypatch):
    """stage1.time_window_until: before that iteration a view is drawn only from the times in the window
    (start share of the range at iteration 1, growing linearly), after it from every view."""
    from method.stage1 import time_window_views
    from method.train import train_stage1

    times = [0.5, 0.0, 1.0, 0.25, 0.75]
    assert time_window_views(times, 1, 0.3, 100) == [1, 3]  # window [0, 0.3]
    assert time_window_views(times, 51, 0.3, 100) == [1, 3, 0]  # 0.3 + 0.7 * 50 / 100 = 0.65
    assert time_window_views(times, 100, 0.3, 100) == list(range(5))
    assert time_window_views(times, 1, 0.3, 0) == list(range(5))
    assert time_window_views(times, 1, 0.01, 100) == [1]  # never empty: the first time at least
    # front: only the newest 0.3 of the range inside the window ([0.35, 0.65] at iteration 51)
    assert time_window_views(times, 51, 0.3, 100, front=True) == [0]
    assert time_window_views(times, 1, 0.3, 100, front=True) == [1, 3]
    assert time_window_views(times, 51, 0.1, 100, front=True) == [0]  # [0.436, 0.536]
    assert time_window_views(times, 41, 0.05, 100, front=True) == [3]  # [0.38, 0.43] is empty: the newest open time
    drawn = []
    real = DynamicScene.deform

    def spy(self, t, *args, **kwargs):
        drawn.append(float(t))
        return real(self, t, *args, **kwargs)

    monkeypatch.setattr(DynamicScene, "deform", spy)
    torch.set_num_threads(1)

    def times_drawn(extra):
        drawn.clear()
        train_stage1(ci_dataset, "city", tmp_path / f"run{len(extra)}", _cfg(["stage1.iterations=40"] + extra),
                     seed=0, progress=False, write_outputs=False)
        return list(drawn)

    from method.data import load_scene

    all_times = [float(v.time) for v in load_scene(ci_dataset, "city", [1.0, 1.0, 1.0], torch.device("cpu")).train]
    lo, hi = min(all_times), max(all_times)
    got = times_drawn(["stage1.time_window_until=30", "stage1.time_window_start=0.2"])
    assert len(got) == 40
    for it, t in enumerate(got[:29], start=1):
        assert t <= lo + (0.2 + 0.8 * (it - 1) / 30) * (hi - lo) + 1e-6, (it, t)
    assert max(got[:10]) < lo + 0.5 * (hi - lo)  # the rule is not vacuous on this data ...
    free = times_drawn(["stage1.time_window_until=0"])  # (the ci profile has a window of its own)
    assert max(free[:10]) > lo + 0.5 * (hi - lo)  # ... a run without the window draws late times early
    front = times_drawn(["stage1.time_window_until=30", "stage1.time_window_start=0.2", "stage1.time_window_front=1"])
    for it, t in enumerate(front[:29], start=1):
        limit = 0.2 + 0.8 * (it - 1) / 30
        assert lo + (limit - 0.2) * (hi - lo) - 1e-6 <= t <= lo + limit * (hi - lo) + 1e-6, (it, t)


def test_overrides_read_exponent_notation_as_numbers():
    from lumibench.errors import UserError
    from method.config import load_method_config, parse_overrides

    # YAML 1.1 reads "3e-3" (no dot) as a string; the override means the number
    assert parse_overrides(["stage1.lr_mlp=3e-3"]) == {"stage1": {"lr_mlp": 0.003}}
    cfg = load_method_config("ci", ["stage1.lr_mlp=3e-3", "stage2.lr_env=1E+0"])
    assert cfg["stage1"]["lr_mlp"] == 0.003 and cfg["stage2"]["lr_env"] == 1.0
    with pytest.raises(UserError, match="key 'stage1.iterations' must be an integer"):
        load_method_config("ci", ["stage1.iterations=2e3"])


def test_existing_run_needs_resume(ci_dataset, tmp_path, capsys):
    from method.__main__ import main

    args = ["train", "--scene", str(ci_dataset), "--run-dir", str(tmp_path / "r"), "--no-progress", "--stage", "1"] + TINY[:1] + \
        ["stage1.iterations=2", "stage1.checkpoint_every=1", "stage1.init_points=100", "stage1.max_gaussians=0"]
    assert main(args) == 0
    capsys.readouterr()
    assert main(args) == 2
    assert "--resume" in capsys.readouterr().err


@pytest.mark.slow
def test_ci_run_of_spheres_learns(ci_dataset, tmp_path):
    """The whole ci profile (what `make train` and `make demo` run): test PSNR rises clearly above the
    first evaluation, every output is written, and the P maps cover the training views; then stage 2."""
    from method.config import load_method_config
    from method.train import train_stage1

    torch.set_num_threads(2)
    run = tmp_path / "ci_run"
    metrics = train_stage1(ci_dataset, "city", run, load_method_config("ci"), seed=0, progress=False)
    log = [json.loads(line) for line in (run / "log_stage1.jsonl").read_text().splitlines()]
    evals = [r["test_psnr"] for r in log if "test_psnr" in r]
    assert log[0]["iteration"] == 0 and len(evals) >= 2
    assert evals[-1] > evals[0] + 4.0, evals
    assert metrics["test"]["psnr"] == pytest.approx(evals[-1], abs=0.05)
    assert 0 < metrics["gaussians"] <= 6000
    for f in ("config.yaml", "timings.json", "metrics_stage1.json", "renders/sheet_stage1.png"):
        assert (run / f).is_file(), f
    timings = json.loads((run / "timings.json").read_text())["stage1"]
    assert timings["seconds"] > 0 and set(timings["breakdown_s"]) >= {"deform", "rasterize", "backward"}
    stems = sorted(p.stem for p in (run / "predictions" / "p_map" / "train").glob("*.png"))
    assert stems == sorted(f"r_{i:04d}" for i in range(16))
    sep = metrics["separation"]
    assert 0 <= sep["dynamic_recall"] <= 1 and 0 <= sep["static_recall"] <= 1

    # stage 2 on the same run, then: relit under the map it estimated for the train light, the test views
    # are close to the NVS render (24.0 dB measured). The map's orientation is pinned by the calibration
    # test (tests/test_shading.py); at ci the map is the fitted sun + sky (stage2.env_init_fit), whose sun
    # shows here too: turned by 180 degrees about +Z it gave 23.26 dB against 24.01 (the learned map of the
    # earlier ci profile had no direction to show: 24.78 against 24.84)
    from method.shading.deferred import display, render_pbr_view
    from method.checkpoints import load_trained
    from method.train import train_stage2

    cfg = load_method_config("ci")
    m2 = train_stage2(ci_dataset, "city", run, cfg, seed=0, progress=False)
    assert (run / "metrics_stage2.json").is_file() and m2["pbr_psnr"] > 15
    scene, mats = load_trained(run, cfg, "cpu")
    est = mats.env().detach()
    turned = torch.roll(est, est.shape[1] // 2, dims=1)
    from method.data import load_scene

    data = load_scene(ci_dataset, "city", cfg["data"]["background"])
    same, rot = [], []
    for v in data.test:
        r = render_pbr_view(scene, mats, v.camera, v.time, data.background, cfg, {"est": est, "rot": turned}, 128,
                            torch.Generator().manual_seed(0), indirect=True)
        fg = r["alpha"] > 0.5
        nvs = r["nvs"][fg]
        same.append(float(((display(r["relit:est"])[fg] - nvs) ** 2).mean()))
        rot.append(float(((display(r["relit:rot"])[fg] - nvs) ** 2).mean()))
    psnr_same = -10 * math.log10(sum(same) / len(same))
    psnr_rot = -10 * math.log10(sum(rot) / len(rot))
    assert psnr_same > 20.0, (psnr_same, psnr_rot)
    assert psnr_same > psnr_rot, (psnr_same, psnr_rot)  # the sun where it was fitted: worse turned round


@pytest.mark.parametrize("nodes", [0, 15])
def test_stage2_trunk_cache_gives_the_same_deformation_and_head_gradients(monkeypatch, nodes):
    """Stage 2 keeps the frozen trunk's features per time: the same Gaussians and colour-head gradients as
    running the whole network, the trunk run once per time, and a refusal while the trunk still trains;
    with the network read at nodes too (the trunk at the nodes, the blended motion and the weights kept)."""
    from method.model.nodes import MotionNodes
    from method.stage2 import freeze_geometry

    scene = _tiny_scene()
    _randomise_heads(scene.net)
    scene.nodes = MotionNodes(nodes) if nodes else None
    head = freeze_geometry(scene)
    cache: dict = {}
    calls = []
    trunk = scene.net.trunk
    monkeypatch.setattr(scene.net, "trunk", lambda x, t: calls.append(t) or trunk(x, t))
    for t in (0.25, 0.25, 0.75):
        outs = []
        for c in (None, cache):
            for p in head:
                p.grad = None
            d = scene.deform(t, p_mode="inference", trunk_cache=c)
            (d.colours.sum() + 0.3 * d.means.sum() + d.quats.sum()).backward()
            outs.append([d.means, d.quats, d.colours] + [p.grad.clone() for p in head])
        for a, b in zip(*outs):
            assert torch.equal(a, b)
    assert sorted(cache) == [0.25, 0.75] and calls.count(0.25) == 3  # uncached twice, cached once
    scene.net.layers[0].weight.requires_grad_(True)
    with pytest.raises(ValueError, match="frozen means, trunk"):
        scene.deform(0.5, trunk_cache={})


def test_stage1_depth_ratio_picks_the_depth_the_normal_consistency_compares_with(ci_dataset, tmp_path, monkeypatch):
    """stage1.depth_ratio reaches stage 1's render: the depth normals come from the expected depth at 0 and
    from the median depth at 1 (and the two differ on this data, so the check can fail); out of [0, 1] it is
    a one-line error naming the key."""
    import method.stage1 as st1
    from lumibench.errors import UserError
    from method.config import load_method_config
    from method.splat.rasterize import normal_from_depth
    from method.train import train_stage1

    seen = []
    real = st1.render

    def spy(d, camera, background, screen_offsets=None, depth_ratio=0.0):
        out = real(d, camera, background, screen_offsets=screen_offsets, depth_ratio=depth_ratio)
        seen.append((camera, out, depth_ratio))
        return out

    monkeypatch.setattr(st1, "render", spy)
    torch.set_num_threads(1)
    for ratio in (0.0, 1.0):
        seen.clear()
        train_stage1(ci_dataset, "city", tmp_path / f"run{int(ratio)}",
                     _cfg(["stage1.iterations=3", f"stage1.depth_ratio={ratio}"]), seed=0, progress=False,
                     write_outputs=False)
        camera, out, got = seen[-1]
        assert got == ratio
        with torch.no_grad():
            used, other = (out.depth_median, out.depth_expected) if ratio else (out.depth_expected, out.depth_median)
            assert torch.allclose(out.normal_from_depth, normal_from_depth(used, camera), atol=1e-6)
            assert (out.normal_from_depth - normal_from_depth(other, camera)).abs().max() > 1e-2
    with pytest.raises(UserError, match="stage1.depth_ratio"):
        load_method_config("ci", ["stage1.depth_ratio=1.5"])
