"""The benchmark predictions of a finished run (lumibench/predictions.py layout, meta.json written last):
NVS, albedo, roughness and normals of the test views, the test views relit under every other light, the
estimated env map, and the P maps of the training views."""
from __future__ import annotations

import json
from pathlib import Path

import torch

from benchmark.align import albedo_scale
from benchmark.protocol import foreground
from lumibench.groundtruth import read_gt, read_lit
from lumibench.predictions import PredictionFolder, srgb_decode
from method import buffers, run_record
from method.checkpoints import final_stage1, load_trained, scene_from_checkpoint
from method.data import load_scene
from method.model.materials import Materials
from method.outputs import write_p_maps
from method.shading.deferred import display, render_pbr_view
from method.devices import device_name

VERSION = "4"  # 2: relight_scaled/ (the albedo scaled before shading, for the lumimotion protocol); 3: the test-time
# normal filter (stage2.normal_filter), recorded in the run's config.yaml and so in settings_sha256; 4: indirect
# light from the Gaussians relit under the test light (stage2.relight_indirect), recorded the same way


def write_predictions(run_dir: Path, scene_dir: Path, light: str, cfg: dict, *, method: str = "lumimotion",
                      device: str = "cpu", seed: int = 0, test_lights: list[str] | None = None,
                      progress: bool = False, albedo_from_colour: bool = False,
                      train_scene_dir: Path | None = None) -> Path:
    """The benchmark predictions of a finished run under ``run_dir/predictions`` (lumibench/predictions.py
    layout; meta.json last). ``albedo_from_colour``: the 'without stage 2' ablation (canonical colour as
    albedo, relit with the same shading). ``scene_dir`` gives the test views and light maps; the P maps of
    the training views are written from the run's model when stage 1 did not leave them there. Refused when
    the run's record names another scene (the training scene: ``train_scene_dir``, default ``scene_dir``),
    light or seed."""
    from baselines_adapters.base import save
    from lumibench.predictions import write_meta
    from generator.envmap import write_hdr
    from method.data import available_lights
    from method.shading.envmap import load_envmap

    dev = torch.device(device)
    run_dir, scene_dir = Path(run_dir), Path(scene_dir)
    train_scene_dir = Path(train_scene_dir) if train_scene_dir is not None else scene_dir
    run_record.check_identity(run_dir, {"scene_name": train_scene_dir.name, "light": light, "seed": int(seed)},
                              "writing predictions")
    pred = run_dir / "predictions"
    (pred / "meta.json").unlink(missing_ok=True)
    run_record.record_prediction_settings(run_dir, cfg)  # how these predictions are shaded (test-time settings)
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

    for v in data.test:  # the maps first: the albedo scale of the relight below is measured on them
        r = render_pbr_view(scene, mats, v.camera, v.time, data.background, cfg, {}, s2["dirs_eval"], gen)
        save(pred, "nvs", v.stem, r["nvs"].cpu().numpy())
        save(pred, "albedo", v.stem, display(r["albedo"]).cpu().numpy())
        save(pred, "roughness", v.stem, r["roughness"].cpu().numpy())
        save(pred, "normal", v.stem, (r["normal"] * 0.5 + 0.5).clamp(0, 1).cpu().numpy())
    scale = relight_albedo_scale(pred, scene_dir, light, data.test) if lights else None
    scale_t = None if scale is None else torch.tensor(scale, dtype=torch.float32, device=dev)
    for v in track(data.test, description="predictions", unit="view", disable=not progress):
        r = render_pbr_view(scene, mats, v.camera, v.time, data.background, cfg, envs, s2["dirs_eval"], gen,
                            albedo_scale=scale_t)
        for x in lights:
            for tag, kind in (("relit", "relight"), ("relit_scaled", "relight_scaled")):
                if f"{tag}:{x}" in r:
                    img = buffers.over_background(display(r[f"{tag}:{x}"]), r["alpha"], data.background)
                    save(pred, kind, v.stem, img.cpu().numpy(), x)
    if env_est is not None:
        (pred / "envmap").mkdir(parents=True, exist_ok=True)
        write_hdr(pred / "envmap" / f"{light}.hdr", env_est.cpu().numpy())
    timings, cpu_timings = {}, {}
    tpath = run_dir / "timings.json"
    if tpath.is_file():
        t = json.loads(tpath.read_text())
        stages = {k: t[k] for k in ("stage1", "stage2") if isinstance(t.get(k), dict)}
        timings = {k: rec["seconds"] for k, rec in stages.items()}
        cpu_timings = {k: c for k, rec in stages.items() if (c := stage_cpu_seconds(rec)) is not None}
    if not scene.static and not _has_every_p_map(pred, train_scene_dir):
        # every training view's P (the benchmark's separation score), also the frames a run that keeps a
        # share of them (data.train_frames) did not train on: stage 1 wrote only those it trained on
        write_p_maps(scene, load_scene(train_scene_dir, light, cfg["data"]["background"], dev), pred)
    n_params = scene.num_parameters() + (0 if albedo_from_colour else mats.num_parameters())
    write_meta(pred, {"method": method, "version": VERSION, "seed": int(seed), "device": device_name(dev),
                      "scene": scene_dir.name, "train_light": light, "timings": timings,
                      **({"cpu_timings": cpu_timings} if cpu_timings else {}),
                      "model_size": {"gaussians": len(scene.g), "parameters": int(n_params)},
                      **({"settings_sha256": h} if (h := run_record.settings_hash(run_dir)) else {}),
                      **({"relight_albedo_scale": [float(c) for c in scale]} if scale is not None else {})})
    return pred


