"""Deferred shading of the 2D Gaussians (paper, stage 2): rasterize colour, albedo, roughness, P and the
normal at a time, then shade chosen pixels by Monte Carlo over the hemisphere (method.shading.render)
with visibility and indirect light traced against the same Gaussians. Stage 2's step, its environment
map fit, relighting and the benchmark predictions all shade through here.
"""
from __future__ import annotations

import dataclasses

import torch

from lumibench.color import linear_to_srgb, srgb_to_linear
from method import buffers
from method.buffers import MATERIALS
from method.model.materials import Materials
from method.model.scene import Deformed, DynamicScene
from method.shading.envmap import luminance, texel_solid_angles
from method.shading.normal_filter import edge_aware_normals
from method.shading.render import shade, shade_maps
from method.shading.visibility import GaussianTracer, build_accel, lifted_points
from method.splat.camera import Camera
from method.splat.rasterize import RasterOutput, rasterize
from method.splat.trace import TraceAccel


def _channels(indirect, maps: list[int] | None):
    """``indirect`` restricted to the 3-channel groups of ``maps`` (all of it for None): one map's bounce light
    out of a tracer that carries several."""
    if maps is None:
        return indirect
    cols = [3 * m + c for m in maps for c in range(3)]
    return lambda o, dirs: indirect(o, dirs)[:, cols]


def display(rgb_linear: torch.Tensor) -> torch.Tensor:
    """Blender's Standard view transform: clip to [0, 1], then the sRGB transfer function."""
    return linear_to_srgb(rgb_linear.clamp(0.0, 1.0))


def raster_materials(d: Deformed, mats: Materials, camera: Camera, background: torch.Tensor) -> RasterOutput:
    """Rasterize the MATERIALS layout (colour, albedo, roughness, P) with the stage-1 colour on the background."""
    feats = buffers.pack(MATERIALS, colour=d.colours, albedo=mats.albedo_display(), roughness=mats.roughness(),
                         p=d.p)
    return rasterize(d.means, d.quats, d.scales, d.opacities, feats, camera,
                     buffers.background_for(MATERIALS, background, feats))


def normal_filter_sigma(s2: dict) -> float:
    """The test-time normal filter's sigma in pixels (``stage2.normal_filter``); a run recorded before the
    setting existed shaded without it (0, run_record.PREDATING)."""
    return float(s2.get("normal_filter", 0.0))


def test_time_raster(d: Deformed, mats: Materials, camera: Camera, background: torch.Tensor,
                     s2: dict) -> RasterOutput:
    """:func:`raster_materials` as test-time shading reads it (predictions, relighting, the diagnostic): the
    normal map edge-aware filtered when ``stage2.normal_filter`` > 0 (method/shading/normal_filter.py).
    Stage 2's training shades the unfiltered normals (filtering there as well costs albedo)."""
    out = raster_materials(d, mats, camera, background)
    sigma = normal_filter_sigma(s2)
    if sigma <= 0:
        return out
    return dataclasses.replace(out, normal=edge_aware_normals(out.normal, out.alpha, out.depth_median, sigma))


def accel_for(d: Deformed, cell_factor: float = 1.0, opacities: torch.Tensor | None = None) -> TraceAccel:
    """The tracer grid of the Gaussians at one time (``opacities``: those the grid is built with, default d's)."""
    return build_accel(d.means, d.quats, d.scales, d.opacities if opacities is None else opacities, cell_factor)


def tracer_for(d: Deformed, accel: TraceAccel, offset: float, indirect: bool, *, extent: float,
               replay: bool = False, radiance: torch.Tensor | None = None) -> GaussianTracer:
    """The tracer of the Gaussians at one time: visibility, and indirect light from their (stage-1) colours,
    or from ``radiance`` (N, 3k) linear (:func:`relit_radiance`)."""
    return GaussianTracer(d.means, d.quats, d.scales, d.opacities, d.colours if indirect else None, offset=offset,
                          extent=extent, accel=accel, replay=replay, radiance=radiance)


def relight_indirect(s2: dict) -> bool:
    """Whether test-time shading traces indirect light from the Gaussians relit under the test light
    (``stage2.relight_indirect``); a run recorded before the setting existed shaded without it."""
    return bool(s2.get("relight_indirect", False))


