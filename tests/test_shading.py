"""Stage-2 shading core (method/shading): env-map convention, BRDF energy, estimator, visibility, and the
calibration against Blender's own renders of calib_sphere (the acceptance test of issue 9)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from generator import envmap as genv
from lumibench import layout
from lumibench.color import srgb_to_linear
from lumibench.io import read_image
from method.shading import brdf
from method.shading.envmap import (EnvSampler, LearnableEnvMap, cosine_weights, load_envmap, lookup,
                                   lower_hemisphere_l2, resample, texel_index, texel_moments, texel_solid_angles)
from method.shading.render import shade
from method.shading.sampling import orthonormal_basis, pdf_ggx, sample_ggx, sample_hemisphere
from method.shading.visibility import GaussianTracer

LIGHTS = ("city", "sunrise", "courtyard", "sunset")


def _unit(x: torch.Tensor) -> torch.Tensor:
    return x / x.norm(dim=-1, keepdim=True)


def _gbuffer(P: int, seed: int = 0, dtype=torch.float64):
    """Random pixels: unit normals, view directions in the normal's hemisphere, albedo, roughness."""
    g = torch.Generator().manual_seed(seed)
    n = _unit(torch.randn(P, 3, generator=g, dtype=dtype))
    v = _unit(torch.randn(P, 3, generator=g, dtype=dtype))
    v = torch.where(((v * n).sum(-1, keepdim=True) < 0.15), _unit(v + 1.5 * n), v)
    albedo = torch.rand(P, 3, generator=g, dtype=dtype) * 0.9 + 0.05
    rough = torch.rand(P, generator=g, dtype=dtype) * 0.8 + 0.15
    return n, v, albedo, rough


def _sun_env(dtype=torch.float64) -> torch.Tensor:
    """A 16 x 32 sky with a 200x brighter sun texel and a dark ground: the hard case for an estimator."""
    dirs = torch.as_tensor(genv.texel_directions(16, 32), dtype=dtype)
    env = (0.3 + 0.5 * dirs[..., 2:3].clamp_min(0.0)) * torch.tensor([0.8, 0.9, 1.0], dtype=dtype)
    env = torch.where(dirs[..., 2:3] < 0, torch.full_like(env, 0.05), env)
    env[4, 9] = torch.tensor([60.0, 55.0, 45.0], dtype=dtype)
    return env


# ------------------------------------------------------------------------------------------ env maps

def test_lookup_is_the_generators_closest_texel():
    """Orientation and texel choice equal generator.envmap (which the Blender tests pin to Cycles)."""
    g = torch.Generator().manual_seed(1)
    dirs = torch.randn(5000, 3, generator=g, dtype=torch.float64) * torch.tensor([1.0, 1.0, 2.0], dtype=torch.float64)
    img = torch.rand(16, 32, 3, generator=g)
    row, col = genv.texel_of_direction(dirs.numpy(), 16, 32)
    expect = img.numpy()[row, col]
    np.testing.assert_array_equal(lookup(img, dirs).numpy(), expect)
    # +X looks at the centre column, +Y at the quarter column, +Z at the top row
    axes = torch.tensor([[1.0, 0, 0.05], [0, 1.0, 0.05], [0, 0, 1.0]])
    marks = torch.zeros(16, 32, 3)
    marks[7, 16] = 1.0
    marks[7, 8] = 2.0
    marks[0, :] = 3.0
    assert lookup(marks, axes)[:, 0].tolist() == [1.0, 2.0, 3.0]


def test_lookup_gradient_reaches_the_map_texels():
    env = torch.ones(16, 32, 3, requires_grad=True)
    dirs = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.01], [1.0, 0.0, 0.02]])
    lookup(env, dirs).sum().backward()
    assert env.grad.sum().item() == 9.0 and env.grad[7, 16].tolist() == [2.0, 2.0, 2.0]


def test_load_envmap_from_file_and_light_name(tmp_path):
    rng = np.random.default_rng(0)
    big = rng.random((64, 128, 3)).astype(np.float32) * 4
    genv.write_hdr(tmp_path / "sky.hdr", big)
    as_read = genv.read_envmap(tmp_path / "sky.hdr")
    small = load_envmap(tmp_path / "sky.hdr")
    assert small.shape == (16, 32, 3) and small.dtype == torch.float32
    # energy preserving: the solid-angle-weighted mean radiance is kept by the resampling
    np.testing.assert_allclose(genv.mean_radiance(small.numpy()), genv.mean_radiance(as_read), rtol=1e-4)
    np.testing.assert_allclose(small.numpy(), resample(as_read), rtol=1e-6)
    full = load_envmap(tmp_path / "sky.hdr", height=None, width=None)
    assert full.shape == (64, 128, 3)
    # a light name: <scene>/<light>.hdr first, exactly as stored
    genv.write_hdr(tmp_path / "dusk.hdr", big[:16, :32])
    np.testing.assert_array_equal(load_envmap("dusk", tmp_path).numpy(), genv.read_envmap(tmp_path / "dusk.hdr"))
    from lumibench.errors import UserError

    with pytest.raises(UserError, match="unknown environment map 'nope'"):
        load_envmap("nope", tmp_path)
    with pytest.raises(UserError, match="not found"):
        load_envmap(tmp_path / "missing.hdr")


