"""The predictions layout: what a method writes so that `python -m benchmark score` can score it.

Part of the data contract (beside lumibench/layout.py): adapters write it, the benchmark reads it, and
neither needs the other's code.

One folder per (method, scene, train light, seed); file stems are those of the scene's test split
(``r_NNNN`` from ``transforms_test.json``), train-split stems for the optional P maps::

    PRED/
      meta.json                      method, version, seed, device, timings, model size (see below)
      nvs/r_NNNN.<ext>               RGB of the test view under the TRAIN light
      albedo/r_NNNN.<ext>            base colour
      roughness/r_NNNN.<ext>         roughness in [0, 1] (one channel; extra channels ignored)
      normal/r_NNNN.<ext>            world-space normal (optional; PNG stores (n + 1) / 2, float stores n)
      relight/<test light>/r_NNNN.<ext>   RGB of the test view relit under each test light
      relight_scaled/<test light>/r_NNNN.<ext>   optional: the same relit with the albedo scaled per channel
                                     before shading by the benchmark's albedo alignment (the authors' rule:
                                     median GT / predicted linear albedo over the foreground of all test
                                     views); scored instead of relight/ under the `lumimotion` protocol
      p_map/train/r_NNNN.<ext>       optional: per-pixel dynamic probability P in [0, 1] of train views
      envmap/<train light>.<ext>     optional: the estimated environment map (linear, equirectangular)

``<ext>`` is ``png`` (8/16-bit, **sRGB-encoded** for albedo and the RGB images, as the ground truth
PNGs), or ``exr`` / ``npz`` (float32, **linear** for albedo and the RGB images; the scorer encodes them
with the sRGB transfer function and clips to [0, 1], as Blender's "Standard" view transform does).
Roughness, normals and P are linear in every format. A fourth (alpha) channel is ignored: the protocol
masks with the ground-truth alpha. Components are optional per kind (a method without NVS gets no NVS
score), but a kind that exists must have a file for every test view. Extensions match in any letter
case; a file in another format (JPEG is lossy and not read), an empty kind folder, or two files for one
view are errors, never skipped.

``meta.json``::

    {"method": str, "version": str, "seed": int, "device": str,
     "timings": {"<stage>": seconds, ...}, "iterations_per_s": float, "peak_memory_bytes": int,
     "model_size": {"gaussians": int, "parameters": int, "bytes": int},
     "relight_albedo_scale": [r, g, b]}   (with relight_scaled/: the per-channel scale it used)

Only ``method``, ``version`` and ``seed`` are required; every other key is reported when present.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lumibench.color import linear_to_srgb, srgb_to_linear
from lumibench.errors import UserError
from lumibench.io import atomic_write_json, read_image, read_json

KINDS = ("nvs", "albedo", "roughness", "normal", "relight", "relight_scaled", "p_map", "envmap")
EXTENSIONS = (".png", ".exr", ".npz")  # any letter case; nothing else is read (no lossy JPEG)
ENVMAP_EXTENSIONS = (".hdr", ".exr", ".npz", ".png")
# kinds whose PNG is display-encoded while float files are linear
COLOUR_KINDS = ("nvs", "albedo", "relight", "relight_scaled")
RELIGHT_KINDS = ("relight", "relight_scaled")  # one folder per test light


def srgb_encode(x: np.ndarray) -> np.ndarray:
    """Linear -> sRGB, clipped to [0, 1] first, as Blender's Standard view transform."""
    return np.asarray(linear_to_srgb(np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)), dtype=np.float32)


def srgb_decode(x: np.ndarray) -> np.ndarray:
    """sRGB -> linear (input clipped to [0, 1])."""
    return np.asarray(srgb_to_linear(np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)), dtype=np.float32)


def find_file(folder: Path, stem: str) -> Path | None:
    """The prediction file for ``stem`` in any accepted format, the extension in any letter case
    (``r_0000.PNG`` is read); two files for one stem (``.png`` and ``.exr``, or ``.png`` and ``.PNG``) are
    ambiguous."""
    if not Path(folder).is_dir():
        return None
    found = sorted(p for p in Path(folder).iterdir()
                   if p.stem == stem and p.suffix.lower() in EXTENSIONS and p.is_file())
    if len(found) > 1:
        raise UserError(f"ambiguous predictions: {', '.join(map(str, found))} (keep one file per view)")
    return found[0] if found else None


def is_float_file(path: Path) -> bool:
    return path.suffix.lower() in (".exr", ".npz", ".npy")


