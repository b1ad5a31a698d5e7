"""Rasterizer: packed fast path vs the dense reference, gradcheck, analytic footprints, conventions."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from method.splat.camera import Camera
from method.splat.rasterize import ALPHA_MIN, rasterize
from method.splat.reference import rasterize_dense

pytestmark = pytest.mark.usefixtures("splat_backend")  # conftest: torch and the compiled backend
F64 = torch.float64
KEYS = ("features", "alpha", "normal", "depth_expected", "depth_median", "distortion", "normal_from_depth")


def random_scene(n=48, seed=0, size=16, channels=3, scale=(0.05, 0.3), opacity=(0.05, 0.95), spread=1.2):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=F64) - 0.5) * spread
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    quats = quats / quats.norm(dim=1, keepdim=True)
    lo, hi = math.log(scale[0]), math.log(scale[1])
    scales = torch.exp(torch.empty(n, 2, dtype=F64).uniform_(lo, hi, generator=g))
    opac = torch.empty(n, dtype=F64).uniform_(*opacity, generator=g)
    feats = torch.rand(n, channels, generator=g, dtype=F64)
    cam = Camera.look_at((0.3, -3.5, 1.0), (0.0, 0.0, 0.0), size, size, dtype=F64)
    return [means, quats, scales, opac, feats], cam


def _fast(params, cam, bg=None, **kw):
    out = rasterize(*params, cam, bg, **kw)
    return {k: getattr(out, k) for k in KEYS}


SCENES = [
    dict(seed=0), dict(seed=1, n=64), dict(seed=2, channels=5),
    dict(seed=3, opacity=(0.9, 1.0), n=64),  # near-opaque stacks: exercises the T < 1e-4 stop and 0.99 clamp
    dict(seed=4, scale=(0.003, 0.02)),  # sub-pixel splats: exercises the low-pass fallback
    dict(seed=5, n=24, scale=(0.3, 0.6), opacity=(0.995, 1.0)),  # large opaque splats: the 0.99 clamp
]


@pytest.mark.parametrize("cfg", SCENES, ids=lambda c: "-".join(f"{k}{v}" for k, v in c.items()))
def test_forward_matches_dense_reference(cfg):
    params, cam = random_scene(**cfg)
    bg = torch.linspace(0.1, 0.9, params[4].shape[1], dtype=F64)
    kw = dict(distortion_near=1.0, distortion_far=10.0, depth_ratio=0.3)
    a, b = _fast(params, cam, bg, **kw), rasterize_dense(*params, cam, bg, **kw)
    assert float(b["alpha"].max()) > 0.5
    for k in KEYS:
        scale = max(1.0, float(b[k].abs().max()))
        torch.testing.assert_close(a[k], b[k], atol=1e-5 * scale, rtol=0, msg=k)


def test_cuda_span_grouping_matches_reference(monkeypatch):
    """The grouping CUDA uses (span lengths padded to powers of two), run here on CPU: padded pixels past a
    row's span must be masked, or pairs from the next image row leak in."""
    import method.splat.rasterize as rz

    monkeypatch.setitem(rz.EXACT_SPAN_MAX, False, rz.EXACT_SPAN_MAX[True])
    for cfg in [SCENES[0], SCENES[4], SCENES[5], dict(seed=8, n=96, spread=3.0)]:  # the last two cross the border
        params, cam = random_scene(**cfg)
        a, b = _fast(params, cam), rasterize_dense(*params, cam)
        for k in KEYS:
            torch.testing.assert_close(a[k], b[k], atol=1e-5 * max(1.0, float(b[k].abs().max())), rtol=0, msg=k)


def test_segment_sums_by_prefix_match_segment_reduce():
    """Per-segment sums through a float64 prefix sum (the CUDA path) equal aten's segment_reduce,
    empty segments included."""
    from method.splat.segments import Segments

    g = torch.Generator().manual_seed(0)
    seg = torch.sort(torch.randint(0, 500, (20_000,), generator=g) * 2).values  # odd segments stay empty
    segs = Segments(seg, 1001)
    for x in (torch.rand(seg.numel(), generator=g), torch.randn(seg.numel(), 4, generator=g)):
        ref = torch.segment_reduce(x.double(), "sum", lengths=segs.counts, axis=0).float()
        got = segs.sum_by_prefix(x)
        assert got.dtype == x.dtype and got.shape == ref.shape
        torch.testing.assert_close(got, ref, atol=1e-5, rtol=1e-6)
        assert torch.all(got[1::2] == 0)


