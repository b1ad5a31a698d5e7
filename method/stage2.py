"""Stage 2: inverse rendering on the frozen stage-1 geometry and motion (paper section "Stage 2").

Per Gaussian: albedo (stored display-encoded through a sigmoid, initialised from the canonical colour,
linearised and clamped to [albedo_min, albedo_max] for shading) and roughness (sigmoid, init 0.75); one
learnable environment map. Fine-tuned at finetune_factor x their stage-1 rate: the canonical colours,
the delta-colour head and opacity. Frozen: positions, rotations, scales, P and the rest of the network.

A step: rasterize colour, albedo, roughness, normal and depth at a training frame's time (deferred
shading); on randomly sampled foreground pixels, Monte Carlo over the hemisphere (method.shading.render)
with visibility and indirect light traced against the Gaussians at that time; loss = L1 of the shaded
pixels against the image + lambda_lc L_c of the rasterized colour + lambda_env_lower L2(lower env).
Because the geometry is frozen, each frame's tracer grid is built once and cached (accel_refresh
rebuilds them as the fine-tuned opacities drift).
"""
from __future__ import annotations

import torch

from lumibench.color import linear_to_srgb, srgb_to_linear
from method import losses
from method.model.gaussians import inverse_sigmoid
from method.shading.envmap import LearnableEnvMap, lower_hemisphere_l2
from method.shading.render import shade
from method.splat.camera import Camera
from method.splat.rasterize import RasterOutput, rasterize
from method.splat.trace import TraceAccel, trace
from method.stage1 import Deformed, DynamicScene

FROZEN = ("means", "quats", "log_scales", "p_logit")


class Materials:
    """Per-Gaussian albedo and roughness logits, and the learnable env map."""

    def __init__(self, albedo_logit: torch.Tensor, roughness_logit: torch.Tensor, env: LearnableEnvMap):
        self.albedo_logit = albedo_logit.detach().clone().requires_grad_(True)
        self.roughness_logit = roughness_logit.detach().clone().requires_grad_(True)
        self.env = env

    @staticmethod
    def init_from(scene: DynamicScene, cfg: dict) -> "Materials":
        s = cfg["stage2"]
        n = len(scene.g)
        col = scene.g.colours.detach()
        rough = torch.full((n,), float(s["roughness_init"]), device=col.device)
        env = LearnableEnvMap(s["env_height"], s["env_width"], s["env_init"]).to(col.device)
        return Materials(inverse_sigmoid(col), inverse_sigmoid(rough), env)

    def albedo_display(self) -> torch.Tensor:
        return torch.sigmoid(self.albedo_logit)

    def roughness(self) -> torch.Tensor:
        return torch.sigmoid(self.roughness_logit)

    def state(self) -> dict:
        return {"albedo_logit": self.albedo_logit.detach().cpu(), "roughness_logit": self.roughness_logit.detach().cpu(),
                "env": self.env.state_dict()}

    @staticmethod
    def from_state(st: dict, cfg: dict, device) -> "Materials":
        s = cfg["stage2"]
        env = LearnableEnvMap(s["env_height"], s["env_width"], s["env_init"]).to(device)
        env.load_state_dict(st["env"])
        return Materials(st["albedo_logit"].to(device), st["roughness_logit"].to(device), env)


def freeze_geometry(scene: DynamicScene) -> list[torch.nn.Parameter]:
    """Stop gradients to the frozen tensors; return the network parameters that stay trainable (the
    delta-colour head)."""
    for k in FROZEN:
        scene.g.t[k].requires_grad_(False)
    head = []
    if scene.net is not None:
        for name, p in scene.net.named_parameters():
            trainable = name.startswith("d_col.")
            p.requires_grad_(trainable)
            if trainable:
                head.append(p)
    return head


def make_optimiser(scene: DynamicScene, mats: Materials, head: list, cfg: dict) -> torch.optim.Adam:
    s1, s2 = cfg["stage1"], cfg["stage2"]
    f = s2["finetune_factor"]
    groups = [
        {"params": [mats.albedo_logit], "lr": s2["lr_albedo"], "name": "albedo"},
        {"params": [mats.roughness_logit], "lr": s2["lr_roughness"], "name": "roughness"},
        {"params": list(mats.env.parameters()), "lr": s2["lr_env"], "name": "env"},
        {"params": [scene.g.t["colour_logit"]], "lr": s1["lr_colour"] * f, "name": "colour"},
        {"params": [scene.g.t["opacity_logit"]], "lr": s1["lr_opacity"] * f, "name": "opacity"},
    ]
    if head:
        groups.append({"params": head, "lr": s1["lr_mlp"] * s1["lr_mlp_final"] * f, "name": "dcol_head"})
    return torch.optim.Adam(groups, eps=1e-15)


