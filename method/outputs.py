"""What a stage-1 run shows: test-view renders (RGB, normals, depth, P), a sheet of them, the
separation score on the training views, and P maps where the benchmark's predictions layout expects them."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from lumibench.io import write_png
from method.data import SceneData, View
from method import buffers
from method.buffers import STAGE1
from method.model.scene import DynamicScene, render

# static (P < 0.5) blue, dynamic (P > 0.5) orange, the background white
_STATIC = np.array([0.2, 0.45, 0.9], np.float32)
_DYNAMIC = np.array([0.95, 0.5, 0.1], np.float32)


def p_colour(p: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """P (H, W) in [0, 1] as a blue (static) -> orange (dynamic) image over white where alpha is low."""
    col = _STATIC[None, None] * (1 - p[..., None]) + _DYNAMIC[None, None] * p[..., None]
    return buffers.over_background(col, alpha, 1.0)


def depth_colour(depth: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    fg = alpha > 0.5
    if not fg.any():
        return np.ones(depth.shape + (3,), np.float32)
    lo, hi = np.percentile(depth[fg], [1, 99])
    x = np.clip((depth - lo) / max(hi - lo, 1e-6), 0, 1)
    import matplotlib

    col = matplotlib.colormaps["viridis"](1 - x)[..., :3].astype(np.float32)
    return buffers.over_background(col, alpha, 1.0)


@torch.no_grad()
def render_view(scene: DynamicScene, view: View, background: torch.Tensor) -> dict[str, np.ndarray]:
    """Inference render (u = 0.5) of one view at its time: rgb, alpha, normal, depth, P (numpy)."""
    d = scene.deform(view.time, p_mode="inference")
    out = render(d, view.camera, background)
    alpha = out.alpha.clamp(0, 1)
    p = buffers.channel(out.features, alpha, STAGE1.p)
    return {"rgb": out.features[..., STAGE1.colour].clamp(0, 1).cpu().numpy(), "alpha": alpha.cpu().numpy(),
            "normal": buffers.unit(out.normal).cpu().numpy(), "depth": out.depth_expected.cpu().numpy(),
            "p": torch.where(alpha > 1e-3, p, torch.zeros_like(p)).cpu().numpy()}


def separation(scene: DynamicScene, data: SceneData) -> dict[str, float] | None:
    """Share of moving-object pixels whose rendered P is > 0.5 (dynamic_recall) and of static
    foreground pixels whose P is < 0.5 (static_recall), over the training views, with the generator's
    dynamic mask; P is rasterized as a feature (alpha-normalised), so a pixel counts as dynamic when
    mostly Gaussians with high P render it. None without masks."""
    tp = fn = tn = fp = 0
    have = False
    for v in data.train:
        if v.dynamic_mask is None:
            continue
        have = True
        r = render_view(scene, v, data.background)
        fg = v.alpha.cpu().numpy() > 0.5
        dyn = v.dynamic_mask.cpu().numpy() > 0.5
        pd = r["p"] > 0.5
        tp += int(np.sum(fg & dyn & pd))
        fn += int(np.sum(fg & dyn & ~pd))
        tn += int(np.sum(fg & ~dyn & ~pd))
        fp += int(np.sum(fg & ~dyn & pd))
    if not have:
        return None
    return {"dynamic_recall": tp / max(tp + fn, 1), "static_recall": tn / max(tn + fp, 1),
            "dynamic_pixels": tp + fn, "static_pixels": tn + fp}


def write_p_maps(scene: DynamicScene, data: SceneData, pred_dir: Path) -> None:
    """P of every training view at its time: ``PRED/p_map/train/<stem>.png`` (benchmark layout)."""
    for v in data.train:
        r = render_view(scene, v, data.background)
        write_png(pred_dir / "p_map" / "train" / f"{v.stem}.png", r["p"][..., None])


def write_test_renders(scene: DynamicScene, data: SceneData, out_dir: Path, tag: str) -> tuple[list[dict], Path | None]:
    """RGB, normals, depth and P of every test view under ``out_dir/<kind>/``, plus a sheet PNG
    (rows: views; columns: ground truth, RGB, normals, depth, P). Returns per-view renders and the sheet."""
    renders, rows = [], []
    for v in data.test:
        r = render_view(scene, v, data.background)
        renders.append(r)
        a = r["alpha"]
        nrm = buffers.over_background(r["normal"] * 0.5 + 0.5, a, 1.0)
        imgs = {"rgb": r["rgb"], "normal": nrm, "depth": depth_colour(r["depth"], a), "p": p_colour(r["p"], a)}
        for kind, img in imgs.items():
            write_png(out_dir / kind / f"{v.stem}.png", img)
        rows.append(np.concatenate([v.rgb.cpu().numpy()] + list(imgs.values()), 1))
    if not rows:
        return renders, None
    sheet = np.concatenate(rows[:8], 0)
    path = out_dir.parent / f"sheet_{tag}.png"
    write_sheet(path, sheet, ["ground truth", "RGB", "normals", "depth", "P: static blue,\ndynamic orange"])
    return renders, path


def write_sheet(path: Path, sheet: np.ndarray, titles: list[str]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h, w = sheet.shape[:2]
    scale = max(1.0, 640 / w)
    fig = plt.figure(figsize=(w * scale / 100, h * scale / 100 + 0.35), dpi=100)
    ax = fig.add_axes([0, 0, 1, h * scale / 100 / (h * scale / 100 + 0.35)])
    ax.imshow(np.clip(sheet, 0, 1), interpolation="nearest")
    ax.set_axis_off()
    cw = w / len(titles)
    for i, t in enumerate(titles):
        fig.text((i + 0.5) * cw / w, 1 - 0.15 / (h * scale / 100 + 0.35), t, ha="center", va="center", fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp)
    plt.close(fig)
    tmp.replace(path)


def stage1_outputs(scene: DynamicScene, data: SceneData, run_dir: Path) -> dict:
    """Test renders + sheet, NVS metrics, separation score, P maps; returns the metrics."""
    from benchmark.metrics import lpips, psnr, ssim

    out: dict = {}
    renders, sheet = write_test_renders(scene, data, run_dir / "renders" / "stage1", "stage1")
    if renders:
        ps, ss, lp = [], [], []
        for r, v in zip(renders, data.test):
            gt = v.rgb.cpu().numpy()
            ps.append(psnr(r["rgb"], gt))
            ss.append(ssim(r["rgb"], gt))
            lp.append(lpips(r["rgb"], gt, net="vgg", input_range="[0,1]"))
        out["test"] = {"psnr": sum(ps) / len(ps), "ssim": sum(ss) / len(ss), "lpips_vgg": sum(lp) / len(lp),
                       "views": len(ps), "note": "test views under the train light, composited on the background"}
        out["sheet"] = str(sheet) if sheet else None
    sep = separation(scene, data) if not scene.static else None
    if sep is not None:
        out["separation"] = sep
    if not scene.static:
        write_p_maps(scene, data, run_dir / "predictions")
    return out