def relit_radiance(d: Deformed, mats: Materials, envs: list[torch.Tensor], camera_center: torch.Tensor, s2: dict,
                   albedo_scales: list[torch.Tensor | None] | None = None) -> torch.Tensor:
    """(N, 3 x len(envs)) linear radiance each Gaussian sends out when the scene is relit under each map: its
    albedo (linearised and clamped as shading clamps it, times the map's ``albedo_scales`` entry where one is
    given) / pi x the map's unshadowed irradiance at its normal, the normal turned towards the camera.

    Why: the paper relights with indirect light traced against the Gaussians with "colors evaluated from the
    rendering equation" under the new light (its stage-1 colours carry the training light). Here the
    Gaussians are diffuse and unshadowed at the bounce: one bounce of the test light, no specular, as the
    surfaces a shadow ray hits are seen from every side at once; the side is the one the camera sees
    (as the authors' tracer turns its normals)."""
    from method.shading.envmap import cosine_weights, texel_moments
    from method.shading.render import quadrature_sub
    from method.splat.splats import quat_to_rotmat

    with torch.no_grad():
        n = quat_to_rotmat(d.quats.detach())[:, :, 2]
        to_cam = camera_center.to(n) - d.means.detach()
        n = torch.where((n * to_cam).sum(-1, keepdim=True) < 0, -n, n)
        albedo = srgb_to_linear(mats.albedo_display().detach().to(n)).clamp(s2["albedo_min"], s2["albedo_max"])
        scales = albedo_scales if albedo_scales is not None else [None] * len(envs)
        if len(scales) != len(envs):
            raise ValueError(f"{len(envs)} maps but {len(scales)} albedo scales")
        weights: dict = {}  # the cosine weights depend on the normals and the map's size only
        out = []
        for env, scale in zip(envs, scales):
            hw = (int(env.shape[0]), int(env.shape[1]))
            if hw not in weights:
                weights[hw] = cosine_weights(n, texel_moments(*hw, quadrature_sub(hw[0]), device=n.device,
                                                              dtype=n.dtype))
            irradiance = weights[hw] @ env.to(n).reshape(-1, 3)
            a = albedo if scale is None else scaled_albedo(albedo, scale)
            out.append(a / torch.pi * irradiance)
        return torch.cat(out, 1)


