"""Per-pixel Monte Carlo of the rendering equation (paper eq. 1) for deferred shading in stage 2.

    L_o(x, v) = integral over the hemisphere of f(l, v) L_i(l) (n.l) dl,
    L_i = V env(l) + (1 - V) indirect(l)      (V = env(l) alone when no callables are given)

Estimator: multiple importance sampling with the balance heuristic over three stratified strategies
(sampling.py): a cosine-weighted Fibonacci lattice for the diffuse term, GGX half vectors for the
specular lobe and env-map texels for small bright suns. With n_k samples of strategy k, each sample l
adds f L_i (n.l) / sum_k n_k p_k(l): unbiased, and no strategy's weak spot (a 0.03 sr sun for the
lattice, a roughness-0.15 lobe for the cosine) dominates the variance. Why not a lattice alone: at
equal directions the cosine lattice's per-pixel error on calib_sphere is 3-8x larger (__init__.py).

Gradients flow to albedo, roughness, normals (through the BRDF, not the sample placement), the env
map (through the lookup) and whatever the callables return; pdfs and directions are constants.

``env_quadrature=True`` adds a control variate to the diffuse term: its unshadowed part, the integral of
w_d rho / pi env(l) (n.l), is summed exactly over the map's texels (envmap.texel_moments), and the samples
only estimate what shadowing changes, (L_i - env)(l) = (1 - V)(indirect - env): zero on every direction
that nothing blocks. Still unbiased. Why: at a few directions per pixel a 0.04 sr sun is missed by most
pixels' samples, so each pixel's estimate is bimodal and an L1 loss learns the miss (BENCHMARKS.md, "the
PBR loss at a small direction budget"); with the quadrature every sunlit pixel sees the sun every time.
The specular lobe stays sampled (a texel quadrature would blur a roughness-0.15 lobe).
"""
from __future__ import annotations

from typing import Callable

import torch

from . import brdf as B
from .envmap import EnvSampler, cosine_weights, texel_index, texel_moments
from .sampling import pdf_ggx, pdf_hemisphere, random_offsets, sample_env, sample_ggx, sample_hemisphere

DEFAULT_MIX = (0.5, 0.25, 0.25)  # share of the directions per strategy: cosine, ggx, env
MAX_SAMPLES_PER_CHUNK = 1 << 20  # pixels x directions evaluated at once (bounds peak memory)
QUADRATURE_ROWS = 64  # env_quadrature cuts texels into cells until the map has this many rows of cells
MAX_QUADRATURE_TERMS = 1 << 26  # pixels x cells in one cosine-weight tensor (256 MiB in float32)


