"""Stage 2 at `small` (method/env_fit.py, stage2.py): the sun-and-sky search, its orientation, the env freeze, and the
shading points lifted off the surface (stage2.normal_offset)."""
from __future__ import annotations

import math

import pytest
import torch

from method.env_fit import fit_sun_sky, spatial_regions, sun_sky_map, texel_directions
from method.shading.envmap import cosine_weights, texel_index, texel_moments

H, W = 16, 32


def test_texel_directions_land_in_their_own_texels():
    d = texel_directions(H, W)
    row, col = texel_index(d, H, W)
    assert torch.equal(row * W + col, torch.arange(H * W))
    assert torch.allclose(d.norm(dim=-1), torch.ones(H * W), atol=1e-6)
    assert d[0, 2] > 0.99 and d[-1, 2] < -0.99  # row 0 at the zenith


def _synthetic_scene(sun: tuple[int, int] | None, ratio: float, n: int = 800, seed: int = 0, lower: float = 1.0,
                     lift: float = 1.0):
    """Points with random upward normals, each with a random block of texels occluded (an object next to
    it), a textured albedo, and their radiance under a unit sky plus a sun texel."""
    g = torch.Generator().manual_seed(seed)
    nrm = torch.randn(n, 3, generator=g)
    nrm[:, 2] = nrm[:, 2].abs() + lift  # lift 0: normals down to the horizon (they see the ground)
    nrm = nrm / nrm.norm(dim=-1, keepdim=True)
    w = cosine_weights(nrm, texel_moments(H, W))
    vis = torch.ones(n, H, W)
    for i in range(n):
        if torch.rand(1, generator=g) < 0.6:
            r0 = int(torch.randint(0, H // 2, (1,), generator=g))
            c0 = int(torch.randint(0, W, (1,), generator=g))
            cols = [(c0 + j) % W for j in range(8)]
            vis[i, r0:r0 + 5][:, cols] = 0.0
    w = w * vis.reshape(n, -1)
    env = torch.ones(H, W)
    env[H // 2:] = lower
    if sun is not None:
        env[sun] += ratio
    albedo = torch.exp(0.4 * torch.randn(n, generator=g)) * 0.4  # texture: +-50 % about 0.4
    radiance = albedo * (w @ env.reshape(-1)) / math.pi
    return w, radiance


def test_fit_finds_the_sun_texel_and_ratio_through_texture_noise():
    w, y = _synthetic_scene((3, 11), 80.0)
    fit = fit_sun_sky(w, y, H, W)
    assert tuple(fit["texel"]) == (3, 11)
    assert 10 ** -0.15 < fit["ratio"] / 80.0 < 10 ** 0.15  # the grid's step is 10^0.1
    assert fit["mad"] < fit["mad_no_sun"]
    k = 3 * W + 11
    assert float((fit["ratio"] * w[:, k] / (w.sum(1) + fit["ratio"] * w[:, k])).median()) > 0.2  # the true sun: 0.29
    env = sun_sky_map(H, W, tuple(fit["texel"]), fit["ratio"], fit["scale"], fit["lower"])
    assert env.shape == (H, W, 3) and torch.equal(env[..., 0], env[..., 2])
    e = w @ env[..., 0].reshape(-1)
    assert float((e / math.pi).quantile(0.99)) == pytest.approx(1.0, rel=0.02)  # the level: the most lit points
    assert int(env[..., 0].argmax()) == 3 * W + 11


def test_coloured_fit_recovers_the_suns_colour_against_the_skys():
    """A warm sun over a blue sky (sunrise's chroma: sun / sky per channel 1.5 : 1 : 0.5 of the luminance
    ratio) and a grey ground: each channel's ratio recovered within the grid's step, and the map's sun, sky
    and ground carry those colours. A grey fit would give all three channels one ratio (chroma 1 : 1 : 1)."""
    sky = torch.tensor([0.7, 1.0, 1.3])
    sun = 60.0 * torch.tensor([1.5, 1.0, 0.5])
    w, _ = _synthetic_scene((3, 11), 80.0, seed=2)
    g = torch.Generator().manual_seed(3)
    n = w.shape[0]  # texture: +-35 % in brightness, +-10 % per channel about 0.4
    albedo = torch.exp(0.3 * torch.randn(n, 1, generator=g) + 0.1 * torch.randn(n, 3, generator=g)) * 0.4
    env = sky.expand(H * W, 3).clone()
    env[3 * W + 11] += sun
    rgb = albedo * (w @ env) / math.pi
    fit = fit_sun_sky(w, rgb, H, W)
    assert tuple(fit["texel"]) == (3, 11)
    want = sun / sky  # each channel's sun-to-sky ratio: 128.6, 60, 23.1
    got = torch.tensor(fit["colour"]["ratio"])
    assert ((got / want).log10().abs() < 0.15).all(), (got, want)
    c = fit["colour"]
    m = sun_sky_map(H, W, tuple(fit["texel"]), c["ratio"], c["scale"], c["lower"])
    sky_fit = m[0, 0] / m[0, 0].mean()
    assert torch.allclose(sky_fit, sky / sky.mean(), rtol=0.2), sky_fit  # blue sky
    sun_fit = m[3, 11] / m[3, 11].mean()
    assert sun_fit[0] > sun_fit[1] > sun_fit[2]  # warm sun
    e = (w @ m.reshape(-1, 3)) / math.pi
    assert torch.allclose(e.quantile(0.99, dim=0), torch.ones(3), rtol=0.02)  # each channel's level
    grey = sun_sky_map(H, W, tuple(fit["texel"]), fit["ratio"], fit["scale"], fit["lower"])
    assert torch.equal(grey[..., 0], grey[..., 2])  # one number each: a grey map, as before
    assert c["warm"]
    with pytest.raises(ValueError, match="radiance must be"):
        fit_sun_sky(w, rgb[:, :2], H, W)
    env = sky.flip(0).expand(H * W, 3).clone()  # a blue sun over a warm sky: not daylight's sun, not used
    env[3 * W + 11] += sun.flip(0)
    assert not fit_sun_sky(w, albedo * (w @ env) / math.pi, H, W)["colour"]["warm"]


def _wall_over_floor(wall_albedo: float, n: int = 600, seed: int = 0, sun=(3, 11), ratio: float = 80.0):
    """jumpingjacks in miniature: a floor (normals up, albedo 0.3) and a wall facing the sun's azimuth
    (albedo ``wall_albedo``), both textured +-20 % and with random blocks of the sky occluded; the points'
    positions put each in its own place. Returns (weights, radiance, positions)."""
    g = torch.Generator().manual_seed(seed)
    sd = texel_directions(H, W)[sun[0] * W + sun[1]]
    facing = torch.tensor([float(sd[0]), float(sd[1]), 0.0])
    facing = facing / facing.norm()
    floor = torch.tensor([0.0, 0.0, 1.0]).expand(n, 3) + 0.05 * torch.randn(n, 3, generator=g)
    wall = facing.expand(n, 3) + 0.05 * torch.randn(n, 3, generator=g)
    nrm = torch.cat([floor, wall])
    nrm = nrm / nrm.norm(dim=-1, keepdim=True)
    vis = torch.ones(2 * n, H, W)
    for i in range(2 * n):
        if torch.rand(1, generator=g) < 0.5:
            r0 = int(torch.randint(0, H // 2, (1,), generator=g))
            c0 = int(torch.randint(0, W, (1,), generator=g))
            vis[i, r0:r0 + 5][:, [(c0 + j) % W for j in range(8)]] = 0.0
    w = cosine_weights(nrm, texel_moments(H, W)) * vis.reshape(2 * n, -1)
    env = torch.ones(H * W)
    env[sun[0] * W + sun[1]] += ratio
    albedo = torch.cat([torch.full((n,), 0.3), torch.full((n,), wall_albedo)])
    radiance = albedo * torch.exp(0.2 * torch.randn(2 * n, generator=g)) * (w @ env) / math.pi
    on_floor = torch.rand(n, 3, generator=g) * 2 - 1
    on_floor[:, 2] = 0.0
    on_wall = -1.5 * facing + torch.rand(n, 3, generator=g) * torch.tensor([0.1, 0.1, 1.0])
    return w, radiance, torch.cat([on_floor, on_wall])


def test_regions_keep_a_bright_wall_from_reading_as_a_low_sun():
    """One grey albedo for the scene explains a white wall over a dark floor with a sun low in the wall's
    direction (the failure on jumpingjacks under city); each spatial region its own grey albedo leaves only
    the shading within each, and the fit finds the true texel. With one material both fits are right."""
    for seed in (0, 1):
        w, y, pos = _wall_over_floor(0.9, seed=seed)
        regions = spatial_regions(pos, 8, torch.Generator().manual_seed(0))
        assert tuple(fit_sun_sky(w, y, H, W)["texel"]) != (3, 11)  # the input exercises the rule: row 7 here
        fit = fit_sun_sky(w, y, H, W, regions=regions)
        assert tuple(fit["texel"]) == (3, 11)
        assert 10 ** -0.25 < fit["ratio"] / 80.0 < 10 ** 0.25
        assert fit["mad"] < fit["mad_no_sun"]
        w, y, pos = _wall_over_floor(0.3, seed=seed)
        assert tuple(fit_sun_sky(w, y, H, W)["texel"]) == (3, 11)
        assert tuple(fit_sun_sky(w, y, H, W, regions=regions)["texel"]) == (3, 11)
    one = fit_sun_sky(w, y, H, W, regions=torch.zeros(y.shape[0], dtype=torch.long))
    assert one == fit_sun_sky(w, y, H, W)  # one region: the scene-wide fit, to the last digit
    with pytest.raises(ValueError, match="regions must be"):
        fit_sun_sky(w, y, H, W, regions=torch.zeros(3, dtype=torch.long))


def test_spatial_regions_are_kmeans_clusters_of_the_positions():
    g = torch.Generator().manual_seed(0)
    blobs = torch.tensor([[0.0, 0, 0], [5.0, 0, 0], [0.0, 5, 0]])
    pts = (blobs[:, None, :] + 0.3 * torch.randn(3, 50, 3, generator=g)).reshape(-1, 3)
    labels = spatial_regions(pts, 3, torch.Generator().manual_seed(1))
    for b in range(3):  # each blob one label, the three labels different
        assert labels[b * 50:(b + 1) * 50].unique().numel() == 1
    assert labels.unique().numel() == 3
    assert torch.equal(labels, spatial_regions(pts, 3, torch.Generator().manual_seed(1)))  # seeded
    assert spatial_regions(pts, 1, g).eq(0).all() and spatial_regions(pts[:2], 3, g).eq(0).all()


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_fit_on_cuda_tensors_equals_the_cpu_fit():
    """Stage 2 on a GPU hands the fit CUDA tensors (a device mix failed there in session 16)."""
    w, y = _synthetic_scene((3, 11), 80.0)
    cpu, gpu = fit_sun_sky(w, y, H, W), fit_sun_sky(w.cuda(), y.cuda(), H, W)
    assert tuple(gpu["texel"]) == tuple(cpu["texel"]) and gpu["ratio"] == cpu["ratio"]
    assert gpu["scale"] == pytest.approx(cpu["scale"], rel=1e-9)


def test_fit_recovers_a_dark_ground():
    w, y = _synthetic_scene((4, 20), 50.0, lower=0.2, lift=0.0, seed=1)
    fit = fit_sun_sky(w, y, H, W)
    assert tuple(fit["texel"]) == (4, 20) and fit["lower"] in (0.1, 0.2, 0.35)
    env = sun_sky_map(H, W, tuple(fit["texel"]), fit["ratio"], fit["scale"], fit["lower"])
    assert float(env[-1, 0, 0] / env[0, 0, 0]) == pytest.approx(fit["lower"])


def test_fit_of_a_sunless_sky_puts_no_strong_sun_anywhere():
    w, y = _synthetic_scene(None, 0.0)
    fit = fit_sun_sky(w, y, H, W)
    k = fit["texel"][0] * W + fit["texel"][1]
    share = fit["ratio"] * w[:, k] / (w.sum(1) + fit["ratio"] * w[:, k])
    assert float(share.median()) < 0.1  # a texel picked from the noise, lighting little (the true sun above: 0.29)
    with pytest.raises(ValueError, match="no points"):
        fit_sun_sky(w[:0], y[:0], H, W)


def test_stage2_starts_from_the_fitted_map_and_logs_it(ci_dataset, tmp_path, monkeypatch):
    import json
    import shutil

    from method.__main__ import main
    from method.config import load_method_config
    from method.checkpoints import checkpoint_paths, load_checkpoint
    from method.train import train_stage2
    from tests.test_method_relight import TINY

    src = tmp_path / "src"
    assert main(["train", "--scene", str(ci_dataset), "--run-dir", str(src), "--no-progress", "--stage", "1"]
                + TINY) == 0
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    shutil.copy(checkpoint_paths(src, 1)[-1][1], run / "checkpoints")
    shutil.copy(src / "config.yaml", run / "config.yaml")
    cfg_args = TINY + ["stage2.iterations=2", "stage2.env_init_fit=true", "stage2.env_fit_views=2",
                       "stage2.env_fit_pixels=32", "stage2.env_fixed=true"]
    cfg = load_method_config("ci", cfg_args)
    train_stage2(ci_dataset, "city", run, cfg, seed=0, progress=False)
    first = json.loads((run / "log_stage2.jsonl").read_text().splitlines()[0])["env_fit"]
    assert first["views"] == 2 and first["points"] == 64 and first["rays"] > 0
    assert 1 < first["regions"] <= cfg["stage2"]["env_fit_regions"]  # each cluster of points its own grey albedo
    env = load_checkpoint(checkpoint_paths(run, 2)[-1][1], "cpu")["materials"]["env"]["log_radiance"].exp()
    want = sun_sky_map(H, W, tuple(first["texel"]), first["ratio"], first["scale"], first["lower"])
    assert torch.allclose(env, want, rtol=1e-5)  # fixed: the fitted map itself
    assert json.loads((run / "timings.json").read_text())["stage2"]["env_fit_seconds"] > 0
    assert torch.equal(env[..., 0], env[..., 2])  # grey unless asked for colour

    coloured = tmp_path / "coloured"  # the same stage 1, each channel its own sun-to-sky ratio and ground
    (coloured / "checkpoints").mkdir(parents=True)
    shutil.copy(checkpoint_paths(src, 1)[-1][1], coloured / "checkpoints")
    shutil.copy(src / "config.yaml", coloured / "config.yaml")
    import method.env_fit as env_fit

    real_fit, fits = env_fit.fit_sun_sky, []

    def fit_as_if(warm):  # the real fit, its sun declared warm or not: which map stage 2 starts from
        def fit(weights, radiance, h, w, **kw):
            out = real_fit(weights, radiance, h, w, **kw)
            out["colour"] = {"ratio": [40.0, 20.0, 10.0], "lower": [0.5, 0.3, 0.2], "scale": [0.2, 0.3, 0.4],
                             "warm": warm}
            fits.append(out)
            return out
        return fit

    for warm in (True, False):
        monkeypatch.setattr(env_fit, "fit_sun_sky", fit_as_if(warm))
        shutil.rmtree(coloured / "checkpoints")
        (coloured / "checkpoints").mkdir()
        shutil.copy(checkpoint_paths(src, 1)[-1][1], coloured / "checkpoints")
        train_stage2(ci_dataset, "city", coloured,
                     load_method_config("ci", [*cfg_args, "stage2.env_fit_colour=true"]), seed=0, progress=False)
        fit = fits[-1]
        assert list(fit["texel"]) == first["texel"] and fit["ratio"] == first["ratio"]  # the luminance search
        env = load_checkpoint(checkpoint_paths(coloured, 2)[-1][1], "cpu")["materials"]["env"]["log_radiance"].exp()
        c = fit["colour"]
        coloured_map = sun_sky_map(H, W, tuple(fit["texel"]), c["ratio"], c["scale"], c["lower"])
        assert torch.allclose(env, coloured_map if warm else want, rtol=1e-5)  # a sun bluer than its sky: grey


def _floor_scene(jitter: float):
    """A floor of overlapping flat splats at z ~ 0 (heights jittered by ``jitter``), normals up."""
    from method.model.gaussians import Gaussians
    from method.stage1 import DynamicScene

    g = torch.Generator().manual_seed(0)
    xs = torch.linspace(-1, 1, 21)
    pts = torch.stack(torch.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
    pts = torch.cat([pts, jitter * torch.randn(pts.shape[0], 1, generator=g)], 1)
    n = pts.shape[0]
    gs = Gaussians({"means": pts, "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                    "log_scales": torch.full((n, 2), math.log(0.08)), "opacity_logit": torch.full((n,), 4.0),
                    "colour_logit": torch.zeros(n, 3), "p_logit": torch.full((n,), -4.0)})
    return DynamicScene(gs, None, torch.zeros(3), 2.0)


def test_normal_offset_removes_self_shadowing_of_a_floor_under_a_low_sun():
    """A sun at the horizon lights a bumpy floor at a grazing angle: shadow rays that start on the surface
    hit the neighbouring splats (shadow acne) and darken it; lifted along the normal they do not, and the
    floor shades as it does with no visibility at all (nothing above it blocks the sky)."""
    from method.config import load_method_config
    from method.splat.camera import Camera
    from method.model.materials import Materials
    from method.shading.deferred import render_pbr_view

    scene = _floor_scene(0.01)
    env = torch.full((H, W, 3), 0.2)
    env[7, 5] = 200.0  # just above the horizon
    cam = Camera.look_at(torch.tensor([0.0, -1.2, 2.0]), torch.zeros(3), 32, 32)
    means = {}
    for lift in (0.0, 0.01):
        cfg = load_method_config("ci", [f"stage2.normal_offset={lift}", "stage2.indirect=false"])
        mats = Materials.init_from(scene, cfg)
        r = render_pbr_view(scene, mats, cam, 0.0, torch.zeros(3), cfg, {"sun": env}, 64,
                            torch.Generator().manual_seed(0))
        fg = r["alpha"] > 0.5
        means[lift] = float(r["relit:sun"][fg].mean())
    cfg = load_method_config("ci", ["stage2.normal_offset=0.0"])
    from method.shading.render import shade
    from method.shading.deferred import raster_materials, surface_points

    d = scene.deform(0.0)
    out = raster_materials(d, Materials.init_from(scene, cfg), cam, torch.zeros(3))
    pix = torch.nonzero((out.alpha > 0.5).reshape(-1)).squeeze(1)
    pts, view = surface_points(out, cam, pix)
    n = torch.nn.functional.normalize(out.normal.reshape(-1, 3)[pix], dim=-1)
    albedo = torch.full((pix.numel(), 3), 0.214)  # the canonical colour 0.5, linearised
    open_sky = float(shade(pts, n, view, albedo, torch.full((pix.numel(),), 0.75), env, 64,
                           torch.Generator().manual_seed(0)).detach().mean())
    assert means[0.0] < 0.8 * open_sky  # acne: the unlifted floor loses a fifth or more of its light
    assert means[0.01] == pytest.approx(open_sky, rel=0.05)


def test_the_fit_traces_from_lifted_points_as_shading_does(monkeypatch):
    """fit_env's visibility weights come from the same lifted points as stage 2's shading: on the bumpy
    floor under a horizon texel, the lifted fit sees that texel unshadowed (weight = its cosine weight);
    from the surface itself the floor shadows itself (acne) and the fit would read a sun that is not there
    as one that is hidden."""
    from types import SimpleNamespace

    import method.env_fit as env_fit
    from method.config import load_method_config
    from method.splat.camera import Camera
    from method.model.materials import Materials

    scene = _floor_scene(0.01)
    cam = Camera.look_at(torch.tensor([0.0, -1.2, 2.0]), torch.zeros(3), 32, 32)
    view = SimpleNamespace(time=0.0, camera=cam, alpha=torch.ones(32, 32), rgb=torch.full((32, 32, 3), 0.5))
    data = SimpleNamespace(train=[view], background=torch.zeros(3))
    captured = {}

    def fake_fit(weights, radiance, h, w, **kw):
        captured["w"] = weights
        return {"texel": (0, 0), "ratio": 1.0, "scale": 1.0, "lower": 1.0,
                "colour": {"ratio": [1.0] * 3, "scale": [1.0] * 3, "lower": [1.0] * 3, "warm": False}}

    monkeypatch.setattr(env_fit, "fit_sun_sky", fake_fit)
    texel = 7 * W + 5  # just above the horizon
    share = {}
    for lift in (0.0, 0.01):
        cfg = load_method_config("ci", [f"stage2.normal_offset={lift}", "stage2.env_fit_pixels=300"])
        env_fit.fit_env(scene, Materials.init_from(scene, cfg), data, cfg, torch.Generator().manual_seed(0))
        w = captured["w"]
        n = torch.tensor([[0.0, 0.0, 1.0]]).expand(w.shape[0], 3)  # the floor's normals
        open_sky = cosine_weights(n, texel_moments(H, W))[:, texel]
        share[lift] = float(w[:, texel].sum() / open_sky.sum())
    assert share[0.0] < 0.8  # acne: a fifth or more of the horizon texel's light lost
    assert share[0.01] == pytest.approx(1.0, abs=0.05)