def stage_cpu_seconds(rec: dict) -> float | None:
    """A stage's CPU seconds (all threads) from its timings.json entry: ``cpu_seconds`` (over every session it
    ran in); in runs from before that was kept, ``cpu_seconds_this_session`` when the stage ran in one
    session, plus stage 2's environment fit (its wall seconds stand in: the fit ran before the count began);
    None when unknown (a stage resumed before the total was kept)."""
    if isinstance(rec.get("cpu_seconds"), (int, float)):
        return float(rec["cpu_seconds"])
    session = rec.get("cpu_seconds_this_session")
    if not isinstance(session, (int, float)) or rec.get("breakdown_iterations") != rec.get("iterations"):
        return None
    return float(session) + float(rec.get("env_fit_seconds", 0.0))


def _has_every_p_map(pred: Path, train_scene_dir: Path) -> bool:
    """True when ``PRED/p_map/train`` holds a map for every training frame of the scene."""
    from lumibench import layout

    folder = pred / "p_map" / "train"
    if not folder.is_dir():
        return False
    have = {p.stem for p in folder.iterdir()}
    return all(f.stem in have for f in layout.read_transforms(train_scene_dir, "train").frames)


def relight_albedo_scale(pred: Path, scene_dir: Path, light: str, views) -> list[float] | None:
    """The per-channel scale the ``lumimotion`` protocol relights with: the benchmark's albedo alignment
    (median of GT / predicted linear albedo over the GT foreground of all test views), measured on the
    albedo predictions as written, exactly as the scorer will read them; None without GT albedo."""
    if not (Path(scene_dir) / "albedo").is_dir():
        return None
    folder = PredictionFolder(pred)
    preds, gts, masks = [], [], []
    for v in views:
        gt = read_gt(Path(scene_dir), "albedo", v.file_path)
        _, alpha = read_lit(Path(scene_dir), light, v.file_path)
        preds.append(srgb_decode(folder.read("albedo", v.stem, gt.shape[:2])))
        gts.append(gt)
        masks.append(foreground(alpha))
    return [float(c) for c in albedo_scale(preds, gts, masks)]
