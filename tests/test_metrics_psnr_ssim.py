"""PSNR against analytic values; SSIM against scikit-image's structural_similarity."""
import math
import sys

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from benchmark.metrics import mse, psnr, ssim, ssim_map
from lumibench.errors import UserError


def sk_ssim(a, b, full=False):
    return structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                 data_range=1.0, channel_axis=-1, full=full)


# ---------------------------------------------------------------- PSNR


@pytest.mark.parametrize("d", [0.5, 0.1, 0.01, 1 / 255])
def test_psnr_constant_offset_is_analytic(d):
    gt = np.full((9, 7, 3), 0.25)
    assert psnr(gt + d, gt) == pytest.approx(10 * math.log10(1 / d**2), abs=1e-9)
    assert psnr(gt - d, gt, per_channel=True) == pytest.approx(-20 * math.log10(d), abs=1e-9)


def test_psnr_identical_is_infinite():
    x = np.random.default_rng(0).random((8, 8, 3))
    assert psnr(x, x) == math.inf


def test_psnr_mask_ignores_outside():
    rng = np.random.default_rng(1)
    gt = rng.random((16, 20, 3))
    pred = gt + 0.05
    mask = np.zeros((16, 20), bool)
    mask[3:11, 4:15] = True
    pred[~mask] = rng.random(((~mask).sum(), 3))  # arbitrary garbage outside the mask
    expected = -20 * math.log10(0.05)
    assert psnr(pred, gt, mask=mask) == pytest.approx(expected, abs=1e-9)
    assert psnr(pred, gt, mask=mask[..., None].astype(np.float32)) == pytest.approx(expected, abs=1e-9)
    assert psnr(pred, gt) < expected - 3  # the garbage does count without the mask


def test_psnr_coverage_weights_are_a_weighted_mean():
    rng = np.random.default_rng(2)
    gt = rng.random((6, 5, 3))
    err = rng.random((6, 5, 1)) * 0.2
    w = rng.random((6, 5))
    expected_mse = float((w[..., None] * err**2).sum() / w.sum())
    assert mse(gt + err, gt, mask=w) == pytest.approx(expected_mse, rel=1e-12)
    assert psnr(gt + err, gt, mask=w) == pytest.approx(-10 * math.log10(expected_mse), rel=1e-12)


def test_psnr_per_channel_vs_pooled():
    gt = np.zeros((4, 4, 3))
    offsets = np.array([0.1, 0.02, 0.3])
    pred = gt + offsets
    pooled = -10 * math.log10(float((offsets**2).mean()))
    averaged = float(np.mean(-20 * np.log10(offsets)))
    assert psnr(pred, gt) == pytest.approx(pooled, abs=1e-9)
    assert psnr(pred, gt, per_channel=True) == pytest.approx(averaged, abs=1e-9)
    assert averaged > pooled  # Jensen: the conventions really differ on coloured errors


def test_psnr_torch_matches_numpy():
    rng = np.random.default_rng(3)
    a, b = rng.random((10, 12, 3)), rng.random((10, 12, 3))
    m = rng.random((10, 12)) > 0.3
    assert psnr(torch.from_numpy(a), torch.from_numpy(b), mask=torch.from_numpy(m)) == pytest.approx(psnr(a, b, mask=m), abs=1e-9)


@pytest.mark.parametrize(
    "pred, gt, mask, words",
    [
        (np.zeros((4, 4, 3)), np.zeros((4, 5, 3)), None, "sizes differ"),
        (np.zeros((4, 4, 3)), np.zeros((4, 4, 3)), np.zeros((4, 4)), "empty"),
        (np.zeros((4, 4, 3)), np.zeros((4, 4, 3)), np.ones((3, 4)), "does not fit"),
        (np.zeros((4, 4, 3)), np.zeros((4, 4, 3)), -np.ones((4, 4)), "negative"),
        (np.zeros((2, 4, 4, 3)), np.zeros((2, 4, 4, 3)), None, "H x W x C"),
        (np.full((4, 4, 3), np.nan), np.zeros((4, 4, 3)), None, "prediction image contains NaN"),
        (np.zeros((4, 4, 3)), np.full((4, 4, 3), np.inf), None, "ground truth image contains NaN"),
    ],
)
def test_psnr_bad_input(pred, gt, mask, words):
    with pytest.raises(UserError, match=words):
        psnr(pred, gt, mask=mask)


