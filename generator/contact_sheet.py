"""A contact sheet of a rendered scene: a few frames x (lit under each light, albedo, roughness, normal, mask).

Read from the dataset files alone, so it shows exactly what the method and the benchmark will read.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from lumibench import layout
from lumibench.errors import UserError
from lumibench.io import atomic_path, read_image

GT_COLUMNS = (("albedo", "albedo"), ("roughness", "roughness"), ("normal", "normal"), ("dynamic_mask", "dynamic mask"))


def _over_grey(rgba: np.ndarray, grey: float = 0.5) -> np.ndarray:
    """RGBA (straight alpha) over a flat grey, so coverage and silhouettes are visible."""
    if rgba.shape[-1] == 1:
        return np.repeat(rgba, 3, axis=-1)
    rgb = rgba[..., :3]
    if rgba.shape[-1] < 4:
        return rgb
    a = rgba[..., 3:4]
    return rgb * a + grey * (1.0 - a)


def pick_frames(n: int, k: int = 4) -> list[int]:
    """``k`` frame indices spread over ``n`` (first and last included)."""
    if n <= k:
        return list(range(n))
    return sorted({int(round(i * (n - 1) / (k - 1))) for i in range(k)})


def lights_of(scene_dir: Path) -> list[str]:
    return sorted(p.stem for p in Path(scene_dir).glob("*.hdr") if (Path(scene_dir) / p.stem).is_dir())


def make_contact_sheet(scene_dir: str | Path, out: str | Path, n_frames: int = 4, split: str = "train") -> Path:
    """Write the sheet as a PNG; rows are frames (with their time), columns the images of each frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scene_dir, out = Path(scene_dir), Path(out)
    frames = layout.read_transforms(scene_dir, split).frames
    if not frames:
        raise UserError(f"{scene_dir}: no {split} frames to show")
    light_names = lights_of(scene_dir)
    rows = [frames[i] for i in pick_frames(len(frames), n_frames)]
    cols = [(f"lit: {n}", "lit", n) for n in light_names] + [(title, "gt", kind) for kind, title in GT_COLUMNS]
    fig, axes = plt.subplots(len(rows), len(cols), figsize=(1.6 * len(cols), 1.7 * len(rows)), squeeze=False)
    for r, frame in enumerate(rows):
        for c, (title, what, name) in enumerate(cols):
            path = (layout.lit_image_path(scene_dir, name, frame.file_path) if what == "lit"
                    else layout.gt_path(scene_dir, name, frame.file_path))
            img = _over_grey(read_image(path))
            ax = axes[r][c]
            ax.imshow(np.clip(img, 0, 1), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(title, fontsize=8)
            if c == 0:
                ax.set_ylabel(f"{frame.stem}\nt={frame.time:.2f}", fontsize=8)
    fig.suptitle(f"{scene_dir.parent.name}/{scene_dir.name}", fontsize=9)
    fig.tight_layout()
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return out
