"""Equirectangular environment maps in Blender's world convention: read, write, rotate, downsample.

The one convention everything shares (renderer, dataset files, the method's relighting) is Cycles'
``direction_to_equirectangular`` for the Environment Texture node with its default vector (the world
direction d = (x, y, z), +Z up):

    u = 0.5 - atan2(y, x) / (2 pi)        v = 1 - acos(z) / pi        (u, v in [0, 1], v = 1 at +Z)

Arrays here are stored top row first (as in the files), so texel (row r, column c) covers
v in [1 - (r + 1) / H, 1 - r / H] and u in [c / W, (c + 1) / W]: the image centre column looks along +X,
the quarter column (u = 0.25) along +Y, the left edge along -X.

numpy only: no bpy here, so the method and the benchmark can use the same functions.
"""
from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from lumibench.color import linear_to_srgb
from lumibench.errors import UserError
from lumibench.io import atomic_path, read_image, write_png

__all__ = [
    "read_envmap", "write_hdr", "downsample_envmap", "rotate_envmap", "direction_to_uv", "uv_to_direction",
    "texel_of_direction", "texel_directions", "solid_angles", "mean_radiance", "brightest_direction",
    "preview_png",
]


# ----------------------------------------------------------------------------------------------- mapping

def direction_to_uv(dirs) -> tuple[np.ndarray, np.ndarray]:
    """World directions (..., 3), any length > 0 -> (u, v) in Blender's equirectangular mapping."""
    d = np.asarray(dirs, dtype=np.float64)
    if d.shape[-1] != 3:
        raise ValueError(f"directions must have a last axis of 3, got shape {d.shape}")
    n = np.linalg.norm(d, axis=-1)
    n = np.where(n > 0, n, 1.0)
    u = np.mod(0.5 - np.arctan2(d[..., 1], d[..., 0]) / (2.0 * math.pi), 1.0)
    v = 1.0 - np.arccos(np.clip(d[..., 2] / n, -1.0, 1.0)) / math.pi
    return u, v


def uv_to_direction(u, v) -> np.ndarray:
    """(u, v) in [0, 1] -> unit world directions (..., 3); the inverse of ``direction_to_uv``."""
    u, v = np.broadcast_arrays(np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64))
    phi = math.pi * (1.0 - 2.0 * u)
    theta = math.pi * (1.0 - v)
    s = np.sin(theta)
    return np.stack([s * np.cos(phi), s * np.sin(phi), np.cos(theta)], axis=-1)


