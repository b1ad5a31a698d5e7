"""The dataset layout: the one contract between generator, method and benchmark.

    DATA/PROFILE/<scene>/                       dynamic variant (one camera per timestep)
      transforms_train.json, transforms_test.json
          {"camera_angle_x": float, "frames": [{"file_path": "train/r_0000",
           "transform_matrix": 4x4 OpenGL camera-to-world, "time": float in [0, 1]}]}
      <light>/<split>/r_NNNN.png      RGBA, sRGB ("Standard" view transform), alpha = coverage
      albedo/<split>/r_NNNN.png       base colour, sRGB-encoded 8-bit   (+ r_NNNN.npz: linear float32 H x W x 3)
      roughness/<split>/r_NNNN.png    linear 8-bit                      (+ .npz: float32 H x W x 1)
      normal/<split>/r_NNNN.png       world-space, (n + 1) / 2          (+ .npz: float32 H x W x 3, unit)
      dynamic_mask/<split>/r_NNNN.png coverage of what moves: the parts of moving objects that move at some
                                      time of the sequence (standup's planted feet are 0)  (+ .npz: float32 H x W x 1)
      <light>.hdr, <light>.png        the env map exactly as rendered (32 x 16, or the light's resolution), and a preview
      dataset.json                    spec hash, Blender version, seed, profile, timings; "complete": true
                                      is written last, so a scene without it is unfinished
    DATA/PROFILE/<scene>_statictimestepNNNN/    static variant: same layout, all cameras at timestep NNNN

Splits: `train` (the dynamic cameras, time = i / (N - 1)) and `test` (novel cameras at the static
timestep, rendered under every light). The npz files hold one array each; values of AOVs are
normalised by alpha (coverage) so that edge pixels carry the surface value, not a blend with black.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import UserError

SPLITS = ("train", "test")
GT_KINDS = ("albedo", "roughness", "normal", "dynamic_mask")


def scene_dir(data: str | Path, profile: str, scene: str) -> Path:
    return Path(data) / profile / scene


def static_scene_name(scene: str, timestep: int) -> str:
    return f"{scene}_statictimestep{timestep:04d}"


def frame_stem(index: int) -> str:
    return f"r_{index:04d}"


def file_path(split: str, index: int) -> str:
    return f"{split}/{frame_stem(index)}"


def lit_image_path(scene: Path, light: str, file_path_: str) -> Path:
    return Path(scene) / light / f"{file_path_}.png"


def gt_path(scene: Path, kind: str, file_path_: str, ext: str = ".png") -> Path:
    if kind not in GT_KINDS:
        raise ValueError(f"unknown ground-truth kind {kind!r}")
    return Path(scene) / kind / f"{file_path_}{ext}"


def envmap_path(scene: Path, light: str) -> Path:
    return Path(scene) / f"{light}.hdr"


LIGHT_FILE_SUFFIXES = (".hdr", ".exr")


def parse_light(spec: str | Path) -> tuple[str, Path | None]:
    """A light as a user gives it -> (its name, its env-map file, or None for a light given by name).

    A light is a name (configs/lights.yaml, a folder of the dataset) or a path to an .hdr/.exr file (anything
    with a path separator or that suffix). A file is named by its stem everywhere: the dataset's
    ``<light>/`` folder, run and result paths, tables, logs; so a path never becomes part of an output path.
    """
    text = str(spec)
    if not (text.lower().endswith(LIGHT_FILE_SUFFIXES) or "/" in text or "\\" in text):
        return text, None
    path = Path(text).expanduser()
    if path.suffix.lower() not in LIGHT_FILE_SUFFIXES:
        raise UserError(f"light file {path}: unsupported format '{path.suffix}' (use .hdr or .exr)")
    if path.stem.startswith(".") or "\\" in path.stem:
        raise UserError(f"light file {path}: its name '{path.stem}' cannot name a light folder; rename the file")
    return path.stem, path


@dataclass(frozen=True)
class Frame:
    file_path: str
    c2w: np.ndarray  # 4 x 4, OpenGL convention (camera looks down -z, +y up)
    time: float

    @property
    def stem(self) -> str:
        return Path(self.file_path).name


@dataclass(frozen=True)
class Transforms:
    camera_angle_x: float
    frames: list[Frame]

    def focal(self, width: int) -> float:
        """Focal length in pixels for an image ``width`` pixels wide."""
        return 0.5 * width / math.tan(0.5 * self.camera_angle_x)


def read_transforms(scene: str | Path, split: str) -> Transforms:
    path = Path(scene) / f"transforms_{split}.json"
    if not path.is_file():
        raise UserError(f"missing {path}: is this a rendered scene directory? (make dataset)")
    try:
        raw = json.loads(path.read_text())
        frames = [
            Frame(str(f["file_path"]), np.asarray(f["transform_matrix"], dtype=np.float64), float(f.get("time", 0.0)))
            for f in raw["frames"]
        ]
        angle = float(raw["camera_angle_x"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise UserError(f"{path}: corrupt transforms file ({type(exc).__name__}: {exc})") from None
    for f in frames:
        if f.c2w.shape != (4, 4):
            raise UserError(f"{path}: frame {f.file_path} has a transform_matrix of shape {f.c2w.shape}")
    return Transforms(angle, frames)


def is_complete(scene: str | Path) -> bool:
    meta = Path(scene) / "dataset.json"
    if not meta.is_file():
        return False
    try:
        return bool(json.loads(meta.read_text()).get("complete"))
    except json.JSONDecodeError:
        return False
