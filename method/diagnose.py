"""Where a run's relighting error is: the test views relit under a test light with one of our per-pixel
buffers replaced by the ground truth at a time (albedo, roughness, normals), then all three, which leaves
only our geometry (the shading points, the traced visibility and, with ``stage2.relight_indirect``, the bounce
light of our Gaussians relit under the test light) and the shading estimator; and all three
without our traced shadows (V = 1), which says whether the shadows our Gaussians cast help or hurt.

Every step shades the same pixels (our coverage > 0.5) with the same directions and traversals, so the
differences between steps are the buffers', not Monte Carlo noise. "ours" is relit with the albedo scaled
as the `lumimotion` protocol scales it (the benchmark's median-ratio alignment, computed here on our albedo
over the ground truth's foreground); the ground-truth albedo is used as it is. Scored like the benchmark's
relight (`lumimotion` protocol: masked full image, per-channel PSNR, LPIPS-VGG fed [0, 1]), under the
training light's coverage of the test views, composited on the dataset's background.

``python -m method diagnose --run RUN --test-light sunrise`` writes ``RUN/diagnose/<test light>/``:
``diagnose.json`` (per step: mean PSNR, SSIM, LPIPS and the gain over "ours") and ``sheet.png``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from benchmark.align import albedo_scale
from benchmark.protocol import foreground, get_protocol
from lumibench.color import srgb_to_linear
from lumibench.errors import UserError
from lumibench.groundtruth import read_gt, read_lit
from lumibench.io import atomic_write_json
from method import buffers
from method.buffers import MATERIALS
from method.checkpoints import load_trained
from method.data import load_scene
from method.devices import check_device
from method.relight import read_run_config, resolve_scene_dir
from method.outputs import write_sheet
from method.shading.deferred import (accel_for, display, normal_filter_sigma, pixel_inputs, relight_indirect,
                                     relit_radiance, test_time_raster, tracer_for)
from method.shading.envmap import load_envmap
from method.shading.render import shade_maps

ALL = ("albedo", "roughness", "normal")
# (name, buffers replaced by the ground truth); "ours_unshadowed" and the last step drop our traced shadows
# (V = 1): where they beat "ours" / "gt_all", the shadows our Gaussians cast under the test light are worse than none
STEPS = (("ours", ()), ("ours_unshadowed", ("no_shadows",)), ("gt_albedo", ("albedo",)), ("gt_roughness", ("roughness",)), ("gt_normal", ("normal",)),
         ("gt_all", ALL), ("gt_all_unshadowed", ALL + ("no_shadows",)))


def _gt_buffers(scene_dir: Path, file_path: str, pix: torch.Tensor, device) -> dict[str, torch.Tensor]:
    """The ground truth's albedo (linear), roughness and unit world normal at flat pixel ids."""
    out = {}
    for kind in ("albedo", "roughness", "normal"):
        x = torch.as_tensor(np.asarray(read_gt(scene_dir, kind, file_path), dtype=np.float32), device=device)
        x = x.reshape(-1, x.shape[-1])[pix]
        if kind == "roughness":
            x = x[:, 0].clamp(0, 1)
        elif kind == "normal":
            x = x[:, :3] / x[:, :3].norm(dim=-1, keepdim=True).clamp_min(1e-8)
        else:
            x = x[:, :3].clamp(0, 1)
        out[kind] = x
    return out