MATERIAL_GROUPS = ("albedo", "roughness", "env")


def material_lr_scale(iteration: int, total: int, final_factor: float) -> float:
    """Exponential decay of the materials' learning rates, 1 at the start to ``final_factor`` at ``total``.
    Each step's estimate uses a few directions per pixel, and at a constant rate the roughness drifts with
    that noise; decayed to 0.1 it stays near its init, but the albedo, still improving late in the run, loses
    up to 0.45 dB (BENCHMARKS.md, session 7), so every profile keeps 1 (constant, as the paper)."""
    from method.train import expon_lr

    return expon_lr(iteration, total, 1.0, float(final_factor))


def set_material_lrs(opt: torch.optim.Optimizer, cfg: dict, iteration: int, total: int) -> None:
    """The materials' rates for the step after ``iteration`` steps: decayed by ``lr_final_factor``, and the
    env map's held at 0 for its first ``env_freeze_until`` steps (a fitted start map is kept while the
    albedo, which starts with the training light's shading in it, adapts to it: env_fit.py)."""
    s2 = cfg["stage2"]
    k = material_lr_scale(iteration, total, s2["lr_final_factor"])
    for grp in opt.param_groups:
        if grp["name"] in MATERIAL_GROUPS:
            frozen = grp["name"] == "env" and iteration < s2["env_freeze_until"]
            grp["lr"] = 0.0 if frozen else s2[f"lr_{grp['name']}"] * k


def raster_materials(d: Deformed, mats: Materials, camera: Camera, background: torch.Tensor) -> RasterOutput:
    """Rasterize [colour (3), albedo (3, display), roughness (1), P (1)] with the stage-1 colour on the background."""
    feats = torch.cat([d.colours, mats.albedo_display(), mats.roughness()[:, None], d.p[:, None]], 1)
    bg = torch.cat([background.to(feats), feats.new_zeros(5)])
    return rasterize(d.means, d.quats, d.scales, d.opacities, feats, camera, bg)


