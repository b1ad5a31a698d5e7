"""Albedo alignment (per-channel median scale) and the sRGB transfer curves."""
import numpy as np
import pytest
import torch

from benchmark.align import albedo_scale, apply_scale, linear_to_srgb, srgb_to_linear
from lumibench.errors import UserError


def _views(rng, scale, sizes=((20, 24), (16, 16), (30, 12))):
    preds, gts, masks = [], [], []
    for h, w in sizes:
        gt = rng.uniform(0.05, 0.9, (h, w, 3))
        mask = np.zeros((h, w))
        mask[2:-3, 3:-2] = 1.0
        pred = gt / scale
        pred[mask == 0] = rng.uniform(0, 1, ((mask == 0).sum(), 3))  # background: unrelated values
        preds.append(pred)
        gts.append(gt)
        masks.append(mask)
    return preds, gts, masks


def test_recovers_known_scale():
    rng = np.random.default_rng(0)
    scale = np.array([1.7, 0.6, 2.3])
    preds, gts, masks = _views(rng, scale)
    np.testing.assert_allclose(albedo_scale(preds, gts, masks), scale, rtol=1e-12)


def test_robust_to_outliers_and_background():
    rng = np.random.default_rng(1)
    scale = np.array([0.8, 1.25, 3.0])
    preds, gts, masks = _views(rng, scale)
    for p, m in zip(preds, masks):
        fg = np.argwhere(m > 0.5)
        bad = fg[rng.choice(len(fg), len(fg) // 5, replace=False)]
        p[bad[:, 0], bad[:, 1]] = rng.uniform(0.0, 50.0, (len(bad), 3))  # 20 % wild predictions
    est = albedo_scale(preds, gts, masks)
    np.testing.assert_allclose(est, scale, rtol=0.1)
    # a least-squares scale would be pulled far away by the same outliers
    p_all = np.concatenate([p[m > 0.5] for p, m in zip(preds, masks)])
    g_all = np.concatenate([g[m > 0.5] for g, m in zip(gts, masks)])
    lsq = (p_all * g_all).sum(0) / (p_all * p_all).sum(0)
    assert np.all(np.abs(lsq / scale - 1) > 0.5)


def test_skips_zero_predictions_and_uses_coverage_threshold():
    rng = np.random.default_rng(2)
    scale = np.array([2.0, 2.0, 0.5])
    preds, gts, masks = _views(rng, scale)
    for p, m in zip(preds, masks):
        fg = m > 0.5
        zero = fg & (rng.random(m.shape) < 0.6)  # majority of foreground pixels predicted black
        p[zero] = 0.0
        m[fg] = 0.8  # coverage above 0.5 still counts as foreground
    np.testing.assert_allclose(albedo_scale(preds, gts, masks), scale, rtol=1e-12)


def test_accepts_torch_and_hw1_masks():
    rng = np.random.default_rng(3)
    scale = np.array([1.1, 0.9, 1.3])
    preds, gts, masks = _views(rng, scale)
    est = albedo_scale([torch.from_numpy(p) for p in preds], gts, [m[..., None] for m in masks])
    np.testing.assert_allclose(est, scale, rtol=1e-12)


def test_apply_scale_clips():
    pred = np.array([[[0.2, 0.5, 0.9]]])
    out = apply_scale(pred, [2.0, 1.0, 3.0])
    np.testing.assert_allclose(out, [[[0.4, 0.5, 1.0]]])
    t = apply_scale(torch.tensor(pred), np.array([2.0, -1.0, 3.0]))
    assert isinstance(t, torch.Tensor)
    np.testing.assert_allclose(t.numpy(), [[[0.4, 0.0, 1.0]]])


@pytest.mark.parametrize(
    "args, words",
    [
        (([], [], []), "at least one view"),
        (([np.ones((4, 4, 3))], [np.ones((4, 4, 3))], []), "as many"),
        (([np.ones((4, 4, 3))], [np.ones((4, 5, 3))], [np.ones((4, 4))]), "view 0"),
        (([np.ones((4, 4, 3))], [np.ones((4, 4, 3))], [np.ones((4, 5))]), "mask"),
        (([np.zeros((4, 4, 3))], [np.ones((4, 4, 3))], [np.ones((4, 4))]), "channel R"),
    ],
)
def test_alignment_errors(args, words):
    with pytest.raises(UserError, match=words):
        albedo_scale(*args)


def test_srgb_known_values_and_roundtrip():
    # IEC 61966-2-1 reference points
    assert srgb_to_linear(np.float64(0.04045)) == pytest.approx(0.04045 / 12.92)
    assert srgb_to_linear(np.float64(0.5)) == pytest.approx(((0.5 + 0.055) / 1.055) ** 2.4, rel=1e-12)
    assert srgb_to_linear(np.float64(0.5)) == pytest.approx(0.21404114, abs=1e-8)
    assert linear_to_srgb(np.float64(0.18)) == pytest.approx(0.46135612, abs=1e-8)
    assert srgb_to_linear(np.float64(1.0)) == pytest.approx(1.0)
    # the two branches meet at the knee (continuity within float error)
    assert linear_to_srgb(np.float64(0.0031308)) == pytest.approx(0.04045, abs=1e-6)
    x = np.linspace(0, 1, 2001)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-12)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-12)
    assert np.all(np.diff(srgb_to_linear(x)) > 0)


def test_srgb_torch_matches_numpy():
    x = np.linspace(-0.05, 1.05, 501)
    for f in (srgb_to_linear, linear_to_srgb):
        t = f(torch.tensor(x))
        assert isinstance(t, torch.Tensor)
        np.testing.assert_allclose(t.numpy(), f(x), atol=1e-12)
    xt = torch.tensor([0.2, 0.7], requires_grad=True)  # differentiable for use in losses
    srgb_to_linear(xt).sum().backward()
    assert torch.isfinite(xt.grad).all()
