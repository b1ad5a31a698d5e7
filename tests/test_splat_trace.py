"""Ray tracer: grid-accelerated vs brute force, gradients, analytic visibility, agreement with the rasterizer."""
from __future__ import annotations

import math

import pytest
import torch

from method.splat.camera import Camera
from method.splat.rasterize import ALPHA_MIN, rasterize
from method.splat.reference import trace_dense
from method.splat.trace import TraceAccel, trace

pytestmark = pytest.mark.usefixtures("splat_backend")  # conftest: torch and the compiled backend
F64 = torch.float64


def random_scene(n=64, seed=0, channels=3, scale=(0.1, 0.4), opacity=(0.05, 0.95)):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=F64) - 0.5) * 1.2
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    quats = quats / quats.norm(dim=1, keepdim=True)
    scales = torch.exp(torch.empty(n, 2, dtype=F64).uniform_(math.log(scale[0]), math.log(scale[1]), generator=g))
    opac = torch.empty(n, dtype=F64).uniform_(*opacity, generator=g)
    feats = torch.rand(n, channels, generator=g, dtype=F64)
    return [means, quats, scales, opac, feats]


def random_rays(r=400, seed=0, unit=True, axis_aligned=0):
    g = torch.Generator().manual_seed(1000 + seed)
    o = (torch.rand(r, 3, generator=g, dtype=F64) - 0.5) * 2.4  # some start outside the grid
    d = torch.randn(r, 3, generator=g, dtype=F64)
    if axis_aligned:  # exact zeros in the direction: the DDA must not divide by them
        d[:axis_aligned] = 0.0
        d[torch.arange(axis_aligned), torch.arange(axis_aligned) % 3] = 1.0
    if unit:
        d = d / d.norm(dim=1, keepdim=True)
    else:
        d = d * torch.rand(r, 1, generator=g, dtype=F64).add(0.3)
    return o, d


@pytest.mark.parametrize("cell_size", [None, 0.03, 5.0])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_accelerated_equals_brute_force(seed, cell_size):
    params = random_scene(seed=seed, opacity=(0.05, 1.0) if seed == 2 else (0.05, 0.95))
    o, d = random_rays(seed=seed, unit=seed != 1, axis_aligned=12)
    tmin = 0.02 if seed != 2 else torch.rand(o.shape[0], dtype=F64) * 0.5
    accel = TraceAccel.build(*params[:4], cell_size=cell_size)
    T1, F1 = trace(*params, o, d, tmin, accel=accel)
    T2, F2 = trace_dense(*params, o, d, tmin)
    assert float(T2.min()) < 0.1 and float(T2.max()) == 1.0  # both occluded and free rays
    torch.testing.assert_close(T1, T2, atol=1e-9, rtol=0)
    torch.testing.assert_close(F1, F2, atol=1e-9, rtol=0)


def test_thresholds_are_parameters():
    params = random_scene(seed=3, opacity=(0.5, 1.0))
    o, d = random_rays(seed=3)
    for kw in (dict(alpha_min=0.2, T_min=0.3), dict(alpha_min=0.001, T_min=0.001, max_alpha=0.9)):
        T1, F1 = trace(*params, o, d, 0.0, **kw)
        T2, F2 = trace_dense(*params, o, d, 0.0, **kw)
        torch.testing.assert_close(T1, T2, atol=1e-9, rtol=0)
        torch.testing.assert_close(F1, F2, atol=1e-9, rtol=0)


def test_stop_rule_includes_the_crossing_hit():
    """Transmittance ends below T_min (the crossing hit counts), and hits behind it are ignored."""
    params = random_scene(seed=4, n=64, opacity=(0.9, 1.0), scale=(0.3, 0.6))
    o, d = random_rays(seed=4)
    T, _ = trace(*params, o, d, 0.0, T_min=0.03)
    T_all, _ = trace(*params, o, d, 0.0, T_min=1e-12)
    stopped = T < 0.03
    assert int(stopped.sum()) > 20
    assert bool((T_all[stopped] < T[stopped]).any())  # later hits would have darkened further