def surface_points(out: RasterOutput, camera: Camera, pix: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World positions (from the camera-z depth) and unit directions towards the camera at flat pixel ids."""
    W = camera.width
    x = (pix % W).to(out.depth_expected.dtype) + 0.5
    y = torch.div(pix, W, rounding_mode="floor").to(out.depth_expected.dtype) + 0.5
    d_cam = torch.stack([(x - camera.cx) / camera.focal, (y - camera.cy) / camera.focal, torch.ones_like(x)], -1)
    d_world = d_cam @ camera.c2w[:3, :3].to(d_cam).T
    depth = out.depth_expected.reshape(-1)[pix]
    pts = camera.center.to(d_cam) + depth[:, None] * d_world
    view = -d_world / d_world.norm(dim=-1, keepdim=True)
    return pts, view


class SceneTracer:
    """Visibility and indirect light against the Gaussians at one time, with one traversal per batch of
    rays shared by both callables (shade() asks for V, then for the indirect radiance of the same rays)."""

    def __init__(self, d: Deformed, accel: TraceAccel, offset: float, indirect: bool, replay: bool = False, *,
                 extent: float):  # the scene's extent: the normal lift scales with it (no default on purpose)
        self.d, self.accel, self.offset, self.use_indirect = d, accel, offset, indirect
        self.extent = float(extent)
        self._key = None
        self._val = None
        self.rays = 0
        self.colours_linear = srgb_to_linear(d.colours.clamp(0, 1)) if indirect else None
        # replay: rays of a second pass that repeat the first pass's rays in the same order (relighting one
        # view under several maps with the same directions) reuse its traversals instead of tracing again
        self.replay = replay
        self._log: list = []
        self._pos = 0

    def rewind(self) -> None:
        self._pos = 0

    def _trace(self, o, dirs):
        if self._key is not None and self._key[0] is o and self._key[1] is dirs:
            return self._val
        if self.replay and self._pos < len(self._log):
            po, pd, val = self._log[self._pos]
            if po.shape == o.shape and torch.equal(po, o) and torch.equal(pd, dirs):
                self._pos += 1
                self._key, self._val = (o, dirs), val
                return val
        d = self.d
        T, comp = trace(d.means.detach(), d.quats.detach(), d.scales.detach(), d.opacities, self.colours_linear,
                        o + self.offset * dirs, dirs, accel=self.accel)
        self.rays += o.shape[0]
        self._key, self._val = (o, dirs), (T, comp)
        if self.replay:
            self._log.append((o, dirs, (T, comp)))
            self._pos = len(self._log)
        return T, comp

    def visibility(self, o, dirs):
        return self._trace(o, dirs)[0]

    def indirect(self, o, dirs):
        T, comp = self._trace(o, dirs)
        return comp / (1.0 - T).clamp_min(1e-4)[:, None]  # shade() weights it by (1 - V)


def build_accel(d: Deformed, cell_factor: float = 1.0) -> TraceAccel:
    """The tracer grid of the Gaussians at one time; cells of ``cell_factor`` x the median support radius
    (stage2.trace_cell: trained scenes mix a few large splats with many small ones, and at 0.5 those
    large splats fill so many cells that one build cost 7 s, BENCHMARKS.md)."""
    with torch.no_grad():
        return TraceAccel.build(d.means, d.quats, d.scales, d.opacities, alpha_min=0.01, cell_factor=cell_factor)


def sampling_mixture(envs: list[torch.Tensor]) -> torch.Tensor:
    """One proposal for several maps: each map scaled to unit total power, then averaged, so every map's
    bright texels (a small sun) keep their share of the samples."""
    from method.shading.envmap import luminance, texel_solid_angles

    out = None
    for e in envs:
        h, w = e.shape[:2]
        power = float((luminance(e).clamp_min(0) * texel_solid_angles(h, w, e.device, e.dtype)).sum())
        part = e / max(power, 1e-12)
        out = part if out is None else out + part
    return out / len(envs)


def lifted_points(pts: torch.Tensor, n: torch.Tensor, view: torch.Tensor, distance: float) -> torch.Tensor:
    """``pts`` moved ``distance`` along the normal turned to face the camera (``view`` points from the surface
    to the camera): shadow rays then start off the surface, so a flat splat floor does not shadow itself
    at grazing angles (stage2.normal_offset). ``distance`` 0: unchanged."""
    if distance <= 0.0:
        return pts
    facing = torch.where((n * view).sum(-1, keepdim=True) < 0, -n, n)
    return pts + distance * facing


def shade_pixels(out: RasterOutput, camera: Camera, pix: torch.Tensor, d: Deformed, mats_cfg: dict, env: torch.Tensor,
                 n_dirs: int, generator: torch.Generator, tracer: SceneTracer | None, sampling_env=None):
    """Linear RGB of the pixels ``pix`` (flat ids) shaded under ``env``; also their albedo (linear) and roughness."""
    s2 = mats_cfg
    a = out.alpha.reshape(-1)[pix].clamp_min(1e-4)
    f = out.features.reshape(-1, out.features.shape[-1])[pix]
    albedo = srgb_to_linear((f[:, 3:6] / a[:, None]).clamp(0, 1)).clamp(s2["albedo_min"], s2["albedo_max"])
    rough = (f[:, 6] / a).clamp(0, 1)
    n = out.normal.reshape(-1, 3)[pix]
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    pts, view = surface_points(out, camera, pix)
    if tracer is not None:
        pts = lifted_points(pts, n, view, float(s2.get("normal_offset", 0.0)) * tracer.extent)
    vis = tracer.visibility if tracer is not None else None
    ind = tracer.indirect if (tracer is not None and tracer.use_indirect) else None
    rgb = shade(pts.detach(), n, view, albedo, rough, env, n_dirs, generator, visibility=vis, indirect=ind,
                sampling_env=sampling_env, env_quadrature=bool(s2.get("env_quadrature", False)))
    return rgb, albedo, rough


def display(rgb_linear: torch.Tensor) -> torch.Tensor:
    """Blender's Standard view transform: clip to [0, 1], then the sRGB transfer function."""
    return linear_to_srgb(rgb_linear.clamp(0.0, 1.0))


def decorrelated_l2(a: torch.Tensor, b: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """mean((a - y)(b - y)) for two independent Monte Carlo estimates a, b of the same pixels: its expectation
    is the squared error of the estimator's mean, so its gradient is unbiased. Why not L1 at a small direction
    budget: a sun texel that most pixels' few directions miss makes each estimate bimodal, L1 drives the
    median (the miss) to the image, and the sun is never learned; plain L2 would add the estimator's
    variance, which also grows with the sun (the two-sample trick of Azinovic et al., CVPR 2019)."""
    return ((a - target) * (b - target)).mean()


def stage2_step_loss(scene: DynamicScene, mats: Materials, view, data_bg, cfg: dict, generator: torch.Generator,
                     accel_cache: dict, frame_key, iteration: int, trunk_cache: dict | None = None):
    """One stage-2 loss evaluation; returns (loss, terms, rays traced). ``trunk_cache``: see
    DynamicScene.deform (the frozen network's trunk once per training time)."""
    s2 = cfg["stage2"]
    d = scene.deform(view.time, p_mode="inference", trunk_cache=trunk_cache)
    out = raster_materials(d, mats, view.camera, data_bg)
    lc, _ = losses.colour_loss(out.features[..., :3], view.rgb, cfg["stage1"]["lambda_dssim"])
    fg = torch.nonzero(((view.alpha > 0.5) & (out.alpha.detach() > 0.5)).reshape(-1)).squeeze(1)
    n_pix = max(1, s2["rays_per_iteration"] // s2["dirs_train"])
    terms = {"l_c": lc}
    total = s2["lambda_lc"] * lc
    rays = 0
    if fg.numel():
        pick = fg[torch.randperm(fg.numel(), generator=generator)[:n_pix].to(fg.device)]
        refresh = s2["accel_refresh"]
        if frame_key not in accel_cache or (refresh and iteration % refresh == 0):
            accel_cache[frame_key] = build_accel(d, s2["trace_cell"])
        tracer = SceneTracer(d, accel_cache[frame_key], s2["trace_offset"] * scene.extent, s2["indirect"],
                             extent=scene.extent)
        gt = view.rgb.reshape(-1, 3)[pick]
        if s2["pbr_loss"] == "l1":
            rgb, _, _ = shade_pixels(out, view.camera, pick, d, s2, mats.env(), s2["dirs_train"], generator, tracer)
            terms["pbr"] = (display(rgb) - gt).abs().mean()
        else:  # two independent half-budget estimates of each pixel (the same rays in all)
            half = max(1, s2["dirs_train"] // 2)
            rgb, _, _ = shade_pixels(out, view.camera, torch.cat([pick, pick]), d, s2, mats.env(), half, generator,
                                     tracer)
            terms["pbr"] = decorrelated_l2(display(rgb[: pick.numel()]), display(rgb[pick.numel():]), gt)
        total = total + terms["pbr"]
        rays = tracer.rays
    if s2["lambda_env_lower"] > 0:
        terms["env_lower"] = lower_hemisphere_l2(mats.env())
        total = total + s2["lambda_env_lower"] * terms["env_lower"]
    return total, terms, rays


@torch.no_grad()
def render_pbr_view(scene: DynamicScene, mats: Materials, camera: Camera, t: float, background: torch.Tensor,
                    cfg: dict, envs: dict[str, torch.Tensor], n_dirs: int, generator: torch.Generator,
                    accel: TraceAccel | None = None, indirect: bool = False) -> dict:
    """Full-image maps of one view: NVS colour, albedo (linear), roughness, normal, alpha, P, and the
    relit linear RGB under each env map of ``envs`` (visibility traced; indirect light off by default,
    since the stage-1 colours carry the training light)."""
    s2 = cfg["stage2"]
    d = scene.deform(t, p_mode="inference")
    out = raster_materials(d, mats, camera, background)
    H, W = camera.height, camera.width
    a = out.alpha.clamp(0, 1)
    fg = torch.nonzero((a > 0.5).reshape(-1)).squeeze(1)
    res = {"nvs": out.features[..., :3].clamp(0, 1), "alpha": a,
           "albedo": srgb_to_linear((out.features[..., 3:6] / a.clamp_min(1e-4)[..., None]).clamp(0, 1)),
           "roughness": (out.features[..., 6] / a.clamp_min(1e-4)).clamp(0, 1),
           "normal": out.normal / out.normal.norm(dim=-1, keepdim=True).clamp_min(1e-8),
           "p": (out.features[..., 7] / a.clamp_min(1e-4)).clamp(0, 1)}
    if fg.numel() and envs:
        acc = accel if accel is not None else build_accel(d, s2["trace_cell"])
        # one direction set for every map (env samples drawn from the maps' mixture), so the traversals of
        # the first map are replayed for the others instead of traced again
        tracer = SceneTracer(d, acc, s2["trace_offset"] * scene.extent, indirect, replay=len(envs) > 1,
                             extent=scene.extent)
        start = generator.get_state()
        same_size = len({tuple(e.shape) for e in envs.values()}) == 1
        mixture = sampling_mixture([e.to(a) for e in envs.values()]) if len(envs) > 1 and same_size else None
        for name, env in envs.items():
            generator.set_state(start)
            tracer.rewind()
            rgb, _, _ = shade_pixels(out, camera, fg, d, s2, env.to(a), n_dirs, generator, tracer,
                                     sampling_env=mixture)
            img = torch.zeros(H * W, 3, dtype=rgb.dtype, device=rgb.device)
            img[fg] = rgb
            res[f"relit:{name}"] = img.reshape(H, W, 3)
    return res
