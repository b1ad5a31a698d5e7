"""The compiled depth normals (method/splat/depth_normals_numba.py) held to the torch reference
(rasterize.normal_from_depth_torch): values and the depth's gradient."""
import pytest
import torch

from method.splat.camera import Camera
from method.splat.rasterize import normal_from_depth, normal_from_depth_torch

pytest.importorskip("numba")


def _depth(h, w, seed):
    """A tilted plane with a box on it and noise: slopes, steps (large |n| changes) and flat parts."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    z = 4.0 + 0.02 * xx - 0.015 * yy
    z[h // 3: h // 2, w // 4: w // 2] -= 0.6
    return z + 0.01 * torch.rand(h, w, generator=g, dtype=torch.float64)


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("shape", [(24, 31), (3, 5)])
def test_compiled_depth_normals_equal_torch(threads, shape):
    cam = Camera.look_at(torch.tensor([3.0, -2.0, 2.5]), torch.zeros(3), shape[1], shape[0]).to("cpu", torch.float64)
    z = _depth(*shape, seed=shape[0])
    g = torch.randn(*shape, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        a = z.clone().requires_grad_(True)
        got = normal_from_depth(a, cam, backend="numba")
        (g_got,) = torch.autograd.grad((got * g).sum(), a)
    finally:
        torch.set_num_threads(before)
    b = z.clone().requires_grad_(True)
    want = normal_from_depth_torch(b, cam)
    (g_want,) = torch.autograd.grad((want * g).sum(), b)
    assert float(want.abs().sum()) > 0 and float(g_want.abs().max()) > 1e-3
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    torch.testing.assert_close(g_got, g_want, rtol=0, atol=1e-9 * float(g_want.abs().max()))


def test_compiled_depth_normals_of_a_flat_image_and_tiny_images():
    """Zero normals where the depth gives no surface (|n| under the clamp) and on images too small for an
    interior, as the reference."""
    cam = Camera.look_at(torch.tensor([0.0, 0.0, 3.0]), torch.zeros(3), 6, 2).to("cpu", torch.float64)
    z = torch.zeros(2, 6, dtype=torch.float64, requires_grad=True)
    out = normal_from_depth(z, cam, backend="numba")
    assert out.shape == (2, 6, 3) and float(out.abs().sum()) == 0.0
    cam = Camera.look_at(torch.tensor([0.0, 0.0, 3.0]), torch.zeros(3), 5, 5).to("cpu", torch.float64)
    z = torch.zeros(5, 5, dtype=torch.float64, requires_grad=True)  # every point at the camera: n = 0
    g = torch.ones(5, 5, 3, dtype=torch.float64)
    (g_got,) = torch.autograd.grad((normal_from_depth(z, cam, backend="numba") * g).sum(), z)
    zz = z.detach().clone().requires_grad_(True)
    (g_want,) = torch.autograd.grad((normal_from_depth_torch(zz, cam) * g).sum(), zz)
    torch.testing.assert_close(g_got, g_want, rtol=1e-12, atol=0)