def test_learnable_envmap_and_lower_hemisphere_term():
    env = LearnableEnvMap(16, 32, init=0.7)
    assert torch.allclose(env(), torch.full((16, 32, 3), 0.7))
    start = torch.rand(16, 32, 3) + 0.1
    assert torch.allclose(LearnableEnvMap(init=start)(), start, rtol=1e-5)
    with pytest.raises(ValueError):
        LearnableEnvMap(init=0.0)
    m = torch.zeros(16, 32, 3)
    m[:8] = 5.0  # sky only: no penalty
    assert lower_hemisphere_l2(m).item() == 0.0
    m[8:] = 2.0
    assert lower_hemisphere_l2(m).item() == pytest.approx(4.0)
    loss = lower_hemisphere_l2(env())
    loss.backward()
    g = env.log_radiance.grad
    assert g[:8].abs().sum() == 0 and (g[8:] > 0).all()


def test_env_sampler_pdf_integrates_to_one_and_matches_its_samples():
    env = _sun_env()
    s = EnvSampler.build(env)
    # integral of the pdf over the sphere, per texel: prob / solid angle * solid angle
    dirs = torch.as_tensor(genv.texel_directions(16, 32))
    sa = texel_solid_angles(16, 32, dtype=torch.float64)
    assert float((s.pdf(dirs) * sa).sum()) == pytest.approx(1.0, abs=1e-9)
    g = torch.Generator().manual_seed(0)
    u = torch.rand(200_000, 3, generator=g, dtype=torch.float64)
    d = s.sample(u[:, 0], u[:, 1], u[:, 2])
    assert torch.allclose(d.norm(dim=-1), torch.ones(1, dtype=torch.float64))
    row, col = genv.texel_of_direction(d.numpy(), 16, 32)
    hist = np.bincount(row * 32 + col, minlength=512) / len(row)
    np.testing.assert_allclose(hist, s.prob.numpy(), atol=3e-3)


def test_ggx_sampling_pdf_is_its_density():
    """pdf_ggx integrated over the sphere (fine quadrature) equals the share of sample_ggx's directions it
    describes: all but the half vectors facing away from v, whose reflections go below the surface and
    add nothing (so MIS stays unbiased)."""
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    zs = (torch.arange(800, dtype=torch.float64) + 0.5) / 400 - 1
    ph = (torch.arange(800, dtype=torch.float64) + 0.5) * 2 * math.pi / 800
    z, p = torch.meshgrid(zs, ph, indexing="ij")
    s = torch.sqrt(1 - z * z)
    ls = torch.stack([s * torch.cos(p), s * torch.sin(p), z], -1).reshape(-1, 3)
    for vz, r in ((1.0, 0.5), (0.3, 0.3), (0.9, 0.8)):
        v = _unit(torch.tensor([math.sqrt(1 - vz * vz), 0.0, vz], dtype=torch.float64))
        h = _unit(ls + v)
        rr = torch.tensor(r, dtype=torch.float64)
        mass = float(pdf_ggx(h[:, 2], (h * v).sum(-1), rr).sum() * 4 * math.pi / ls.shape[0])
        d = sample_ggx(n, v[None], rr[None], 50_000, torch.Generator().manual_seed(0))[0]
        hd = _unit(d + v)
        described = float((hd[:, 2] > 0).double().mean())
        assert mass == pytest.approx(described, abs=0.004), (vz, r)
        assert mass > 0.95 and float((d[hd[:, 2] <= 0, 2] > 0).sum()) == 0  # the rest is below the surface


def test_hemisphere_lattice_is_around_the_normal_and_rotated_per_pixel():
    n = _unit(torch.randn(50, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64))
    t, b = orthonormal_basis(n)
    frame = torch.stack([t, b, n], -1)
    assert torch.allclose(frame.transpose(1, 2) @ frame, torch.eye(3, dtype=torch.float64).expand(50, 3, 3), atol=1e-12)
    d = sample_hemisphere(n, 64, torch.Generator().manual_seed(0))
    cos = (d * n[:, None]).sum(-1)
    assert (cos > 0).all()
    # cosine-weighted lattice: the mean of cos over the lattice is 2/3 (exactly for the stratified z)
    assert torch.allclose(cos.mean(1), torch.full((50,), 2.0 / 3.0, dtype=torch.float64), atol=2e-3)
    same = sample_hemisphere(n, 64, torch.Generator().manual_seed(0))
    other = sample_hemisphere(n, 64, torch.Generator().manual_seed(1))
    assert torch.equal(d, same) and not torch.allclose(d, other)


# ----------------------------------------------------------------------------------------- the BRDF

