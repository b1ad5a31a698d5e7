"""Indirect light at test time from the Gaussians relit under the test light (stage2.relight_indirect,
method/shading/deferred.py relit_radiance): the bounce radiance on analytic maps, one channel group per map in
the shading, and the `lumimotion` protocol's scaled pass lit by the scaled bounce."""
from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from lumibench.color import linear_to_srgb, srgb_to_linear
from method.shading.deferred import relit_radiance
from method.shading.render import shade_maps

S2 = {"albedo_min": 0.03, "albedo_max": 0.97}


class _Albedo:
    """What relit_radiance reads of the materials: the albedo as displayed (sRGB-encoded)."""

    def __init__(self, display: torch.Tensor):
        self.display = display

    def albedo_display(self) -> torch.Tensor:
        return self.display


def _gaussians(normal_sign: float):
    """Two Gaussians at the origin and at (1, 0, 0), each a disc in the xy plane (normal +z; -z when
    ``normal_sign`` is -1: a quarter turn about x twice)."""
    q = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2, dtype=torch.float64)
    if normal_sign < 0:
        q = torch.tensor([[0.0, 1.0, 0.0, 0.0]] * 2, dtype=torch.float64)  # 180 degrees about x: normal -z
    return SimpleNamespace(quats=q, means=torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64))


def _upper_half_map(radiance) -> torch.Tensor:
    """A 16 x 32 map lit with ``radiance`` above the horizon (rows 0-7: polar angles 0 to 90 degrees), dark below."""
    env = torch.zeros(16, 32, 3, dtype=torch.float64)
    env[:8] = torch.tensor(radiance, dtype=torch.float64)
    return env


def test_bounce_radiance_is_albedo_over_pi_times_the_irradiance_of_the_side_the_camera_sees():
    lin = torch.tensor([[0.2, 0.4, 0.6], [0.5, 0.1, 0.3]], dtype=torch.float64)
    mats = _Albedo(linear_to_srgb(lin))
    L = (0.5, 1.0, 2.0)
    uniform = torch.tensor(L, dtype=torch.float64).expand(16, 32, 3).clone()
    above, below = torch.tensor([0.3, -0.2, 3.0]), torch.tensor([0.3, -0.2, -3.0])
    for sign in (1.0, -1.0):  # the disc's own orientation does not matter: it is turned to the camera
        d = _gaussians(sign)
        # a uniform sky: irradiance pi L on either side, so the bounce is albedo x L
        out = relit_radiance(d, mats, [uniform], above, S2)
        torch.testing.assert_close(out, lin * torch.tensor(L, dtype=torch.float64), rtol=2e-3, atol=0)
        # a sky lit above the horizon only: seen from above, the lit side (pi L); from below, the dark side (0)
        half = _upper_half_map(L)
        torch.testing.assert_close(relit_radiance(d, mats, [half], above, S2), lin * torch.tensor(L), rtol=2e-3,
                                   atol=0)
        assert float(relit_radiance(d, mats, [half], below, S2).abs().max()) < 1e-12


def test_one_channel_group_per_map_in_order_each_with_its_albedo_scale():
    lin = torch.tensor([[0.2, 0.4, 0.6], [0.5, 0.1, 0.3]], dtype=torch.float64)
    mats = _Albedo(linear_to_srgb(lin))
    d = _gaussians(1.0)
    cam = torch.tensor([0.0, 0.0, 2.0])
    a = _upper_half_map((1.0, 1.0, 1.0))
    b = _upper_half_map((0.2, 0.3, 4.0))
    scale = torch.tensor([2.0, 0.5, 1.0], dtype=torch.float64)
    out = relit_radiance(d, mats, [a, b, b], cam, S2, [None, None, scale])
    assert out.shape == (2, 9)
    torch.testing.assert_close(out[:, 0:3], lin, rtol=2e-3, atol=0)
    torch.testing.assert_close(out[:, 3:6], lin * torch.tensor([0.2, 0.3, 4.0], dtype=torch.float64), rtol=2e-3,
                               atol=0)
    # the scaled albedo is kept in [0, 1] (0.6 x 2 = 1.2 -> 1), as the scaled relight's primary albedo is
    want = (lin * scale).clamp(0, 1) * torch.tensor([0.2, 0.3, 4.0], dtype=torch.float64)
    torch.testing.assert_close(out[:, 6:9], want, rtol=2e-3, atol=0)
    # the albedo shading clamps: a display value of 0 shades as albedo_min
    dark = relit_radiance(d, _Albedo(torch.zeros(2, 3, dtype=torch.float64)), [a], cam, S2)
    torch.testing.assert_close(dark, torch.full((2, 3), 0.03, dtype=torch.float64), rtol=2e-3, atol=0)
    with pytest.raises(ValueError, match="albedo scales"):
        relit_radiance(d, mats, [a, b], cam, S2, [None])