def test_stop_and_clamp_are_exercised(monkeypatch):
    """The near-opaque scene really stops early (else the comparison above would not cover the rule)."""
    import method.splat.rasterize as rz

    params, cam = random_scene(seed=3, opacity=(0.9, 1.0), n=64)
    out = rasterize(*params, cam)
    assert float(out.alpha.max()) > 1 - 2e-4  # transmittance reached ~1e-4
    monkeypatch.setattr(rz, "T_STOP", 1e-300)
    assert rasterize(*params, cam).num_pairs > out.num_pairs + 20


@pytest.mark.parametrize("seed", [0, 3, 4, 5])
def test_gradients_match_dense_reference(seed):
    cfg = dict(SCENES[seed])
    params, cam = random_scene(**cfg)
    g = torch.Generator().manual_seed(100 + seed)
    weights = {}
    grads = []
    for fn in (_fast, rasterize_dense):
        leaves = [p.clone().requires_grad_(True) for p in params]
        out = fn(leaves, cam, None, distortion_near=1.0, distortion_far=10.0) if fn is _fast else \
            fn(*leaves, cam, None, distortion_near=1.0, distortion_far=10.0)
        loss = 0.0
        for k in KEYS:
            if k not in weights:
                weights[k] = torch.randn(out[k].shape, generator=g, dtype=F64)
            loss = loss + (out[k] * weights[k]).sum()
        loss.backward()
        grads.append([p.grad for p in leaves])
    for name, ga, gb in zip(("means", "quats", "scales", "opacities", "features"), *grads):
        scale = max(1.0, float(gb.abs().max()))
        torch.testing.assert_close(ga, gb, atol=1e-5 * scale, rtol=0, msg=name)


def test_gradcheck_few_splats():
    """Large, camera-facing, semi-transparent splats: no pair near the skip/stop/clamp thresholds or the
    fallback switch, so the function is smooth where gradcheck probes it."""
    torch.manual_seed(0)
    cam = Camera.look_at((0.0, -4.0, 0.0), (0.0, 0.0, 0.0), 8, 8, dtype=F64)
    means = torch.tensor([[0.0, 0.0, 0.0], [0.15, 0.4, 0.1], [-0.2, -0.3, -0.15]], dtype=F64)
    # quaternion turning +z into -y (facing the camera), slightly perturbed per splat
    base = torch.tensor([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0], dtype=F64)
    quats = base + 0.1 * torch.randn(3, 4, dtype=F64)
    scales = torch.tensor([[2.0, 1.6], [1.5, 1.8], [2.2, 1.4]], dtype=F64)
    opac = torch.tensor([0.5, 0.6, 0.4], dtype=F64)
    feats = torch.rand(3, 2, dtype=F64)
    offsets = torch.zeros(3, 2, dtype=F64)

    def fn(m, q, s, o, f, off):
        out = rasterize(m, q, s, o, f, cam, screen_offsets=off, distortion_near=1.0, distortion_far=10.0)
        return (out.features, out.alpha, out.normal, out.depth_expected, out.distortion,
                out.normal_from_depth[2:-2, 2:-2])

    # guard: every pair is far from the thresholds
    out = rasterize(means, quats, scales, opac, feats, cam)
    assert out.num_pairs == 3 * 64 and float(out.alpha.min()) > 0.1
    inputs = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, feats, offsets)]
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def _facing_splat(distance, sx, sy, size, opacity, angle=0.0):
    """One splat at the origin facing a camera on the -y axis; its axes rotated by ``angle`` in the image."""
    cam = Camera.look_at((0.0, -distance, 0.0), (0.0, 0.0, 0.0), size, size, dtype=F64)
    # rotation: local z -> world -y (towards the camera), local x -> world (cos a, 0, sin a)
    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[c, -s, 0.0], [0.0, 0.0, -1.0], [s, c, 0.0]])
    rot[:, 1] = np.cross(rot[:, 2], rot[:, 0])
    w = math.sqrt(max(0.0, 1 + np.trace(rot))) / 2
    q = torch.tensor([w, (rot[2, 1] - rot[1, 2]) / (4 * w), (rot[0, 2] - rot[2, 0]) / (4 * w),
                      (rot[1, 0] - rot[0, 1]) / (4 * w)], dtype=F64)
    params = [torch.zeros(1, 3, dtype=F64), q[None], torch.tensor([[sx, sy]], dtype=F64),
              torch.tensor([opacity], dtype=F64), torch.ones(1, 1, dtype=F64)]
    return params, cam