def test_brdf_terms_are_the_papers():
    """D, F, G and the specular value at one configuration, written out from DESIGN.md's formulas."""
    r, nl, nv, nh, vh = 0.5, 0.6, 0.8, 0.9, 0.7
    a = r * r
    d = a * a / (math.pi * (nh * nh * (a * a - 1) + 1) ** 2)
    f = 0.04 + 0.96 * (1 - vh) ** 5
    k = (r + 1) ** 2 / 8
    g = nl / (nl * (1 - k) + k) * nv / (nv * (1 - k) + k)
    t = lambda x: torch.tensor(x, dtype=torch.float64)  # noqa: E731
    assert float(brdf.ggx_d(t(nh), t(r))) == pytest.approx(d, rel=1e-12)
    assert float(brdf.fresnel_schlick(t(vh))) == pytest.approx(f, rel=1e-12)
    assert float(brdf.smith_g(t(nl), t(nv), t(r))) == pytest.approx(g, rel=1e-12)
    assert float(brdf.specular(t(nl), t(nv), t(nh), t(vh), t(r))) == pytest.approx(d * f * g / (4 * nl * nv), rel=1e-12)
    assert float(brdf.specular(t(-0.1), t(nv), t(nh), t(vh), t(r))) == 0.0  # light from below


def test_specular_albedo_table_matches_a_direct_integral():
    """E_s(mu, r) (bilinear table) against a brute-force integral of the BRDF over the hemisphere."""
    zs = (torch.arange(2000, dtype=torch.float64) + 0.5) / 2000
    ph = (torch.arange(720, dtype=torch.float64) + 0.5) * 2 * math.pi / 720
    z, p = torch.meshgrid(zs, ph, indexing="ij")
    s = torch.sqrt(1 - z * z)
    ls = torch.stack([s * torch.cos(p), s * torch.sin(p), z], -1).reshape(-1, 3)
    for mu, r in ((0.9, 0.5), (0.4, 0.8), (0.2, 1.0), (0.7, 0.35)):
        v = torch.tensor([math.sqrt(1 - mu * mu), 0.0, mu], dtype=torch.float64)
        h = _unit(ls + v)
        rr = torch.tensor(r, dtype=torch.float64)
        f = brdf.specular(ls[:, 2], torch.full_like(ls[:, 2], mu), h[:, 2], (h * v).sum(-1), rr)
        direct = float((f * ls[:, 2]).sum() * 2 * math.pi / ls.shape[0])
        table = float(brdf.specular_albedo(torch.tensor(mu, dtype=torch.float64), rr))
        assert table == pytest.approx(direct, abs=3e-3), (mu, r)


@pytest.mark.parametrize("mix", [(1.0, 0.0, 0.0), (0.5, 0.25, 0.25)])
def test_white_furnace(mix):
    """Under a constant sky L: a white Lambertian returns L exactly with the cosine lattice (and within
    MC noise with MIS); the full BRDF at albedo 1 returns L (the diffuse gets what the specular lobe
    does not reflect), at albedo < 1 and roughness 1 less than L; the paper's literal sum (diffuse not
    weighted) creates energy."""
    P, L = 400, 0.7
    n, v, _, _ = _gbuffer(P, seed=5)
    env = torch.full((16, 32, 3), L, dtype=torch.float64)
    one = torch.ones(P, 3, dtype=torch.float64)
    rough1 = torch.ones(P, dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    rgb, parts = shade(None, n, v, one, rough1, env, 256, g, mix=mix, diffuse_weighting="none", return_parts=True)
    tol = 1e-9 if mix[1] == 0 else 0.02
    assert torch.allclose(parts["diffuse"], torch.full_like(rgb, L), atol=tol * L, rtol=0)
    full = shade(None, n, v, one, rough1, env, 256, g, mix=mix)
    assert torch.allclose(full, torch.full_like(full, L), atol=0.02 * L, rtol=0)
    assert abs(float(full.mean()) - L) < 0.003 * L
    half = shade(None, n, v, 0.5 * one, rough1, env, 256, g, mix=mix)
    e_s = brdf.specular_albedo((n * v).sum(-1), rough1)[:, None]
    assert (half < L).all()
    assert torch.allclose(half, L * (0.5 * (1 - e_s) + e_s), atol=0.02 * L, rtol=0)
    paper = shade(None, n, v, one, rough1, env, 256, g, mix=mix, diffuse_weighting="none")
    assert float(paper.mean()) > 1.01 * L


def test_estimator_error_falls_with_more_directions():
    P = 200
    n, v, a, r = _gbuffer(P, seed=2)
    env = _sun_env()
    ref = shade(None, n, v, a, r, env, 8192, torch.Generator().manual_seed(99))
    errs = {}
    for nd in (64, 256, 1024):
        est = shade(None, n, v, a, r, env, nd, torch.Generator().manual_seed(nd))
        errs[nd] = float(((est - ref).abs() / ref).mean())
    assert errs[1024] < errs[256] < errs[64]
    assert errs[1024] < 0.5 * errs[64] and errs[1024] < 0.02, errs
    # unbiased whatever the split between strategies: all agree at high N
    for mix in ((1.0, 0.0, 0.0), (0.2, 0.6, 0.2), (0.2, 0.1, 0.7)):
        alt = shade(None, n, v, a, r, env, 4096, torch.Generator().manual_seed(7), mix=mix)
        assert abs(float(alt.mean() / ref.mean()) - 1) < 0.01, mix


def test_texel_moments_integrate_the_cosine_over_each_texel():
    m = texel_moments(16, 32, dtype=torch.float64)
    # cell k of texel j lies in texel j (the lookup's indexing), and its moment's length is at most its solid angle
    row, col = texel_index(m.reshape(-1, 3), 16, 32)
    assert torch.equal(row * 32 + col, torch.arange(512).repeat_interleave(16))
    assert torch.allclose(m.norm(dim=-1).sum(-1), texel_solid_angles(16, 32, dtype=torch.float64).reshape(-1), rtol=0.05)
    # the cosine integral over the hemisphere is pi: exact where the horizon follows texel edges
    up = cosine_weights(torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], dtype=torch.float64), m)
    assert torch.allclose(up.sum(-1), torch.full((2,), math.pi, dtype=torch.float64), atol=1e-12)
    assert float(up[0, :256].min()) > 0 and float(up[0, 256:].abs().max()) == 0  # the lower half gives nothing
    n = _unit(torch.randn(50, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64))
    assert (cosine_weights(n, m).sum(-1) - math.pi).abs().max() < 2e-3
    # against a dense sum over each texel: max(0, n.w) dw with w on a 64 x 64 grid of the texel
    dirs = torch.as_tensor(genv.texel_directions(16 * 64, 32 * 64), dtype=torch.float64)
    dw = texel_solid_angles(16 * 64, 32 * 64, dtype=torch.float64)
    dense = ((dirs @ n[0]).clamp_min(0) * dw).reshape(16, 64, 32, 64).sum((1, 3)).reshape(-1)
    assert torch.allclose(cosine_weights(n[:1], m)[0], dense, atol=2e-5)