def quadrature_sub(height: int) -> int:
    """Cells per texel side for ``env_quadrature``: 4 for the 16-row maps (as always), 1 from 64 rows up, so a
    finer map (a 128 x 64 light) costs what a 32 x 16 one does and its cells are no coarser."""
    return max(1, -(-QUADRATURE_ROWS // max(int(height), 1)))

Visibility = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
Indirect = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def split_directions(n_dirs: int, mix=DEFAULT_MIX) -> tuple[int, int, int]:
    """Directions per strategy (cosine, ggx, env) summing to n_dirs; every positive share gets >= 1."""
    if n_dirs < 1:
        raise ValueError(f"n_dirs must be >= 1, got {n_dirs}")
    w = [max(0.0, float(m)) for m in mix]
    if len(w) != 3 or sum(w) <= 0 or w[0] <= 0:
        raise ValueError(f"mix must be 3 non-negative shares with cosine > 0, got {mix}")
    counts = [int(round(n_dirs * x / sum(w))) if x > 0 else 0 for x in w]
    for k in (1, 2):
        if w[k] > 0 and counts[k] == 0 and n_dirs >= 3:
            counts[k] = 1
    counts[0] = n_dirs - counts[1] - counts[2]
    if counts[0] < 1:
        raise ValueError(f"n_dirs = {n_dirs} is too small for mix {mix}")
    return counts[0], counts[1], counts[2]


def shade(points: torch.Tensor | None, normals: torch.Tensor, view_dirs: torch.Tensor, albedo: torch.Tensor,
          roughness: torch.Tensor, envmap: torch.Tensor, n_dirs: int = 256,
          generator: torch.Generator | None = None, visibility: Visibility | None = None,
          indirect: Indirect | None = None, *, mix=DEFAULT_MIX, diffuse_weighting: str = B.DIFFUSE_WEIGHTING,
          max_samples: int = MAX_SAMPLES_PER_CHUNK, return_parts: bool = False,
          sampling_env: torch.Tensor | None = None, env_quadrature: bool = False):
    """Outgoing linear radiance (P, 3) of P surface points.

    points (P, 3) world positions (only passed to the callables; may be None without them);
    normals (P, 3) unit; view_dirs (P, 3) unit, from the point towards the camera; albedo (P, 3) linear;
    roughness (P,) or (P, 1) in [0, 1] (clamped to brdf.MIN_ROUGHNESS); envmap (H, W, 3) linear radiance
    in the generator's orientation. n_dirs directions per pixel, split by ``mix`` (cosine, ggx, env).
    visibility(origins (R, 3), dirs (R, 3)) -> (R,) in [0, 1]; indirect(origins, dirs) -> (R, 3) radiance
    of what blocks the ray; both are called only on directions that can contribute (above the surface,
    non-zero BRDF), in chunks. return_parts: also the diffuse and specular parts, and the irradiance E the
    diffuse part is albedo / pi x E of (so any other albedo shades as albedo' / pi x E + specular), as a dict.
    env_quadrature: the diffuse term's unshadowed part summed over the texels (module docstring).
    """
    parts = shade_maps(points, normals, view_dirs, albedo, roughness, [envmap], n_dirs, generator, visibility,
                       indirect, mix=mix, diffuse_weighting=diffuse_weighting, max_samples=max_samples,
                       sampling_env=sampling_env, env_quadrature=env_quadrature)[0]
    if return_parts:
        return parts["rgb"], {k: parts[k] for k in ("diffuse", "specular", "irradiance")}
    return parts["rgb"]


def shade_maps(points: torch.Tensor | None, normals: torch.Tensor, view_dirs: torch.Tensor, albedo: torch.Tensor,
               roughness: torch.Tensor, envmaps, n_dirs: int = 256, generator: torch.Generator | None = None,
               visibility: Visibility | None = None, indirect: Indirect | None = None, *, mix=DEFAULT_MIX,
               diffuse_weighting: str = B.DIFFUSE_WEIGHTING, max_samples: int = MAX_SAMPLES_PER_CHUNK,
               sampling_env: torch.Tensor | None = None, env_quadrature: bool = False) -> list[dict]:
    """:func:`shade` under several maps with one set of directions: per map a dict of "rgb", "diffuse",
    "specular" and "irradiance" (P, 3), each equal to what shade() returns for that map alone with the same
    generator state and ``sampling_env``; ``indirect`` may return 3 channels per map (the Gaussians relit under
    each, in the maps' order) or 3 for all. Why: relighting a view under several maps (the benchmark's
    predictions) samples the directions, evaluates the BRDF and traces the visibility once instead of once
    per map. Several maps need a shared proposal (``sampling_env``, e.g. deferred.sampling_mixture)."""
    envmaps = list(envmaps)
    P = normals.shape[0]
    if not envmaps:
        raise ValueError("shade_maps needs at least one env map")
    if len(envmaps) > 1 and sampling_env is None:
        raise ValueError("several env maps share one set of directions: pass sampling_env (their mixture)")
    if normals.shape != (P, 3) or view_dirs.shape != (P, 3) or albedo.shape != (P, 3):
        raise ValueError(f"normals, view_dirs and albedo must be (P, 3), got {tuple(normals.shape)}, "
                         f"{tuple(view_dirs.shape)}, {tuple(albedo.shape)}")
    if (visibility is not None or indirect is not None) and (points is None or points.shape != (P, 3)):
        raise ValueError("points (P, 3) are needed when visibility or indirect is given")
    if indirect is not None and visibility is None:
        raise ValueError("indirect light needs a visibility callable (it weights indirect by 1 - V)")
    for envmap in envmaps:
        if envmap.dim() != 3 or envmap.shape[-1] != 3:
            raise ValueError(f"envmap must be (H, W, 3), got {tuple(envmap.shape)}")
    counts = split_directions(n_dirs, mix)
    moments = [None] * len(envmaps)
    if env_quadrature:
        if diffuse_weighting == "fresnel":
            raise ValueError("env_quadrature needs a diffuse weight that does not depend on the direction "
                             "(diffuse_weighting 'albedo' or 'none')")
        per_size = {}  # maps of one size share their moments (and, per chunk, the cosine weights)
        for e in envmaps:
            hw = (e.shape[0], e.shape[1])
            if hw not in per_size:
                per_size[hw] = texel_moments(*hw, quadrature_sub(hw[0]), device=normals.device, dtype=normals.dtype)
        moments = [per_size[(e.shape[0], e.shape[1])] for e in envmaps]
    rough = B.clamp_roughness(roughness.reshape(P))
    # the env strategy's proposal: this map, or another one (relighting one view under several maps with one
    # shared direction set samples from their mixture, which stays unbiased for each map)
    sampler = EnvSampler.build(envmaps[0] if sampling_env is None else sampling_env) if counts[2] > 0 else None
    # every random number of the call, per pixel: results do not depend on the chunking
    offsets = random_offsets((P, 5), generator, normals.device, normals.dtype)
    chunk = max(1, max_samples // n_dirs)
    keys = ("rgb", "diffuse", "specular", "irradiance")
    outs: list[dict] = [{k: [] for k in keys} for _ in envmaps]
    for s in range(0, P, chunk):
        e = min(P, s + chunk)
        per_map = _shade_chunk(None if points is None else points[s:e], normals[s:e], view_dirs[s:e],
                               albedo[s:e], rough[s:e], envmaps, sampler, counts, offsets[s:e], visibility,
                               indirect, diffuse_weighting, moments)
        for out, vals in zip(outs, per_map):
            for k, v in zip(keys, vals):
                out[k].append(v)
    empty = albedo.new_zeros(0, 3)
    return [{k: torch.cat(v) if v else empty for k, v in out.items()} for out in outs]


def _shade_chunk(points, normals, view_dirs, albedo, rough, envmaps, sampler, counts, offsets, visibility,
                 indirect, weighting, moments):
    """Per map (rgb, diffuse, specular, irradiance) of one chunk of pixels; the directions, pdfs, BRDF and
    the traced V (and indirect light) are computed once and serve every map."""
    n_cos, n_ggx, n_env = counts
    with torch.no_grad():
        nd, vd, rd = normals.detach(), view_dirs.detach(), rough.detach()
        parts = [sample_hemisphere(nd, n_cos, cosine=True, rotation=offsets[:, 0:1])]
        if n_ggx:
            parts.append(sample_ggx(nd, vd, rd, n_ggx, rotation=offsets[:, 1:2]))
        if n_env:
            parts.append(sample_env(sampler, n_env, offsets[:, 2:5]))
        dirs = _normalize(torch.cat(parts, 1))  # (P, S, 3)
        h = _normalize(dirs + vd[:, None, :])
        vh = _dot(h, vd[:, None, :])  # depends on the directions only: no gradient needed
    # cosines with gradients to the normals (the directions are constants of the estimator)
    nl = _dot(dirs, normals[:, None, :])
    nh = _dot(h, normals[:, None, :])
    nv = _dot(view_dirs, normals)[:, None]
    r = rough[:, None]
    texels = {}  # texel ids per map grid: one lookup serves the radiance and the env pdf
    with torch.no_grad():  # balance-heuristic denominator sum_k n_k p_k(l)
        nl0, nh0 = nl.detach(), nh.detach()
        denom = n_cos * pdf_hemisphere(nl0, cosine=True)
        if n_ggx:
            denom = denom + n_ggx * pdf_ggx(nh0, vh, rd[:, None])
        for e in envmaps:
            hw = (e.shape[0], e.shape[1])
            if hw not in texels:
                row, col = texel_index(dirs, *hw)
                texels[hw] = row * hw[1] + col
        if n_env:  # a proposal on another grid (several maps' mixture) looks its own texels up
            hw = (sampler.height, sampler.width)
            denom = denom + n_env * (sampler.pdf_of_texel(texels[hw]) if hw in texels else sampler.pdf(dirs))
        live = (nl0 > 0) & (nv.detach() > 0) & (denom > 0)
        inv = torch.where(live, 1.0 / denom.clamp_min(1e-30), torch.zeros_like(denom))
    spec = B.specular(nl, nv.expand_as(nl), nh, vh, r)  # (P, S)
    wd = B.diffuse_weight(nv, vh, r, weighting)  # (P, 1), (P, S) or a float
    cos_w = nl.clamp_min(0.0) * inv  # (n.l) / sum_k n_k p_k
    dw = wd * cos_w if torch.is_tensor(wd) else cos_w * wd
    blocked = _blocked(points, dirs, live, visibility, indirect)
    unshadowed = _irradiance(normals, moments, [e.reshape(e.shape[0] * e.shape[1], -1) for e in envmaps])
    out = []
    for e, mom, irradiance in zip(envmaps, moments, unshadowed):
        h_env, w_env = e.shape[0], e.shape[1]
        env_l = e.reshape(h_env * w_env, -1)[texels[(h_env, w_env)]]
        radiance = _incident(env_l, blocked, len(out), len(envmaps))
        if mom is None:
            irr = (dw[..., None] * radiance).sum(1)
        else:  # exact unshadowed irradiance + the sampled change that shadowing makes (zero where V = 1)
            irradiance = irradiance * (wd if torch.is_tensor(wd) else float(wd)) * (nv > 0).to(irradiance)
            irr = irradiance + (dw[..., None] * (radiance - env_l)).sum(1)
        diffuse = albedo / torch.pi * irr
        specular = ((spec * cos_w)[..., None] * radiance).sum(1)
        out.append((diffuse + specular, diffuse, specular, irr))
    return out


def _irradiance(normals: torch.Tensor, moments: list, env_flats: list) -> list:
    """Unshadowed irradiance (P, 3) under each map (None where its moments are None), from the texel cosine
    weights, which depend on the normals and the map's size only: computed once for the maps of one size, in
    groups of pixels small enough that one group's (pixels, texels, cells) weights stay under
    MAX_QUADRATURE_TERMS (a map of any size fits)."""
    out: list = [None] * len(env_flats)
    groups: dict = {}
    for i, mom in enumerate(moments):
        if mom is not None:
            groups.setdefault(id(mom), []).append(i)
    for idx in groups.values():
        mom = moments[idx[0]]
        step = max(1, MAX_QUADRATURE_TERMS // max(mom.shape[0] * mom.shape[1], 1))
        parts: dict = {i: [] for i in idx}
        for s in range(0, normals.shape[0], step):
            w = cosine_weights(normals[s:s + step], mom)
            for i in idx:
                parts[i].append(w @ env_flats[i])
        for i in idx:
            out[i] = parts[i][0] if len(parts[i]) == 1 else torch.cat(parts[i])
    return out


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Dot product over the last axis of length 3, written out: torch's reductions over a length-3 axis
    (sum, norm) are several times slower on CPU than three multiply-adds (measured: norm was half of a
    512 x 512 shade call)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _normalize(x: torch.Tensor) -> torch.Tensor:
    return x * torch.rsqrt(_dot(x, x).clamp_min(1e-24))[..., None]


def _blocked(points, dirs, live, visibility, indirect):
    """What the traced rays say, shared by every map: None without a visibility callable, else the live
    directions' flat ids, V (R, 1) and the indirect radiance (R, 3) or None."""
    if visibility is None:
        return None
    idx = torch.nonzero(live.reshape(-1)).squeeze(1)
    P, S = dirs.shape[:2]
    o = points[:, None, :].expand(P, S, 3).reshape(-1, 3).index_select(0, idx)
    d = dirs.reshape(-1, 3).index_select(0, idx)
    V = visibility(o, d).reshape(-1, 1)
    return idx, V, (indirect(o, d) if indirect is not None else None)


def _incident(env, blocked, map_index: int = 0, num_maps: int = 1):
    """L_i (P, S, 3) from env(l) (P, S, 3): env(l), or V env + (1 - V) indirect on the live directions. An
    indirect radiance of 3 x ``num_maps`` channels holds one per map (the blocking Gaussians relit under each,
    deferred.relit_radiance): map ``map_index`` takes its three."""
    if blocked is None:
        return env
    idx, V, ind = blocked
    L = env.reshape(-1, 3).index_select(0, idx) * V
    if ind is not None:
        if ind.shape[1] == 3 * num_maps and num_maps > 1:
            ind = ind[:, 3 * map_index:3 * map_index + 3]
        elif ind.shape[1] != 3:
            raise ValueError(f"indirect radiance must have 3 or 3 x {num_maps} (one per map) channels, "
                             f"got {ind.shape[1]}")
        L = L + (1.0 - V) * ind
    full = env.new_zeros(env.shape[0] * env.shape[1], 3).index_copy(0, idx, L.to(env.dtype))
    return full.reshape(env.shape)