def surface_points(out: RasterOutput, camera: Camera, pix: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World positions (from the camera-z depth) and unit directions towards the camera at flat pixel ids."""
    W = camera.width
    x = (pix % W).to(out.depth_expected.dtype) + 0.5
    y = torch.div(pix, W, rounding_mode="floor").to(out.depth_expected.dtype) + 0.5
    d_cam = torch.stack([(x - camera.cx) / camera.focal, (y - camera.cy) / camera.focal, torch.ones_like(x)], -1)
    d_world = d_cam @ camera.c2w[:3, :3].to(d_cam).T
    depth = out.depth_expected.reshape(-1)[pix]
    pts = camera.center.to(d_cam) + depth[:, None] * d_world
    view = -d_world / d_world.norm(dim=-1, keepdim=True)
    return pts, view


def common_grid(envs: list[torch.Tensor]) -> list[torch.Tensor] | None:
    """The maps on the finest grid among them, each texel repeated (a 16 x 32 map on a 64 x 128 grid is the
    same function under the nearest-texel lookup), when every size divides that grid; else None."""
    h = max(e.shape[0] for e in envs)
    w = max(e.shape[1] for e in envs)
    if any(h % e.shape[0] or w % e.shape[1] for e in envs):
        return None
    return [e.repeat_interleave(h // e.shape[0], 0).repeat_interleave(w // e.shape[1], 1) for e in envs]


def sampling_mixture(envs: list[torch.Tensor]) -> torch.Tensor | None:
    """One proposal for several maps: each map scaled to unit total power, then averaged, so every map's
    bright texels (a small sun) keep their share of the samples. Maps of different sizes are mixed on the
    finest grid (:func:`common_grid`); None when their sizes do not divide it (each map samples itself)."""
    if len({tuple(e.shape) for e in envs}) > 1:
        envs = common_grid(envs)
        if envs is None:
            return None
    out = None
    for e in envs:
        h, w = e.shape[:2]
        power = float((luminance(e).clamp_min(0) * texel_solid_angles(h, w, e.device, e.dtype)).sum())
        part = e / max(power, 1e-12)
        out = part if out is None else out + part
    return out / len(envs)


def pixel_inputs(out: RasterOutput, camera: Camera, pix: torch.Tensor, s2: dict, tracer: GaussianTracer | None,
                 albedo_scale: torch.Tensor | None = None, override: dict | None = None):
    """What shade() takes at the pixels ``pix`` (flat ids): points (lifted off the surface when traced),
    unit normals, view directions, linear albedo (clamped as stage 2 clamps it, then scaled) and roughness;
    ``override`` as in :func:`shade_pixels`."""
    a = out.alpha.reshape(-1)[pix]
    f = out.features.reshape(-1, out.features.shape[-1])[pix]
    albedo = srgb_to_linear(buffers.channel(f, a, MATERIALS.albedo)).clamp(s2["albedo_min"], s2["albedo_max"])
    if albedo_scale is not None:
        albedo = scaled_albedo(albedo, albedo_scale)
    rough = buffers.channel(f, a, MATERIALS.roughness)
    n = buffers.unit(out.normal.reshape(-1, 3)[pix])
    if override:
        albedo = override.get("albedo", albedo)
        rough = override.get("roughness", rough)
        n = override.get("normal", n)
    pts, view = surface_points(out, camera, pix)
    if tracer is not None:
        pts = lifted_points(pts, n, view, float(s2["normal_offset"]) * tracer.extent)
    return pts, n, view, albedo, rough


def scaled_albedo(albedo: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Linear albedo multiplied per channel by ``scale`` (3,) and kept in [0, 1] (the `lumimotion` protocol's
    alignment before shading)."""
    return (albedo * scale.to(albedo)).clamp(0.0, 1.0)


def shade_pixels(out: RasterOutput, camera: Camera, pix: torch.Tensor, s2: dict, env: torch.Tensor,
                 n_dirs: int, generator: torch.Generator, tracer: GaussianTracer | None, sampling_env=None,
                 albedo_scale: torch.Tensor | None = None, override: dict | None = None):
    """Linear RGB of the pixels ``pix`` (flat ids) shaded under ``env``; also their albedo (linear) and
    roughness. ``s2``: the stage-2 settings (albedo clamp, normal lift, env quadrature). ``albedo_scale``
    (3,): the linear albedo multiplied per channel (and kept in [0, 1]) before shading. ``override``: any of
    "albedo" (P, 3 linear), "roughness" (P,), "normal" (P, 3 unit) used instead of the rasterized buffer
    (method/diagnose.py puts the ground truth there; the points and the visibility stay ours)."""
    pts, n, view, albedo, rough = pixel_inputs(out, camera, pix, s2, tracer, albedo_scale, override)
    vis = tracer.visibility if tracer is not None else None
    ind = tracer.indirect if (tracer is not None and tracer.use_indirect) else None
    rgb = shade(pts.detach(), n, view, albedo, rough, env, n_dirs, generator, visibility=vis, indirect=ind,
                sampling_env=sampling_env, env_quadrature=bool(s2["env_quadrature"]))
    return rgb, albedo, rough


@torch.no_grad()
def render_pbr_view(scene: DynamicScene, mats: Materials, camera: Camera, t: float, background: torch.Tensor,
                    cfg: dict, envs: dict[str, torch.Tensor], n_dirs: int, generator: torch.Generator,
                    accel: TraceAccel | None = None, indirect: bool = False,
                    albedo_scale: torch.Tensor | None = None) -> dict:
    """Full-image maps of one view: NVS colour, albedo (linear), roughness, normal, alpha, P, and the
    relit linear RGB under each env map of ``envs`` (visibility traced; indirect light off by default,
    since the stage-1 colours carry the training light); with ``albedo_scale`` (3,) also ``relit_scaled:``
    each map, shaded with the albedo scaled per channel (the same directions and traversals). Without
    ``indirect``, ``stage2.relight_indirect`` traces indirect light from the Gaussians relit under each map
    (:func:`relit_radiance`; with ``albedo_scale``, the scaled pass's bounce light scaled too)."""
    s2 = cfg["stage2"]
    d = scene.deform(t, p_mode="inference")
    out = test_time_raster(d, mats, camera, background, s2)
    H, W = camera.height, camera.width
    a = out.alpha.clamp(0, 1)
    fg = torch.nonzero((a > 0.5).reshape(-1)).squeeze(1)
    res = {"nvs": out.features[..., MATERIALS.colour].clamp(0, 1), "alpha": a,
           "albedo": srgb_to_linear(buffers.channel(out.features, a, MATERIALS.albedo)),
           "roughness": buffers.channel(out.features, a, MATERIALS.roughness),
           "normal": buffers.unit(out.normal),
           "p": buffers.channel(out.features, a, MATERIALS.p)}
    if fg.numel() and envs:
        acc = accel if accel is not None else accel_for(d, s2["trace_cell"])
        # one direction set for every map (env samples drawn from the maps' mixture): the directions, the BRDF
        # and the traversals serve every map (shade_maps); maps of different sizes (a 128 x 64 light beside
        # 32 x 16 ones) share one proposal on the finest grid, and where their sizes do not divide it each
        # map samples itself and the traversals are traced again
        env_list = [e.to(a) for e in envs.values()]
        mixture = sampling_mixture(env_list) if len(envs) > 1 else None
        relit = not indirect and relight_indirect(s2)
        # with relit bounce light the scaled pass has its own (the hit Gaussians' albedo scaled too): each map
        # is shaded twice from the same directions and traversals, its second copy lit by the scaled bounce
        copies = 2 if (relit and albedo_scale is not None) else 1
        radiance = None
        if relit:
            radiance = relit_radiance(d, mats, env_list * copies, camera.center, s2,
                                      [None] * len(env_list) + [albedo_scale] * (copies - 1) * len(env_list))
        tracer = tracer_for(d, acc, s2["trace_offset"] * scene.extent, indirect, extent=scene.extent,
                            radiance=radiance)
        pts, n, view, albedo, rough = pixel_inputs(out, camera, fg, s2, tracer)
        kw = dict(visibility=tracer.visibility, env_quadrature=bool(s2["env_quadrature"]))
        if mixture is not None or len(envs) == 1:  # one set of directions and traversals serves every map
            maps = shade_maps(pts.detach(), n, view, albedo, rough, env_list * copies, n_dirs, generator,
                              sampling_env=mixture if mixture is not None else env_list[0],
                              indirect=tracer.indirect if tracer.use_indirect else None, **kw)
        else:  # no shared proposal: each map samples itself, from the same generator state
            start = generator.get_state()
            per_env = []
            for i, env in enumerate(env_list):
                generator.set_state(start)
                ind = None
                if tracer.use_indirect:
                    cols = [i + k * len(env_list) for k in range(copies)] if relit else None
                    ind = _channels(tracer.indirect, cols)
                per_env.append(shade_maps(pts.detach(), n, view, albedo, rough, [env] * copies, n_dirs, generator,
                                          sampling_env=env, indirect=ind, **kw))
            maps = [m[0] for m in per_env] + ([m[1] for m in per_env] if copies > 1 else [])
        # the scaled albedo shades with the same irradiance: diffuse albedo' / pi x E, the specular part as it is
        # (with relit bounce light, the irradiance of the map's second copy, lit by the scaled bounce)
        scaled = None if albedo_scale is None else scaled_albedo(albedo, albedo_scale)
        for i, (name, m) in enumerate(zip(envs, maps)):
            passes = [("relit", m["rgb"])]
            if scaled is not None:
                ms = maps[len(env_list) + i] if copies > 1 else m
                passes.append(("relit_scaled", scaled / torch.pi * ms["irradiance"] + ms["specular"]))
            for tag, rgb in passes:
                img = torch.zeros(H * W, 3, dtype=rgb.dtype, device=rgb.device)
                img[fg] = rgb
                res[f"{tag}:{name}"] = img.reshape(H, W, 3)
    return res