def test_compiled_cosine_weights_match_the_torch_reference():
    """The compiled quadrature (method/shading/quadrature_numba.py, what a CPU stage 2 runs) against the torch
    reference: the weights and their gradient w.r.t. the normals in float64, on one and on two threads;
    normals near the horizon of some cells included (the clamp's kink)."""
    pytest.importorskip("numba")
    from method.shading.envmap import cosine_weights_torch
    from method.shading.quadrature_numba import cosine_weights_compiled

    m = texel_moments(8, 16, 4, dtype=torch.float64)
    gen = torch.Generator().manual_seed(5)
    n = _unit(torch.randn(38, 3, generator=gen, dtype=torch.float64))  # 41 rows in all: an odd count for the 2 threads
    n = torch.cat([n, torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.3, -0.2, 0.01]], dtype=torch.float64)])
    n = _unit(n).requires_grad_(True)
    g = torch.randn(n.shape[0], 128, generator=gen, dtype=torch.float64)
    ref = cosine_weights_torch(n, m)
    ref_g, = torch.autograd.grad((ref * g).sum(), n)
    threads = torch.get_num_threads()  # the kernels follow torch's count
    try:
        for k in (1, 2):
            torch.set_num_threads(k)
            got = cosine_weights_compiled(n, m)
            got_g, = torch.autograd.grad((got * g).sum(), n)
            assert torch.allclose(got, ref, rtol=0, atol=1e-13)
            assert torch.allclose(got_g, ref_g, rtol=0, atol=1e-11)
    finally:
        torch.set_num_threads(threads)


def test_compiled_cosine_weights_skip_whole_texels_bit_for_bit():
    """Texels wholly above or below a normal's horizon skip their loop over the cells (texel_cones): the
    weights and the gradient are bit-identical to the loop over every cell of every texel (a bound of 1
    classifies nothing), on normals that put texels in all three classes, float32 unit normals included."""
    pytest.importorskip("numba")
    from method.shading import quadrature_numba as qn

    gen = torch.Generator().manual_seed(11)
    for h, w, sub in ((8, 16, 4), (16, 32, 4)):
        mom = texel_moments(h, w, sub, dtype=torch.float64).numpy()
        n = _unit(torch.randn(57, 3, generator=gen, dtype=torch.float64))
        n = torch.cat([n, torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)])
        n = _unit(n).float().double().numpy()  # unit in float32, as stage 2 passes them
        g = torch.randn(n.shape[0], h * w, generator=gen, dtype=torch.float64).numpy()
        centre, lim, total = qn.texel_cones(mom)
        dc = n @ centre.T
        bound = np.linalg.norm(n, axis=1)[:, None] * lim[None, :] + qn.CONE_MARGIN
        above, below = int((dc > bound).sum()), int((dc < -bound).sum())
        assert above > 0 and below > 0 and above + below < dc.size  # every class is exercised
        loop_all = np.ones_like(lim)
        for nt in (1, 2):
            assert np.array_equal(qn.cosine_forward(n, mom, centre, lim, nt),
                                  qn.cosine_forward(n, mom, centre, loop_all, nt))
            assert np.array_equal(qn.cosine_backward(n, mom, centre, lim, total, g, nt),
                                  qn.cosine_backward(n, mom, centre, loop_all, total, g, nt))