def test_shade_maps_gives_each_map_its_own_bounce_light():
    """An indirect callable with 3 channels per map: map i is shaded with its group, exactly as shading that
    map alone with that group (same directions from the shared proposal)."""
    g = torch.Generator().manual_seed(3)
    P = 40
    normals = torch.nn.functional.normalize(torch.randn(P, 3, generator=g, dtype=torch.float64) * 0.3
                                            + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), dim=-1)
    view = torch.nn.functional.normalize(normals + 0.3 * torch.randn(P, 3, generator=g, dtype=torch.float64), dim=-1)
    pts = torch.randn(P, 3, generator=g, dtype=torch.float64)
    albedo = 0.2 + 0.6 * torch.rand(P, 3, generator=g, dtype=torch.float64)
    rough = 0.3 + 0.5 * torch.rand(P, generator=g, dtype=torch.float64)
    maps = [_upper_half_map((1.0, 0.8, 0.6)), 0.5 + torch.rand(16, 32, 3, generator=g, dtype=torch.float64)]
    mix = (maps[0] + maps[1]) / 2

    def visibility(o, dirs):  # half the sky blocked, smoothly
        return 0.5 + 0.4 * dirs[:, 0]

    def bounce(o, dirs):  # a different bounce per map
        return torch.cat([0.3 + 0.2 * dirs.abs(), 2.0 + dirs[:, [2, 0, 1]]], 1)

    both = shade_maps(pts, normals, view, albedo, rough, maps, 64, torch.Generator().manual_seed(9), visibility,
                      bounce, sampling_env=mix, env_quadrature=True)
    for i in range(2):
        alone = shade_maps(pts, normals, view, albedo, rough, [maps[i]], 64, torch.Generator().manual_seed(9),
                           visibility, lambda o, dirs, i=i: bounce(o, dirs)[:, 3 * i:3 * i + 3], sampling_env=mix,
                           env_quadrature=True)[0]
        for k in ("rgb", "irradiance", "specular"):
            torch.testing.assert_close(both[i][k], alone[k], rtol=1e-12, atol=1e-12)
    # the two bounces differ, so a map shaded with the other's group would show it
    wrong = shade_maps(pts, normals, view, albedo, rough, [maps[1]], 64, torch.Generator().manual_seed(9), visibility,
                       lambda o, dirs: bounce(o, dirs)[:, 0:3], sampling_env=mix, env_quadrature=True)[0]
    assert float((both[1]["irradiance"] - wrong["irradiance"]).abs().max()) > 0.1
    with pytest.raises(ValueError, match="3 x 2"):
        shade_maps(pts, normals, view, albedo, rough, maps, 64, torch.Generator().manual_seed(9), visibility,
                   lambda o, dirs: bounce(o, dirs)[:, :4], sampling_env=mix)


def _scaled_materials(mats, scale: torch.Tensor):
    """A copy of ``mats`` whose albedo is ``scale`` x its linear albedo (the same roughness and map)."""
    from method.model.materials import Materials
    from method.model.gaussians import inverse_sigmoid

    lin = srgb_to_linear(mats.albedo_display().detach())
    disp = linear_to_srgb(lin * scale)
    return Materials(inverse_sigmoid(disp), mats.roughness_logit.detach().clone(), mats.env)


