"""The stage-2 training loop (same guarantees as stage 1: progress, checkpoints, resume, NaN guard,
timings) and the benchmark predictions a finished run writes."""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from lumibench.errors import UserError
from lumibench.io import atomic_path, atomic_write_json
from method.data import SceneData, load_scene
from method.splat.backend import resolve as resolve_backend
from method.stage2 import (Materials, display, freeze_geometry, make_optimiser, render_pbr_view,
                           set_material_lrs, stage2_step_loss)
from method.train import (Timer, _finite_or_raise, _merge_json, checkpoint_paths, device_name, load_checkpoint,
                          peak_memory_bytes, scene_from_checkpoint)

VERSION = "1"


def final_stage1(run_dir: Path, device) -> dict:
    cks = checkpoint_paths(run_dir, 1)
    if not cks:
        raise UserError(f"no stage-1 checkpoint in {run_dir}: train stage 1 first (make train STAGE=1 ...)")
    ck = load_checkpoint(cks[-1][1], device)
    if int(ck["iteration"]) < int(ck.get("total_iterations", ck["iteration"])):
        raise UserError(f"stage 1 in {run_dir} stopped at iteration {ck['iteration']} of {ck['total_iterations']}: "
                        f"finish it first (make train STAGE=1 RESUME=1 ...)")
    return ck


def load_trained(run_dir: Path, cfg: dict, device) -> tuple:
    """(scene, materials) of the run's last stage-2 checkpoint."""
    cks = checkpoint_paths(run_dir, 2)
    if not cks:
        raise UserError(f"no stage-2 checkpoint in {run_dir}: train stage 2 first (make train STAGE=2 ...)")
    ck = load_checkpoint(cks[-1][1], device)
    scene = scene_from_checkpoint(ck, cfg, device)
    return scene, Materials.from_state(ck["materials"], cfg, device)


def record_stage2_config(run_dir: Path, cfg: dict) -> None:
    """Put the stage-2 settings this run trains with into its config.yaml (stage 2 may be started with
    other overrides than stage 1; relighting reads them back). The stage-1 sections stay as trained."""
    import yaml

    from lumibench.io import atomic_write_text

    path = run_dir / "config.yaml"
    rec = yaml.safe_load(path.read_text()) if path.is_file() else None
    if not isinstance(rec, dict):
        return
    rec["stage2"] = dict(cfg["stage2"])
    atomic_write_text(path, yaml.safe_dump(rec, sort_keys=False))