def test_env_quadrature_is_exact_unshadowed_and_unbiased_under_shadow():
    """The control variate (render.py): with nothing blocking, the diffuse term is the exact integral at
    any direction count; with a blocker, its mean over seeds is the plain estimator's (unbiased) and a
    sunlit pixel's spread is smaller."""
    P = 120
    n, v, a, r = _gbuffer(P, seed=8)
    env = _sun_env()
    ref = shade(None, n, v, a, r, env, 16384, torch.Generator().manual_seed(1), return_parts=True)[1]["diffuse"]
    for seed in (2, 3):
        q = shade(None, n, v, a, r, env, 8, torch.Generator().manual_seed(seed), env_quadrature=True,
                  return_parts=True)[1]["diffuse"]
        assert float(((q - ref).abs() / ref).mean()) < 0.01
    # a wall blocking every direction with y < -0.2 (the sun, at (4, 9), is on the y > 0 side: sunlit pixels)
    sun = torch.as_tensor(genv.texel_directions(16, 32)[4, 9], dtype=torch.float64)
    assert float(sun[1]) > 0.5
    vis = lambda o, d: (d[:, 1] >= -0.2).to(d)  # noqa: E731
    pts = torch.zeros(P, 3, dtype=torch.float64)
    ref = shade(pts, n, v, a, r, env, 32768, torch.Generator().manual_seed(1), visibility=vis)
    runs = {q: torch.stack([shade(pts, n, v, a, r, env, 16, torch.Generator().manual_seed(s), visibility=vis,
                                  env_quadrature=q) for s in range(64)]) for q in (False, True)}
    for q, x in runs.items():
        assert abs(float(x.mean(0).sum() / ref.sum()) - 1) < 0.02, q
    # sunlit pixels: 0.17 -> 0.04 mean relative error measured (the quadrature carries the sun); over all
    # pixels the summed absolute error halves (pixels facing the wall get noisier: the samples must cancel
    # most of the quadrature there)
    lit = (n @ sun) > 0.2
    err = {q: (x - ref).abs() for q, x in runs.items()}
    lit_err = {q: float((e / ref)[:, lit].mean()) for q, e in err.items()}
    assert lit.sum() > 20 and lit_err[True] < 0.4 * lit_err[False], lit_err
    assert float(err[True].sum()) < 0.75 * float(err[False].sum())
    with pytest.raises(ValueError, match="env_quadrature"):
        shade(None, n, v, a, r, env, 8, env_quadrature=True, diffuse_weighting="fresnel")


def test_shade_gradients_and_chunking():
    P = 64
    n, v, a, r = _gbuffer(P, seed=4, dtype=torch.float32)
    env = LearnableEnvMap(16, 32, init=0.6)
    a = a.clone().requires_grad_(True)
    r = r.clone().requires_grad_(True)
    out = shade(None, n, v, a, r, env(), 64, torch.Generator().manual_seed(0))
    chunked = shade(None, n, v, a, r, env(), 64, torch.Generator().manual_seed(0), max_samples=64 * 5)
    assert torch.allclose(out, chunked)
    out.sum().backward()
    assert a.grad.abs().sum() > 0 and r.grad.abs().sum() > 0 and env.log_radiance.grad.abs().sum() > 0
    assert torch.isfinite(a.grad).all() and torch.isfinite(r.grad).all()


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    n, v, a, r = _gbuffer(256, seed=6, dtype=torch.float32)
    env = _sun_env(torch.float32)
    cpu = shade(None, n, v, a, r, env, 256, torch.Generator().manual_seed(0))
    gpu = shade(None, n.cuda(), v.cuda(), a.cuda(), r.cuda(), env.cuda(), 256, torch.Generator().manual_seed(0))
    assert torch.allclose(gpu.cpu(), cpu, rtol=1e-3, atol=1e-4)


# ------------------------------------------------------------------------------- visibility (tracer)

def _box_splats(half: float = 0.5, spacing: float = 0.1, colour=(0.5, 0.5, 0.5), open_bottom: bool = False):
    """Opaque faces of the cube [-half, half]^3 tiled with flat splats (scale = spacing)."""
    means, quats = [], []
    ticks = torch.arange(-half + spacing / 2, half, spacing)
    u, w = torch.meshgrid(ticks, ticks, indexing="ij")
    u, w = u.reshape(-1), w.reshape(-1)
    c = torch.full_like(u, half)
    s2 = math.sqrt(0.5)
    faces = [  # (points on the face, quaternion w-x-y-z turning the splat normal +z onto the face normal)
        (torch.stack([u, w, c], 1), (1.0, 0.0, 0.0, 0.0)),
        (torch.stack([u, w, -c], 1), (0.0, 1.0, 0.0, 0.0)),
        (torch.stack([c, u, w], 1), (s2, 0.0, s2, 0.0)),
        (torch.stack([-c, u, w], 1), (s2, 0.0, -s2, 0.0)),
        (torch.stack([u, c, w], 1), (s2, -s2, 0.0, 0.0)),
        (torch.stack([u, -c, w], 1), (s2, s2, 0.0, 0.0)),
    ]
    if open_bottom:
        faces.pop(1)
    for pts, q in faces:
        means.append(pts)
        quats.append(torch.tensor(q).expand(pts.shape[0], 4))
    means, quats = torch.cat(means), torch.cat(quats)
    N = means.shape[0]
    return (means, quats, torch.full((N, 2), spacing), torch.full((N,), 0.99),
            torch.tensor(colour).expand(N, 3).contiguous())