# ---------------------------------------------------------------- SSIM


@pytest.mark.parametrize("shape", [(11, 11, 3), (32, 32, 3), (40, 27, 3), (23, 64, 1), (64, 48, 4)])
def test_ssim_matches_skimage_on_random_images(shape):
    rng = np.random.default_rng(sum(shape))
    a = rng.random(shape)
    b = np.clip(a + rng.normal(0, 0.15, shape), 0, 1)
    c = rng.random(shape)  # unrelated image: SSIM near 0
    for x, y in ((a, b), (a, c), (b, a)):
        assert abs(ssim(x, y) - sk_ssim(x, y)) < 1e-6


def _structured(h, w):
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    checker = ((np.arange(h)[:, None] // 4 + np.arange(w)[None] // 4) % 2).astype(float)
    return np.stack([xx, 0.5 + 0.5 * np.sin(12 * yy), 0.2 + 0.6 * checker], -1)


def test_ssim_matches_skimage_on_structured_images():
    a = _structured(48, 56)
    shifted = np.roll(a, 2, axis=1)
    dimmer = 0.7 * a + 0.1
    quantised = np.round(a * 8) / 8
    for b in (shifted, dimmer, quantised):
        assert abs(ssim(b, a) - sk_ssim(b, a)) < 1e-6
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-12)


def test_ssim_float32_inputs_are_computed_in_float64():
    rng = np.random.default_rng(5)
    a = rng.random((30, 30, 3)).astype(np.float32)
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1).astype(np.float32)
    assert abs(ssim(a, b) - sk_ssim(a.astype(np.float64), b.astype(np.float64))) < 1e-6
    assert abs(ssim(torch.from_numpy(a), torch.from_numpy(b)) - ssim(a, b)) < 1e-12


def test_ssim_map_is_skimage_full_map_without_border():
    rng = np.random.default_rng(6)
    a = rng.random((25, 31, 3))
    b = np.clip(a + rng.normal(0, 0.2, a.shape), 0, 1)
    _, full = sk_ssim(a, b, full=True)
    ours = ssim_map(a, b)
    assert ours.shape == (15, 21, 3)
    np.testing.assert_allclose(ours, full[5:-5, 5:-5], atol=1e-9)


def test_ssim_mask_is_the_mean_of_the_map_over_the_mask():
    rng = np.random.default_rng(7)
    a = rng.random((30, 34, 3))
    b = np.clip(a + rng.normal(0, 0.2, a.shape), 0, 1)
    assert ssim(a, b, mask=np.ones((30, 34))) == pytest.approx(ssim(a, b), abs=1e-12)
    mask = np.zeros((30, 34))
    mask[8:20, 10:25] = 1
    _, full = sk_ssim(a, b, full=True)
    assert ssim(a, b, mask=mask) == pytest.approx(full[8:20, 10:25].mean(), abs=1e-9)
    # A disturbance outside the mask changes nothing inside it (beyond the window reach).
    b2 = b.copy()
    b2[:2] = 0.0
    assert ssim(a, b2, mask=mask) == pytest.approx(ssim(a, b, mask=mask), abs=1e-12)


def test_ssim_bad_input():
    with pytest.raises(UserError, match="too small"):
        ssim(np.zeros((10, 30, 3)), np.zeros((10, 30, 3)))
    with pytest.raises(UserError, match="border"):
        m = np.zeros((20, 20))
        m[:3] = 1
        ssim(np.zeros((20, 20, 3)), np.zeros((20, 20, 3)), mask=m)


def test_ssim_device_paths_agree():
    """The conv2d path (used off the CPU) and the scipy path (CPU) compute the same blur."""
    ssim_module = sys.modules["benchmark.metrics.ssim"]
    x = torch.from_numpy(np.random.default_rng(8).random((4, 30, 33)))
    k = ssim_module._kernel(torch.float64, x.device)
    a, b = ssim_module._blur_valid(x, k), ssim_module._blur_valid_conv(x, k)
    assert a.shape == b.shape == (4, 20, 23)
    assert float((a - b).abs().max()) < 1e-14
