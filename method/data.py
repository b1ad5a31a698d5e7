"""Scene loading for training: our dataset layout, and the original LumiMotion / D-NeRF reader's.

Conventions (shared with the authors' reader, so their released scenes load too): cameras from
``transforms_<split>.json`` (``camera_angle_x``, OpenGL camera-to-world ``transform_matrix``, ``time``),
the image of a frame at ``<scene>/<light>/<file_path>.png`` (a leading ``./`` is ignored), frames ordered
by the number at the end of ``file_path``. RGBA images are composited on a background colour; alpha is
the foreground mask. Colours stay in display (sRGB) space: stage 1 fits what the camera saw.
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from lumibench import layout
from lumibench.errors import UserError
from lumibench.io import read_image
from method.splat.camera import Camera

_TRAILING_NUMBER = re.compile(r"(\d+)$")


@dataclass
class View:
    """One camera at one time, with its image (H, W, 3 display space, on the background) and alpha."""

    stem: str
    file_path: str
    camera: Camera
    time: float
    rgb: torch.Tensor
    alpha: torch.Tensor
    dynamic_mask: torch.Tensor | None = None  # (H, W) where the generator wrote one


@dataclass
class SceneData:
    root: Path
    light: str
    train: list[View]
    test: list[View]
    background: torch.Tensor
    center: torch.Tensor  # (3,) point the cameras look at
    extent: float         # half size of the scene box around ``center``
    static: bool          # every training view shares one time
    meta: dict = field(default_factory=dict)

    @property
    def resolution(self) -> tuple[int, int]:
        return self.train[0].camera.height, self.train[0].camera.width


def frame_order(file_path: str) -> tuple[int, str]:
    """Sort key: the number at the end of the file path (r_2 before r_10), then the path."""
    stem = Path(file_path).name
    m = _TRAILING_NUMBER.search(stem)
    return (int(m.group(1)) if m else -1, file_path)


def _clean(file_path: str) -> str:
    return file_path[2:] if file_path.startswith("./") else file_path


def available_lights(scene: Path) -> list[str]:
    """Light folders that hold a train split (a light is a folder of lit images; ground-truth kinds and
    hidden bookkeeping folders are not lights)."""
    if not Path(scene).is_dir():
        return []
    return sorted(p.name for p in Path(scene).iterdir()
                  if (p / "train").is_dir() and p.name not in layout.GT_KINDS and not p.name.startswith("."))


def check_scene(scene: Path, light: str) -> None:
    """One-line errors for a missing or unfinished scene and an unknown light."""
    scene = Path(scene)
    if not (scene / "transforms_train.json").is_file():
        raise UserError(f"{scene} is not a scene directory (no transforms_train.json): render it with "
                        f"`make dataset` or pass the right path")
    meta = scene / "dataset.json"
    if meta.is_file() and not layout.is_complete(scene):
        raise UserError(f"{scene} is unfinished (dataset.json lacks \"complete\": true): re-run `make dataset`")
    lights = available_lights(scene)
    if light not in lights:
        raise UserError(f"unknown light '{light}' for scene {scene} (available: {', '.join(lights) or 'none'})")


def read_view_image(path: Path, background: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if not path.is_file():
        raise UserError(f"missing image {path}")
    try:
        img = read_image(path)
    except UserError:
        raise
    except Exception as exc:  # corrupt PNG
        raise UserError(f"cannot read image {path}: {exc}") from None
    if img.ndim != 3 or img.shape[-1] < 3:
        raise UserError(f"{path}: expected an RGB or RGBA image, got shape {img.shape}")
    rgb = img[..., :3].astype(np.float32)
    alpha = img[..., 3].astype(np.float32) if img.shape[-1] >= 4 else np.ones(img.shape[:2], np.float32)
    return rgb * alpha[..., None] + background[None, None, :] * (1.0 - alpha[..., None]), alpha


def _dynamic_mask(scene: Path, file_path: str) -> np.ndarray | None:
    for ext in (".npz", ".png"):
        p = layout.gt_path(scene, "dynamic_mask", file_path, ext)
        if p.is_file():
            return read_image(p)[..., 0].astype(np.float32)
    return None


def _frame_matrix(frame: dict, path: Path, fp: str) -> np.ndarray:
    """A frame's camera-to-world matrix: 4 x 4 and finite, else a one-line error naming file and frame."""
    if "transform_matrix" not in frame:
        raise UserError(f"{path}: frame {fp} has no transform_matrix")
    try:
        m = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise UserError(f"{path}: frame {fp}: transform_matrix is not a 4 x 4 matrix of numbers ({exc})") from None
    if m.shape != (4, 4):
        raise UserError(f"{path}: frame {fp}: transform_matrix has shape {m.shape}, expected 4 x 4")
    if not np.isfinite(m).all():
        raise UserError(f"{path}: frame {fp}: transform_matrix has NaN or infinite entries")
    return m


def _frame_time(frame: dict, path: Path, fp: str) -> float:
    """A frame's time: a number in [0, 1] (the dataset convention), else a one-line error."""
    if "time" not in frame:
        raise UserError(f"{path}: frame {fp} has no time (every frame needs a \"time\" in [0, 1])")
    t = frame["time"]
    if isinstance(t, bool) or not isinstance(t, (int, float)):
        raise UserError(f"{path}: frame {fp}: time {t!r} is not a number (expected one in [0, 1])")
    if not 0.0 <= t <= 1.0:  # NaN fails this too
        raise UserError(f"{path}: frame {fp}: time {t} is outside [0, 1]")
    return float(t)