def test_occluded_point_has_no_visibility_and_open_point_full():
    means, quats, scales, opac, cols = _box_splats()
    tracer = GaussianTracer(means, quats, scales, opac, cols, offset=0.02)
    dirs = sample_hemisphere(torch.tensor([[0.0, 0.0, 1.0]]), 256, torch.Generator().manual_seed(0))[0]
    inside = torch.zeros(256, 3)  # the box's centre: every direction hits a face
    above = torch.tensor([[0.0, 0.0, 0.8]]).expand(256, 3)  # over the lid, looking up: nothing
    assert tracer.visibility(inside, dirs).max() < 0.05
    assert torch.equal(tracer.visibility(above, dirs), torch.ones(256))
    # a prebuilt grid gives the same answer (stage 2 reuses it across iterations)
    again = GaussianTracer(means, quats, scales, opac, cols, offset=0.02, accel=tracer.accel)
    assert torch.equal(again.visibility(inside, dirs), tracer.visibility(inside, dirs))


def test_shade_with_traced_visibility_and_indirect_light():
    means, quats, scales, opac, cols = _box_splats(colour=(0.5, 0.5, 0.5))
    tracer = GaussianTracer(means, quats, scales, opac, cols, offset=0.02)
    up = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.8]])
    view = _unit(torch.tensor([[0.3, 0.0, 1.0], [0.3, 0.0, 1.0]]))
    white = torch.ones(2, 3)
    env = torch.full((16, 32, 3), 2.0)
    rough = torch.ones(2)
    g = torch.Generator().manual_seed(0)
    lit = shade(pts, up, view, white, rough, env, 256, g, visibility=tracer.visibility)
    assert lit[0].max() < 0.05 * 2.0  # shadowed inside the box
    assert torch.allclose(lit[1], torch.full((3,), 2.0), rtol=0.02)  # open sky above the lid
    glow = shade(pts, up, view, white, rough, env, 256, g, visibility=tracer.visibility, indirect=tracer.indirect)
    inner = float(srgb_to_linear(torch.tensor(0.5)))  # the walls' stage-1 colour, decoded from sRGB
    # white diffuse surface (rough 1): the light that leaks through (lit[0]) plus the walls' colour on
    # the blocked rest (1 - V), i.e. T env + composite
    assert torch.allclose(glow[0], lit[0] + inner * (1 - lit[0] / 2.0), rtol=0.02)
    assert glow[0].min() > 0.9 * inner
    assert torch.allclose(glow[1], lit[1], rtol=0.02)  # nothing blocks the sky above the lid


# ------------------------------------------------------------------ calibration against Blender renders

@pytest.fixture(scope="session")
def calib_datasets(tmp_path_factory) -> dict[str, Path]:
    """calib_sphere (roughness 0.4) and calib_sphere_glossy (0.15) rendered once at the ci profile."""
    from generator.pipeline import render_scene

    data = tmp_path_factory.mktemp("calib_data")
    return {name: render_scene(name, "ci", data, jobs=2, progress=False)
            for name in ("calib_sphere", "calib_sphere_glossy")}


def _erode(mask: np.ndarray, steps: int) -> np.ndarray:
    for _ in range(steps):
        p = np.pad(mask, 1, constant_values=False)
        mask = mask & p[:-2, 1:-1] & p[2:, 1:-1] & p[1:-1, :-2] & p[1:-1, 2:] & p[:-2, :-2] & p[2:, 2:] & p[:-2, 2:] & p[2:, :-2]
    return mask


def calibration_errors(scene: Path, n_dirs: int = 128, weighting: str = brdf.DIFFUSE_WEIGHTING, env_transform=None,
                       env_quadrature: bool = False):
    """Shade every interior foreground pixel of every view from the dataset's ground truth and compare
    with Blender's lit renders, per light: (global error, mean normal-bin error, pixels).

    Pixels: alpha == 1 eroded by two pixels (edge pixels blend the sphere with the background and the
    pixel filter spreads the sharp terminator there), no channel clipped by Blender, none near clipping
    in ours (dropping only Blender's clipped pixels would select on its noise). Blender renders at 8 spp
    with one seed for all views, so a pixel is +-12..25 % noisy and a view's sum +-5 %: errors are of
    sums. "global": |sum ours / sum Blender - 1| over all pixels of all 20 views, mean over channels.
    "bins": the same per world-normal sector (3 bands in z x 4 azimuth quadrants, >= 100 pixels),
    weighted mean over sectors; it is what sees the env map's orientation (a rotation or mirror of the
    map keeps the global sum over cameras all around the sphere, but moves light between sectors).
    """
    from method.splat.camera import Camera

    views = []
    for split in ("train", "test"):
        tr = layout.read_transforms(scene, split)
        for f in tr.frames:
            nrm = read_image(layout.gt_path(scene, "normal", f.file_path, ".npz"))
            h, w = nrm.shape[:2]
            _, d = Camera.from_blender(tr.camera_angle_x, f.c2w, w, h).pixel_rays()
            views.append((f.file_path, nrm, read_image(layout.gt_path(scene, "albedo", f.file_path, ".npz")),
                          read_image(layout.gt_path(scene, "roughness", f.file_path, ".npz")), d.numpy()))
    out = {}
    for light in LIGHTS:
        env = load_envmap(light, scene)
        if env_transform is not None:
            env = env_transform(env)
        ours, blender, normals = [], [], []
        for k, (fp, nrm, alb, rough, d) in enumerate(views):
            rgba = read_image(layout.lit_image_path(scene, light, fp))
            idx = np.nonzero(_erode(rgba[..., 3] >= 1.0, 2).reshape(-1))[0]
            n = _unit(torch.as_tensor(nrm.reshape(-1, 3)[idx]))
            c = shade(None, n, -torch.as_tensor(d.reshape(-1, 3)[idx]), torch.as_tensor(alb.reshape(-1, 3)[idx]),
                      torch.as_tensor(rough.reshape(-1)[idx]), env, n_dirs, torch.Generator().manual_seed(k),
                      diffuse_weighting=weighting, env_quadrature=env_quadrature).numpy()
            g = rgba[..., :3].reshape(-1, 3)[idx]
            keep = (g.max(-1) < 1.0) & (c.max(-1) < 0.95)
            ours.append(c[keep])
            blender.append(srgb_to_linear(g[keep]))
            normals.append(n.numpy()[keep])
        o, b, n = (np.concatenate(x) for x in (ours, blender, normals))
        glob = float(np.abs(o.sum(0) / b.sum(0) - 1).mean())
        band = np.minimum(((1 - n[:, 2]) / 2 * 3).astype(int), 2)
        quad = np.minimum(((np.arctan2(n[:, 1], n[:, 0]) + np.pi) / (2 * np.pi) * 4).astype(int), 3)
        sector = band * 4 + quad
        errs, counts = [], []
        for s in np.unique(sector):
            m = sector == s
            if m.sum() >= 100:
                errs.append(np.abs(o[m].sum(0) / b[m].sum(0) - 1).mean())
                counts.append(m.sum())
        out[light] = (glob, float(np.average(errs, weights=counts)), len(o))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["calib_sphere", "calib_sphere_glossy"])