def train_stage2(scene_dir, light: str, run_dir, cfg: dict, *, seed: int = 0, device: str = "cpu",
                 resume: bool = False, progress: bool = True, data: SceneData | None = None) -> dict:
    dev = torch.device(device)
    run_dir = Path(run_dir)
    s2 = cfg["stage2"]
    data = data or load_scene(scene_dir, light, cfg["data"]["background"], dev)
    existing = checkpoint_paths(run_dir, 2)
    if existing and not resume:
        raise UserError(f"{run_dir} already has stage-2 checkpoints: pass --resume to continue it")
    gen = torch.Generator().manual_seed(seed + 1_000_003)
    total = s2["iterations"]
    start_it, prior = 0, 0.0
    env_fit_record = None
    if existing:
        ck = load_checkpoint(existing[-1][1], dev)
        scene = scene_from_checkpoint(ck, cfg, dev)
        mats = Materials.from_state(ck["materials"], cfg, dev)
        head = freeze_geometry(scene)
        opt = make_optimiser(scene, mats, head, cfg)
        opt.load_state_dict(ck["opt"])
        gen.set_state(ck["rng"])
        start_it, prior = int(ck["iteration"]), float(ck.get("seconds", 0.0))
        total = int(ck.get("total_iterations", total))
    else:
        ck1 = final_stage1(run_dir, dev)
        scene = scene_from_checkpoint(ck1, cfg, dev)
        mats = Materials.init_from(scene, cfg)
        if s2["env_init_fit"]:
            from method.env_fit import fit_env
            from method.shading.envmap import LearnableEnvMap

            env0, env_fit_record = fit_env(scene, mats, data, cfg, gen)
            mats.env = LearnableEnvMap(s2["env_height"], s2["env_width"], env0).to(dev)
            prior = env_fit_record["seconds"]  # stage 2's seconds include the fit
        head = freeze_geometry(scene)
        opt = make_optimiser(scene, mats, head, cfg)
        record_stage2_config(run_dir, cfg)
    (run_dir / "failure.json").unlink(missing_ok=True)
    log_path = run_dir / "log_stage2.jsonl"
    if start_it == 0:
        log_path.unlink(missing_ok=True)
        if env_fit_record is not None:
            with open(log_path, "a") as fh:
                fh.write(json.dumps({"iteration": 0, "env_fit": env_fit_record}) + "\n")
    timer = Timer(dev)
    accel_cache: dict = {}
    trunk_cache: dict | None = {} if scene.net is not None else None  # ~10 MB per training time at 20k
    rays_total = 0
    t0 = time.perf_counter()
    c0 = time.process_time()
    from lumibench.progress import make_progress

    with make_progress(disable=not progress) as bar:
        task = bar.add_task("stage 2", total=total, completed=start_it, rate="")
        ema = None
        for it in range(start_it + 1, total + 1):
            timer.start()
            k = int(torch.randint(len(data.train), (1,), generator=gen))
            view = data.train[k]
            loss, terms, rays = stage2_step_loss(scene, mats, view, data.background, cfg, gen, accel_cache, k, it,
                                                 trunk_cache)
            rays_total += rays
            for name, val in terms.items():
                _finite_or_raise(run_dir, it, f"loss term '{name}'", val, stage=2)
            timer.lap("forward (raster, trace, shade)")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            timer.lap("backward")
            for grp in opt.param_groups:
                for p in grp["params"]:
                    if p.grad is not None:
                        _finite_or_raise(run_dir, it, f"gradient of {grp['name']}", p.grad.sum(), stage=2)
            set_material_lrs(opt, cfg, it - 1, total)
            opt.step()
            for grp in opt.param_groups:
                for p in grp["params"]:
                    _finite_or_raise(run_dir, it, f"parameter {grp['name']}", p.detach().sum(), stage=2)
            timer.lap("step")
            lval = float(loss.detach())
            ema = lval if ema is None else 0.9 * ema + 0.1 * lval
            if it % s2["log_every"] == 0 or it == total:
                with open(log_path, "a") as fh:
                    fh.write(json.dumps({"iteration": it, "loss": lval, "seconds": prior + time.perf_counter() - t0,
                                         **{k2: float(v.detach()) for k2, v in terms.items()}}) + "\n")
            rate = (it - start_it) / max(time.perf_counter() - t0, 1e-9)
            bar.update(task, completed=it, rate=f"{rate:.1f} it/s", description=f"stage 2  loss {ema:.4f}")
            if it % s2["checkpoint_every"] == 0 or it == total:
                state = {"iteration": it, "total_iterations": total, "gaussians": scene.g.state(),
                         "net": None if scene.net is None else scene.net.state_dict(), "materials": mats.state(),
                         "opt": opt.state_dict(), "rng": gen.get_state(), "center": scene.center.cpu(),
                         "extent": scene.extent, "temperature": scene.temperature, "model": dict(scene.model_cfg),
                         "seconds": prior + time.perf_counter() - t0}
                with atomic_path(run_dir / "checkpoints" / f"stage2_{it:06d}.pt") as tmp:
                    torch.save(state, tmp)
                for _, old in checkpoint_paths(run_dir, 2)[:-2]:
                    old.unlink(missing_ok=True)
    seconds = prior + time.perf_counter() - t0
    _merge_json(run_dir / "timings.json", {
        "stage2": {"seconds": seconds, "iterations": total, "iterations_per_s": total / max(seconds, 1e-9),
                   "cpu_seconds_this_session": time.process_time() - c0,
                   **({"env_fit_seconds": env_fit_record["seconds"]} if env_fit_record is not None else {}),
                   "rays_traced": rays_total, "breakdown_s": {k: round(v, 4) for k, v in timer.sums.items()},
                   "breakdown_iterations": total - start_it, "cached_tracer_grids": len(accel_cache)},
        "device": device_name(dev), "peak_memory_bytes": peak_memory_bytes(dev), "threads": torch.get_num_threads(),
        "splat_backend": resolve_backend(None, dev)})
    metrics = stage2_metrics(scene, mats, data, cfg, gen)
    metrics["seconds"] = seconds
    atomic_write_json(run_dir / "metrics_stage2.json", metrics)
    return metrics


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
    from method.losses import psnr

    views = data.train[:: max(1, len(data.train) // 4)][:4]
    env = mats.env().detach()
    pbr, alb = [], []
    for v in views:
        r = render_pbr_view(scene, mats, v.camera, v.time, data.background, cfg, {"est": env},
                            cfg["stage2"]["dirs_eval"], gen, indirect=cfg["stage2"]["indirect"])
        a = r["alpha"][..., None]
        img = display(r["relit:est"]) * a + data.background * (1 - a)
        pbr.append(psnr(img, v.rgb))
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


def write_predictions(run_dir: Path, scene_dir: Path, light: str, cfg: dict, *, method: str = "lumimotion",
                      device: str = "cpu", seed: int = 0, test_lights: list[str] | None = None,
                      progress: bool = False, albedo_from_colour: bool = False,
                      train_scene_dir: Path | None = None) -> Path:
    """The benchmark predictions of a finished run under ``run_dir/predictions`` (lumibench/predictions.py
    layout; meta.json last). ``albedo_from_colour``: the 'without stage 2' ablation (canonical colour as
    albedo, relit with the same shading). ``scene_dir`` gives the test views and light maps; the P maps of
    the training views come from stage 1 (written by ``train_stage1``)."""
    from baselines_adapters.base import save
    from lumibench.predictions import write_meta
    from generator.envmap import write_hdr
    from method.data import available_lights
    from method.shading.envmap import load_envmap

    dev = torch.device(device)
    run_dir, scene_dir = Path(run_dir), Path(scene_dir)
    pred = run_dir / "predictions"
    (pred / "meta.json").unlink(missing_ok=True)
    data = load_scene(scene_dir, light, cfg["data"]["background"], dev)
    if albedo_from_colour:
        ck = final_stage1(run_dir, dev)
        scene = scene_from_checkpoint(ck, cfg, dev)
        mats = Materials.init_from(scene, cfg)
        env_est = None
    else:
        scene, mats = load_trained(run_dir, cfg, dev)
        env_est = mats.env().detach()
    lights = test_lights if test_lights is not None else [
        x for x in available_lights(scene_dir) if x != light and (scene_dir / x / "test").is_dir()]
    envs = {x: load_envmap(x, scene_dir, height=None, width=None, device=dev) for x in lights}
    gen = torch.Generator().manual_seed(seed + 77)
    s2 = cfg["stage2"]
    from lumibench.progress import track

    for v in track(data.test, description="predictions", unit="view", disable=not progress):
        r = render_pbr_view(scene, mats, v.camera, v.time, data.background, cfg, envs, s2["dirs_eval"], gen)
        a = r["alpha"][..., None]
        bg = data.background
        save(pred, "nvs", v.stem, r["nvs"].cpu().numpy())
        save(pred, "albedo", v.stem, display(r["albedo"]).cpu().numpy())
        save(pred, "roughness", v.stem, r["roughness"].cpu().numpy())
        save(pred, "normal", v.stem, (r["normal"] * 0.5 + 0.5).clamp(0, 1).cpu().numpy())
        for x in lights:
            img = display(r[f"relit:{x}"]) * a + bg * (1 - a)
            save(pred, "relight", v.stem, img.cpu().numpy(), x)
    if env_est is not None:
        (pred / "envmap").mkdir(parents=True, exist_ok=True)
        write_hdr(pred / "envmap" / f"{light}.hdr", env_est.cpu().numpy())
    timings = {}
    tpath = run_dir / "timings.json"
    if tpath.is_file():
        t = json.loads(tpath.read_text())
        timings = {k: t[k]["seconds"] for k in ("stage1", "stage2") if isinstance(t.get(k), dict)}
    n_params = scene.num_parameters() + (0 if albedo_from_colour else mats.albedo_logit.numel()
                                         + mats.roughness_logit.numel() + sum(p.numel() for p in mats.env.parameters()))
    write_meta(pred, {"method": method, "version": VERSION, "seed": int(seed), "device": device_name(dev),
                      "scene": scene_dir.name, "train_light": light, "timings": timings,
                      "model_size": {"gaussians": len(scene.g), "parameters": int(n_params)}})
    return pred
