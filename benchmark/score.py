"""Scoring one predictions folder against one rendered scene: the benchmark's train -> test protocol.

Albedo is aligned to the ground truth by one per-channel median ratio over the foreground of all test
views, in linear space, then scored in display (sRGB) space like the ground-truth PNGs. Relight is scored
as predicted (no per-image rescaling), NVS against the test views under the train light, roughness by
its MSE over the foreground, Delta PSNR as the drop from NVS to relight (dB and percent of the NVS PSNR,
as the paper's supplementary table). A P map on the train views gives the static/dynamic separation score.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from lumibench import layout
from lumibench.errors import UserError
from lumibench.io import sha256_file

from lumibench.groundtruth import read_gt, read_lit  # noqa: F401  (re-exported: older imports)
from lumibench.predictions import PredictionFolder, srgb_decode, srgb_encode
from .protocol import Protocol, cap_psnr, foreground, get_protocol
from .results import SCHEMA_VERSION, now_iso, validate

SSIM_DESCRIPTION = "Gaussian window 11, sigma 1.5, data range 1"

# which relight a result scored, as written into its metric_config (read back by the image grids)
RELIGHT_NOTES = {"relight_scaled": "scaled per channel by the albedo alignment before shading (relight_scaled/)",
                 "relight": "as predicted (relight/)"}


def scored_relight_kind(result: dict[str, Any]) -> str:
    """The predictions folder (``relight`` or ``relight_scaled``) whose images a result's relight scores came
    from, so a picture of the run shows the images the table scored."""
    note = (result.get("metric_config") or {}).get("relight_albedo")
    return next((kind for kind, text in RELIGHT_NOTES.items() if text == note), "relight")


def available_lights(scene: Path) -> list[str]:
    """Lights rendered for the test split of a scene (folders holding test/ that are not GT kinds)."""
    return sorted(p.name for p in Path(scene).iterdir()
                  if p.is_dir() and p.name not in layout.GT_KINDS and (p / "test").is_dir())


def check_light(scene: Path, light: str, role: str) -> None:
    lights = available_lights(scene)
    if light not in lights:
        raise UserError(f"unknown {role} light '{light}' for scene {scene} (rendered: {', '.join(lights) or 'none'})")


def check_scene(scene: Path) -> None:
    """A finished rendered scene directory, or one line saying what it is instead."""
    if not scene.is_dir():
        raise UserError(f"scene directory not found: {scene}")
    if not (scene / "transforms_test.json").is_file():
        inside = sorted(p.name for p in scene.iterdir() if (p / "transforms_test.json").is_file())
        hint = (f"; the scenes inside it are {', '.join(inside)}: give one of them" if inside else
                " (a scene directory is DATA/PROFILE/<scene>, as written by make dataset)")
        raise UserError(f"{scene} is not a rendered scene: it has no transforms_test.json{hint}")
    if not layout.is_complete(scene):
        raise UserError(f"dataset {scene} is not complete (its dataset.json does not say \"complete\": true): "
                        "the render was interrupted or is still running; finish it with make dataset")


def check_meta(meta: dict[str, Any], path: Path, scene: Path, train_light: str, scene_name: str | None) -> None:
    """meta.json may name the scene and train light the predictions were made for: they must be these."""
    names = {scene.name, scene.resolve().name} | ({scene_name} if scene_name else set())
    if meta.get("scene") is not None and meta["scene"] not in names:
        raise UserError(f"{path}: the predictions are for scene '{meta['scene']}', not '{scene_name or scene.name}' "
                        "(wrong predictions folder or scene directory?)")
    if meta.get("train_light") is not None and meta["train_light"] != train_light:
        raise UserError(f"{path}: the predictions were trained under light '{meta['train_light']}', not "
                        f"'{train_light}' (wrong predictions folder or train light?)")


def predictions_hash(pred_dir: Path) -> str | None:
    """sha256 of the predictions' meta.json (rewritten whenever they are): ties a result to the predictions it
    scored, so an image grid is never drawn from other predictions that later took the same folder."""
    meta = Path(pred_dir) / "meta.json"
    return sha256_file(meta) if meta.is_file() else None


def dataset_inputs(scene: Path) -> dict[str, Any]:
    """Hashes that tie a result to the exact dataset it was scored on."""
    meta_path = Path(scene) / "dataset.json"
    out: dict[str, Any] = {"dataset_spec_hash": None, "dataset_json_sha256": None}
    if meta_path.is_file():
        out["dataset_json_sha256"] = sha256_file(meta_path)
        try:
            meta = json.loads(meta_path.read_text())
        except json.JSONDecodeError:
            raise UserError(f"{meta_path}: corrupt JSON") from None
        for key in ("spec_hash", "spec_sha256", "hash"):
            if isinstance(meta.get(key), str):
                out["dataset_spec_hash"] = meta[key]
                break
    return out


def _mean(rows: dict[str, dict[str, float]], key: str) -> float:
    return float(np.mean([r[key] for r in rows.values()]))


def _summary(rows: dict[str, dict[str, float]]) -> dict[str, float]:
    keys = next(iter(rows.values())).keys()
    return {k: _mean(rows, k) for k in keys}


def nvs_regions(region_sq: dict) -> dict[str, float]:
    """NVS PSNR over the moving objects' pixels (the GT dynamic mask of the test views, foreground only)
    beside the PSNR over all foreground pixels, both from the pooled squared error of all test views (the
    same for either protocol): a moving object that is missing or blurred shows as a gap."""
    def db(sq, n):
        return cap_psnr(-10.0 * math.log10(max(sq / n, 1e-20)))
    fgp, mov = db(*region_sq["foreground"]), db(*region_sq["moving"])
    return {"foreground_psnr": fgp, "moving_psnr": mov, "gap_db": fgp - mov,
            "moving_pixels": region_sq["moving"][1] // 3}


def score(scene_dir: str | Path, pred_dir: str | Path, train_light: str, test_light: str,
          protocol: str | Protocol = "lumimotion", lpips_net: str = "vgg", profile: str | None = None,
          scene_name: str | None = None) -> dict[str, Any]:
    """Score ``pred_dir`` on ``scene_dir`` and return a validated result dictionary."""
    from benchmark import align, metrics

    scene = Path(scene_dir)
    check_scene(scene)
    proto = get_protocol(protocol) if isinstance(protocol, str) else protocol
    check_light(scene, train_light, "train")
    check_light(scene, test_light, "test")
    pred = PredictionFolder(Path(pred_dir))
    meta = pred.meta()
    check_meta(meta, Path(pred_dir) / "meta.json", scene, train_light, scene_name)
    pred.check_files()
    frames = layout.read_transforms(scene, "test").frames
    if not frames:
        raise UserError(f"{scene}/transforms_test.json lists no test view")

    kinds = {k: pred.has(k) for k in ("nvs", "albedo", "roughness", "normal")}
    kinds["relight"] = pred.has("relight", test_light)
    # the lumimotion protocol scores the relight made with the aligned albedo where the method provides it
    relight_kind = ("relight_scaled" if proto.relight_albedo_scaled and pred.has("relight_scaled", test_light)
                    else "relight")
    kinds["relight"] = kinds["relight"] or relight_kind == "relight_scaled"
    relit = sorted(p.name for p in (Path(pred_dir) / "relight").glob("*") if p.is_dir())
    if relit and not kinds["relight"]:
        raise UserError(f"missing predictions {Path(pred_dir) / 'relight' / test_light}/: the method relit "
                        f"{', '.join(relit)} only (run it with test light {test_light})")
    if not any(kinds[k] for k in ("nvs", "albedo", "roughness", "relight")):
        raise UserError(f"no predictions to score in {pred_dir}: expected nvs/, albedo/, roughness/ or "
                        f"relight/{test_light}/ (layout: lumibench/predictions.py)")

    # fail fast, before any metric runs: every present kind needs a file for every test view
    for kind, present in kinds.items():
        if present:
            for frame in frames:
                if kind == "relight":
                    pred.path(relight_kind, frame.stem, test_light)
                else:
                    pred.path(kind, frame.stem)

    per_image: dict[str, dict[str, dict[str, float]]] = {k: {} for k in ("nvs", "albedo", "roughness", "relight", "normal")}
    albedo_pred, albedo_gt, albedo_mask, albedo_stems = [], [], [], []
    region_sq = {"foreground": [0.0, 0], "moving": [0.0, 0]}  # squared error sum, pixel count (NVS)
    have_dyn = (scene / "dynamic_mask" / "test").is_dir()
    for frame in frames:
        stem, fp = frame.stem, frame.file_path
        gt_train, alpha = read_lit(scene, train_light, fp)
        shape = gt_train.shape[:2]
        fg = foreground(alpha)
        if kinds["nvs"]:
            nvs_img = pred.read("nvs", stem, shape)
            per_image["nvs"][stem] = proto.score_rgb(nvs_img, gt_train, alpha, lpips_net)
            if have_dyn:
                moving = (read_gt(scene, "dynamic_mask", fp)[..., 0] > 0.5) & (fg[..., 0] > 0)
                for region, m in (("foreground", fg[..., 0] > 0), ("moving", moving)):
                    err = (np.asarray(nvs_img, np.float64) - np.asarray(gt_train, np.float64))[m]
                    region_sq[region][0] += float((err ** 2).sum())
                    region_sq[region][1] += int(err.size)
        if kinds["relight"]:
            gt_test, _ = read_lit(scene, test_light, fp)
            per_image["relight"][stem] = proto.score_rgb(pred.read(relight_kind, stem, shape, test_light), gt_test,
                                                         alpha, lpips_net)
        if kinds["roughness"]:
            gt_r = read_gt(scene, "roughness", fp)
            per_image["roughness"][stem] = {"mse": float(metrics.mse(pred.read("roughness", stem, shape), gt_r, mask=fg))}
        if kinds["normal"]:
            n_p = _unit(pred.read("normal", stem, shape))
            n_g = _unit(read_gt(scene, "normal", fp))
            cos = np.clip((n_p * n_g).sum(-1), -1.0, 1.0)
            ang = np.degrees(np.arccos(cos))[fg[..., 0] > 0]
            per_image["normal"][stem] = {"mae_deg": float(ang.mean())}
        if kinds["albedo"]:
            albedo_pred.append(srgb_decode(pred.read("albedo", stem, shape)))
            albedo_gt.append(read_gt(scene, "albedo", fp))
            albedo_mask.append(fg)
            albedo_stems.append((stem, alpha))

    result_metrics: dict[str, Any] = {k: None for k in ("nvs", "albedo", "roughness", "relight", "delta_psnr",
                                                         "separation", "normal", "nvs_moving")}
    scale = None
    if kinds["albedo"]:
        scale = np.asarray(align.albedo_scale(albedo_pred, albedo_gt, albedo_mask), dtype=np.float64).reshape(3)
        for (stem, alpha), p_lin, g_lin in zip(albedo_stems, albedo_pred, albedo_gt):
            aligned = srgb_encode(np.asarray(align.apply_scale(p_lin, scale)))
            per_image["albedo"][stem] = proto.score_rgb(aligned, srgb_encode(g_lin), alpha, lpips_net)
    for task in ("nvs", "albedo", "roughness", "relight", "normal"):
        if per_image[task]:
            result_metrics[task] = _summary(per_image[task])
    if scale is not None:
        result_metrics["albedo"]["scale"] = [float(s) for s in scale]
    if relight_kind == "relight_scaled" and isinstance(meta.get("relight_albedo_scale"), list):
        result_metrics["relight"]["albedo_scale"] = [float(s) for s in meta["relight_albedo_scale"]]
    if result_metrics["nvs"] and result_metrics["relight"]:
        db = result_metrics["nvs"]["psnr"] - result_metrics["relight"]["psnr"]
        result_metrics["delta_psnr"] = {"db": db, "percent": 100.0 * db / result_metrics["nvs"]["psnr"]}
    if pred.has("p_map"):
        result_metrics["separation"] = separation_score(scene, pred, train_light)
    if region_sq["moving"][1] and region_sq["foreground"][1]:
        result_metrics["nvs_moving"] = nvs_regions(region_sq)

    weights = metrics.lpips_weights_info(lpips_net)
    result: dict[str, Any] = {
        "schema_version": SCHEMA_VERSION,
        "status": "ok",
        "error": None,
        "method": meta["method"],
        "adapter_version": meta["version"],
        "scene": scene_name or scene.name,
        "train_light": train_light,
        "test_light": test_light,
        "seed": int(meta["seed"]),
        "profile": profile or meta.get("profile"),
        "protocol": proto.name,
        "metric_config": {
            "lpips_net": lpips_net,
            "lpips_input_range": proto.lpips_input_range,
            "psnr_channels": "per-channel mean" if proto.psnr_per_channel else "pooled",
            "masking": proto.describe(),
            "ssim": SSIM_DESCRIPTION,
            "lpips_weights": dict(weights),
            "albedo_alignment": "per-channel median ratio, linear space, foreground of all test views",
            "relight_albedo": RELIGHT_NOTES[relight_kind],
        },
        "inputs": {"scene_dir": str(scene.resolve()), "pred_dir": str(Path(pred_dir).resolve()),
                   **dataset_inputs(scene), "pred_meta_sha256": predictions_hash(Path(pred_dir)),
                   **({"method_settings_sha256": meta["settings_sha256"]}
                      if isinstance(meta.get("settings_sha256"), str) else {})},
        "metrics": result_metrics,
        "per_image": {k: v for k, v in per_image.items() if v},
        "timings": _numbers(meta.get("timings")),
        "cpu_timings": _numbers(meta.get("cpu_timings")),
        "iterations_per_s": meta.get("iterations_per_s"),
        "peak_memory_bytes": meta.get("peak_memory_bytes"),
        "device": meta.get("device"),
        "model_size": _numbers(meta.get("model_size")),
        "created": now_iso(),
    }
    # the method's relight diagnostic for this test light, as its adapter computed it (method/diagnose.py)
    diag = meta.get("diagnose")
    if isinstance(diag, dict) and isinstance(diag.get(test_light), dict):
        result["diagnose"] = diag[test_light]
    return validate(result, f"result for {pred_dir}")


def separation_score(scene: Path, pred: PredictionFolder, train_light: str) -> dict[str, float]:
    """IoU and balanced accuracy of (P > 0.5) against the GT dynamic mask, foreground of the train views, and
    each class's recall (the dynamic pixels marked dynamic, the static ones marked static): a balanced
    accuracy of 0.9 can hide a moving class at 0.8, and the moving class is the one that fails."""
    tp = fp = fn = tn = 0
    for frame in layout.read_transforms(scene, "train").frames:
        _, alpha = read_lit(scene, train_light, frame.file_path)
        fg = foreground(alpha)[..., 0] > 0
        p = pred.read("p_map", frame.stem, alpha.shape[:2])[..., 0] > 0.5
        g = read_gt(scene, "dynamic_mask", frame.file_path)[..., 0] > 0.5
        p, g = p[fg], g[fg]
        tp += int(np.sum(p & g))
        fp += int(np.sum(p & ~g))
        fn += int(np.sum(~p & g))
        tn += int(np.sum(~p & ~g))
    union = tp + fp + fn
    iou = tp / union if union else 1.0
    tpr = tp / (tp + fn) if tp + fn else 1.0
    tnr = tn / (tn + fp) if tn + fp else 1.0
    return {"iou": float(iou), "balanced_accuracy": float(0.5 * (tpr + tnr)), "dynamic_recall": float(tpr),
            "static_recall": float(tnr)}


def _unit(n: np.ndarray) -> np.ndarray:
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-8)


def _numbers(obj: Any) -> dict[str, float] | None:
    """Keep the numeric entries of a meta.json mapping (timings, model size)."""
    if not isinstance(obj, dict):
        return None
    out = {str(k): float(v) for k, v in obj.items()
           if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)}
    return out or None