def test_shading_matches_blender_on_calib_sphere(calib_datasets, scene):
    """Issue 9 acceptance: env-map orientation, light scale, BRDF and estimator pinned to Blender.

    Measured (ci, 128 directions; global / sector errors): see method/shading/__init__.py. The global
    error must be <= 2 % under every light; the sector error, bounded by Blender's 8-spp noise (one
    seed for every view), <= 4 % (a map turned by 90 degrees or mirrored gives 47..160 %).
    """
    for quadrature in (False, True):  # the plain estimator and stage 2's env_quadrature control variate
        errs = calibration_errors(calib_datasets[scene], env_quadrature=quadrature)
        report = {k: tuple(round(x, 4) if isinstance(x, float) else x for x in v) for k, v in errs.items()}
        for light, (glob, sectors, npx) in errs.items():
            assert npx > 2500, (quadrature, report)
            assert glob <= 0.02, (quadrature, report)
            assert sectors <= 0.04, (quadrature, report)


# ------------------------------------------------------------- the production tracer against brute force

def _jittered_floor(n: int = 12, spacing: float = 0.1, jitter: float = 0.02, seed: int = 0):
    """A floor of splats around z = 0 with small random heights and tilts, plus a few coloured blockers above."""
    g = torch.Generator().manual_seed(seed)
    ticks = (torch.arange(n, dtype=torch.float64) - (n - 1) / 2) * spacing
    x, y = torch.meshgrid(ticks, ticks, indexing="ij")
    floor = torch.stack([x.reshape(-1), y.reshape(-1), jitter * (torch.rand(n * n, generator=g, dtype=torch.float64) - 0.5)], 1)
    tilt = 0.15 * (torch.rand(n * n, 2, generator=g, dtype=torch.float64) - 0.5)
    fq = torch.cat([torch.ones(n * n, 1, dtype=torch.float64), tilt, torch.zeros(n * n, 1, dtype=torch.float64)], 1)
    blockers = torch.tensor([[0.1, 0.0, 0.3], [-0.2, 0.1, 0.25], [0.0, -0.2, 0.4]], dtype=torch.float64)
    bq = torch.tensor([[1.0, 0.3, 0.0, 0.0], [0.9, 0.0, 0.4, 0.0], [1.0, 0.0, 0.0, 0.2]], dtype=torch.float64)
    means, quats = torch.cat([floor, blockers]), torch.cat([fq, bq])
    N = means.shape[0]
    scales = torch.cat([torch.full((n * n, 2), spacing * 0.7, dtype=torch.float64),
                        torch.full((3, 2), 0.12, dtype=torch.float64)])
    opac = 0.3 + 0.6 * torch.rand(N, generator=g, dtype=torch.float64)
    cols = torch.rand(N, 3, generator=g, dtype=torch.float64)
    return means, quats, scales, opac, cols


def test_tracer_visibility_and_indirect_match_the_brute_force_trace():
    """GaussianTracer (the one stage 2, relighting and the env fit use): V is the brute-force transmittance
    from x + offset omega and indirect the brute-force composite of the linearised colours over its
    coverage, so shade's V env + (1 - V) indirect = T env + composite."""
    from method.splat.reference import trace_dense

    means, quats, scales, opac, cols = _jittered_floor()
    g = torch.Generator().manual_seed(1)
    o = torch.cat([torch.rand(64, 2, generator=g, dtype=torch.float64) * 0.6 - 0.3,
                   torch.zeros(64, 1, dtype=torch.float64)], 1)
    d = _unit(torch.rand(64, 3, generator=g, dtype=torch.float64) * torch.tensor([2.0, 2.0, 1.0], dtype=torch.float64)
              - torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64))
    tracer = GaussianTracer(means, quats, scales, opac, cols, offset=0.03)
    V, ind = tracer.visibility(o, d), tracer.indirect(o, d)
    T, comp = trace_dense(means, quats, scales, opac, srgb_to_linear(cols), o + 0.03 * d, d)
    assert 0.2 < float((T < 0.9).double().mean()) < 0.9  # some rays blocked, some not: the case has both
    assert torch.allclose(V, T, atol=1e-9)
    assert torch.allclose(ind, comp / (1 - T).clamp_min(1e-4)[:, None], atol=1e-8)
    env = torch.rand(3, dtype=torch.float64)
    assert torch.allclose(V[:, None] * env + (1 - V[:, None]) * ind, T[:, None] * env + comp, atol=1e-8)


