"""The test-time normal filter (method/shading/normal_filter.py) on an analytic case, and how a run records it."""
from __future__ import annotations

import pytest
import torch
import yaml

from method.shading.normal_filter import edge_aware_normals


def _angle_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    a = a / a.norm(dim=-1, keepdim=True)
    b = b / b.norm(dim=-1, keepdim=True)
    return torch.rad2deg(torch.acos((a * b).sum(-1).clamp(-1, 1)))


def _step_scene(noise: float = 0.25, seed: int = 0):
    """A 24 x 24 image: a floor facing +z at depth 2 on the left half, a wall facing +x at depth 3 on the
    right, each pixel's normal jittered; a 3-pixel empty border at the top (alpha 0, depth 0)."""
    g = torch.Generator().manual_seed(seed)
    H = W = 24
    truth = torch.zeros(H, W, 3, dtype=torch.float64)
    truth[:, : W // 2, 2] = 1.0
    truth[:, W // 2:, 0] = 1.0
    depth = torch.full((H, W), 2.0, dtype=torch.float64)
    depth[:, W // 2:] = 3.0
    alpha = torch.ones(H, W, dtype=torch.float64)
    alpha[:3] = 0.0
    depth[:3] = 0.0
    noisy = truth + noise * torch.randn(H, W, 3, generator=g, dtype=torch.float64)
    noisy = noisy / noisy.norm(dim=-1, keepdim=True) * alpha[..., None]  # length = alpha, as rasterized
    return truth, noisy, alpha, depth


def test_the_filter_smooths_a_noisy_plane_and_mixes_nothing_across_a_depth_step():
    truth, noisy, alpha, depth = _step_scene()
    out = edge_aware_normals(noisy, alpha, depth, 1.0)
    inside = alpha > 0
    before = _angle_deg(noisy, truth)[inside]
    after = _angle_deg(out, truth)[inside]
    assert after.mean() < 0.6 * before.mean()  # the speckle goes (a 5 x 5 Gaussian: ~2x fewer degrees)
    # the two columns beside the step keep their own side's normal: averaged across it they would lean 20-45
    # degrees towards the other side (the depth weight off shows it)
    edge = inside.clone()
    edge[:, : 11] = False
    edge[:, 13:] = False
    assert _angle_deg(out, truth)[edge].max() < 20.0
    mixed = edge_aware_normals(noisy, alpha, depth, 1.0, depth_tolerance=1e6)
    assert _angle_deg(mixed, truth)[edge].mean() > 15.0 > _angle_deg(out, truth)[edge].mean() + 5.0
    # unit normals times alpha (the rasterizer's convention); nothing where nothing was hit
    torch.testing.assert_close(out.norm(dim=-1), alpha)
    assert float(out[~inside].abs().max()) == 0.0


def test_sigma_zero_leaves_the_normals_as_they_are_and_a_flat_plane_stays_flat():
    truth, noisy, alpha, depth = _step_scene()
    assert edge_aware_normals(noisy, alpha, depth, 0.0) is noisy
    flat = truth * alpha[..., None]
    out = edge_aware_normals(flat, alpha, depth, 1.5)
    torch.testing.assert_close(out, flat)


def test_a_low_alpha_neighbour_counts_less():
    """A pixel among faint neighbours of another orientation at the same depth keeps most of its own
    normal: neighbours count by their alpha."""
    H = W = 5
    depth = torch.full((H, W), 2.0, dtype=torch.float64)
    alpha = torch.full((H, W), 0.05, dtype=torch.float64)
    alpha[2, 2] = 1.0
    n = torch.zeros(H, W, 3, dtype=torch.float64)
    n[..., 0] = 1.0
    n[2, 2] = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    n = n * alpha[..., None]
    out = edge_aware_normals(n, alpha, depth, 1.0)
    centre = float(_angle_deg(out[2, 2], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)))
    weighted_equally = edge_aware_normals(n / alpha[..., None], torch.ones_like(alpha), depth, 1.0)
    assert centre < 10.0 < float(_angle_deg(weighted_equally[2, 2], torch.tensor([0.0, 0.0, 1.0],
                                                                                dtype=torch.float64)))


def test_a_run_records_the_filter_its_predictions_were_shaded_with(tmp_path):
    """The filter is a test-time setting: a resume of stage 2 under another value is not refused, writing the
    predictions records the value used, and the settings hash then tells the two apart (0, the value before
    the setting existed, hashes as a record without it)."""
    from method.config import load_method_config
    from method.run_record import (check_settings, identity, record_prediction_settings, settings_hash,
                                   write_record)

    small = load_method_config("small", [])
    assert small["stage2"]["normal_filter"] == 1.0
    off = load_method_config("small", ["stage2.normal_filter=0"])
    run = tmp_path / "run"
    write_record(run, off, identity(tmp_path / "s", "city", 0, "cpu", False))
    rec = yaml.safe_load((run / "config.yaml").read_text())
    del rec["stage2"]["normal_filter"]  # a run recorded before the setting
    (run / "config.yaml").write_text(yaml.safe_dump(rec, sort_keys=False))
    old_hash = settings_hash(run)
    check_settings(run, small, 2, "resuming stage 2")  # not refused: it trains the same
    record_prediction_settings(run, off)
    assert yaml.safe_load((run / "config.yaml").read_text())["stage2"]["normal_filter"] == 0.0
    assert settings_hash(run) == old_hash
    record_prediction_settings(run, small)
    assert yaml.safe_load((run / "config.yaml").read_text())["stage2"]["normal_filter"] == 1.0
    assert settings_hash(run) != old_hash
    fresh = tmp_path / "fresh"
    write_record(fresh, small, identity(tmp_path / "s", "city", 0, "cpu", False))
    assert settings_hash(fresh) == settings_hash(run)
    with pytest.raises(Exception, match="stage2.lr_albedo"):  # a training setting still is compared
        check_settings(run, load_method_config("small", ["stage2.lr_albedo=0.5"]), 2, "resuming stage 2")


def test_test_time_shading_filters_only_when_asked():
    """render_pbr_view (the predictions, relighting, the diagnostic) shades the normals filtered when
    stage2.normal_filter > 0 and as rasterized at 0; every other buffer is the same either way."""
    from method import buffers
    from method.config import load_method_config
    from method.shading.deferred import raster_materials, render_pbr_view, test_time_raster
    from tests.test_stage2_gradients import _setup

    s = _setup()
    v = s.view
    with torch.no_grad():
        d = s.scene.deform(v.time, p_mode="inference")
        plain = raster_materials(d, s.mats, v.camera, s.bg)
        for s2 in ({"normal_filter": 0.0}, {}):  # {}: a run recorded before the setting
            torch.testing.assert_close(test_time_raster(d, s.mats, v.camera, s.bg, s2).normal, plain.normal,
                                       rtol=0, atol=0)
        filt = test_time_raster(d, s.mats, v.camera, s.bg, {"normal_filter": 1.0})
    torch.testing.assert_close(filt.features, plain.features)
    torch.testing.assert_close(filt.normal, edge_aware_normals(plain.normal, plain.alpha, plain.depth_median, 1.0))
    assert float((filt.normal - plain.normal).abs().max()) > 1e-3  # the occluder's tilted normal meets the floor's
    for sigma in (0.0, 1.0):
        cfg = {**s.cfg, "stage2": {**s.cfg["stage2"], "normal_filter": sigma}}
        r = render_pbr_view(s.scene, s.mats, v.camera, v.time, s.bg, cfg, {}, 4, torch.Generator().manual_seed(0))
        want = filt.normal if sigma else plain.normal
        torch.testing.assert_close(r["normal"], buffers.unit(want))