def test_opaque_splat_blocks_and_misses_pass():
    q = torch.tensor([[math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0]], dtype=F64)  # normal -> +x
    params = [torch.zeros(1, 3, dtype=F64), q, torch.tensor([[0.5, 0.5]], dtype=F64),
              torch.ones(1, dtype=F64), torch.tensor([[1.0, 2.0]], dtype=F64)]
    o = torch.tensor([[-1.0, 0, 0], [-1.0, 0, 0], [1.0, 0, 0], [-1.0, 0, 0], [-1.0, 0.5, 0.0]], dtype=F64)
    d = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [1.0, 0, 0], [1.0, 0, 0], [1.0, 0.0, 0.0]], dtype=F64)
    tmin = torch.tensor([0.0, 0.0, 0.0, 2.0, 0.0], dtype=F64)
    T, F = trace(*params, o, d, tmin)
    # through the centre: alpha = min(0.99, 1) -> V = 0.01; one sigma off-centre: 1 - exp(-1/2)
    expect = torch.tensor([0.01, 1.0, 1.0, 1.0, 1.0 - math.exp(-0.5)], dtype=F64)
    torch.testing.assert_close(T, expect, atol=1e-12, rtol=0)
    torch.testing.assert_close(F[0], torch.tensor([0.99, 1.98], dtype=F64))
    torch.testing.assert_close(F[1:4], torch.zeros(3, 2, dtype=F64))


def test_gradients_match_brute_force():
    params = random_scene(seed=5)
    o, d = random_rays(seed=5)
    g = torch.Generator().manual_seed(7)
    w_t = torch.randn(o.shape[0], generator=g, dtype=F64)
    w_f = torch.randn(o.shape[0], 3, generator=g, dtype=F64)
    grads = []
    for fn in (trace, trace_dense):
        leaves = [p.clone().requires_grad_(True) for p in params]
        T, F = fn(*leaves, o, d, 0.0)
        ((T * w_t).sum() + (F * w_f).sum()).backward()
        grads.append([p.grad for p in leaves])
    for name, a, b in zip(("means", "quats", "scales", "opacities", "features"), *grads):
        torch.testing.assert_close(a, b, atol=1e-8 * max(1.0, float(b.abs().max())), rtol=0, msg=name)


def test_gradcheck_few_splats():
    """Big semi-transparent splats crossed by every ray well inside their support: smooth region."""
    torch.manual_seed(1)
    q = torch.tensor([math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0], dtype=F64)
    params = [torch.tensor([[0.0, 0, 0], [0.5, 0.05, -0.02], [1.0, -0.03, 0.04]], dtype=F64),
              q + 0.05 * torch.randn(3, 4, dtype=F64), torch.tensor([[1.0, 0.8], [0.9, 1.1], [1.2, 1.0]], dtype=F64),
              torch.tensor([0.5, 0.4, 0.6], dtype=F64), torch.rand(3, 2, dtype=F64)]
    o = torch.tensor([[-1.0, 0.0, 0.0], [-1.0, 0.1, -0.1], [-1.0, -0.2, 0.1]], dtype=F64)
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.1, 0.05], [1.0, -0.05, 0.1]], dtype=F64)

    def fn(m, qq, s, op, f):
        return trace(m, qq, s, op, f, o, d, 0.0)

    T, _ = fn(*params)
    assert float(T.min()) > 0.1  # no stop, and every ray hits all three splats (checked by gradcheck values)
    assert torch.autograd.gradcheck(fn, [p.clone().requires_grad_(True) for p in params], eps=1e-6, atol=1e-6)


def test_camera_rays_match_rasterized_pixels():
    """Same scene, same thresholds (alpha_min = 1/255, no stop reached), large camera-facing splats at
    distinct depths: the traced pixel rays reproduce the rasterized colour and alpha to 1e-9.

    In general they differ slightly, by design: the rasterizer orders splats by centre depth (not by
    hit distance), applies the low-pass fallback to sub-pixel splats, and stops before the hit that
    would take T below 1e-4, whereas the tracer counts that hit (its stop is T_min)."""
    cam = Camera.look_at((0.0, -4.0, 0.3), (0.0, 0.0, 0.0), 20, 16, dtype=F64)
    g = torch.Generator().manual_seed(3)
    n = 5
    means = torch.stack([torch.rand(n, generator=g, dtype=F64) - 0.5, torch.linspace(-1.2, 1.2, n, dtype=F64),
                         torch.rand(n, generator=g, dtype=F64) - 0.5], 1)
    base = torch.tensor([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0], dtype=F64)
    quats = base + 0.1 * torch.randn(n, 4, generator=g, dtype=F64)
    scales = 0.2 + 0.3 * torch.rand(n, 2, generator=g, dtype=F64)
    opac = 0.3 + 0.5 * torch.rand(n, generator=g, dtype=F64)
    feats = torch.rand(n, 3, generator=g, dtype=F64)
    out = rasterize(means, quats, scales, opac, feats, cam)
    o, d = cam.pixel_rays()
    T, F = trace(means, quats, scales, opac, feats, o.reshape(-1, 3), d.reshape(-1, 3), 0.0,
                 alpha_min=ALPHA_MIN, T_min=1e-4)
    assert float(out.alpha.max()) > 0.7 and float(out.alpha.min()) == 0.0
    torch.testing.assert_close(1.0 - T.reshape(16, 20), out.alpha, atol=1e-9, rtol=0)
    torch.testing.assert_close(F.reshape(16, 20, 3), out.features, atol=1e-9, rtol=0)


