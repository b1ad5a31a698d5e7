"""Score a stage-2 checkpoint's materials on the test views without writing predictions.

`python -m method.score_checkpoint RUN_DIR [--iteration N] [--colour]`: albedo PSNR / SSIM (aligned as the
benchmark aligns it, 8-bit as the predictions store it, the run's protocol masks) and roughness MSE of the
rasterized maps, in seconds instead of the minutes that relighting every test view takes. For comparing
stage-2 settings along a run; the published numbers come from `python -m benchmark score`.
``--colour`` scores the stage-1 canonical colour as albedo (the "without stage 2" row)."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch


def score(run_dir: Path, iteration: int | None = None, colour: bool = False, protocol: str = "lumimotion") -> dict:
    from lumibench.errors import UserError
    from method.relight import read_run_config
    from method.checkpoints import checkpoint_paths, load_checkpoint, scene_from_checkpoint
    from method.model.materials import Materials

    run_dir = Path(run_dir)
    cfg = read_run_config(run_dir)
    stage = 1 if colour else 2
    cks = dict(checkpoint_paths(run_dir, stage))
    if not cks:
        raise UserError(f"no stage-{stage} checkpoint in {run_dir}")
    it = max(cks) if iteration is None else iteration
    if it not in cks:
        raise UserError(f"no stage-{stage} checkpoint at iteration {it} in {run_dir} (have {sorted(cks)})")
    dev = torch.device("cpu")
    ck = load_checkpoint(cks[it], dev)
    scene = scene_from_checkpoint(ck, cfg, dev)
    mats = Materials.init_from(scene, cfg) if colour else Materials.from_state(ck["materials"], cfg, dev)
    scene_dir = Path(cfg["run"]["scene"])
    if not (scene_dir / "transforms_test.json").is_file():
        raise UserError(f"the run's scene directory {scene_dir} is gone: render it again (make dataset)")
    return _score(scene, mats, scene_dir, cfg, it, protocol)


def _score(scene, mats, scene_dir: Path, cfg: dict, it: int, protocol: str) -> dict:
    from benchmark import align
    from benchmark.metrics import mse
    from benchmark.protocol import foreground, get_protocol
    from lumibench.groundtruth import read_gt
    from lumibench.predictions import srgb_decode, srgb_encode
    from method.data import load_scene
    from method.shading.deferred import display, render_pbr_view

    proto = get_protocol(protocol)
    light = cfg["run"]["light"]
    data = load_scene(scene_dir, light, cfg["data"]["background"], torch.device("cpu"))
    gen = torch.Generator().manual_seed(0)
    preds, gts, masks, alphas, rough = [], [], [], [], []
    with torch.no_grad():
        for v in data.test:
            r = render_pbr_view(scene, mats, v.camera, v.time, data.background, cfg, {}, 1, gen)
            preds.append(srgb_decode(_as_png(display(r["albedo"]).cpu().numpy())))
            gts.append(read_gt(scene_dir, "albedo", v.file_path))
            alpha = v.alpha.cpu().numpy()[..., None]
            alphas.append(alpha)
            masks.append(foreground(alpha))
            gr = read_gt(scene_dir, "roughness", v.file_path)
            rough.append(float(mse(_as_png(r["roughness"].cpu().numpy())[..., None], gr, mask=masks[-1])))
    scale = np.asarray(align.albedo_scale(preds, gts, masks), dtype=np.float64).reshape(3)
    psnrs, ssims, lpipss = [], [], []
    for p, g, alpha in zip(preds, gts, alphas):
        s = proto.score_rgb(srgb_encode(np.asarray(align.apply_scale(p, scale))), srgb_encode(g), alpha, "vgg")
        psnrs.append(s["psnr"])
        ssims.append(s["ssim"])
        lpipss.append(s["lpips"])
    return {"iteration": it, "albedo_psnr": float(np.mean(psnrs)), "albedo_ssim": float(np.mean(ssims)),
            "albedo_lpips": float(np.mean(lpipss)),
            "roughness_mse": float(np.mean(rough)), "views": len(psnrs)}


def _as_png(x: np.ndarray) -> np.ndarray:
    """The values an 8-bit prediction PNG holds (lumibench.io.write_png's rounding)."""
    return (np.clip(x, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8).astype(np.float32) / 255.0


def main(argv: list[str] | None = None) -> int:
    from lumibench.errors import UserError

    ap = argparse.ArgumentParser(prog="python -m method.score_checkpoint", description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("--iteration", type=int, default=None, help="checkpoint iteration (default: the last)")
    ap.add_argument("--colour", action="store_true", help="score the stage-1 canonical colour as albedo")
    args = ap.parse_args(argv)
    try:
        print(json.dumps(score(args.run_dir, args.iteration, args.colour)))
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