@pytest.mark.parametrize("o", [0.8, 1.0])
def test_single_facing_splat_footprint_alpha_depth(o):
    D, size, sigma_px = 4.0, 32, 3.0
    cam = Camera.look_at((0.0, -D, 0.0), (0.0, 0.0, 0.0), size, size, dtype=F64)
    s = sigma_px * D / cam.focal  # world size whose 1-sigma footprint is sigma_px pixels
    params, cam = _facing_splat(D, s, s, size, o)
    out = rasterize(*params, cam)
    c = torch.arange(size, dtype=F64) + 0.5 - size / 2
    r2 = c[:, None] ** 2 + c[None, :] ** 2
    expect = (o * torch.exp(-0.5 * r2 / sigma_px ** 2)).clamp_max(0.99)
    expect = torch.where(expect >= ALPHA_MIN, expect, torch.zeros_like(expect))
    torch.testing.assert_close(out.alpha, expect, atol=1e-9, rtol=0)
    covered = expect > 0
    torch.testing.assert_close(out.depth_expected[covered], torch.full_like(out.alpha[covered], D))
    torch.testing.assert_close(out.depth_median[covered], torch.full_like(out.alpha[covered], D))
    # normal faces the camera (world -y), weighted by alpha
    torch.testing.assert_close(out.normal[..., 1], -out.alpha, atol=1e-12, rtol=0)
    # depth-derived normal of the flat disc, away from its edge
    inner = expect > 0.2
    inner[1:-1, 1:-1] &= covered[:-2, 1:-1] & covered[2:, 1:-1] & covered[1:-1, :-2] & covered[1:-1, 2:]
    torch.testing.assert_close(out.normal_from_depth[inner][:, 1], torch.full_like(out.alpha[inner], -1.0))


def test_anisotropic_footprint_area():
    """Pixels with alpha >= o exp(-1/2) fill the 1-sigma ellipse: area pi sx sy (in pixels)."""
    D, size, o = 4.0, 64, 0.9
    cam = Camera.look_at((0.0, -D, 0.0), (0.0, 0.0, 0.0), size, size, dtype=F64)
    sx_px, sy_px = 12.0, 5.0
    params, cam = _facing_splat(D, sx_px * D / cam.focal, sy_px * D / cam.focal, size, o, angle=0.6)
    out = rasterize(*params, cam)
    area = float((out.alpha >= o * math.exp(-0.5)).sum())
    assert abs(area - math.pi * sx_px * sy_px) < 2 * math.pi * (sx_px + sy_px) * 0.5  # within half a pixel ring


@pytest.mark.parametrize("angle", [0.6, -1.1])
def test_anisotropic_footprint_orientation(angle):
    """The long axis lies along the splat's rotated local x: on screen (x right, y down) the direction
    (cos a, -sin a) for a rotation by a about the view axis, exactly o exp(-(u^2/sx^2 + v^2/sy^2)/2) per pixel."""
    D, size, o = 4.0, 48, 0.9
    cam = Camera.look_at((0.0, -D, 0.0), (0.0, 0.0, 0.0), size, size, dtype=F64)
    sx_px, sy_px = 7.0, 2.5  # long local x, short local y
    params, cam = _facing_splat(D, sx_px * D / cam.focal, sy_px * D / cam.focal, size, o, angle=angle)
    out = rasterize(*params, cam)
    c = torch.arange(size, dtype=F64) + 0.5 - size / 2
    dx, dy_up = c[None, :], -c[:, None]  # image right = world x, image up = world z
    u = dx * math.cos(angle) + dy_up * math.sin(angle)
    v = -dx * math.sin(angle) + dy_up * math.cos(angle)
    expect = (o * torch.exp(-0.5 * ((u / sx_px) ** 2 + (v / sy_px) ** 2))).clamp_max(0.99)
    expect = torch.where(expect >= ALPHA_MIN, expect, torch.zeros_like(expect))
    torch.testing.assert_close(out.alpha, expect, atol=1e-9, rtol=0)
    # the same read off the image: principal axis of the alpha-weighted second moments
    w = out.alpha
    xs, ys = dx.expand_as(w), (-dy_up).expand_as(w)  # pixel offsets, y down
    cov = torch.stack([torch.stack([(w * xs * xs).sum(), (w * xs * ys).sum()]),
                       torch.stack([(w * xs * ys).sum(), (w * ys * ys).sum()])]) / w.sum()
    evals, evecs = torch.linalg.eigh(cov)
    long_axis = evecs[:, 1]
    found = math.atan2(-float(long_axis[1]), float(long_axis[0]))  # angle measured counter-clockwise, y up
    diff = (found - angle + math.pi / 2) % math.pi - math.pi / 2  # an axis: defined modulo pi
    assert abs(diff) < math.radians(1.0), (math.degrees(found), math.degrees(angle))
    assert float(evals[1] / evals[0]) == pytest.approx((sx_px / sy_px) ** 2, rel=0.05)


