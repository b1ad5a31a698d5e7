"""Relighting a trained run: any view and time under any environment map (paper: same shading as
stage 2, with a given map). Orbit cameras circle the scene box's centre at the test cameras' median
distance and elevation."""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch
import yaml

from lumibench.errors import UserError
from lumibench.io import atomic_path, write_png
from lumibench.layout import parse_light
from method.devices import check_device
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


# what one relight writes into its output folder: a relight into a folder that holds an earlier one removes
# these first (and nothing else), so a shorter orbit or other test views leave no stale frames beside the new
OUTPUT_KINDS = {"albedo": (".png", ".npz"), "roughness": (".png",), "normal": (".png",), "relit": (".png",)}
OUTPUT_FILES = ("envmap_estimated.hdr", "envmap_estimated_clipped.png", "envmap_estimated_scaled.png",
                "envmap_given_scaled.png", "relit_orbit.gif")


def resolve_scene_dir(run_dir: Path, ident: dict, profile: str | None, data=None) -> Path:
    """The run's scene directory: the recorded ``run.scene``, or, given ``data`` (--data), that scene
    directory itself or <data>/<profile>/<scene_name> (or <data>/<scene_name>) for a moved dataset."""
    name = str(ident.get("scene_name") or Path(str(ident.get("scene", ""))).name)
    if data is not None:
        root = Path(data).expanduser()
        candidates = [root]
        if profile:
            candidates.append(root / str(profile) / name)
        candidates.append(root / name)
        for c in candidates:
            if (c / "transforms_train.json").is_file():
                return c
        where = f"{root / str(profile) / name} or " if profile else ""
        raise UserError(f"--data {root}: neither a scene directory (no transforms_train.json) nor a data root "
                        f"holding this run's scene ({where}{root / name})")
    if "scene" not in ident:
        raise UserError(f"{run_dir / 'config.yaml'} records no scene (run.scene): pass --data <scene dir or data root>")
    scene = Path(str(ident["scene"]))
    if not scene.exists():
        raise UserError(f"the scene this run was trained on is gone: {scene} (recorded in {run_dir / 'config.yaml'}); "
                        f"if the dataset moved, pass --data <its scene dir or data root>")
    return scene


def prepare_output(out: Path) -> None:
    """Make sure ``out`` is a folder we can write, before the run loads (one line naming the path if not)."""
    import tempfile

    if out.exists() and not out.is_dir():
        raise UserError(f"output {out} is an existing file, not a folder: pass another --out")
    try:
        out.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".tmp-probe-", dir=out)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise UserError(f"cannot write the relight output to {out}: {exc.strerror or exc} "
                        f"({exc.filename or out}); pass a writable --out") from None


def clear_previous_outputs(out: Path) -> list[Path]:
    """Remove what an earlier relight wrote into ``out`` (OUTPUT_KINDS images at the top of those folders,
    OUTPUT_FILES); other files, and anything in subfolders, stay. Returns what was removed."""
    removed = []
    for kind, suffixes in OUTPUT_KINDS.items():
        folder = out / kind
        if not folder.is_dir():
            continue
        for p in sorted(folder.iterdir()):
            if p.suffix.lower() in suffixes and (p.is_file() or p.is_symlink()):
                p.unlink()
                removed.append(p)
    for name in OUTPUT_FILES:
        p = out / name
        if p.is_file() or p.is_symlink():
            p.unlink()
            removed.append(p)
    return removed


def relight(run_dir, envmap: str, *, views: str = "test", time: float | None = None, frames: int = 24,
            dirs: int | None = None, out=None, device: str = "cpu", seed: int = 0, data=None) -> Path:
    """Render the run's test views (or an orbit of ``frames`` cameras) under ``envmap`` into ``out``
    (default RUN/relight/<envmap name>). An earlier relight's outputs in ``out`` are removed first (see
    ``clear_previous_outputs``), so the folder holds exactly this relight. ``data``: where the run's scene
    is now, when the dataset moved since training (a scene directory or a data root)."""
    from method.checkpoints import load_trained
    from method.data import load_scene
    from method.shading.envmap import load_envmap

    run_dir = Path(run_dir)
    cfg = read_run_config(run_dir)
    ident = cfg.pop("run")
    if not isinstance(ident, dict):
        raise UserError(f"{run_dir / 'config.yaml'}: malformed 'run' section")
    if views not in ("test", "orbit"):
        raise UserError(f"--views must be test or orbit, got {views!r}")
    if time is not None and not 0.0 <= time <= 1.0:
        raise UserError(f"--time must be in [0, 1], got {time}")
    if views == "orbit" and (isinstance(frames, bool) or int(frames) != frames or frames < 1):
        raise UserError(f"--frames must be a whole number >= 1 (orbit frames), got {frames}")
    if dirs is not None and (isinstance(dirs, bool) or int(dirs) != dirs or dirs < 1):
        raise UserError(f"--dirs must be a whole number >= 1 (directions per pixel), got {dirs}")
    dev = check_device(device)
    scene_dir = resolve_scene_dir(run_dir, ident, cfg.get("profile"), data)
    name, _ = parse_light(envmap)
    out = Path(out) if out else run_dir / "relight" / name
    env = load_envmap(envmap, scene_dir, height=None, width=None, device=dev)
    prepare_output(out)
    scene, mats = load_trained(run_dir, cfg, dev)
    sd = load_scene(scene_dir, ident["light"], cfg["data"]["background"], dev)
    if views == "test":
        if not sd.test:
            raise UserError(f"{scene_dir} has no test views under {ident['light']}: use --views orbit")
        cams = [(v.stem, v.camera, v.time if time is None else time) for v in sd.test]
    else:
        src = [v.camera for v in (sd.test or sd.train)]
        cams = [(f"orbit_{i:03d}", c, 0.0 if time is None else time)
                for i, c in enumerate(orbit_cameras(src, scene.center, frames))]
    try:
        clear_previous_outputs(out)
        _render_and_write(scene, mats, cams, sd, cfg, env, name, out, views, dirs or cfg["stage2"]["dirs_eval"],
                          torch.Generator().manual_seed(seed))
    except OSError as exc:
        raise UserError(f"cannot write the relight output {exc.filename or out}: {exc.strerror or exc}") from None
    return out


def _render_and_write(scene, mats, cams, sd, cfg, env, name, out: Path, views: str, n_dirs: int, gen) -> None:
    from generator.envmap import write_hdr
    from lumibench.color import linear_to_srgb
    from lumibench.progress import track
    from method.shading.deferred import display, render_pbr_view

    relit_frames = []
    for stem, cam, t in track(cams, description=f"relight {name}", unit="view"):
        r = render_pbr_view(scene, mats, cam, t, sd.background, cfg, {name: env}, n_dirs, gen)
        a = r["alpha"][..., None]
        alb = r["albedo"].cpu().numpy()
        with atomic_path(out / "albedo" / f"{stem}.npz") as tmp:
            np.savez_compressed(tmp, image=alb.astype(np.float32))
        write_png(out / "albedo" / f"{stem}.png", (display(r["albedo"]) * a).cpu().numpy())
        write_png(out / "roughness" / f"{stem}.png", (r["roughness"][..., None] * a).cpu().numpy())
        write_png(out / "normal" / f"{stem}.png", ((r["normal"] * 0.5 + 0.5) * a).cpu().numpy())
        relit = (display(r[f"relit:{name}"]) * a + sd.background * (1 - a)).cpu().numpy()
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