def test_normal_lift_stops_a_jittered_floor_shadowing_itself():
    """stage2.normal_offset: a point on a floor of slightly tilted splats, traced towards grazing directions,
    is shadowed by its neighbours (brute force) unless it is first lifted along its normal turned to the
    camera; the lift moves it by exactly that distance, whichever way the normal pointed."""
    from method.shading.visibility import lifted_points
    from method.splat.reference import trace_dense

    means, quats, scales, opac, cols = _jittered_floor()
    p = torch.tensor([[0.02, -0.03, 0.0]], dtype=torch.float64).expand(32, 3)
    az = torch.arange(32, dtype=torch.float64) * (2 * math.pi / 32)
    el = math.radians(4.0)
    d = torch.stack([math.cos(el) * torch.cos(az), math.cos(el) * torch.sin(az), torch.full_like(az, math.sin(el))], 1)
    view = _unit(torch.tensor([[0.3, 0.2, 1.0]], dtype=torch.float64)).expand(32, 3)
    for n in (torch.tensor([0.0, 0.0, 1.0]), torch.tensor([0.0, 0.0, -1.0])):
        lifted = lifted_points(p, n.to(p).expand(32, 3), view, 0.05)
        assert torch.allclose(lifted, p + torch.tensor([0.0, 0.0, 0.05], dtype=torch.float64))
    tracer = GaussianTracer(means, quats, scales, opac, cols, offset=0.01)
    low = tracer.visibility(p.clone(), d)
    high = tracer.visibility(lifted, d)
    assert torch.allclose(low, trace_dense(means, quats, scales, opac, None, p + 0.01 * d, d)[0], atol=1e-9)
    assert float(low.mean()) < 0.8 and float(high.min()) > float(low.mean())
    assert float(high.mean()) > 0.9


@pytest.mark.parametrize("quad", [False, True])
def test_shade_maps_equals_one_map_at_a_time(quad):
    """Several maps with one set of directions (the benchmark's predictions relight a view under each test
    light this way) give for each map exactly what shade() gives for it alone from the same generator state
    and proposal: maps of two sizes, the env quadrature, traced visibility and indirect light; and the
    irradiance part shades any other albedo as albedo' / pi x E + specular."""
    from method.shading.deferred import sampling_mixture
    from method.shading.render import shade_maps

    P = 96
    n, v, a, r = _gbuffer(P, seed=11)
    g = torch.Generator().manual_seed(4)
    sun = _sun_env()
    other = torch.rand(64, 128, 3, generator=g, dtype=torch.float64) + 0.05
    other[40, 20] = 150.0
    envs = [sun, other, torch.flip(sun, [1])]
    mix = sampling_mixture(envs)
    pts = torch.randn(P, 3, generator=g, dtype=torch.float64)
    vis = lambda o, d: torch.sigmoid(4 * (d[:, 1] + o[:, 0]))  # noqa: E731  (depends on origin and direction)
    ind = lambda o, d: torch.stack([d[:, 0].abs(), o[:, 1].abs(), d[:, 2] ** 2], -1)  # noqa: E731
    maps = shade_maps(pts, n, v, a, r, envs, 48, torch.Generator().manual_seed(9), vis, ind, sampling_env=mix,
                      env_quadrature=quad, max_samples=48 * 40)
    scaled = (a * torch.tensor([1.3, 0.7, 1.1], dtype=torch.float64)).clamp(0, 1)
    for env, m in zip(envs, maps):
        rgb, parts = shade(pts, n, v, a, r, env, 48, torch.Generator().manual_seed(9), vis, ind, sampling_env=mix,
                           env_quadrature=quad, return_parts=True)
        # equal up to the last bits: on AVX-512 CPUs the batched products round differently (2026-11-28)
        torch.testing.assert_close(m["rgb"], rgb, rtol=1e-12, atol=1e-15)
        torch.testing.assert_close(m["specular"], parts["specular"], rtol=1e-12, atol=1e-15)
        alone = shade(pts, n, v, scaled, r, env, 48, torch.Generator().manual_seed(9), vis, ind, sampling_env=mix,
                      env_quadrature=quad)
        torch.testing.assert_close(scaled / math.pi * m["irradiance"] + m["specular"], alone, rtol=1e-12, atol=0)
    assert not torch.allclose(maps[0]["rgb"], maps[2]["rgb"])  # the maps do differ
    with pytest.raises(ValueError, match="sampling_env"):
        shade_maps(pts, n, v, a, r, envs, 48, visibility=vis)
