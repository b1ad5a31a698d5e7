"""Stage 2's starting env map: one sun texel plus a uniform sky, fitted to the training images on the frozen
stage-1 geometry (``stage2.env_init_fit``; off at ``full``, where the map starts uniform as in the paper).

Why: per-Gaussian albedo can absorb any static shading, so the only force that makes the learnable map grow
a sun is the little that moving shadows and specular highlights tell it; the albedo starts from the
canonical colour, which already holds the sun's shading, and the map learns to agree with it. Measured at
`small`: a map started at the ground truth's sun (50x the sky) loses it within 1,500 iterations (brightest
texel 1.2-1.4; BENCHMARKS.md, session 10). Here a low-dimensional model breaks the ambiguity instead: over
a few thousand training pixels, the observed radiance is albedo x irradiance / pi, and with albedo taken
as one grey value (its texture becomes noise of a robust fit), the irradiance of "sky s everywhere + sun L
at texel k", with visibility traced towards every texel, must explain where the scene is darker. The fit
is a search: for every upper-hemisphere texel k and sun-to-sky ratio rho = L / s on a log grid, the mean
absolute log residual about the residuals' median (which absorbs the unknown scale); the best (k, rho) wins.
A ground level (the lower hemisphere's radiance relative to the sky's) is searched the same way.
The median is taken per region (``stage2.env_fit_regions``: k-means clusters of the points' positions), so
each region has its own grey albedo: one grey value for the whole scene let the sun explain materials (a
white wall over a wooden floor read as a sun 35-46 degrees too low on jumpingjacks; BENCHMARKS.md, session 59).
Cost: one tracer grid and P x (H W / 2) shadow rays per fitted view (1-2 CPU seconds each at `small`).
"""
from __future__ import annotations

import math
import time

import torch

from lumibench.color import srgb_to_linear
from method import buffers
from method.clustering import lloyd
from method.shading.deferred import accel_for, raster_materials, surface_points, tracer_for
from method.shading.envmap import cosine_weights, luminance, texel_moments
from method.shading.visibility import lifted_points

DEFAULT_RATIOS = tuple([0.0] + [10.0 ** (k / 10.0) for k in range(0, 41)])  # 0, then 1 ... 10^4
LEVEL_QUANTILE = 0.99  # the map's level: irradiance / pi = 1 at this quantile of the fitted points (fit_sun_sky)
DEFAULT_LOWER = (0.02, 0.05, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0)  # lower-hemisphere sky / upper sky