def texel_of_direction(dirs, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(row from top, column) of the texel a 'Closest' lookup picks for each direction."""
    u, v = direction_to_uv(dirs)
    col = np.mod(np.floor(u * width).astype(np.int64), width)
    row_from_bottom = np.clip(np.floor(v * height).astype(np.int64), 0, height - 1)
    return height - 1 - row_from_bottom, col


def texel_directions(height: int, width: int) -> np.ndarray:
    """Unit direction through the centre of every texel, H x W x 3 (row 0 = top)."""
    v = 1.0 - (np.arange(height) + 0.5) / height
    u = (np.arange(width) + 0.5) / width
    return uv_to_direction(u[None, :], v[:, None])


def solid_angles(height: int, width: int) -> np.ndarray:
    """Exact solid angle of every texel, H x W (sums to 4 pi): (cos theta_top - cos theta_bottom) 2 pi / W."""
    theta = np.linspace(0.0, math.pi, height + 1)
    band = np.cos(theta[:-1]) - np.cos(theta[1:])
    return np.repeat((band * (2.0 * math.pi / width))[:, None], width, axis=1)


def mean_radiance(img: np.ndarray) -> np.ndarray:
    """Solid-angle-weighted mean radiance per channel (the quantity downsampling must preserve)."""
    img = np.asarray(img, dtype=np.float64)
    w = solid_angles(img.shape[0], img.shape[1])
    return np.tensordot(w, img, axes=([0, 1], [0, 1])) / (4.0 * math.pi)


def brightest_direction(img: np.ndarray) -> tuple[float, float]:
    """(azimuth phi = atan2(y, x), elevation) in degrees of the texel with the largest luminance."""
    lum = _luminance(np.asarray(img, dtype=np.float64))
    r, c = np.unravel_index(int(np.argmax(lum)), lum.shape)
    d = texel_directions(img.shape[0], img.shape[1])[r, c]
    return math.degrees(math.atan2(d[1], d[0])), math.degrees(math.asin(np.clip(d[2], -1.0, 1.0)))


def _luminance(img: np.ndarray) -> np.ndarray:
    return img[..., 0] * 0.2126 + img[..., 1] * 0.7152 + img[..., 2] * 0.0722


# ---------------------------------------------------------------------------------------- resampling

def _overlap(n_src: int, n_dst: int) -> np.ndarray:
    """n_dst x n_src lengths of overlap (in units of the [0, 1] axis) of source and target cells."""
    src = np.linspace(0.0, 1.0, n_src + 1)
    dst = np.linspace(0.0, 1.0, n_dst + 1)
    lo = np.maximum(dst[:-1, None], src[None, :-1])
    hi = np.minimum(dst[1:, None], src[None, 1:])
    return np.clip(hi - lo, 0.0, None)


def _row_weights(n_src: int, n_dst: int) -> np.ndarray:
    """n_dst x n_src solid-angle factor of (source row intersected with target row): cos(a) - cos(b)."""
    src = np.linspace(0.0, math.pi, n_src + 1)
    dst = np.linspace(0.0, math.pi, n_dst + 1)
    lo = np.maximum(dst[:-1, None], src[None, :-1])
    hi = np.minimum(dst[1:, None], src[None, 1:])
    hi = np.maximum(hi, lo)
    return np.cos(lo) - np.cos(hi)


def downsample_envmap(img: np.ndarray, width: int = 32, height: int = 16) -> np.ndarray:
    """Area-weighted block average to height x width that preserves the solid-angle-weighted mean.

    Every target texel is the solid-angle-weighted mean of the source texels (and fractions of texels,
    when the sizes are not multiples) it covers, so sum(Omega * L) is the same before and after: the
    total light, hence the irradiance a diffuse surface receives from each region, is kept.
    """
    img = np.asarray(img, dtype=np.float32)
    if img.ndim != 3 or img.shape[0] < 1 or img.shape[1] < 1:
        raise ValueError(f"expected an H x W x C image, got shape {img.shape}")
    if width < 1 or height < 1:
        raise ValueError(f"target size must be positive, got {width} x {height}")
    if img.shape[0] == height and img.shape[1] == width:
        return img.copy()
    wr = _row_weights(img.shape[0], height)
    wc = _overlap(img.shape[1], width)
    rows = np.einsum("jr,rcx->jcx", wr, img.astype(np.float64), optimize=True)
    out = np.einsum("kc,jcx->jkx", wc, rows, optimize=True)
    out /= wr.sum(axis=1)[:, None, None] * wc.sum(axis=1)[None, :, None]
    return out.astype(np.float32)


def rotate_envmap(img: np.ndarray, degrees: float) -> np.ndarray:
    """Rotate about world +Z: a feature at azimuth phi = atan2(y, x) moves to phi + degrees.

    Columns run towards decreasing phi, so this is a cyclic shift of the columns by -degrees / 360 * W,
    linearly interpolated in longitude for fractional shifts. Apply at source resolution.
    """
    img = np.asarray(img, dtype=np.float32)
    w = img.shape[1]
    shift = (float(degrees) / 360.0) * w  # new[:, c] = old[:, c + shift]
    if shift == 0.0:
        return img.copy()
    base = math.floor(shift)
    frac = shift - base
    cols = (np.arange(w) + base) % w
    out = img[:, cols].astype(np.float64)
    if frac > 1e-12:
        out = (1.0 - frac) * out + frac * img[:, (cols + 1) % w]
    return out.astype(np.float32)


# -------------------------------------------------------------------------------------- file formats

def read_envmap(path: str | Path) -> np.ndarray:
    """Read an .hdr (Radiance RGBE) or .exr map as float32 H x W x 3 linear radiance.

    Non-finite values make the file unusable (UserError); small negative values (resampling ringing
    in some EXRs) are clamped to 0 because radiance cannot be negative.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"environment map not found: {path}")
    suffix = path.suffix.lower()
    if suffix == ".hdr":
        img = _read_hdr(path)
    elif suffix == ".exr":
        img = read_image(path)
        if img.shape[2] == 1:
            img = np.repeat(img, 3, axis=2)
        elif img.shape[2] < 3:
            raise UserError(f"environment map {path} has {img.shape[2]} channels; expected RGB")
        img = img[..., :3]
    else:
        raise UserError(f"environment map {path}: unsupported format '{path.suffix}' (use .hdr or .exr)")
    img = np.ascontiguousarray(img, dtype=np.float32)
    if not np.all(np.isfinite(img)):
        raise UserError(f"environment map {path} contains NaN or infinite values")
    return np.maximum(img, 0.0)


