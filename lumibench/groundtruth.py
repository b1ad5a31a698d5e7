"""Reading a scene's ground truth and lit images (the data contract, beside lumibench/layout.py):
what adapters, the method and the benchmark all read, with one decoding rule."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from lumibench import layout
from lumibench.io import read_image
from lumibench.predictions import srgb_decode


def read_gt(scene: Path, kind: str, file_path: str) -> np.ndarray:
    """Ground truth of ``kind``: the float .npz when the generator wrote one, else the PNG (decoded).

    Albedo comes back linear; roughness and dynamic_mask one channel; normals unit vectors.
    """
    npz = layout.gt_path(scene, kind, file_path, ".npz")
    if npz.is_file():
        img = read_image(npz)
        encoded = False
    else:
        img = read_image(layout.gt_path(scene, kind, file_path, ".png"))
        encoded = True
    if kind == "albedo":
        rgb = img[..., :3] if img.shape[-1] >= 3 else np.repeat(img[..., :1], 3, -1)
        return srgb_decode(rgb) if encoded else rgb
    if kind == "normal":
        rgb = img[..., :3]
        return rgb * 2.0 - 1.0 if encoded else rgb
    return img[..., :1]


def read_lit(scene: Path, light: str, file_path: str) -> tuple[np.ndarray, np.ndarray]:
    """(RGB in display space, alpha H x W x 1) of a rendered view."""
    img = read_image(layout.lit_image_path(scene, light, file_path))
    alpha = img[..., 3:4] if img.shape[-1] >= 4 else np.ones_like(img[..., :1])
    rgb = img[..., :3] if img.shape[-1] >= 3 else np.repeat(img[..., :1], 3, -1)
    return rgb, alpha