def test_camera_rays_close_on_random_scene():
    """Generic interpenetrating scene, footprints of a few pixels: stated tolerance mean |diff| < 0.03 for
    colour and alpha (measured 0.010-0.015 colour, 0.016-0.024 alpha over three seeds). The residual is the
    order difference where splats intersect, and the low-pass fallback widening sub-pixel splats in
    the rasterizer only; for footprints below a pixel the gap grows (0.05 colour, 0.09 alpha measured)."""
    params = random_scene(seed=8, n=64, scale=(0.05, 0.3))
    cam = Camera.look_at((0.3, -3.5, 1.0), (0.0, 0.0, 0.0), 24, 24, dtype=F64)
    out = rasterize(*params, cam)
    o, d = cam.pixel_rays()
    T, F = trace(*params, o.reshape(-1, 3), d.reshape(-1, 3), 0.0, alpha_min=ALPHA_MIN, T_min=1e-4)
    diff = (F.reshape(24, 24, 3) - out.features).abs()
    assert float(diff.mean()) < 0.03
    assert float((1 - T.reshape(24, 24) - out.alpha).abs().mean()) < 0.03


def test_accel_reuse_and_mismatch():
    params = random_scene(seed=9)
    o, d = random_rays(seed=9)
    accel = TraceAccel.build(*params[:4])
    a = trace(*params, o, d, accel=accel)[0]
    b = trace(*params, o[:50], d[:50], accel=accel)[0]
    torch.testing.assert_close(a[:50], b)
    with pytest.raises(ValueError, match="rebuild"):
        trace(*[p[:10] for p in params], o, d, accel=accel)
    with pytest.raises(ValueError, match="origins"):
        trace(*params, o[:, :2], d)
    T, F = trace(*params[:4], None, o, d)
    assert F is None and T.shape == (o.shape[0],)


def test_float32_close_to_float64():
    params = random_scene(seed=10)
    o, d = random_rays(seed=10)
    T1, F1 = trace(*[p.float() for p in params], o.float(), d.float(), 0.0)
    T2, F2 = trace(*params, o, d, 0.0)
    assert float((T1.double() - T2).abs().mean()) < 1e-4
    assert float((F1.double() - F2).abs().mean()) < 1e-4


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cpu_cuda_agree():
    params = random_scene(seed=11)
    o, d = random_rays(seed=11)
    T1, F1 = trace(*params, o, d, 0.0)
    T2, F2 = trace(*[p.cuda() for p in params], o.cuda(), d.cuda(), 0.0)
    torch.testing.assert_close(T2.cpu(), T1, atol=1e-9, rtol=0)
    torch.testing.assert_close(F2.cpu(), F1, atol=1e-9, rtol=0)


def test_empty_and_transparent_splat_sets():
    o, d = random_rays(r=8, seed=12)
    z = torch.zeros(0, dtype=F64)
    T, F = trace(z.reshape(0, 3), z.reshape(0, 4), z.reshape(0, 2), z, z.reshape(0, 2), o, d)
    assert torch.equal(T, torch.ones(8, dtype=F64)) and F.shape == (8, 2)
    params = random_scene(n=5, seed=12, opacity=(0.001, 0.005))  # all below alpha_min: nothing registered
    T, F = trace(*params, o, d)
    assert torch.equal(T, torch.ones(8, dtype=F64)) and float(F.abs().max()) == 0.0


