"""The compiled training SSIM (method/ssim_numba.py) held to the torch reference (losses.ssim_torch)."""
import numba
import pytest
import torch

from method import losses
from method.ssim_numba import ssim_compiled


def _pair(h, w, seed):
    """A structured image and a target that resembles it (blurred, shifted, with noise): SSIM far from 0
    and 1, edges near the borders, so the zero padding and every term of the gradient matter."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h, dtype=torch.float64), torch.linspace(0, 1, w, dtype=torch.float64),
                            indexing="ij")
    base = torch.stack([torch.sin(9 * xx + 3 * yy), (xx > 0.93).double(), torch.cos(7 * yy * xx)], -1) * 0.4 + 0.5
    img = (base + 0.1 * torch.rand(h, w, 3, generator=g, dtype=torch.float64)).clamp(0, 1)
    ref = (0.8 * base.roll(1, 1) + 0.15 * torch.rand(h, w, 3, generator=g, dtype=torch.float64)).clamp(0, 1)
    return img, ref


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("shape", [(40, 56), (17, 9)])  # wider and narrower than the window on one side
def test_compiled_ssim_values_and_gradients_equal_torch(threads, shape):
    img, ref = _pair(*shape, seed=shape[0])
    window = losses._window(torch.float64, "cpu")
    before = numba.get_num_threads()
    torch.set_num_threads(threads)  # the kernels follow torch's count (raster_numba.match_torch_threads)
    try:
        a = img.clone().requires_grad_(True)
        got = ssim_compiled(a, ref, window)
        (g_got,) = torch.autograd.grad(3.0 * got, a)
    finally:
        torch.set_num_threads(before)
    b = img.clone().requires_grad_(True)
    want = losses.ssim_torch(b, ref)
    (g_want,) = torch.autograd.grad(3.0 * want, b)
    assert 0.05 < float(want) < 0.95
    assert float(got) == pytest.approx(float(want), abs=1e-13)
    assert float(g_want.abs().max()) > 1e-4
    torch.testing.assert_close(g_got, g_want, rtol=0, atol=1e-13)


def test_the_loss_takes_the_compiled_ssim_on_the_cpu_and_keeps_float32():
    """losses.ssim dispatches to the kernel where the backend is Numba; float32 in, float32 out, and the
    value and gradient within float32 rounding of the float64 reference (the kernel sums in float64)."""
    img, ref = _pair(32, 32, seed=1)
    a = img.float().requires_grad_(True)
    got = losses.ssim(a, ref.float())
    assert got.dtype == torch.float32 and "SSIM" in type(got.grad_fn).__name__
    got.backward()
    b = img.float().double().requires_grad_(True)
    want = losses.ssim_torch(b, ref.float().double())
    want.backward()
    assert float(got) == pytest.approx(float(want), abs=1e-7)
    torch.testing.assert_close(a.grad.double(), b.grad, rtol=1e-6, atol=1e-10)


def test_compiled_ssim_refuses_a_window_its_backward_does_not_hold_for():
    img, ref = _pair(16, 16, seed=2)
    lopsided = torch.linspace(0.01, 0.2, 11, dtype=torch.float64)
    with pytest.raises(ValueError, match="symmetric"):
        ssim_compiled(img, ref, lopsided)