def texel_directions(height: int, width: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """(H * W, 3) unit directions through the texel centres, row-major from the top-left (``lookup``'s
    indexing; envmap.py's orientation: u = 0.5 - atan2(y, x) / 2 pi, rows from the zenith down)."""
    theta = (torch.arange(height, dtype=torch.float64) + 0.5) * (math.pi / height)
    u = (torch.arange(width, dtype=torch.float64) + 0.5) / width
    phi = (0.5 - u) * 2.0 * math.pi
    th, ph = theta[:, None].expand(height, width), phi[None, :].expand(height, width)
    d = torch.stack([torch.sin(th) * torch.cos(ph), torch.sin(th) * torch.sin(ph), torch.cos(th)], -1)
    return d.reshape(-1, 3).to(device=device, dtype=dtype)


def fit_sun_sky(weights: torch.Tensor, radiance: torch.Tensor, height: int, width: int,
                ratios=DEFAULT_RATIOS, lower_levels=DEFAULT_LOWER, regions: torch.Tensor | None = None) -> dict:
    """The sun texel, sun-to-sky ratio and ground level that best explain ``radiance`` (P,) > 0 as a grey
    albedo times the irradiance sum_j weights[:, j] env_j, env = 1 on the upper hemisphere, ``lower`` on
    the lower one (the ground is darker than the sky; what the undersides of objects see), + rho at one
    upper-hemisphere texel.

    weights (P, H * W): each texel's cosine integral at each point times that texel's visibility.
    Returns {"texel": (row, col), "ratio": rho, "lower": the ground level, "scale": s, "mad": the fit's
    mean absolute log residual about the median, "mad_no_sun": the same for the sky alone}; s is the sky
    radiance for which the irradiance / pi of the most strongly lit points (the LEVEL_QUANTILE quantile) is 1.

    ``radiance`` (P, 3): the texel and the ground level are searched on the luminance as above, then each
    channel gets its own ratio at that texel (and its own scale by the same rule), returned as "colour":
    {"ratio": [3], "lower": [3], "scale": [3], "warm": the sun redder than the sky}: the sun's colour
    against the sky's. ``fit_env`` uses it only when "warm": daylight's direct sun is warmer than the sky
    it shines through, so a fitted sun bluer than its sky is a texel that is not the sun (measured at
    `small`: on every scene where it happened, the fitted texel was off the ground truth's sun or there
    is no sun; BENCHMARKS.md, session 27), and its colour would tint the albedo the wrong way. The ground
    stays grey: fitted per channel, its level sat at the grid's ends in 13 of 14 fits and came out cyan
    under city (albedo LPIPS +8 % on jumpingjacks; session 27).

    Why that level: images fix albedo x light, not either alone. Started uniform, the learned map settles
    where the most strongly lit surfaces reflect about their canonical colour (the albedo starts there and
    is clamped below albedo_max), which left the albedo 0.77-0.93 x the ground truth's at `small`; the
    same rule for the fitted map gives 1.07 x on both scenes, where "irradiance / pi = 1 at the median
    point" gave 1.8-2.4 x too dark an albedo and relighting 2.5-5 dB worse (BENCHMARKS.md, session 10).
    """
    P, n_tex = weights.shape
    if n_tex != height * width:
        raise ValueError(f"weights must be (P, {height * width}), got {tuple(weights.shape)}")
    if P == 0:
        raise ValueError("no points to fit the env map to")
    if regions is not None and regions.shape != (P,):
        raise ValueError(f"regions must be (P,) with P = {P}, got {tuple(regions.shape)}")
    groups = _groups(regions, weights.device)
    rgb = None
    if radiance.dim() == 2:
        if radiance.shape != (P, 3):
            raise ValueError(f"radiance must be (P,) or (P, 3) with P = {P}, got {tuple(radiance.shape)}")
        rgb, radiance = radiance, luminance(radiance)
    w = weights.to(torch.float64)
    log_y = radiance.to(torch.float64).clamp_min(1e-6).log()
    is_upper = torch.arange(height * width, device=w.device) // width < height // 2
    sky_up = w[:, is_upper].sum(1, keepdim=True)  # irradiance x pi from a unit upper sky
    sky_low = w[:, ~is_upper].sum(1, keepdim=True)
    rho = torch.as_tensor(ratios, dtype=torch.float64, device=w.device)
    upper = [k for k in range(height * width) if bool(is_upper[k])]
    best = None
    for k in upper:
        mad, j, lower, bright_e = _search(sky_up, sky_low, w[:, k:k + 1], log_y, rho, lower_levels, groups)
        if best is None or mad < best[0]:
            best = (mad, k, j, lower, bright_e)
    mad, k, j, lower, bright_e = best
    no_sun = ((sky_up + sky_low).clamp_min(1e-12).log() - log_y[:, None])
    no_sun_mad = float(_spread(no_sun, groups)[0])
    out = {"texel": (k // width, k % width), "ratio": float(rho[j]), "lower": lower,
           "scale": math.pi / bright_e, "mad": mad, "mad_no_sun": no_sun_mad}
    if rgb is not None:
        per = [_search(sky_up, sky_low, w[:, k:k + 1], rgb[:, c].to(torch.float64).clamp_min(1e-6).log(), rho,
                       (lower,), groups) for c in range(3)]  # the ground grey, at the luminance fit's level (see above)
        out["colour"] = {"ratio": [float(rho[p[1]]) for p in per], "lower": [p[2] for p in per],
                         "scale": [math.pi / p[3] for p in per]}
        out["colour"]["warm"] = out["colour"]["ratio"][0] > out["colour"]["ratio"][2]
    return out


def _groups(regions: torch.Tensor | None, device) -> list[torch.Tensor] | None:
    """The row indices of each region (None: one region, the whole set)."""
    if regions is None:
        return None
    regions = regions.to(device)
    return [torch.nonzero(regions == r).squeeze(1) for r in torch.unique(regions)]


def _spread(r: torch.Tensor, groups: list[torch.Tensor] | None) -> torch.Tensor:
    """(R,): the mean absolute deviation of each column of ``r`` (P, R) about its median, the median taken
    within each group of rows (each region's own albedo)."""
    if groups is None:
        return (r - r.median(0).values).abs().mean(0)
    total = torch.zeros(r.shape[1], dtype=r.dtype, device=r.device)
    for rows in groups:
        part = r[rows]
        total += (part - part.median(0).values).abs().sum(0)
    return total / r.shape[0]


def _search(sky_up, sky_low, w_k, log_y, rho, lower_levels, groups=None) -> tuple[float, int, float, float]:
    """Over the ground levels and ratios, the best fit of log_y (P,) by sky + rho x the texel's w_k (P, 1):
    (mean absolute log residual about the median (each group's own, :func:`_spread`), the ratio's index, the
    ground level, the LEVEL_QUANTILE quantile of that fit's irradiance)."""
    best = None
    for lower in lower_levels:
        e = (sky_up + float(lower) * sky_low + rho[None, :] * w_k).clamp_min(1e-12)  # (P, R)
        mad = _spread(e.log() - log_y[:, None], groups)
        j = int(mad.argmin())
        if best is None or float(mad[j]) < best[0]:
            best = (float(mad[j]), j, float(lower), float(e[:, j].quantile(LEVEL_QUANTILE)))
    return best


def spatial_regions(points: torch.Tensor, count: int, generator: torch.Generator, iterations: int = 20) -> torch.Tensor:
    """(P,) labels: ``count`` k-means clusters of the points' positions (P, 3), started from points drawn with
    ``generator``. Nearby surface points mostly share a material, so each cluster stands for one grey albedo;
    shadows and normals vary within a cluster, and that variation is what the fit reads the sun from."""
    P = points.shape[0]
    if count <= 1 or P <= count:
        return torch.zeros(P, dtype=torch.long, device=points.device)
    x = points.detach().to(torch.float64)
    centres = x[torch.randperm(P, generator=generator)[:count].to(x.device)].clone()
    return lloyd(x, centres, iterations)


def sun_sky_map(height: int, width: int, texel: tuple[int, int], ratio, scale, lower=1.0) -> torch.Tensor:
    """(H, W, 3) map: ``scale`` on the upper hemisphere, ``scale * lower`` on the lower one,
    ``scale * (1 + ratio)`` at ``texel``; each of ratio, scale and lower one number (a grey map) or three
    (one per channel: the fit's "colour")."""
    def per_channel(x):
        return torch.as_tensor(x, dtype=torch.float32).reshape(-1).expand(3)

    scale, ratio, lower = per_channel(scale), per_channel(ratio), per_channel(lower)
    env = scale.expand(height, width, 3).clone()
    env[height // 2:] *= lower
    env[texel] = scale * (1.0 + ratio)
    return env.contiguous()


@torch.no_grad()
def fit_env(scene, mats, data, cfg: dict, generator: torch.Generator) -> tuple[torch.Tensor, dict]:
    """The sun-and-sky map fitted on ``stage2.env_fit_views`` training views x ``env_fit_pixels`` foreground
    pixels each (random, from ``generator``), at the map size of the config; and a record of the fit."""

    s2 = cfg["stage2"]
    H, W = s2["env_height"], s2["env_width"]
    t0, c0 = time.perf_counter(), time.process_time()
    dev = scene.g.means.device
    moments = texel_moments(H, W, device=dev)
    dirs = texel_directions(H, W, device=dev)
    n_views = min(int(s2["env_fit_views"]), len(data.train))
    picks = torch.randperm(len(data.train), generator=generator)[:n_views].tolist()
    weights, radiance, points, rays = [], [], [], 0
    for k in picks:
        v = data.train[k]
        d = scene.deform(v.time, p_mode="inference")
        out = raster_materials(d, mats, v.camera, data.background)
        fg = torch.nonzero(((v.alpha > 0.5) & (out.alpha > 0.5)).reshape(-1)).squeeze(1)
        if fg.numel() == 0:
            continue
        pix = fg[torch.randperm(fg.numel(), generator=generator)[: int(s2["env_fit_pixels"])].to(fg.device)]
        pts, view = surface_points(out, v.camera, pix)
        n = buffers.unit(out.normal.reshape(-1, 3)[pix])
        pts = lifted_points(pts, n, view, float(s2["normal_offset"]) * scene.extent)  # as shading lifts them
        cw = cosine_weights(n, moments)  # (P, H W)
        pi_, ti = torch.nonzero(cw > 0, as_tuple=True)
        o, dd = pts[pi_], dirs[ti]
        tracer = tracer_for(d, accel_for(d, s2["trace_cell"]), s2["trace_offset"] * scene.extent, False,
                            extent=scene.extent)
        T = tracer.visibility(o, dd)
        rays += int(o.shape[0])
        vis = torch.zeros_like(cw)
        vis[pi_, ti] = T.to(vis)
        weights.append(cw * vis)
        radiance.append(srgb_to_linear(v.rgb.reshape(-1, 3)[pix].clamp(0, 1)))
        points.append(pts)
    if not weights:
        raise ValueError("no foreground pixels in the training views to fit the env map to")
    rgb = torch.cat(radiance)
    # a small dense search (one candidate sun per upper texel): on the CPU, not as hundreds of GPU launches
    coloured = bool(s2["env_fit_colour"])
    regions = spatial_regions(torch.cat(points).cpu(), int(s2["env_fit_regions"]), generator)
    fit = fit_sun_sky(torch.cat(weights).cpu(), (rgb if coloured else luminance(rgb)).cpu(), H, W, regions=regions)
    c = fit["colour"] if coloured and fit["colour"]["warm"] else fit  # see fit_sun_sky on "warm"
    env = sun_sky_map(H, W, fit["texel"], c["ratio"], c["scale"], c["lower"]).to(dev)
    record = {**fit, "texel": list(fit["texel"]), "points": int(rgb.shape[0]), "regions": int(torch.unique(regions).numel()),
              "views": len(weights), "rays": rays, "seconds": time.perf_counter() - t0,
              "cpu_seconds": time.process_time() - c0}
    return env, record