def test_ray_chunks_give_the_same_result():
    params = random_scene(seed=13)
    o, d = random_rays(seed=13)
    a = trace(*params, o, d, 0.0)
    b = trace(*params, o, d, 0.0, ray_chunk=37)
    torch.testing.assert_close(a[0], b[0], atol=0, rtol=0)
    torch.testing.assert_close(a[1], b[1], atol=1e-12, rtol=0)


def test_small_splats_in_fine_cells_equal_brute_force():
    """Splats much smaller than a cell, each registered in one or two cells, and every ray aimed at one of
    them: a DDA step into a wrong cell, or a hit claimed by the wrong cell, loses or doubles hits."""
    params = random_scene(n=400, seed=14, scale=(0.001, 0.002), opacity=(0.5, 1.0))
    g = torch.Generator().manual_seed(14)
    target = params[0][torch.randint(0, 400, (3000,), generator=g)]
    o = (torch.rand(3000, 3, generator=g, dtype=F64) - 0.5) * 1.4
    d = target + 0.001 * torch.randn(3000, 3, generator=g, dtype=F64) - o
    d = d / d.norm(dim=1, keepdim=True)
    accel = TraceAccel.build(*params[:4], cell_size=0.02)
    T1, F1 = trace(*params, o, d, 0.0, accel=accel)
    T2, F2 = trace_dense(*params, o, d, 0.0)
    assert float((T2 < 1).float().mean()) > 0.5  # most rays hit something
    torch.testing.assert_close(T1, T2, atol=1e-9, rtol=0)
    torch.testing.assert_close(F1, F2, atol=1e-9, rtol=0)


@pytest.mark.parametrize("block,chunk", [(1, 1 << 18), (3, 40), (16, 7)])
def test_block_width_and_candidate_chunks_do_not_change_hits(block, chunk, monkeypatch):
    """Cell entries padded to blocks of any width, candidates tested in chunks of any size (down to a
    single block): the same result as brute force."""
    import method.splat.trace as trace_mod

    monkeypatch.setattr(trace_mod, "CANDIDATE_CHUNK", chunk)
    params = random_scene(seed=5)
    o, d = random_rays(seed=5, axis_aligned=6)
    accel = TraceAccel.build(*params[:4], cell_size=0.1, block=block)
    assert accel.blk_plane.shape[1] == 4 * block
    T1, F1 = trace(*params, o, d, 0.02, accel=accel)
    T2, F2 = trace_dense(*params, o, d, 0.02)
    assert float(T2.min()) < 0.1
    torch.testing.assert_close(T1, T2, atol=1e-9, rtol=0)
    torch.testing.assert_close(F1, F2, atol=1e-9, rtol=0)


def test_cuda_traversal_settings_match_brute_force_on_cpu(monkeypatch):
    """The CUDA defaults (large candidate chunks, 16 DDA steps per round, 2^20 rays per traversal), run on
    CPU: the same hits as brute force."""
    import method.splat.trace as trace_mod

    monkeypatch.setattr(trace_mod, "CANDIDATE_CHUNK", trace_mod.CUDA_CANDIDATE_CHUNK)
    params = random_scene(seed=5)
    o, d = random_rays(seed=5, axis_aligned=6)
    T1, F1 = trace(*params, o, d, 0.02, steps_per_round=trace_mod.STEPS_PER_ROUND[True],
                   ray_chunk=trace_mod.RAY_CHUNK[True])
    T2, F2 = trace_dense(*params, o, d, 0.02)
    torch.testing.assert_close(T1, T2, atol=1e-9, rtol=0)
    torch.testing.assert_close(F1, F2, atol=1e-9, rtol=0)


def test_values_without_gradients_equal_the_differentiable_path(splat_backend):
    """Without gradients the traversal's alphas are reused (torch) or formed from its Gaussian factors and
    composited by the compiled pass (its exp, not torch's, and products of (1 - alpha) where torch sums
    logarithms: equal to the last bits); with them they are recomputed: same values."""
    params = random_scene(seed=6, opacity=(0.3, 1.0))
    o, d = random_rays(seed=6)
    T0, F0 = trace(*params, o, d, 0.0)
    leaves = [p.clone().requires_grad_(True) for p in params]
    T1, F1 = trace(*leaves, o, d, 0.0)
    assert T1.requires_grad and not T0.requires_grad
    assert float(T0.min()) < 0.1
    tol = 0 if splat_backend == "torch" else 1e-13
    torch.testing.assert_close(T0, T1.detach(), atol=tol, rtol=0)
    torch.testing.assert_close(F0, F1.detach(), atol=tol, rtol=0)