def test_relighting_traces_the_relit_bounce_and_the_scaled_pass_is_a_model_with_the_scaled_albedo():
    """render_pbr_view with stage2.relight_indirect: (1) the floor under the occluder gets the occluder's bounce
    light (brighter than without, nowhere darker); (2) the `lumimotion` protocol's scaled pass equals relighting
    a model whose albedo is scaled, its bounce included (the same directions: one map)."""
    from tests.test_stage2_gradients import _setup
    from method.shading.deferred import render_pbr_view

    s = _setup()
    v = s.view
    env = {"sun": _upper_half_map((0.4, 0.5, 0.7)) + 0.0}
    env["sun"][2:4, 5:7] = torch.tensor([30.0, 28.0, 25.0], dtype=torch.float64)  # a sun high in the sky
    scale = torch.tensor([1.4, 1.1, 1.2], dtype=torch.float64)
    lin = srgb_to_linear(s.mats.albedo_display().detach())
    assert float((lin * scale).max()) < 0.97 and float(lin.min()) > 0.03  # no clamp on either side
    runs = {}
    for on in (False, True):
        cfg = {**s.cfg, "stage2": {**s.cfg["stage2"], "relight_indirect": on, "normal_filter": 0.0}}
        with torch.no_grad():
            runs[on] = render_pbr_view(s.scene, s.mats, v.camera, v.time, s.bg, cfg, env, 256,
                                       torch.Generator().manual_seed(0), albedo_scale=scale)
            if on:
                model = render_pbr_view(s.scene, _scaled_materials(s.mats, scale), v.camera, v.time, s.bg, cfg, env,
                                        256, torch.Generator().manual_seed(0))
    off, on = runs[False]["relit:sun"], runs[True]["relit:sun"]
    assert float((on - off).min()) > -1e-9  # the bounce adds light
    assert float((on - off).max()) > 1e-3  # and there is some (under the occluder)
    torch.testing.assert_close(runs[True]["relit_scaled:sun"], model["relit:sun"], rtol=1e-9, atol=1e-9)
    # without the setting (a run recorded before it), the relight is today's: no indirect light
    cfg = {**s.cfg, "stage2": {k: v for k, v in s.cfg["stage2"].items() if k != "relight_indirect"}}
    cfg["stage2"]["normal_filter"] = 0.0
    with torch.no_grad():
        old = render_pbr_view(s.scene, s.mats, v.camera, v.time, s.bg, cfg, env, 256, torch.Generator().manual_seed(0),
                              albedo_scale=scale)
    torch.testing.assert_close(old["relit:sun"], off, rtol=0, atol=0)
    assert math.isfinite(float(on.sum()))


def test_maps_without_a_shared_proposal_each_get_their_own_bounce():
    """Maps whose sizes share no grid (16 x 32 and 12 x 24) are shaded one by one (render_pbr_view's second
    branch), each with its own channel groups of the tracer: every map's relit and scaled images equal those
    of relighting under that map alone."""
    from tests.test_stage2_gradients import _setup
    from method.shading.deferred import render_pbr_view

    s = _setup()
    v = s.view
    g = torch.Generator().manual_seed(5)
    envs = {"a": _upper_half_map((0.4, 0.5, 0.7)) + 0.0,
            "b": 0.2 + torch.rand(12, 24, 3, generator=g, dtype=torch.float64)}
    envs["a"][2:4, 5:7] = torch.tensor([30.0, 28.0, 25.0], dtype=torch.float64)
    envs["b"][1, 3] = torch.tensor([5.0, 40.0, 9.0], dtype=torch.float64)  # a green sun elsewhere: another bounce
    scale = torch.tensor([1.4, 1.1, 1.2], dtype=torch.float64)
    cfg = {**s.cfg, "stage2": {**s.cfg["stage2"], "relight_indirect": True, "normal_filter": 0.0}}
    with torch.no_grad():
        both = render_pbr_view(s.scene, s.mats, v.camera, v.time, s.bg, cfg, envs, 64,
                               torch.Generator().manual_seed(0), albedo_scale=scale)
        for name, env in envs.items():
            alone = render_pbr_view(s.scene, s.mats, v.camera, v.time, s.bg, cfg, {name: env}, 64,
                                    torch.Generator().manual_seed(0), albedo_scale=scale)
            for tag in ("relit", "relit_scaled"):
                torch.testing.assert_close(both[f"{tag}:{name}"], alone[f"{tag}:{name}"], rtol=1e-10, atol=1e-10)
