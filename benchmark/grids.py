"""Image grids: ground truth next to prediction (albedo as scored, roughness, relight; env maps).

Built from a result file alone: it names the scene and predictions folder, holds the albedo scale and says
which relight it scored, so the grid shows exactly what was scored (aligned albedo, the relight shaded with
it under `lumimotion`, GT-alpha masking).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from lumibench import layout
from lumibench.errors import UserError
from lumibench.io import read_image

from .predictions import PredictionFolder, srgb_decode, srgb_encode
from .score import read_gt, read_lit, scored_relight_kind

MAX_VIEWS = 3


def _tonemap(env: np.ndarray) -> np.ndarray:
    """Reinhard then sRGB, normalised by the mean radiance: a sky at its mean shows mid-grey, a sun white.
    (Normalised by the 99th percentile, a uniform sky with one sun texel, stage 2's fitted map at `small`,
    showed as a blank white rectangle.)"""
    x = env / max(float(np.mean(env)), 1e-6)
    return srgb_encode(x / (1.0 + x))


def grid_images(result: dict[str, Any], max_views: int = MAX_VIEWS
                ) -> tuple[list[tuple[str, str]], list[tuple[str, dict[str, np.ndarray | None]]]]:
    """The grid's columns (key, title) and, per test view (stem), its panels as arrays in [0, 1] (None where
    the method did not predict that kind): the albedo aligned as scored, the relight the result scored."""
    scene = Path(result["inputs"]["scene_dir"])
    pred = PredictionFolder(Path(result["inputs"]["pred_dir"]))
    train, test = result["train_light"], result["test_light"]
    scale = np.asarray((result["metrics"].get("albedo") or {}).get("scale", [1, 1, 1]), dtype=np.float32)
    relit = scored_relight_kind(result)  # under `lumimotion`, the relight shaded with the aligned albedo
    cols = [("albedo", "GT albedo"), ("albedo_p", "albedo (aligned)"), ("rough", "GT roughness"),
            ("rough_p", "roughness"), ("relight", f"GT {test}"),
            ("relight_p", f"relit {test}" + (", albedo aligned" if relit == "relight_scaled" else ""))]
    views = []
    for frame in layout.read_transforms(scene, "test").frames[:max_views]:
        fp, stem = frame.file_path, frame.stem
        _, alpha = read_lit(scene, train, fp)
        shape = alpha.shape[:2]
        imgs: dict[str, np.ndarray | None] = {
            "albedo": srgb_encode(read_gt(scene, "albedo", fp)) * alpha,
            "rough": read_gt(scene, "roughness", fp)[..., 0] * alpha[..., 0],
            "relight": read_lit(scene, test, fp)[0] * alpha,
            "albedo_p": None, "rough_p": None, "relight_p": None,
        }
        if pred.has("albedo"):
            lin = srgb_decode(pred.read("albedo", stem, shape)) * scale
            imgs["albedo_p"] = srgb_encode(lin) * alpha
        if pred.has("roughness"):
            imgs["rough_p"] = pred.read("roughness", stem, shape)[..., 0] * alpha[..., 0]
        if pred.has(relit, test):
            imgs["relight_p"] = pred.read(relit, stem, shape, test) * alpha
        views.append((stem, imgs))
    return cols, views


def image_grid(result: dict[str, Any], path: Path, max_views: int = MAX_VIEWS) -> Path:
    """Write a GT-vs-prediction grid PNG for one scored run; returns ``path``."""
    from .charts import _plt, _save

    if result.get("status") != "ok":
        raise UserError(f"no image grid for a failed run ({result.get('method')} {result.get('scene')})")
    scene = Path(result["inputs"]["scene_dir"])
    pred = PredictionFolder(Path(result["inputs"]["pred_dir"]))
    train, test = result["train_light"], result["test_light"]
    cols, views = grid_images(result, max_views)
    plt = _plt()
    fig, axes = plt.subplots(len(views) + 1, len(cols), figsize=(1.9 * len(cols), 1.95 * (len(views) + 1)),
                             squeeze=False)
    for i, (stem, imgs) in enumerate(views):
        for j, (key, title) in enumerate(cols):
            ax = axes[i, j]
            img = imgs[key]
            if img is None:
                ax.text(0.5, 0.5, "not predicted", ha="center", va="center", fontsize=8, color="0.4")
            elif img.ndim == 2:
                ax.imshow(img, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
            else:
                ax.imshow(np.clip(img, 0, 1), interpolation="nearest")
            if i == 0:
                ax.set_title(title, fontsize=8)
            ax.set_axis_off()
        axes[i, 0].text(-0.08, 0.5, stem, transform=axes[i, 0].transAxes, rotation=90, va="center", ha="right",
                        fontsize=7)
    env_row = axes[len(views)]
    for ax in env_row:
        ax.set_axis_off()
    envs = ((env_row[0], _true_envmap(scene, train), f"true env ({train})"),
            (env_row[1], pred.envmap(train), f"estimated env ({train})"),
            (env_row[4], _true_envmap(scene, test), f"true env ({test})"))
    for ax, env, title in envs:
        if env is None:
            ax.text(0.5, 0.5, "not provided", ha="center", va="center", fontsize=8, color="0.4")
        else:
            ax.imshow(_tonemap(env), interpolation="nearest")
        ax.set_title(title, fontsize=8)
    fig.suptitle(f"{result['method']} | {result['scene']} | {train} → {test} | seed {result['seed']}", fontsize=9)
    return _save(fig, path)


def _true_envmap(scene: Path, light: str) -> np.ndarray | None:
    hdr = layout.envmap_path(scene, light)
    if hdr.is_file():
        from generator.envmap import read_envmap

        try:
            return read_envmap(hdr)
        except UserError:
            pass
    preview = Path(scene) / f"{light}.png"
    return srgb_decode(read_image(preview)[..., :3]) if preview.is_file() else None
