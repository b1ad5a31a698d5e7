"""Methods that need no training: the floors of the benchmark and a noisy-oracle sanity row.

* ``lit_as_albedo``: the test view as seen under the train light is taken as the albedo and as the
  relit image (no inverse rendering at all: shadows and shading stay baked in); roughness 0.5.
  It writes no NVS (that would be the ground truth itself).
* ``mean_albedo``: a constant grey albedo (the per-channel median alignment turns it into the scene's
  median albedo colour), roughness 0.5, and as relight the mean foreground colour of the training
  images under the train light. No NVS.
* ``noisy_gt``: every ground-truth map plus i.i.d. Gaussian noise of standard deviation ``sigma``
  (seeded), written as float so that no quantisation adds to it; its PSNR is known analytically.
"""
from __future__ import annotations

import numpy as np

from lumibench.predictions import srgb_decode, srgb_encode
from lumibench.groundtruth import read_gt, read_lit
from generator.envmap import read_envmap
from lumibench import layout

from .base import MethodAdapter, save

CONSTANT_ROUGHNESS = 0.5


class LitAsAlbedo(MethodAdapter):
    name = "lit_as_albedo"
    version = "1"
    seed_dependent = False

    def predict(self, scene_dir, train_light, test_lights, seed, profile, out_dir, runs_dir):
        for frame in layout.read_transforms(scene_dir, "test").frames:
            rgb, _ = read_lit(scene_dir, train_light, frame.file_path)
            save(out_dir, "albedo", frame.stem, rgb)
            save(out_dir, "roughness", frame.stem, np.full(rgb.shape[:2], CONSTANT_ROUGHNESS, np.float32))
            for light in test_lights:
                save(out_dir, "relight", frame.stem, rgb, light)
        return None


class MeanAlbedo(MethodAdapter):
    name = "mean_albedo"
    version = "1"
    seed_dependent = False

    def predict(self, scene_dir, train_light, test_lights, seed, profile, out_dir, runs_dir):
        total, weight = np.zeros(3), 0.0
        for frame in layout.read_transforms(scene_dir, "train").frames:
            rgb, alpha = read_lit(scene_dir, train_light, frame.file_path)
            total += (rgb * alpha).reshape(-1, 3).sum(0)
            weight += float(alpha.sum())
        mean_rgb = (total / max(weight, 1e-8)).astype(np.float32)
        for frame in layout.read_transforms(scene_dir, "test").frames:
            _, alpha = read_lit(scene_dir, train_light, frame.file_path)
            h, w = alpha.shape[:2]
            save(out_dir, "albedo", frame.stem, np.full((h, w, 3), 0.5, np.float32))
            save(out_dir, "roughness", frame.stem, np.full((h, w), CONSTANT_ROUGHNESS, np.float32))
            for light in test_lights:
                save(out_dir, "relight", frame.stem, np.broadcast_to(mean_rgb, (h, w, 3)), light)
        return {"mean_train_colour": [float(c) for c in mean_rgb]}


class NoisyGT(MethodAdapter):
    """Ground truth + N(0, sigma^2) in display space for RGB kinds, linear for roughness and P."""

    name = "noisy_gt"
    version = "1"

    def __init__(self, sigma: float = 0.03):
        if not sigma >= 0:
            raise ValueError("sigma must be >= 0")
        self.sigma = float(sigma)

    def predict(self, scene_dir, train_light, test_lights, seed, profile, out_dir, runs_dir):
        rng = np.random.default_rng(seed)

        def noisy(x: np.ndarray) -> np.ndarray:
            return (x + rng.normal(0.0, self.sigma, size=x.shape)).astype(np.float32)

        def save_display(kind: str, stem: str, rgb: np.ndarray, light: str | None = None) -> None:
            # float files are linear by the layout: decode so that the scorer's encode gives back rgb
            save(out_dir, kind, stem, srgb_decode(np.clip(noisy(rgb), 0.0, 1.0)), light, fmt="npz")

        for frame in layout.read_transforms(scene_dir, "test").frames:
            stem, fp = frame.stem, frame.file_path
            rgb, _ = read_lit(scene_dir, train_light, fp)
            save_display("nvs", stem, rgb)
            save_display("albedo", stem, srgb_encode(read_gt(scene_dir, "albedo", fp)))
            save(out_dir, "roughness", stem, noisy(read_gt(scene_dir, "roughness", fp)), fmt="npz")
            normal = read_gt(scene_dir, "normal", fp)
            save(out_dir, "normal", stem, noisy(normal), fmt="npz")
            for light in test_lights:
                lit, _ = read_lit(scene_dir, light, fp)
                save_display("relight", stem, lit, light)
        for frame in layout.read_transforms(scene_dir, "train").frames:
            mask = read_gt(scene_dir, "dynamic_mask", frame.file_path)
            save(out_dir, "p_map", frame.stem, np.clip(noisy(mask), 0.0, 1.0), fmt="npz")
        env_path = layout.envmap_path(scene_dir, train_light)
        if env_path.is_file():  # the "estimated" env map: the true one with multiplicative noise
            env = read_envmap(env_path)
            save(out_dir, "envmap", train_light, env * np.exp(noisy(np.zeros_like(env))), fmt="npz")
        return {"sigma": self.sigma}


def expected_psnr(sigma: float) -> float:
    """PSNR (dB, data range 1) of unclipped Gaussian noise of standard deviation ``sigma``."""
    return float(10.0 * np.log10(1.0 / sigma**2))