_RES_RE = re.compile(rb"^([-+])Y\s+(\d+)\s+([-+])X\s+(\d+)\s*$")


def _read_hdr(path: Path) -> np.ndarray:
    data = path.read_bytes()
    try:
        return _decode_hdr(data)
    except _HdrError as exc:
        raise UserError(f"cannot read Radiance HDR {path}: {exc}") from None


class _HdrError(Exception):
    pass


def _decode_hdr(data: bytes) -> np.ndarray:
    if not (data.startswith(b"#?RADIANCE") or data.startswith(b"#?RGBE")):
        raise _HdrError("missing '#?RADIANCE' signature")
    pos = 0
    fmt = None
    while True:  # header lines until an empty line
        end = data.find(b"\n", pos)
        if end < 0:
            raise _HdrError("truncated header")
        line = data[pos:end].strip()
        pos = end + 1
        if not line:
            break
        if line.startswith(b"FORMAT="):
            fmt = line[len(b"FORMAT="):].strip()
    if fmt is not None and fmt != b"32-bit_rle_rgbe":
        raise _HdrError(f"unsupported pixel format {fmt.decode(errors='replace')!r} (only 32-bit_rle_rgbe)")
    end = data.find(b"\n", pos)
    if end < 0:
        raise _HdrError("missing resolution line")
    m = _RES_RE.match(data[pos:end].strip())
    if not m or m.group(3) != b"+":
        raise _HdrError(f"unsupported resolution line {data[pos:end][:40]!r} (expected '-Y H +X W')")
    flip = m.group(1) == b"+"
    height, width = int(m.group(2)), int(m.group(4))
    if height <= 0 or width <= 0:
        raise _HdrError(f"bad size {width} x {height}")
    pos = end + 1
    rgbe = _decode_pixels(data, pos, width, height)
    img = _rgbe_to_float(rgbe)
    return img[::-1].copy() if flip else img


def _decode_pixels(data: bytes, pos: int, width: int, height: int) -> np.ndarray:
    """Scanlines -> H x W x 4 uint8 RGBE; new-style RLE, flat, and old-style (1,1,1,n) runs."""
    n = len(data)
    new_rle = 8 <= width < 32768 and pos + 4 <= n and data[pos] == 2 and data[pos + 1] == 2 and data[pos + 2] < 128
    if not new_rle:
        return _decode_flat(data, pos, width, height)
    out = np.empty((height, width, 4), dtype=np.uint8)
    buf = memoryview(data)
    for y in range(height):
        if pos + 4 > n:
            raise _HdrError(f"truncated at scanline {y}")
        if data[pos] != 2 or data[pos + 1] != 2 or ((data[pos + 2] << 8) | data[pos + 3]) != width:
            raise _HdrError(f"corrupt run-length header at scanline {y}")
        pos += 4
        for ch in range(4):
            x = 0
            row = out[y, :, ch]
            while x < width:
                if pos >= n:
                    raise _HdrError(f"truncated at scanline {y}")
                count = data[pos]
                pos += 1
                if count > 128:
                    count -= 128
                    if x + count > width or pos >= n:
                        raise _HdrError(f"bad run at scanline {y}")
                    row[x:x + count] = data[pos]
                    pos += 1
                else:
                    if count == 0 or x + count > width or pos + count > n:
                        raise _HdrError(f"bad literal run at scanline {y}")
                    row[x:x + count] = np.frombuffer(buf[pos:pos + count], dtype=np.uint8)
                    pos += count
                x += count
    return out