@pytest.mark.parametrize("dtype, max_alpha", [(torch.float64, 0.99), (torch.float32, 0.99), (torch.float64, 0.8)])
def test_gradients_with_the_geometry_frozen_match_brute_force(dtype, max_alpha):
    """Stage 2's case: means, quats and scales constant, opacities and features trained. The compiled
    backend then forms each alpha from the traversal's Gaussian factor and the given opacity (no
    recomputation of the geometry) and composites the hits in one compiled pass each way; values and both
    gradients are the brute-force tracer's (with a max_alpha that clamps some hits: no opacity gradient
    through those), and where a grid built with other opacities selects the hits, those of the
    recomputation a gradient to the geometry takes."""
    params = [p.to(dtype) for p in random_scene(seed=8, opacity=(0.2, 0.97))]
    o, d = (v.to(dtype) for v in random_rays(seed=8))
    g = torch.Generator().manual_seed(9)
    w_t = torch.randn(o.shape[0], generator=g, dtype=F64).to(dtype)
    w_f = torch.randn(o.shape[0], 3, generator=g, dtype=F64).to(dtype)
    tol = 1e-10 if dtype == torch.float64 else 2e-5
    stale = TraceAccel.build(*params[:3], (params[3] * 0.9).clamp_max(0.95))
    for accel in (None, stale):
        res = []
        for geometry_grad in (False, True):
            geo = [p.clone().requires_grad_(geometry_grad) for p in params[:3]]
            op, ft = (params[3].clone().requires_grad_(True), params[4].clone().requires_grad_(True))
            if accel is None and geometry_grad:
                T, F = trace_dense(*geo, op, ft, o, d, 0.0, max_alpha=max_alpha)
            else:
                T, F = trace(*geo, op, ft, o, d, 0.0, accel=accel, max_alpha=max_alpha)
            ((T * w_t).sum() + (F * w_f).sum()).backward()
            res.append((T.detach(), F.detach(), op.grad, ft.grad))
        assert float(res[1][0].min()) < 0.1  # some rays pass several splats
        for name, a, b in zip(("T", "features", "d opacities", "d features"), *res):
            torch.testing.assert_close(a, b, atol=tol * max(1.0, float(b.abs().max())), rtol=0, msg=name)


def test_a_grid_built_with_other_opacities_traces_with_the_given_ones(splat_backend):
    """A grid kept while opacities change (stage 2 fine-tunes them) selects the hits; the alphas come from
    the opacities passed, with or without gradients and on either backend."""
    from method.splat.trace import TraceAccel, trace

    g = torch.Generator().manual_seed(0)
    N = 40
    means = torch.rand(N, 3, generator=g, dtype=torch.float64) - 0.5
    quats = torch.randn(N, 4, generator=g, dtype=torch.float64)
    scales = 0.1 + 0.1 * torch.rand(N, 2, generator=g, dtype=torch.float64)
    op0 = 0.3 + 0.5 * torch.rand(N, generator=g, dtype=torch.float64)
    op1 = (op0 * 1.2).clamp_max(0.95)
    cols = torch.rand(N, 3, generator=g, dtype=torch.float64)
    o = torch.zeros(64, 3, dtype=torch.float64) + torch.tensor([0.0, 0.0, -2.0], dtype=torch.float64)
    d = torch.randn(64, 3, generator=g, dtype=torch.float64) * 0.2 + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    kept = TraceAccel.build(means, quats, scales, op0)
    with torch.no_grad():
        T_nograd, c_nograd = trace(means, quats, scales, op1, cols, o, d, accel=kept)
    w = op1.clone().requires_grad_(True)
    T_grad, c_grad = trace(means, quats, scales, w, cols, o, d, accel=kept)
    assert torch.allclose(T_nograd, T_grad.detach(), atol=1e-12) and torch.allclose(c_nograd, c_grad.detach(), atol=1e-12)
    T_old, _ = trace(means, quats, scales, op0, cols, o, d, accel=kept)
    assert (T_old - T_nograd).abs().max() > 1e-3  # the opacities matter on these rays
