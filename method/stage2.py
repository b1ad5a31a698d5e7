"""Stage 2: inverse rendering on the frozen stage-1 geometry and motion (paper section "Stage 2").

Per Gaussian: albedo (stored display-encoded through a sigmoid, initialised from the canonical colour,
linearised and clamped to [albedo_min, albedo_max] for shading) and roughness (sigmoid, init 0.75); one
environment map, learned (paper) or kept as it starts (``stage2.env_fixed``). Fine-tuned at
finetune_factor x their stage-1 rate: the canonical colours, the delta-colour head and opacity. Frozen:
positions, rotations, scales, P and the rest of the network.

A step: rasterize colour, albedo, roughness, normal and depth at a training frame's time (deferred
shading); on randomly sampled foreground pixels, Monte Carlo over the hemisphere (method.shading.render)
with visibility and indirect light traced against the Gaussians at that time; loss = L1 of the shaded
pixels against the image + lambda_lc L_c of the rasterized colour + lambda_env_lower L2(lower env).
Because the geometry is frozen, each frame's tracer grid is built once, from the opacities stage 2 started
with, and cached (the tracer's alphas use the current, fine-tuned opacities).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from method import buffers, losses
from method.buffers import MATERIALS
from method.checkpoints import final_stage1, scene_from_checkpoint, scene_state
from method.data import SceneData
from method.env_fit import fit_env
from method.model.materials import Materials
from method.optim import adam
from method.model.scene import DynamicScene
from method.shading.deferred import (accel_for, display, raster_materials, render_pbr_view, shade_pixels,
                                     tracer_for)
from method.shading.envmap import LearnableEnvMap, lower_hemisphere_l2

FROZEN = ("means", "quats", "log_scales", "p_logit", "basis_logit")


def freeze_geometry(scene: DynamicScene) -> list[torch.nn.Parameter]:
    """Stop gradients to the frozen tensors; return the network parameters that stay trainable (the
    delta-colour head)."""
    for k in FROZEN:
        if k in scene.g.t:
            scene.g.t[k].requires_grad_(False)
    if scene.basis is not None:
        scene.basis.requires_grad_(False)
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
        *([] if s2["env_fixed"] else [{"params": list(mats.env.parameters()), "lr": s2["lr_env"], "name": "env"}]),
        {"params": [scene.g.t["colour_logit"]], "lr": s1["lr_colour"] * f, "name": "colour"},
        {"params": [scene.g.t["opacity_logit"]], "lr": s1["lr_opacity"] * f, "name": "opacity"},
    ]
    if head:
        groups.append({"params": head, "lr": s1["lr_mlp"] * s1["lr_mlp_final"] * f, "name": "dcol_head"})
    return adam(groups, eps=1e-15)


def stage2_step_loss(scene: DynamicScene, mats: Materials, view, data_bg, cfg: dict, generator: torch.Generator,
                     accel_cache: dict, frame_key, trunk_cache: dict | None = None,
                     grid_opacities: torch.Tensor | None = None):
    """One stage-2 loss evaluation; returns (loss, terms, rays traced).

    ``accel_cache``: the tracer grid of each training frame (``frame_key``), built on its first use from
    ``grid_opacities`` (default: the current ones). Stage 2 passes the opacities it started from, so a
    frame's grid does not depend on when it was first drawn and a resumed run rebuilds the same grids.
    ``trunk_cache``: see DynamicScene.deform (the frozen network's trunk once per training time)."""
    s2 = cfg["stage2"]
    d = scene.deform(view.time, p_mode="inference", trunk_cache=trunk_cache)
    out = raster_materials(d, mats, view.camera, data_bg)
    lc, _ = losses.colour_loss(out.features[..., MATERIALS.colour], view.rgb, cfg["stage1"]["lambda_dssim"])
    fg = torch.nonzero(((view.alpha > 0.5) & (out.alpha.detach() > 0.5)).reshape(-1)).squeeze(1)
    n_pix = max(1, s2["rays_per_iteration"] // s2["dirs_train"])
    terms = {"l_c": lc}
    total = s2["lambda_lc"] * lc
    rays = 0
    if fg.numel():
        pick = fg[torch.randperm(fg.numel(), generator=generator)[:n_pix].to(fg.device)]
        if frame_key not in accel_cache:
            accel_cache[frame_key] = accel_for(d, s2["trace_cell"], grid_opacities)
        tracer = tracer_for(d, accel_cache[frame_key], s2["trace_offset"] * scene.extent, s2["indirect"],
                            extent=scene.extent)
        rgb, _, _ = shade_pixels(out, view.camera, pick, s2, mats.env(), s2["dirs_train"], generator, tracer)
        terms["pbr"] = (display(rgb) - view.rgb.reshape(-1, 3)[pick]).abs().mean()
        total = total + terms["pbr"]
        rays = tracer.rays
    if s2["lambda_env_lower"] > 0 and not s2["env_fixed"]:
        terms["env_lower"] = lower_hemisphere_l2(mats.env())
        total = total + s2["lambda_env_lower"] * terms["env_lower"]
    return total, terms, rays


def _albedo_psnr_aligned(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    """PSNR (display space, over the mask) of linear albedo aligned by the benchmark's per-channel median ratio."""
    from benchmark.align import albedo_scale, apply_scale
    from lumibench.color import linear_to_srgb

    p = apply_scale(pred, albedo_scale([pred], [gt], [mask[..., None].astype(np.float32)]))
    a, b = linear_to_srgb(p)[mask], linear_to_srgb(np.clip(gt, 0, 1))[mask]
    mse = float(np.mean((a - b) ** 2))
    return float("inf") if mse == 0 else -10 * np.log10(mse)


def stage2_metrics(scene, mats, data: SceneData, cfg: dict, gen) -> dict:
    """Training-view numbers: PSNR of the PBR render under the estimated map, aligned albedo PSNR."""
    from lumibench.groundtruth import read_gt

    views = data.train[:: max(1, len(data.train) // 4)][:4]
    env = mats.env().detach()
    pbr, alb = [], []
    for v in views:
        r = render_pbr_view(scene, mats, v.camera, v.time, data.background, cfg, {"est": env},
                            cfg["stage2"]["dirs_eval"], gen, indirect=cfg["stage2"]["indirect"])
        img = buffers.over_background(display(r["relit:est"]), r["alpha"], data.background)
        pbr.append(losses.psnr(img, v.rgb))
        gt_path = Path(data.root) / "albedo"
        if gt_path.is_dir():
            gt = read_gt(Path(data.root), "albedo", v.file_path)
            mask = (v.alpha.cpu().numpy() > 0.5) & (r["alpha"].cpu().numpy() > 0.5)
            if mask.any():
                alb.append(_albedo_psnr_aligned(r["albedo"].cpu().numpy(), gt, mask))
    out = {"train_views": len(views), "pbr_psnr": float(np.mean(pbr))}
    if alb:
        out["albedo_psnr_aligned"] = float(np.mean(alb))
    return out


class Stage2:
    """What stage 2 optimises and how one step goes, for the training loop (method/train.py).

    Starts from the run's finished stage 1: materials initialised from the canonical colours (and the env
    map fitted when stage2.env_init_fit), the geometry frozen; optimises albedo, roughness, the env map and
    the fine-tuned stage-1 colours, opacities and delta-colour head (one Adam). Each step shades random
    foreground pixels of one training view (stage2_step_loss)."""

    number = 2
    generator_offset = 1_000_003
    forward_lap = "forward (raster, trace, shade)"

    def __init__(self, data: SceneData, cfg: dict, run_dir: Path, *, device: torch.device):
        self.data, self.cfg, self.run_dir, self.device = data, cfg, Path(run_dir), device
        self.scene: DynamicScene | None = None
        self.mats: Materials | None = None
        self.opt: torch.optim.Optimizer | None = None
        self.prior_seconds = self.prior_cpu_seconds = 0.0
        self.env_fit_record: dict | None = None
        self.accel_cache: dict = {}
        self.trunk_cache: dict | None = None
        self.rays_total = 0

    def _ready(self, grid_opacity_logit: torch.Tensor) -> None:
        """Freeze what stage 2 keeps, build the optimiser; the tracer grids use the stage's start opacities."""
        self._grid_logit = grid_opacity_logit.detach().cpu()
        self.grid_opacities = torch.sigmoid(grid_opacity_logit.to(self.device))
        if self.cfg["stage2"]["env_fixed"]:
            self.mats.env.requires_grad_(False)
        head = freeze_geometry(self.scene)
        self.opt = make_optimiser(self.scene, self.mats, head, self.cfg)
        self.trunk_cache = {} if self.scene.net is not None else None  # ~10 MB per training time at 20k

    def start(self, gen: torch.Generator, log) -> None:
        s2 = self.cfg["stage2"]
        self.scene = scene_from_checkpoint(final_stage1(self.run_dir, self.device), self.cfg, self.device)
        self.mats = Materials.init_from(self.scene, self.cfg)
        if s2["env_init_fit"]:
            env0, self.env_fit_record = fit_env(self.scene, self.mats, self.data, self.cfg, gen)
            self.mats.env = LearnableEnvMap(s2["env_height"], s2["env_width"], env0).to(self.device)
            self.prior_seconds = self.env_fit_record["seconds"]  # stage 2's seconds include the fit
            self.prior_cpu_seconds = self.env_fit_record["cpu_seconds"]
            log({"iteration": 0, "env_fit": self.env_fit_record})
        self._ready(self.scene.g.t["opacity_logit"].detach().clone())

    def resume(self, ck: dict) -> None:
        self.scene = scene_from_checkpoint(ck, self.cfg, self.device)
        self.mats = Materials.from_state(ck["materials"], self.cfg, self.device)
        self._ready(ck["grid_opacity_logit"])
        self.opt.load_state_dict(ck["opt"])

    def state(self) -> dict:
        return {**scene_state(self.scene), "materials": self.mats.state(), "opt": self.opt.state_dict(),
                "grid_opacity_logit": self._grid_logit}

    def forward(self, it: int, total: int, gen: torch.Generator, timer, log):
        k = int(torch.randint(len(self.data.train), (1,), generator=gen))
        loss, terms, rays = stage2_step_loss(self.scene, self.mats, self.data.train[k], self.data.background,
                                             self.cfg, gen, self.accel_cache, k, self.trunk_cache,
                                             self.grid_opacities)
        self.rays_total += rays
        return loss, terms

    def guarded(self) -> list[tuple[str, list[torch.Tensor]]]:
        return [(grp["name"], list(grp["params"])) for grp in self.opt.param_groups]

    def zero_grad(self) -> None:
        self.opt.zero_grad(set_to_none=True)

    def optimiser_step(self, it: int, total: int) -> None:
        self.opt.step()

    def after_step(self, it: int, gen: torch.Generator, timer) -> None:
        pass

    def log_fields(self, it: int, total: int) -> dict:
        return {}

    def describe(self) -> str:
        return ""

    def timing_fields(self) -> dict:
        out = {"rays_traced": self.rays_total, "cached_tracer_grids": len(self.accel_cache)}
        if self.env_fit_record is not None:
            out["env_fit_seconds"] = self.env_fit_record["seconds"]
        return out

    def finish(self, run_dir: Path, seconds: float, write_outputs: bool, gen: torch.Generator) -> dict:
        metrics = stage2_metrics(self.scene, self.mats, self.data, self.cfg, gen)
        metrics["seconds"] = seconds
        return metrics