def _decode_flat(data: bytes, pos: int, width: int, height: int) -> np.ndarray:
    total = width * height
    raw = np.frombuffer(data, dtype=np.uint8, count=(len(data) - pos) // 4 * 4, offset=pos).reshape(-1, 4)
    old_runs = (raw[:, 0] == 1) & (raw[:, 1] == 1) & (raw[:, 2] == 1)
    if not old_runs.any():
        if raw.shape[0] < total:
            raise _HdrError(f"truncated: {raw.shape[0]} of {total} pixels")
        return raw[:total].reshape(height, width, 4).copy()
    out = np.empty((total, 4), dtype=np.uint8)  # old-style RLE: (1,1,1,n) repeats the previous pixel
    i = 0
    shift = 0
    for px in raw:
        if i >= total:
            break
        if px[0] == 1 and px[1] == 1 and px[2] == 1:
            if i == 0:
                raise _HdrError("run before the first pixel")
            count = int(px[3]) << shift
            if i + count > total:
                raise _HdrError("run past the end of the image")
            out[i:i + count] = out[i - 1]
            i += count
            shift += 8
        else:
            out[i] = px
            i += 1
            shift = 0
    if i < total:
        raise _HdrError(f"truncated: {i} of {total} pixels")
    return out.reshape(height, width, 4)


def _rgbe_to_float(rgbe: np.ndarray) -> np.ndarray:
    """mantissa * 2^(e - 136), zero when e == 0: the decoding Blender (OpenImageIO) applies when it
    renders with the file, so the method reads exactly the radiance the dataset was lit by (Radiance's
    own tools add half a step to the mantissa; we deliberately do not)."""
    e = rgbe[..., 3].astype(np.int32)
    scale = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0)
    return (rgbe[..., :3].astype(np.float64) * scale[..., None]).astype(np.float32)


def _float_to_rgbe(img: np.ndarray) -> np.ndarray:
    """Shared exponent of the largest channel, mantissas rounded to nearest (error <= half a step)."""
    img = np.maximum(np.asarray(img, dtype=np.float64), 0.0)
    v = img.max(axis=-1)
    ok = v >= 1e-32
    _, exp = np.frexp(np.where(ok, v, 1.0))  # v = m 2^exp, m in [0.5, 1): largest mantissa byte in [128, 256)
    exp = np.where(np.round(np.ldexp(np.where(ok, v, 0.0), 8 - exp)) >= 256, exp + 1, exp)
    ok &= exp + 128 >= 1
    exp = np.clip(exp, -127, 127)
    mant = np.round(np.ldexp(img, (8 - exp)[..., None]))
    out = np.zeros(img.shape[:-1] + (4,), dtype=np.uint8)
    out[..., :3] = np.where(ok[..., None], np.clip(mant, 0, 255), 0).astype(np.uint8)
    out[..., 3] = np.where(ok, exp + 128, 0).astype(np.uint8)
    return out


def write_hdr(path: str | Path, img: np.ndarray) -> None:
    """Write float H x W x 3 radiance as Radiance RGBE (.hdr), atomically.

    Widths 8..32767 use new-style run-length scanlines (literal runs only): a flat scanline whose first
    pixel happens to read (2, 2, x < 128, .) would be mistaken for a run-length header by every reader.
    """
    img = np.asarray(img, dtype=np.float32)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"expected an H x W x 3 image, got shape {img.shape}")
    if not np.all(np.isfinite(img)):
        raise ValueError("refusing to write NaN or infinite radiance")
    h, w = img.shape[:2]
    rgbe = _float_to_rgbe(img)
    parts = [b"#?RADIANCE\n# written by lumibench\nFORMAT=32-bit_rle_rgbe\n\n", f"-Y {h} +X {w}\n".encode()]
    if 8 <= w < 32768:
        for y in range(h):
            parts.append(bytes((2, 2, w >> 8, w & 255)))
            for ch in range(4):
                chan = rgbe[y, :, ch].tobytes()
                for x in range(0, w, 128):
                    chunk = chan[x:x + 128]
                    parts.append(bytes((len(chunk),)) + chunk)
    else:
        parts.append(rgbe.tobytes())
    with atomic_path(path) as tmp:
        tmp.write_bytes(b"".join(parts))


def preview_png(path: str | Path, img: np.ndarray, min_width: int = 256) -> None:
    """Tone-mapped sRGB preview (exposure to a mid-grey mean, Reinhard), upscaled with nearest texels."""
    img = np.asarray(img, dtype=np.float64)
    lum = _luminance(img)
    key = float(np.exp(np.mean(np.log(lum + 1e-6))))
    x = img * (0.18 / max(key, 1e-6))
    x = x / (1.0 + _luminance(x)[..., None])
    srgb = linear_to_srgb(x)
    k = max(1, int(math.ceil(min_width / img.shape[1])))
    srgb = np.repeat(np.repeat(srgb, k, axis=0), k, axis=1)
    write_png(path, np.clip(srgb, 0.0, 1.0))
