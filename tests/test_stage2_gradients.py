"""Stage 2's step (method.stage2.stage2_step_loss): autograd gradients against central finite differences
on a tiny scene, in float64, with the splat kernels' torch reference.

The scene: a floor of nine coplanar splats (normal +z) and one tilted occluder above it that shadows part of
the floor and lights it indirectly; a camera above. The foreground mask of the view keeps only floor pixels
the occluder does not cover, so at the shaded pixels the rasterized normal and depth do not depend on the
opacities (coplanar splats), and the tracer's hit set is fixed by the cached grid (built at the first call,
as in training). The Monte Carlo estimator is made deterministic by seeding the generator the same way
before every evaluation (same pixels, same random offsets).

What the estimator holds constant: the sample directions and their pdfs (method.shading.render: gradients
flow through the BRDF and the lookups, not the sample placement). Where the placement depends on a
parameter, finite differences would see it and autograd would not, by design:
- GGX half vectors depend on the roughness at the pixel: checked with the training mix only where that
  roughness is fixed (the floor's splats share one roughness, so opacities do not move it), and the
  roughness itself with the cosine strategy alone;
- the env strategy's texel probabilities depend on the env map: the env map is checked with the cosine
  strategy alone.
Each check compares the directional derivative along random directions (one pair of evaluations each).
"""
from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from method.config import load_method_config
from method.model.deform import DeformNet
from method.model.gaussians import Gaussians, inverse_sigmoid
from method.model.materials import Materials
from method.model.scene import DynamicScene
from method.shading import render as render_mod
from method.shading.envmap import LearnableEnvMap
from method.splat.camera import Camera
from method.splat.rasterize import rasterize
from method.stage2 import stage2_step_loss

D = torch.float64
SIZE = 16
FROZEN = ("means", "quats", "log_scales", "p_logit")
H_STEP = 1e-5  # on logits / log radiance: float64 central differences here agree with autograd to ~2e-11
RTOL, ATOL = 1e-6, 1e-10


@pytest.fixture(autouse=True)
def _torch_splats(monkeypatch):
    """The torch reference kernels (float64 and autograd throughout)."""
    import method.splat.backend as backend_mod

    monkeypatch.setattr(backend_mod, "_default", "torch")


@pytest.fixture
def cosine_only(monkeypatch):
    """Every direction from the cosine lattice (no GGX or env-map samples): then no sample direction or pdf
    depends on the roughness or the env map."""
    monkeypatch.setattr(render_mod, "split_directions", lambda n_dirs, mix=None: (n_dirs, 0, 0))


