"""Atomic writes and image reading: nothing half-written is ever mistaken for complete."""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from .errors import UserError


_UMASK = os.umask(0)
os.umask(_UMASK)


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it over ``path`` only if the block succeeds.

    The temporary name keeps the file's suffix (writers pick the format from it) and starts with
    ``.tmp-`` so that a crash leaves a file no reader takes for a finished one.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".tmp-{path.stem}-", suffix=suffix or path.suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp creates 0600; finished files get the usual mode
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())


def atomic_write_text(path: str | Path, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | Path, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n")


def _json_default(obj: Any) -> Any:
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def sha256_file(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_json(path: str | Path) -> Any:
    path = Path(path)
    if not path.is_file():
        raise UserError(f"file not found: {path}")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: corrupt JSON ({exc})") from None


def read_image(path: str | Path) -> np.ndarray:
    """Read PNG/JPEG (-> float32 in [0, 1]), EXR or NPZ (-> float32 as stored), as H x W x C.

    Any unreadable file raises a UserError that names it.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"image not found: {path}")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npz":
            with np.load(path) as z:
                if len(z.files) != 1:
                    raise ValueError(f"expected one array, found {z.files}")
                arr = np.asarray(z[z.files[0]], dtype=np.float32)
        elif suffix == ".npy":
            arr = np.load(path).astype(np.float32)
        elif suffix == ".exr":
            arr = _read_exr(path)
        else:
            import imageio.v3 as iio

            raw = iio.imread(path)
            if raw.dtype == np.uint8:
                arr = raw.astype(np.float32) / 255.0
            elif raw.dtype == np.uint16:
                arr = raw.astype(np.float32) / 65535.0
            else:
                arr = raw.astype(np.float32)
    except UserError:
        raise
    except Exception as exc:  # any decoder failure means a corrupt or truncated file
        detail = (str(exc).strip().splitlines() or [""])[0]
        raise UserError(f"cannot read image {path}: {type(exc).__name__}: {detail}") from None
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3:
        raise UserError(f"image {path} has shape {arr.shape}; expected H x W x C")
    return arr


def _read_exr(path: Path) -> np.ndarray:
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        channels = f.channels()
        names = list(channels.keys())
        if len(names) == 1 and channels[names[0]].pixels.ndim == 3:
            return np.asarray(channels[names[0]].pixels, dtype=np.float32)
        order = [c for c in ("R", "G", "B", "A") if c in channels] or sorted(names)
        return np.stack([np.asarray(channels[c].pixels, dtype=np.float32) for c in order], axis=-1)


def write_png(path: str | Path, image: np.ndarray) -> None:
    """Write a float image in [0, 1] (H x W or H x W x C) as 8-bit PNG, atomically."""
    import imageio.v3 as iio

    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if img.ndim == 3 and img.shape[-1] == 1:
        img = img[..., 0]
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, img, extension=".png")