def even_subset(n: int, fraction: float) -> list[int]:
    """Which of ``n`` time-ordered frames a run that keeps ``fraction`` of them trains on: m = round(fraction n)
    frames (at least 2 when n >= 2, so the first and the last time are always kept) at the positions
    round(j (n - 1) / (m - 1)), j = 0 .. m - 1, i.e. every 1 / fraction-th frame evenly over the time range (the
    gaps differ by at most one frame). No randomness: every seed trains on the same frames, so the seeds'
    spread is the training's, not the choice of frames'."""
    if not 0 < fraction <= 1:
        raise UserError(f"the share of training frames kept must be in (0, 1], got {fraction}")
    if n <= 0:
        return []
    m = min(n, max(min(n, 2), int(round(fraction * n))))
    if m == n:
        return list(range(n))
    return sorted({int(round(j * (n - 1) / (m - 1))) for j in range(m)})


def load_views(scene: Path, light: str, split: str, background: np.ndarray, device, with_masks: bool,
               keep: float = 1.0) -> tuple[float, list[View]]:
    """The views of ``split`` in frame order; ``keep`` < 1: only the frames :func:`even_subset` keeps of them
    ordered by time (the images of the others are not read)."""
    path = Path(scene) / f"transforms_{split}.json"
    if not path.is_file():
        raise UserError(f"missing {path}")
    try:
        raw = json.loads(path.read_text())
        angle = float(raw["camera_angle_x"])
        frames = sorted(raw["frames"], key=lambda f: frame_order(_clean(str(f["file_path"]))))
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise UserError(f"{path}: corrupt transforms file ({type(exc).__name__}: {exc})") from None
    if not (math.isfinite(angle) and 0.0 < angle < math.pi):
        raise UserError(f"{path}: camera_angle_x is {angle}, expected a field of view in (0, pi) radians")
    if keep < 1.0:
        times = [_frame_time(f, path, _clean(str(f["file_path"]))) for f in frames]
        by_time = sorted(range(len(frames)), key=lambda i: (times[i], i))
        frames = [frames[i] for i in sorted(by_time[k] for k in even_subset(len(frames), keep))]
    views = []
    for f in frames:
        fp = _clean(str(f["file_path"]))
        c2w = _frame_matrix(f, path, fp)
        t = _frame_time(f, path, fp)
        rgb, alpha = read_view_image(Path(scene) / light / f"{fp}.png", background)
        h, w = alpha.shape
        try:
            cam = Camera.from_blender(angle, c2w, w, h, device=device)
        except (ValueError, RuntimeError) as exc:  # RuntimeError: torch's singular-matrix error
            raise UserError(f"{path}: frame {fp}: unusable transform_matrix ({exc})") from None
        mask = _dynamic_mask(scene, fp) if with_masks else None
        views.append(View(stem=Path(fp).name, file_path=fp, camera=cam, time=t,
                          rgb=torch.from_numpy(rgb).to(device), alpha=torch.from_numpy(alpha).to(device),
                          dynamic_mask=None if mask is None else torch.from_numpy(mask).to(device)))
    if not views:
        raise UserError(f"{path}: no frames")
    return angle, views


def scene_box(views: list[View], angle: float) -> tuple[torch.Tensor, float]:
    """The point all optical axes pass closest to (least squares) and the half size of the box the
    cameras frame there (distance x tan(fov / 2)): the region random initial points are drawn from."""
    a = np.zeros((3, 3))
    b = np.zeros(3)
    centres, dists = [], []
    for v in views:
        c2w = v.camera.c2w.double().cpu().numpy()
        o, d = c2w[:3, 3], c2w[:3, 2]  # vision frame: +z forward
        d = d / np.linalg.norm(d)
        proj = np.eye(3) - np.outer(d, d)
        a += proj
        b += proj @ o
        centres.append(o)
    try:
        target = np.linalg.solve(a, b)
    except np.linalg.LinAlgError:
        target = np.mean(centres, 0)
    dists = [np.linalg.norm(c - target) for c in centres]
    half = float(np.median(dists) * math.tan(0.5 * angle))
    return torch.tensor(target, dtype=torch.float32), half


def load_scene(scene: str | Path, light: str, background=(1.0, 1.0, 1.0), device="cpu",
               load_test: bool = True, train_frames: float = 1.0) -> SceneData:
    """The scene under ``light``: training views (``train_frames`` < 1: the share of them :func:`even_subset`
    keeps, evenly over time; the method's ``data.train_frames``) and test views."""
    scene = Path(scene)
    check_scene(scene, light)
    bg = np.asarray(background, dtype=np.float32)
    angle, train = load_views(scene, light, "train", bg, device, with_masks=True, keep=train_frames)
    test = []
    if load_test and (scene / "transforms_test.json").is_file() and (scene / light / "test").is_dir():
        _, test = load_views(scene, light, "test", bg, device, with_masks=False)
    sizes = {(v.camera.height, v.camera.width) for v in train + test}
    if len(sizes) != 1:
        raise UserError(f"{scene}: images of different sizes {sorted(sizes)}; every view must match")
    center, extent = scene_box(train, angle)
    times = {round(v.time, 9) for v in train}
    meta = {}
    if (scene / "dataset.json").is_file():
        try:
            meta = json.loads((scene / "dataset.json").read_text())
        except json.JSONDecodeError:
            meta = {}
    return SceneData(root=scene, light=light, train=train, test=test, background=torch.from_numpy(bg).to(device),
                     center=center.to(device), extent=extent, static=len(times) == 1, meta=meta)
