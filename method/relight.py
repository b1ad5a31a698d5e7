"""Relighting a trained run: any view and time under any environment map (paper: same shading as
stage 2, with a given map). Orbit cameras circle the scene box's centre at the test cameras' median
distance and elevation."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
import yaml

from lumibench.errors import UserError
from lumibench.io import atomic_path, write_png
from method.splat.camera import Camera


def read_run_config(run_dir: Path) -> dict:
    path = Path(run_dir) / "config.yaml"
    if not path.is_file():
        raise UserError(f"{run_dir} is not a run directory (no config.yaml): train one with `make train`")
    try:
        cfg = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise UserError(f"{path}: malformed YAML ({exc.__class__.__name__})") from None
    if not isinstance(cfg, dict) or "run" not in cfg:
        raise UserError(f"{path}: not a LumiMotion run configuration")
    return cfg


def orbit_cameras(test_cameras: list[Camera], center: torch.Tensor, n: int) -> list[Camera]:
    pos = np.stack([c.center.double().cpu().numpy() for c in test_cameras])
    c = center.double().cpu().numpy()
    rel = pos - c
    radius = float(np.median(np.linalg.norm(rel, axis=1)))
    elev = float(np.median(np.arcsin(np.clip(rel[:, 2] / np.linalg.norm(rel, axis=1), -1, 1))))
    ref = test_cameras[0]
    angle = 2 * math.atan(0.5 * ref.width / ref.focal)
    cams = []
    for i in range(n):
        az = 2 * math.pi * i / n
        eye = c + radius * np.array([math.cos(elev) * math.cos(az), math.cos(elev) * math.sin(az), math.sin(elev)])
        cams.append(Camera.look_at(eye, c, ref.width, ref.height, camera_angle_x=angle, device=ref.device))
    return cams


def relight(run_dir, envmap: str, *, views: str = "test", time: float | None = None, frames: int = 24,
            dirs: int | None = None, out=None, device: str = "cpu", seed: int = 0) -> Path:
    from generator.envmap import write_hdr
    from lumibench.color import linear_to_srgb
    from method.data import load_scene
    from method.shading.envmap import load_envmap
    from method.stage2 import display, render_pbr_view
    from method.train2 import load_trained

    run_dir = Path(run_dir)
    cfg = read_run_config(run_dir)
    ident = cfg.pop("run")
    if time is not None and not 0.0 <= time <= 1.0:
        raise UserError(f"--time must be in [0, 1], got {time}")
    dev = torch.device(device)
    scene_dir = Path(ident["scene"])
    scene, mats = load_trained(run_dir, cfg, dev)
    env = load_envmap(envmap, scene_dir if scene_dir.is_dir() else None, height=None, width=None, device=dev)
    name = Path(envmap).stem if ("/" in envmap or envmap.lower().endswith((".hdr", ".exr"))) else envmap
    out = Path(out) if out else run_dir / "relight" / name
    data = load_scene(scene_dir, ident["light"], cfg["data"]["background"], dev)
    if views == "test":
        if not data.test:
            raise UserError(f"{scene_dir} has no test views under {ident['light']}: use --views orbit")
        cams = [(v.stem, v.camera, v.time if time is None else time) for v in data.test]
    else:
        src = [v.camera for v in (data.test or data.train)]
        cams = [(f"orbit_{i:03d}", c, 0.0 if time is None else time)
                for i, c in enumerate(orbit_cameras(src, scene.center, frames))]
    gen = torch.Generator().manual_seed(seed)
    n_dirs = dirs or cfg["stage2"]["dirs_eval"]
    relit_frames = []
    from lumibench.progress import track

    for stem, cam, t in track(cams, description=f"relight {name}", unit="view"):
        r = render_pbr_view(scene, mats, cam, t, data.background, cfg, {name: env}, n_dirs, gen)
        a = r["alpha"][..., None]
        alb = r["albedo"].cpu().numpy()
        with atomic_path(out / "albedo" / f"{stem}.npz") as tmp:
            np.savez_compressed(tmp, image=alb.astype(np.float32))
        write_png(out / "albedo" / f"{stem}.png", (display(r["albedo"]) * a).cpu().numpy())
        write_png(out / "roughness" / f"{stem}.png", (r["roughness"][..., None] * a).cpu().numpy())
        write_png(out / "normal" / f"{stem}.png", ((r["normal"] * 0.5 + 0.5) * a).cpu().numpy())
        relit = (display(r[f"relit:{name}"]) * a + data.background * (1 - a)).cpu().numpy()
        write_png(out / "relit" / f"{stem}.png", relit)
        relit_frames.append(relit)
    est = mats.env().detach().cpu().numpy()
    write_hdr(out / "envmap_estimated.hdr", est)
    write_png(out / "envmap_estimated_clipped.png", linear_to_srgb(np.clip(est, 0, 1)))
    write_png(out / "envmap_estimated_scaled.png", linear_to_srgb(est / max(float(est.max()), 1e-8)))
    write_png(out / "envmap_given_scaled.png", linear_to_srgb(env.cpu().numpy() / max(float(env.max()), 1e-8)))
    if views == "orbit":
        import imageio.v2 as imageio

        gif = out / "relit_orbit.gif"
        with atomic_path(gif) as tmp:
            imageio.mimsave(tmp, [(np.clip(f, 0, 1) * 255).astype(np.uint8) for f in relit_frames],
                            format="GIF", duration=0.08, loop=0)
    return out