def _setup(dynamic=False, uniform_floor_roughness=True, overrides=(), seed=0):
    gen = torch.Generator().manual_seed(seed)
    xs = torch.tensor([-0.4, 0.0, 0.4], dtype=D)
    floor = torch.stack(torch.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
    nf = floor.shape[0]
    n = nf + 1
    means = torch.cat([torch.cat([floor, torch.zeros(nf, 1, dtype=D)], 1),
                       torch.tensor([[0.1, 0.05, 0.45]], dtype=D)])
    quats = torch.zeros(n, 4, dtype=D)
    quats[:, 0] = 1.0
    quats[-1] = torch.tensor([0.95, 0.2, -0.1, 0.05], dtype=D)  # the occluder, tilted
    scales = torch.full((n, 2), 0.3, dtype=D)
    scales[-1] = torch.tensor([0.18, 0.14], dtype=D)
    # opacities well inside (alpha_min, max_alpha): no hit is near a cut or the 0.99 clamp
    opac = 0.55 + 0.25 * torch.rand(n, generator=gen, dtype=D)
    col = 0.25 + 0.5 * torch.rand(n, 3, generator=gen, dtype=D)
    g = Gaussians({"means": means, "quats": quats, "log_scales": scales.log(), "opacity_logit": inverse_sigmoid(opac),
                   "colour_logit": inverse_sigmoid(col), "p_logit": torch.full((n,), 1.5, dtype=D)})
    net = None
    if dynamic:
        net = DeformNet(2, 16, 0, 2, 2, 8, 6).to(D)
        with torch.no_grad():
            for m in net.modules():  # every weight from the test's generator (not torch's global one)
                if isinstance(m, torch.nn.Linear):
                    m.weight.copy_(torch.randn(m.weight.shape, generator=gen, dtype=D) / m.weight.shape[1] ** 0.5)
                    m.bias.copy_(0.1 * torch.randn(m.bias.shape, generator=gen, dtype=D))
            # motion in the floor's plane only (the floor stays coplanar), no rotation, a small colour change
            net.d_mu.weight.copy_(0.2 * torch.randn(net.d_mu.weight.shape, generator=gen, dtype=D))
            net.d_mu.bias.copy_(0.05 * torch.randn(3, generator=gen, dtype=D))
            net.d_mu.weight[2] = 0.0
            net.d_mu.bias[2] = 0.0
            net.d_rot.weight.zero_()
            net.d_rot.bias.zero_()
            net.d_col.weight.copy_(0.1 * torch.randn(net.d_col.weight.shape, generator=gen, dtype=D))
            net.d_col.bias.copy_(0.1 * torch.randn(3, generator=gen, dtype=D))
        for name, p in net.named_parameters():  # stage 2: only the delta-colour head trains
            p.requires_grad_(name.startswith("d_col."))
    scene = DynamicScene(g, net, torch.zeros(3, dtype=D), 1.0)
    for k in FROZEN:
        g.t[k].requires_grad_(False)

    # the learned map (the paper's stage 2; the ci profile keeps a fitted one: stage2.env_fixed)
    cfg = load_method_config("ci", ["stage2.rays_per_iteration=64", "stage2.dirs_train=8", "stage2.env_height=4",
                                    "stage2.env_width=8", "stage2.lambda_env_lower=0.01", "stage2.env_fixed=false",
                                    *overrides])
    s2 = cfg["stage2"]
    env = LearnableEnvMap(s2["env_height"], s2["env_width"], 0.5).to(D)
    with torch.no_grad():
        env.log_radiance.add_(0.3 * torch.randn(env.log_radiance.shape, generator=gen, dtype=D))
    rough = 0.3 + 0.5 * torch.rand(n, generator=gen, dtype=D)
    if uniform_floor_roughness:
        rough[:nf] = 0.45
    mats = Materials(inverse_sigmoid(0.2 + 0.6 * torch.rand(n, 3, generator=gen, dtype=D)), inverse_sigmoid(rough),
                     env)

    t = 0.3
    cam = Camera.look_at((0.3, -2.2, 1.6), (0.0, 0.0, 0.0), SIZE, SIZE, dtype=D)
    bg = torch.ones(3, dtype=D)
    with torch.no_grad():
        d = scene.deform(t, p_mode="inference")
        only_occ = torch.zeros(n, dtype=D)
        only_occ[-1] = d.opacities[-1]
        occ = rasterize(d.means, d.quats, d.scales, only_occ, d.colours, cam, bg)
        full = rasterize(d.means, d.quats, d.scales, d.opacities, d.colours, cam, bg)
    mask = ((full.alpha > 0.5) & (occ.alpha == 0)).to(D)  # floor pixels the occluder does not cover
    assert 40 < int(mask.sum()) and int((occ.alpha > 0).sum()) > 10
    view = SimpleNamespace(time=t, camera=cam, rgb=0.1 + 0.8 * torch.rand(SIZE, SIZE, 3, generator=gen, dtype=D),
                           alpha=mask)
    params = {"albedo": mats.albedo_logit, "roughness": mats.roughness_logit, "env": env.log_radiance,
              "colour": g.t["colour_logit"], "opacity": g.t["opacity_logit"]}
    if dynamic:
        params["dcol_weight"] = net.d_col.weight
        params["dcol_bias"] = net.d_col.bias
    return SimpleNamespace(scene=scene, mats=mats, view=view, bg=bg, cfg=cfg, params=params, cache={})


def _loss(s) -> tuple[torch.Tensor, dict, int]:
    gen = torch.Generator().manual_seed(123)  # the same pixels and offsets at every evaluation
    return stage2_step_loss(s.scene, s.mats, s.view, s.bg, s.cfg, gen, accel_cache=s.cache, frame_key="frame")


def _autograd(s) -> dict[str, torch.Tensor]:
    for p in s.params.values():
        p.grad = None
    loss, terms, rays = _loss(s)
    assert rays > 0 and "pbr" in terms
    loss.backward()
    return {k: (p.grad.clone() if p.grad is not None else torch.zeros_like(p)) for k, p in s.params.items()}


def _check(s, names, directions=1, seed=1):
    grads = _autograd(s)
    gen = torch.Generator().manual_seed(seed)
    for name in names:
        p = s.params[name]
        for _ in range(directions):
            v = torch.randn(p.shape, generator=gen, dtype=D)
            # evaluated with autograd on, as in training: without it the torch tracer reuses the alphas of its
            # traversal, which come from the opacities the cached grid was built with
            with torch.no_grad():
                p.add_(H_STEP * v)
            lp = float(_loss(s)[0].detach())
            with torch.no_grad():
                p.add_(-2 * H_STEP * v)
            lm = float(_loss(s)[0].detach())
            with torch.no_grad():
                p.add_(H_STEP * v)
            fd = (lp - lm) / (2 * H_STEP)
            auto = float((grads[name] * v).sum())
            assert abs(fd) > 1e-5, f"{name}: the loss barely depends on it ({fd}): the check would be vacuous"
            assert abs(auto - fd) <= RTOL * abs(fd) + ATOL, f"{name}: autograd {auto!r}, finite differences {fd!r}"
    return grads


def test_training_estimator_gradients_match_finite_differences():
    """The estimator as trained (cosine, GGX and env samples; L1): albedo, colours and opacities."""
    _check(_setup(), ["albedo", "colour", "opacity"])


@pytest.mark.parametrize("overrides", [(), ("stage2.env_quadrature=true",)], ids=["sampled", "env_quadrature"])
def test_every_stage2_parameter_matches_finite_differences(cosine_only, overrides):
    """With cosine samples only, also the roughness (varied per splat) and the env map; with the diffuse
    term sampled and with its unshadowed part summed over the texels (env_quadrature)."""
    s = _setup(uniform_floor_roughness=False, overrides=overrides)
    grads = _check(s, ["albedo", "roughness", "env", "colour", "opacity"])
    # the lower hemisphere (rows 2, 3 of 4) is lit from nowhere the floor sees: its gradient is the
    # regulariser's alone, d/d log e of lambda mean(e^2) = 2 lambda e^2 / count
    e = s.mats.env().detach()
    low = e[2:]
    torch.testing.assert_close(grads["env"][2:], 2 * 0.01 * low.square() / low.numel(), rtol=1e-12, atol=0)


def test_dynamic_scene_delta_colour_head_matches_finite_differences():
    """With a deformation network (motion in the floor's plane, a delta-colour head): the head's weights and
    bias, the canonical colours and the opacities."""
    _check(_setup(dynamic=True), ["dcol_weight", "dcol_bias", "colour", "opacity", "albedo"])


def test_the_scene_exercises_the_traced_paths(cosine_only):
    """Not vacuous: with the image terms off (lambda_lc = 0, no regulariser) the occluder, which covers no
    shaded pixel, still gets opacity (visibility) and colour (indirect light) gradients."""
    s = _setup(overrides=("stage2.lambda_lc=0.0", "stage2.lambda_env_lower=0.0"))
    grads = _autograd(s)
    assert abs(float(grads["opacity"][-1])) > 1e-6
    assert float(grads["colour"][-1].abs().min()) > 1e-7
    assert float(grads["albedo"][-1].abs().max()) == 0.0  # no shaded pixel sees the occluder's albedo