def test_lowpass_fallback_for_tiny_splat():
    D, size, o = 4.0, 16, 0.7
    params, cam = _facing_splat(D, 1e-5, 1e-5, size, o)
    params[0] = torch.tensor([[0.013, 0.0, -0.021]], dtype=F64)  # off the pixel grid
    out = rasterize(*params, cam)
    p_cam = params[0][0] @ cam.w2c[:3, :3].T + cam.w2c[:3, 3]
    cx = cam.focal * p_cam[0] / p_cam[2] + cam.cx
    cy = cam.focal * p_cam[1] / p_cam[2] + cam.cy
    xs = torch.arange(size, dtype=F64) + 0.5
    d2 = (xs[None, :] - cx) ** 2 + (xs[:, None] - cy) ** 2
    expect = o * torch.exp(-d2)  # 2D filter: exp(-0.5 * 2 d^2)
    expect = torch.where(expect >= ALPHA_MIN, expect, torch.zeros_like(expect))
    torch.testing.assert_close(out.alpha, expect, atol=1e-9, rtol=0)
    assert 3 <= int((out.alpha > 0).sum()) <= 30
    torch.testing.assert_close(out.depth_expected[out.alpha > 0], p_cam[2].expand(int((out.alpha > 0).sum())))


def test_tilted_plane_normal_from_depth():
    """A big opaque tilted splat: the depth-derived normal equals the splat's own (camera-facing) normal."""
    cam = Camera.look_at((0.0, -4.0, 0.5), (0.0, 0.0, 0.0), 24, 24, dtype=F64)
    ang = 0.5
    q = torch.tensor([[math.cos(ang / 2), math.sin(ang / 2), 0.0, 0.0]], dtype=F64)  # rotate about x
    params = [torch.zeros(1, 3, dtype=F64), q, torch.tensor([[3.0, 3.0]], dtype=F64),
              torch.tensor([0.99], dtype=F64), torch.ones(1, 1, dtype=F64)]
    out = rasterize(*params, cam)
    n = torch.tensor([0.0, -math.sin(ang), math.cos(ang)], dtype=F64)  # R(ang) e_z
    if float(n @ (cam.center - params[0][0])) < 0:
        n = -n
    nd = out.normal_from_depth[2:-2, 2:-2].reshape(-1, 3)
    torch.testing.assert_close(nd, n.expand_as(nd), atol=1e-9, rtol=0)
    nr = (out.normal / out.alpha[..., None])[2:-2, 2:-2].reshape(-1, 3)
    torch.testing.assert_close(nr, n.expand_as(nd), atol=1e-9, rtol=0)


def test_blender_camera_convention():
    """OpenGL c2w: identity looks down -z with +y up; a point above the axis lands in the top rows."""
    cam = Camera.from_blender(0.6911112070083618, np.eye(4), 20, 10, dtype=F64)
    assert math.isclose(cam.focal, 10.0 / math.tan(0.6911112070083618 / 2))
    params = [torch.tensor([[0.3, 0.2, -3.0]], dtype=F64), torch.tensor([[1.0, 0, 0, 0]], dtype=F64),
              torch.tensor([[1e-4, 1e-4]], dtype=F64), torch.tensor([0.9], dtype=F64), torch.ones(1, 1, dtype=F64)]
    out = rasterize(*params, cam)
    i, j = np.unravel_index(int(out.alpha.argmax()), out.alpha.shape)
    assert j == int(10 + cam.focal * 0.3 / 3.0) and i == int(5 - cam.focal * 0.2 / 3.0)
    torch.testing.assert_close(out.depth_expected[i, j], torch.tensor(3.0, dtype=F64))


def test_empty_and_culled():
    params, cam = random_scene(n=4)
    params[0] = params[0] + torch.tensor([0.0, -10.0, 0.0], dtype=F64)  # all behind the camera
    out = rasterize(*params, cam, torch.tensor([0.5, 0.5, 0.5], dtype=F64))
    assert out.num_pairs == 0 and float(out.alpha.abs().max()) == 0.0
    torch.testing.assert_close(out.features, torch.full((16, 16, 3), 0.5, dtype=F64))
    assert not bool(out.visible.any())


