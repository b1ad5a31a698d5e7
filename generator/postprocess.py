"""Ground-truth pass (multilayer EXR) -> the dataset's albedo/roughness/normal/dynamic_mask files.

Works from the EXR file alone (OpenEXR), never from Blender state, so it can be tested and re-run
without bpy. Cycles accumulates AOVs and normals over the samples that hit a surface, so a pixel's
value is (coverage x surface value); dividing by the pass's alpha (coverage) restores the surface
value at silhouette pixels. The dynamic mask keeps its coverage meaning (fraction of the pixel covered
by moving objects), so it is not divided.
"""
from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np

from lumibench.color import linear_to_srgb
from lumibench import layout
from lumibench.io import atomic_path, write_png

ALPHA_EPS = 1e-4  # below this coverage a pixel is background: its GT values are 0
_COMPONENTS = {4: "RGBA", 3: "RGB"}


def read_exr_layers(path: str | Path) -> dict[str, np.ndarray]:
    """All channels of a (multi-part, multilayer) EXR as {"<pass>.<component>": H x W float32}.

    The view-layer prefix Blender writes ("ViewLayer.") is dropped, so a pass reads "albedo.R",
    "Normal.X", "Combined.A", "roughness.X".
    """
    import OpenEXR

    out: dict[str, np.ndarray] = {}
    with OpenEXR.File(str(path)) as f:
        for part in f.parts:
            for name, ch in part.channels.items():
                px = np.asarray(ch.pixels, dtype=np.float32)
                parts = name.split(".")
                if px.ndim == 3:  # grouped RGB(A): "ViewLayer.Combined"
                    short = ".".join(parts[1:]) if len(parts) >= 2 else name
                    comps = _COMPONENTS.get(px.shape[2], "".join(str(i) for i in range(px.shape[2])))
                    for i, c in enumerate(comps):
                        out[f"{short}.{c}"] = px[..., i]
                else:  # one channel: "ViewLayer.Normal.X"
                    out[".".join(parts[1:]) if len(parts) >= 3 else name] = px
    return out


def ground_truth_arrays(layers: dict[str, np.ndarray], aov_albedo: str = "albedo", aov_roughness: str = "roughness",
                        aov_dynamic: str = "dynamic") -> dict[str, np.ndarray]:
    """Normalised GT arrays: alpha, albedo (linear RGB), roughness, normal (unit, world), dynamic_mask."""
    def need(name: str) -> np.ndarray:
        if name not in layers:
            raise KeyError(f"ground-truth EXR lacks the '{name}' channel (has: {', '.join(sorted(layers))})")
        return layers[name]

    alpha = np.clip(need("Combined.A"), 0.0, 1.0)
    fg = alpha > ALPHA_EPS
    inv = np.where(fg, 1.0 / np.where(fg, alpha, 1.0), 0.0).astype(np.float32)[..., None]

    albedo = np.stack([need(f"{aov_albedo}.{c}") for c in "RGB"], axis=-1) * inv
    rough = need(f"{aov_roughness}.X")[..., None] * inv
    normal = np.stack([need(f"Normal.{c}") for c in "XYZ"], axis=-1) * inv
    norm = np.linalg.norm(normal, axis=-1, keepdims=True)
    normal = np.where(norm > 1e-6, normal / np.maximum(norm, 1e-6), 0.0)
    dyn = need(f"{aov_dynamic}.X")[..., None]
    return {
        "alpha": alpha[..., None].astype(np.float32),
        "albedo": np.clip(albedo, 0.0, 1.0).astype(np.float32),
        "roughness": np.clip(rough, 0.0, 1.0).astype(np.float32),
        "normal": normal.astype(np.float32),
        "dynamic_mask": np.clip(dyn, 0.0, 1.0).astype(np.float32),
    }


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 transfer function, for values clipped to [0, 1] (float64)."""
    return linear_to_srgb(np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0))


def write_npz(path: str | Path, name: str, array: np.ndarray) -> None:
    """One array in a compressed .npz, byte-for-byte reproducible (numpy's savez stamps the time)."""
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.ascontiguousarray(array), allow_pickle=False)
    info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
    info.compress_type = zipfile.ZIP_DEFLATED
    info.external_attr = 0o644 << 16
    with atomic_path(path) as tmp:
        with zipfile.ZipFile(tmp, "w") as zf:
            zf.writestr(info, buf.getvalue(), compresslevel=6)


def write_ground_truth(gt: dict[str, np.ndarray], scene_dir: Path, file_path: str) -> list[Path]:
    """PNG (for eyes and 8-bit readers) + NPZ (exact float) per kind; returns the written paths."""
    alpha = gt["alpha"]
    pngs = {
        "albedo": np.concatenate([srgb_encode(gt["albedo"]), alpha], axis=-1),
        "roughness": gt["roughness"],
        "normal": np.concatenate([(gt["normal"] + 1.0) * 0.5 * (alpha > ALPHA_EPS), alpha], axis=-1),
        "dynamic_mask": gt["dynamic_mask"],
    }
    written = []
    for kind in layout.GT_KINDS:
        npz = layout.gt_path(scene_dir, kind, file_path, ".npz")
        write_npz(npz, kind, gt[kind])
        png = layout.gt_path(scene_dir, kind, file_path, ".png")
        write_png(png, pngs[kind])
        written += [npz, png]
    return written


def exr_to_ground_truth(exr: str | Path, scene_dir: Path, file_path: str) -> dict[str, np.ndarray]:
    gt = ground_truth_arrays(read_exr_layers(exr))
    write_ground_truth(gt, scene_dir, file_path)
    return gt
