"""Environment maps as torch tensors (H, W, 3) of linear radiance, in the generator's convention.

Orientation (generator/envmap.py, i.e. Cycles' direction_to_equirectangular): a world direction
d = (x, y, z), +Z up, maps to u = 0.5 - atan2(y, x) / (2 pi), v = 1 - acos(z) / pi; rows are stored top
row first. Lookup is nearest-texel because the generator lights every scene with an Environment Texture
set to 'Closest' (generator/blender/world.py) at world strength 1, so the piecewise-constant map *is*
the radiance Blender rendered with; a bilinear lookup would shade the dataset with a different sky.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from generator import envmap as genv
from lumibench import layout
from lumibench.errors import UserError

DEFAULT_HEIGHT, DEFAULT_WIDTH = 16, 32


def direction_to_uv(dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(..., 3) world directions (any length > 0) -> (u, v) in [0, 1], Blender's mapping."""
    x, y, z = dirs.unbind(-1)
    u = torch.remainder(0.5 - torch.atan2(y, x) / (2.0 * math.pi), 1.0)
    v = 0.5 + torch.atan2(z, torch.sqrt(x * x + y * y)) / math.pi  # = 1 - acos(z / |d|) / pi, any |d|
    return u, v


def texel_index(dirs: torch.Tensor, height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(row from the top, column) of the texel a 'Closest' lookup returns for each direction."""
    u, v = direction_to_uv(dirs.detach())
    col = torch.floor(u * width).long().remainder(width)
    row_from_bottom = torch.floor(v * height).long().clamp(0, height - 1)
    return height - 1 - row_from_bottom, col


def lookup(env: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Radiance (..., 3) arriving from each direction (..., 3); differentiable w.r.t. ``env``."""
    h, w = env.shape[0], env.shape[1]
    row, col = texel_index(dirs, h, w)
    return env.reshape(h * w, -1)[row * w + col]


def texel_solid_angles(height: int, width: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """Exact solid angle of every texel, (H, W), summing to 4 pi."""
    theta = torch.linspace(0.0, math.pi, height + 1, dtype=torch.float64)
    band = (torch.cos(theta[:-1]) - torch.cos(theta[1:])) * (2.0 * math.pi / width)
    return band[:, None].expand(height, width).to(device=device, dtype=dtype)


def texel_moments(height: int, width: int, sub: int = 4, device=None, dtype=torch.float32) -> torch.Tensor:
    """(H * W, sub * sub, 3): the integral of the direction w over each of sub x sub equal-angle cells of
    every texel (row-major from the top-left, as ``lookup`` indexes), in closed form.

    Why: the cosine-weighted integral of a piecewise-constant map is sum_j env_j int_texel max(0, n.w) dw,
    and n . (integral of w over a cell) is that cell's exact cosine integral wherever the cell lies on one
    side of n's horizon; cutting texels into cells confines the clamp's error to the few cells that straddle
    it (render.py's control variate)."""
    k = torch.arange(height * sub + 1, dtype=torch.float64)
    theta = k * (math.pi / (height * sub))  # polar angle from +z; row 0 (top) starts at the zenith
    m = torch.arange(width * sub + 1, dtype=torch.float64)
    phi = math.pi - m * (2.0 * math.pi / (width * sub))  # u = 0.5 - phi / (2 pi): column 0 starts at phi = pi
    a, b = theta[:-1], theta[1:]
    s2 = (b - a) / 2 - (torch.sin(2 * b) - torch.sin(2 * a)) / 4  # int sin^2
    sc = (torch.sin(b) ** 2 - torch.sin(a) ** 2) / 2  # int sin cos
    p0, p1 = phi[:-1], phi[1:]  # p1 < p0
    cx = torch.sin(p0) - torch.sin(p1)  # int over [p1, p0] of cos
    cy = torch.cos(p1) - torch.cos(p0)  # ... of sin
    x = s2[:, None] * cx[None, :]
    y = s2[:, None] * cy[None, :]
    z = sc[:, None] * (p0 - p1)[None, :]
    cells = torch.stack([x, y, z], -1)  # (H sub, W sub, 3)
    cells = cells.reshape(height, sub, width, sub, 3).permute(0, 2, 1, 3, 4).reshape(height * width, sub * sub, 3)
    return cells.to(device=device, dtype=dtype)


def cosine_weights(normals: torch.Tensor, moments: torch.Tensor) -> torch.Tensor:
    """(P, H * W): int over each texel of max(0, n . w) dw for unit normals (P, 3), from ``texel_moments``.
    By the compiled kernel (method/shading/quadrature_numba.py) where the splat backend resolves to Numba
    (CPU tensors), by the torch reference below otherwise."""
    from method.splat.backend import resolve

    if resolve(None, normals.device) == "numba":
        from method.shading.quadrature_numba import cosine_weights_compiled

        return cosine_weights_compiled(normals, moments)
    return cosine_weights_torch(normals, moments)


def cosine_weights_torch(normals: torch.Tensor, moments: torch.Tensor) -> torch.Tensor:
    """``cosine_weights`` in torch: the reference, and the CUDA path."""
    c = torch.einsum("pk,tsk->pts", normals, moments).clamp_min(0.0)
    return c.sum(-1)


def luminance(rgb: torch.Tensor) -> torch.Tensor:
    return rgb[..., 0] * 0.2126 + rgb[..., 1] * 0.7152 + rgb[..., 2] * 0.0722


def lower_hemisphere_l2(env: torch.Tensor) -> torch.Tensor:
    """Mean squared radiance of the texels below the horizon (rows whose centre has z < 0).

    Stage 2's regulariser: no scene is lit from below, so energy there is an artefact of the fit.
    """
    h = env.shape[0]
    return env[(h + 1) // 2:].square().mean()


# ------------------------------------------------------------------------------------------- loading

def resample(img, height: int = DEFAULT_HEIGHT, width: int = DEFAULT_WIDTH) -> np.ndarray:
    """Any map -> height x width by solid-angle-weighted area averaging (the generator's downsampling,
    so the total light, hence diffuse shading, is preserved; a smaller map is upsampled the same way)."""
    arr = img.detach().cpu().numpy() if torch.is_tensor(img) else np.asarray(img)
    return genv.downsample_envmap(arr.astype(np.float32), width, height)


def check_envmap(img: np.ndarray, where) -> np.ndarray:
    """An equirectangular map as read from ``where``: H x W x 3 with W = 2 H, finite, some light.

    Anything else -> UserError naming the file: a map of another aspect would be looked up with the wrong
    angles (direction_to_uv assumes 2:1), and a dark or NaN map shades every pixel black or NaN."""
    if img.ndim != 3 or img.shape[-1] < 3:
        raise UserError(f"environment map {where}: expected an RGB image, got shape {img.shape}")
    h, w = img.shape[:2]
    if h < 1 or w != 2 * h:
        raise UserError(f"environment map {where} is {w} x {h}: an equirectangular map must be twice as wide as "
                        f"high (e.g. {2 * h} x {h})")
    if not np.isfinite(img).all():
        raise UserError(f"environment map {where} contains NaN or infinite values")
    if not (img[..., :3] > 0).any():
        raise UserError(f"environment map {where} has no positive radiance (all zero or negative): it lights nothing")
    return img


def load_envmap(source: str | Path, scene_dir: str | Path | None = None, *, height: int | None = DEFAULT_HEIGHT,
                width: int | None = DEFAULT_WIDTH, device=None, dtype=torch.float32) -> torch.Tensor:
    """An env map as an (H, W, 3) tensor from an .hdr/.exr path or a light name.

    A light name is looked up as ``<scene_dir>/<light>.hdr`` (the map exactly as the dataset was rendered)
    and, failing that, in configs/lights.yaml (rotated and scaled as the generator does). The map is
    resampled to height x width unless it already has that size (None keeps the file's size).
    Bad input -> UserError with one line.
    """
    text = str(source)
    _, path = layout.parse_light(text)
    if path is not None:
        img = check_envmap(genv.read_envmap(path), path)
    elif scene_dir is not None and layout.envmap_path(Path(scene_dir), text).is_file():
        img = check_envmap(genv.read_envmap(layout.envmap_path(Path(scene_dir), text)),
                           layout.envmap_path(Path(scene_dir), text))
    else:
        from generator import lights as glights

        try:
            spec = glights.resolve_light(text)
        except UserError:
            where = f" (no {layout.envmap_path(Path(scene_dir), text)})" if scene_dir is not None else ""
            raise UserError(f"unknown environment map '{text}'{where}: give an .hdr/.exr path or a light name "
                            f"({', '.join(sorted(glights.load_lights()))})") from None
        img = glights.prepare_envmap(spec)
    if height is not None and width is not None and img.shape[:2] != (height, width):
        img = resample(img, height, width)
    return torch.as_tensor(np.ascontiguousarray(img[..., :3]), dtype=dtype, device=device)


# --------------------------------------------------------------------------------------- learnable map

class LearnableEnvMap(torch.nn.Module):
    """One environment map for the whole scene, stored as log radiance with an exp activation.

    exp keeps radiance positive and makes the learning rate act on relative change (a sun texel 100x
    brighter than the sky needs no larger steps than the sky).
    """

    def __init__(self, height: int = DEFAULT_HEIGHT, width: int = DEFAULT_WIDTH, init: float | torch.Tensor = 0.5):
        super().__init__()
        if torch.is_tensor(init) and init.dim() == 3:
            if init.shape[-1] != 3:
                raise ValueError(f"init map must be (H, W, 3), got {tuple(init.shape)}")
            start = init.detach().to(torch.float32).clamp_min(1e-6).log()
        else:
            value = float(init)
            if not value > 0.0:
                raise ValueError(f"init radiance must be positive, got {value}")
            start = torch.full((height, width, 3), math.log(value))
        self.log_radiance = torch.nn.Parameter(start.clone())

    def forward(self) -> torch.Tensor:
        """The (H, W, 3) radiance."""
        return self.log_radiance.exp()


# ------------------------------------------------------------------------------- importance sampling

@dataclass
class EnvSampler:
    """Texel probabilities proportional to luminance x solid angle (a fixed, gradient-free proposal).

    A small uniform floor keeps every texel reachable so the pdf is never zero where radiance is not.
    """

    height: int
    width: int
    cdf: torch.Tensor  # (H W,) inclusive cumulative texel probabilities
    prob: torch.Tensor  # (H W,)
    solid_angle: torch.Tensor  # (H W,)

    @staticmethod
    def build(env: torch.Tensor, floor: float = 0.05) -> "EnvSampler":
        h, w = env.shape[0], env.shape[1]
        with torch.no_grad():
            sa = texel_solid_angles(h, w, env.device, torch.float64).reshape(-1)
            power = luminance(env.detach().to(torch.float64)).clamp_min(0.0).reshape(-1) * sa
            total = float(power.sum())
            p = power / total if total > 0 else sa / sa.sum()
            p = (1.0 - floor) * p + floor * sa / sa.sum()
            cdf = torch.cumsum(p, 0)
            cdf = cdf / cdf[-1]
        dt = env.dtype
        return EnvSampler(h, w, cdf.to(dt), p.to(dt), sa.to(dt))

    def sample(self, u_texel: torch.Tensor, u_phi: torch.Tensor, u_z: torch.Tensor) -> torch.Tensor:
        """Uniform numbers in [0, 1) -> directions (...) x 3, uniform in solid angle within the texel."""
        idx = torch.searchsorted(self.cdf, u_texel.contiguous().to(self.cdf.dtype), right=True)
        idx = idx.clamp(0, self.height * self.width - 1)
        row, col = torch.div(idx, self.width, rounding_mode="floor"), idx.remainder(self.width)
        u = (col.to(u_phi.dtype) + u_phi) / self.width
        # texel row r (from the top) spans z = cos(theta) from cos(r pi / H) down to cos((r + 1) pi / H)
        z_hi = torch.cos(row.to(u_z.dtype) * math.pi / self.height)
        z_lo = torch.cos((row.to(u_z.dtype) + 1.0) * math.pi / self.height)
        z = z_lo + (z_hi - z_lo) * u_z
        phi = math.pi * (1.0 - 2.0 * u)
        s = torch.sqrt((1.0 - z * z).clamp_min(0.0))
        return torch.stack([s * torch.cos(phi), s * torch.sin(phi), z], -1)

    def pdf(self, dirs: torch.Tensor) -> torch.Tensor:
        """Solid-angle density of ``sample`` at each direction."""
        row, col = texel_index(dirs, self.height, self.width)
        return self.pdf_of_texel(row * self.width + col)

    def pdf_of_texel(self, flat_index: torch.Tensor) -> torch.Tensor:
        """The density inside texel row * W + col (constant over the texel)."""
        return self.prob[flat_index] / self.solid_angle[flat_index]