def _where(mask: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.where(mask[:, None] if a.dim() == 2 else mask, a, b)


@torch.no_grad()
def diagnose(run_dir, test_light: str, *, dirs: int | None = None, views: int | None = None, device: str = "cpu",
             seed: int = 0, data=None, out=None, progress: bool = True) -> dict:
    """Relight the run's test views under ``test_light`` step by step (module docstring); returns the record."""
    from lumibench.progress import track

    run_dir = Path(run_dir)
    cfg = read_run_config(run_dir)
    ident = cfg.pop("run")
    dev = check_device(device)
    scene_dir = resolve_scene_dir(run_dir, ident, cfg.get("profile"), data)
    if not (scene_dir / "albedo").is_dir():
        raise UserError(f"{scene_dir} has no ground-truth buffers (albedo/, roughness/, normal/): the diagnostic "
                        f"needs a LumiBench scene")
    if dirs is not None and dirs < 1:
        raise UserError(f"--dirs must be >= 1, got {dirs}")
    env = load_envmap(test_light, scene_dir, height=None, width=None, device=dev)
    scene, mats = load_trained(run_dir, cfg, dev)
    sd = load_scene(scene_dir, ident["light"], cfg["data"]["background"], dev)
    test = sd.test[:views] if views else sd.test
    if not test:
        raise UserError(f"{scene_dir} has no test views")
    s2 = cfg["stage2"]
    n_dirs = dirs or s2["dirs_eval"]
    proto = get_protocol("lumimotion")
    bg = sd.background

    # the lumimotion protocol's albedo scale, on our albedo over the GT foreground of all test views
    renders = []
    preds, gts, masks = [], [], []
    for v in test:
        d = scene.deform(v.time, p_mode="inference")
        r = test_time_raster(d, mats, v.camera, bg, s2)
        renders.append((d, r))
        a = r.alpha.clamp(0, 1)
        preds.append(srgb_to_linear(buffers.channel(r.features, a, MATERIALS.albedo)).cpu().numpy())
        gts.append(read_gt(scene_dir, "albedo", v.file_path))
        masks.append(foreground(read_lit(scene_dir, ident["light"], v.file_path)[1]))
    scale = torch.tensor(albedo_scale(preds, gts, masks), dtype=torch.float32, device=dev)

    scores: dict[str, list[dict]] = {name: [] for name, _ in STEPS}
    rows = []
    gen = torch.Generator().manual_seed(seed)
    for v, (d, r) in track(list(zip(test, renders)), description=f"diagnose {test_light}", unit="view",
                           disable=not progress):
        gt_img, gt_alpha = read_lit(scene_dir, test_light, v.file_path)
        a = r.alpha.clamp(0, 1)
        H, W = v.camera.height, v.camera.width
        fg = torch.nonzero((a > 0.5).reshape(-1)).squeeze(1)
        gt_fg = torch.as_tensor(gt_alpha[..., 0] > 0.5, device=dev).reshape(-1)[fg]
        gtb = _gt_buffers(scene_dir, v.file_path, fg, dev)
        f = r.features.reshape(-1, r.features.shape[-1])[fg]
        af = a.reshape(-1)[fg]
        a_lin = srgb_to_linear(buffers.channel(f, af, MATERIALS.albedo)).clamp(s2["albedo_min"], s2["albedo_max"])
        mine = {"albedo": (a_lin * scale).clamp(0, 1), "roughness": buffers.channel(f, af, MATERIALS.roughness),
                "normal": buffers.unit(r.normal.reshape(-1, 3)[fg])}
        # bounce light from our Gaussians relit under the test light with the scaled albedo (as the benchmark's
        # relight_scaled is shaded), at every step: the steps swap the shaded pixel's buffers, not the scene
        radiance = (relit_radiance(d, mats, [env], v.camera.center, s2, [scale]) if relight_indirect(s2) else None)
        tracer = tracer_for(d, accel_for(d, s2["trace_cell"]), s2["trace_offset"] * scene.extent, False,
                            extent=scene.extent, replay=True, radiance=radiance)
        start = gen.get_state()
        row = [buffers.over_background(gt_img, gt_alpha[..., 0], bg.cpu().numpy())]
        ours = None
        for name, swap in STEPS:
            # each buffer is the GT's where the GT has a surface, ours where only our coverage reaches
            override = {k: _where(gt_fg, gtb[k], mine[k]) if k in swap else mine[k] for k in mine}
            if swap == ("albedo",) and ours is not None:
                # the same directions, traversals and irradiance as "ours": only the diffuse part's albedo differs
                rgb = override["albedo"] / torch.pi * ours["irradiance"] + ours["specular"]
            else:
                gen.set_state(start)
                tracer.rewind()
                step_tracer = None if "no_shadows" in swap else tracer
                pts, n, view, alb, rough = pixel_inputs(r, v.camera, fg, s2, step_tracer, override=override)
                parts = shade_maps(pts.detach(), n, view, alb, rough, [env], n_dirs, gen,
                                   None if step_tracer is None else step_tracer.visibility,
                                   step_tracer.indirect if step_tracer is not None and step_tracer.use_indirect
                                   else None, env_quadrature=bool(s2["env_quadrature"]))[0]
                rgb = parts["rgb"]
                if name == "ours":
                    ours = parts
            img = torch.zeros(H * W, 3, dtype=rgb.dtype, device=dev)
            img[fg] = rgb
            img = buffers.over_background(display(img.reshape(H, W, 3)), a, bg).cpu().numpy()
            row.append(img)
        # the steps of one view in one LPIPS batch (the ground truth's features taken once)
        for (name, _), sc in zip(STEPS, proto.score_rgb_to_one(row[1:], gt_img, gt_alpha, "vgg")):
            scores[name].append(sc)
        rows.append(row)
    summary = {}
    for name, _ in STEPS:
        mean = {k: float(np.mean([s[k] for s in scores[name]])) for k in ("psnr", "ssim", "lpips")}
        summary[name] = mean
    for name, _ in STEPS:
        summary[name]["psnr_gain"] = summary[name]["psnr"] - summary["ours"]["psnr"]
    record = {"run": str(run_dir), "scene": scene_dir.name, "train_light": ident["light"], "test_light": test_light,
              "views": len(test), "dirs": n_dirs, "normal_filter": normal_filter_sigma(s2),
              "relight_indirect": relight_indirect(s2),
              "albedo_scale": [float(c) for c in scale],
              "protocol": "lumimotion", "steps": summary,
              "per_view_psnr": {name: [s["psnr"] for s in scores[name]] for name, _ in STEPS}}
    out = Path(out) if out else run_dir / "diagnose" / test_light
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "diagnose.json", record)
    sheet = np.concatenate([np.concatenate(r, 1) for r in rows[:4]], 0)
    titles = ["GT " + test_light] + [f"{n}\n{summary[n]['psnr']:.2f} dB" for n, _ in STEPS]
    write_sheet(out / "sheet.png", sheet, titles)
    return record