def test_bad_shapes_raise():
    params, cam = random_scene(n=4)
    with pytest.raises(ValueError, match="scales"):
        rasterize(params[0], params[1], params[2][:, :1], params[3], params[4], cam)
    with pytest.raises(ValueError, match="camera_angle_x"):
        Camera.from_blender(4.0, np.eye(4), 8, 8)


def test_float32_close_to_float64():
    params, cam = random_scene(seed=5, n=64)
    a = rasterize(*params, cam)
    b = rasterize(*[p.float() for p in params], cam.to(dtype=torch.float32))
    for k in ("features", "alpha", "depth_expected"):
        torch.testing.assert_close(getattr(b, k).double(), getattr(a, k), atol=2e-4, rtol=1e-4, msg=k)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cpu_cuda_agree():
    params, cam = random_scene(seed=6, n=64, size=24)
    a = rasterize(*params, cam)
    b = rasterize(*[p.cuda() for p in params], cam.to("cuda"))
    for k in KEYS:
        torch.testing.assert_close(getattr(b, k).cpu(), getattr(a, k), atol=1e-9, rtol=0, msg=k)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cpu_cuda_agree_float32_with_gradients():
    """float32 takes CUDA's own paths (prefix-sum segment sums, power-of-two span groups)."""
    params, cam = random_scene(seed=7, n=200, size=48)
    outs, grads = [], []
    for dev in ("cpu", "cuda"):
        p = [t.float().to(dev).requires_grad_(True) for t in params]
        out = rasterize(*p, cam.to(dev, torch.float32))
        (out.features.sum() + out.distortion.sum() + out.normal.sum() + 0.1 * out.depth_expected.sum()).backward()
        outs.append({k: getattr(out, k).detach().cpu() for k in KEYS})
        grads.append([t.grad.cpu() for t in p])
    # normal_from_depth (finite differences of depth) is ill-conditioned in float32 at silhouettes; it is
    # compared in float64 by test_cpu_cuda_agree
    for k in [k for k in KEYS if k != "normal_from_depth"]:
        torch.testing.assert_close(outs[1][k], outs[0][k], atol=2e-5 * max(1.0, float(outs[0][k].abs().max())),
                                   rtol=0, msg=k)
    for ga, gb in zip(grads[0], grads[1]):
        torch.testing.assert_close(gb, ga, atol=1e-4 * max(1.0, float(ga.abs().max())), rtol=0)


def test_camera_inside_the_cloud_matches_reference():
    """Splats around and behind the camera, some crossing its plane (unbounded footprints)."""
    params, _ = random_scene(n=64, seed=2, scale=(0.2, 0.8), spread=2.0)
    cam = Camera.look_at((0.05, -0.1, 0.02), (0.3, 1.0, 0.1), 16, 12, dtype=F64)
    a, b = _fast(params, cam), rasterize_dense(*params, cam)
    for k in KEYS:
        torch.testing.assert_close(a[k], b[k], atol=1e-5 * max(1.0, float(b[k].abs().max())), rtol=0, msg=k)


def test_grazing_splat_plane_through_the_camera_gives_finite_gradients():
    """A splat whose plane contains the camera centre (the middle pixel column of an odd-width image looks
    exactly along it): the ray-plane hit is undefined there, only the low-pass fallback may apply, and
    neither a zero depth nor an overflowed u may turn the backward pass into NaN (it stopped a training)."""
    import math

    cam = Camera.look_at((0, -4, 0), (0, 0, 0), 15, 15, dtype=torch.float32)
    s = math.sqrt(0.5)
    means = torch.tensor([[0.0, 0.0, 0.0], [0.02, 0.3, 0.01]], requires_grad=True)
    quats = torch.tensor([[s, 0.0, s, 0.0], [s, 0.0, s, 0.0]], requires_grad=True)  # normals along x
    scales = torch.tensor([[0.3, 0.3], [0.2, 0.2]], requires_grad=True)
    op = torch.tensor([0.9, 0.9], requires_grad=True)
    feats = torch.ones(2, 3, requires_grad=True)
    out = rasterize(means, quats, scales, op, feats, cam)
    assert out.num_pairs > 0
    (out.features.sum() + out.depth_expected.sum() + out.distortion.sum()).backward()
    for t in (means, quats, scales, op, feats):
        assert torch.isfinite(t.grad).all()
    assert torch.isfinite(out.depth_expected).all() and torch.isfinite(out.distortion).all()