@dataclass(frozen=True)
class PredictionFolder:
    """Reads one predictions folder, checking shapes and naming the file on every failure."""

    root: Path

    def __post_init__(self):
        if not Path(self.root).is_dir():
            raise UserError(f"predictions folder not found: {self.root}")

    def meta(self) -> dict[str, Any]:
        path = Path(self.root) / "meta.json"
        meta = read_json(path)
        if not isinstance(meta, dict):
            raise UserError(f"{path}: must hold a JSON object")
        for key, typ in (("method", str), ("version", str), ("seed", int)):
            if not isinstance(meta.get(key), typ) or isinstance(meta.get(key), bool):
                raise UserError(f"{path}: field '{key}' is missing or not a {typ.__name__}")
        return meta

    def kind_dir(self, kind: str, light: str | None = None) -> Path:
        if kind in RELIGHT_KINDS:
            return Path(self.root) / kind / str(light)
        if kind == "p_map":
            return Path(self.root) / "p_map" / "train"
        return Path(self.root) / kind

    def check_files(self) -> None:
        """Refuse what scoring would otherwise pass over in silence: an empty kind folder, or files in a
        format it does not read (``.jpg``, ``.npy``, ...) in any kind folder. Hidden files are ignored."""
        root = Path(self.root)
        folders = [root / k for k in ("nvs", "albedo", "roughness", "normal")]
        for parent, what in ((root / "relight", "a folder per test light"),
                             (root / "relight_scaled", "a folder per test light"), (root / "p_map", "train/")):
            if not parent.is_dir():
                continue
            entries = _visible(parent)
            strays = [p.name for p in entries if not p.is_dir()]
            if strays:
                raise UserError(f"{parent}/ holds files ({_names(strays)}); it should hold {what} "
                                f"(layout: lumibench/predictions.py)")
            if not entries:
                raise UserError(f"empty predictions folder {parent}/: write the predictions into {what} "
                                "or remove the folder")
            folders += entries if parent.name in RELIGHT_KINDS else [parent / "train"]
        for folder, exts in [(f, EXTENSIONS) for f in folders] + [(root / "envmap", ENVMAP_EXTENSIONS)]:
            if not folder.is_dir():
                continue
            entries = _visible(folder)
            if not entries:
                raise UserError(f"empty predictions folder {folder}/: write one file per view "
                                f"({'/'.join(e.lstrip('.') for e in exts)}) or remove the folder")
            bad = [p.name for p in entries if not (p.is_file() and p.suffix.lower() in exts)]
            if bad:
                raise UserError(f"{folder}/ holds files the scorer does not read: {_names(bad)} (prediction files "
                                f"are {', '.join(exts)}; convert or remove the others)")

    def has(self, kind: str, light: str | None = None) -> bool:
        folder = self.kind_dir(kind, light)
        return folder.is_dir() and any(p.suffix.lower() in EXTENSIONS for p in folder.iterdir())

    def path(self, kind: str, stem: str, light: str | None = None) -> Path:
        folder = self.kind_dir(kind, light)
        found = find_file(folder, stem)
        if found is None:
            raise UserError(f"missing prediction file {folder / stem}.png (or .exr/.npz): "
                            f"the method wrote '{kind}' for some views but not for {stem}")
        return found

    def read(self, kind: str, stem: str, shape: tuple[int, int], light: str | None = None) -> np.ndarray:
        """One image as float32 H x W x C: RGB kinds in display (sRGB) space, others linear."""
        path = self.path(kind, stem, light)
        img = read_image(path)
        if img.shape[:2] != tuple(shape):
            raise UserError(f"prediction {path} is {img.shape[1]}x{img.shape[0]} pixels; "
                            f"the ground truth is {shape[1]}x{shape[0]}")
        if not np.all(np.isfinite(img)):
            raise UserError(f"prediction {path} contains NaN or infinite values")
        if kind in COLOUR_KINDS:
            img = _rgb(img, path)
            return srgb_encode(img) if is_float_file(path) else np.clip(img, 0.0, 1.0)
        if kind == "normal":
            img = _rgb(img, path)
            return img if is_float_file(path) else img * 2.0 - 1.0
        return np.clip(img[..., :1], 0.0, 1.0)  # roughness, p_map: one channel

    def envmap(self, light: str) -> np.ndarray | None:
        """The estimated env map (linear RGB) if the method wrote one."""
        folder = Path(self.root) / "envmap"
        if folder.is_dir():
            for path in sorted(folder.iterdir(), key=lambda p: _envmap_rank(p.suffix)):
                if path.stem != light or not path.is_file() or path.suffix.lower() not in ENVMAP_EXTENSIONS:
                    continue
                ext = path.suffix.lower()
                if ext == ".hdr":
                    from generator.envmap import read_envmap  # Radiance RGBE, which imageio cannot read

                    return read_envmap(path)
                img = _rgb(read_image(path), path)
                return srgb_decode(img) if ext == ".png" else img
        return None


def _envmap_rank(suffix: str) -> int:
    s = suffix.lower()
    return ENVMAP_EXTENSIONS.index(s) if s in ENVMAP_EXTENSIONS else len(ENVMAP_EXTENSIONS)


def _visible(folder: Path) -> list[Path]:
    return sorted(p for p in Path(folder).iterdir() if not p.name.startswith("."))


def _names(names: list[str], limit: int = 4) -> str:
    more = f" and {len(names) - limit} more" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


def _rgb(img: np.ndarray, path: Path) -> np.ndarray:
    if img.shape[-1] == 1:
        return np.repeat(img, 3, axis=-1)
    if img.shape[-1] < 3:
        raise UserError(f"prediction {path} has {img.shape[-1]} channels; expected RGB")
    return img[..., :3]


def write_meta(out_dir: Path, meta: dict[str, Any]) -> None:
    """Written last by adapters: a folder with meta.json is a finished prediction."""
    atomic_write_json(Path(out_dir) / "meta.json", meta)
