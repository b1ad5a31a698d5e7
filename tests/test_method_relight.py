"""`python -m method relight` and the stage-2 bad-input cases, on a tiny trained run."""
from __future__ import annotations

import pytest

TINY = ["stage1.iterations=12", "stage1.init_points=300", "stage1.max_gaussians=0", "stage1.warmup=4",
        "stage1.densify_from=100", "stage1.eval_every=0", "stage2.iterations=6", "stage2.dirs_train=8",
        "stage2.dirs_eval=8", "stage2.rays_per_iteration=512"]


@pytest.fixture(scope="module")
def tiny_run(ci_dataset, tmp_path_factory):
    from method.__main__ import main

    run = tmp_path_factory.mktemp("tiny_run") / "run"
    assert main(["train", "--scene", str(ci_dataset), "--run-dir", str(run), "--no-progress"] + TINY) == 0
    return run


def test_train_writes_both_stages_and_predictions(tiny_run):
    import json

    assert (tiny_run / "metrics_stage2.json").is_file()
    t = json.loads((tiny_run / "timings.json").read_text())
    assert t["stage1"]["iterations"] == 12 and t["stage2"]["iterations"] == 6 and t["stage2"]["rays_traced"] > 0
    meta = json.loads((tiny_run / "predictions" / "meta.json").read_text())
    assert meta["method"] == "lumimotion" and set(meta["timings"]) == {"stage1", "stage2"}
    # CPU seconds of both stages (stage 2's with its environment fit), which a loaded machine does not stretch
    assert set(meta["cpu_timings"]) == {"stage1", "stage2"} and all(v > 0 for v in meta["cpu_timings"].values())
    assert meta["cpu_timings"]["stage2"] == t["stage2"]["cpu_seconds"] > t["stage2"]["cpu_seconds_this_session"]


def test_relight_test_views_and_orbit(ci_dataset, tiny_run, tmp_path):
    import numpy as np

    from lumibench.io import read_image
    from method.__main__ import main

    out = tmp_path / "sunset"
    assert main(["relight", "--run", str(tiny_run), "--envmap", "sunset", "--out", str(out), "--dirs", "8"]) == 0
    stems = sorted(p.stem for p in (out / "relit").glob("*.png"))
    assert stems == ["r_0000", "r_0001", "r_0002", "r_0003"]
    for kind in ("albedo", "roughness", "normal"):
        assert (out / kind / "r_0000.png").is_file(), kind
    alb = np.load(out / "albedo" / "r_0000.npz")["image"]
    assert alb.shape == (64, 64, 3) and np.isfinite(alb).all()
    for name in ("envmap_estimated_clipped.png", "envmap_estimated_scaled.png", "envmap_estimated.hdr"):
        assert (out / name).is_file(), name
    assert read_image(out / "envmap_estimated_scaled.png").max() == pytest.approx(1.0, abs=1 / 255)
    orbit = tmp_path / "orbit"
    hdr = ci_dataset / "city.hdr"
    assert main(["relight", "--run", str(tiny_run), "--envmap", str(hdr), "--views", "orbit", "--frames", "3",
                 "--time", "0.5", "--out", str(orbit), "--dirs", "8"]) == 0
    assert len(list((orbit / "relit").glob("orbit_*.png"))) == 3 and (orbit / "relit_orbit.gif").is_file()


def test_relight_and_stage2_bad_input(ci_dataset, tiny_run, tmp_path, capsys):
    from method.__main__ import main

    bad = tmp_path / "bad.hdr"
    bad.write_bytes(b"not an hdr file")
    cases = [
        (["relight", "--run", str(tiny_run), "--envmap", str(bad)], "bad.hdr"),
        (["relight", "--run", str(tmp_path / "nowhere"), "--envmap", "city"], "not a run directory"),
        (["relight", "--run", str(tiny_run), "--envmap", "moonlight"], "unknown environment map 'moonlight'"),
        (["train", "--scene", str(ci_dataset), "--stage", "2", "--run-dir", str(tmp_path / "fresh"), "--no-progress"],
         "no stage-1 checkpoint"),
    ]
    for argv, needle in cases:
        rc = main(argv)
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1 and needle in err[0], (argv, err)


def test_stage2_records_its_own_settings_in_the_run_config(ci_dataset, tiny_run, tmp_path):
    import shutil

    import yaml

    from lumibench.errors import UserError
    from method.config import load_method_config
    from method.checkpoints import checkpoint_paths
    from method.train import train_stage2

    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    shutil.copy(checkpoint_paths(tiny_run, 1)[-1][1], run / "checkpoints")
    shutil.copy(tiny_run / "config.yaml", run / "config.yaml")
    before = yaml.safe_load((run / "config.yaml").read_text())
    # a stage-1 setting other than the one stage 1 trained with is refused, naming it; the record is unchanged
    other = load_method_config("ci", TINY + ["stage2.iterations=2", "stage1.lr_p=0.5"])
    with pytest.raises(UserError, match="stage1.lr_p=0.02"):
        train_stage2(ci_dataset, "city", run, other, seed=0, progress=False)
    assert yaml.safe_load((run / "config.yaml").read_text()) == before
    cfg = load_method_config("ci", TINY + ["stage2.iterations=2", "stage2.lr_env=0.123"])
    train_stage2(ci_dataset, "city", run, cfg, seed=0, progress=False)
    after = yaml.safe_load((run / "config.yaml").read_text())
    assert after["stage2"]["lr_env"] == 0.123 and after["stage2"]["iterations"] == 2
    assert after["stage1"] == before["stage1"] and after["run"] == before["run"]  # stage 1 ran with these


def test_score_checkpoint_matches_the_benchmark_on_the_runs_predictions(ci_dataset, tiny_run):
    """The quick stage-2 scorer reads the same albedo and roughness numbers as `benchmark score` on the
    predictions the run wrote (same maps, same 8-bit rounding, alignment and masks)."""
    from benchmark.score import score as bench_score
    from method.score_checkpoint import score

    quick = score(tiny_run)
    full = bench_score(ci_dataset, tiny_run / "predictions", "city", "sunrise")["metrics"]
    assert quick["views"] == 4
    assert quick["albedo_psnr"] == pytest.approx(full["albedo"]["psnr"], abs=1e-4)
    assert quick["albedo_ssim"] == pytest.approx(full["albedo"]["ssim"], abs=1e-5)
    assert quick["roughness_mse"] == pytest.approx(full["roughness"]["mse"], rel=1e-5)
    colour = score(tiny_run, colour=True)  # the canonical colour is a different albedo
    assert abs(colour["albedo_psnr"] - quick["albedo_psnr"]) > 1e-3


def test_a_fixed_env_map_is_kept_and_not_optimised(ci_dataset, tiny_run, tmp_path):
    """stage2.env_fixed: the start map leaves stage 2 unchanged and has no optimiser group; the materials learn."""
    import shutil

    import torch

    from method.checkpoints import checkpoint_paths, load_checkpoint
    from method.config import load_method_config
    from method.train import train_stage2

    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    shutil.copy(checkpoint_paths(tiny_run, 1)[-1][1], run / "checkpoints")
    # the uniform start (the ci profile fits one: env_init_fit), so that "unchanged" is the known constant
    cfg = load_method_config("ci", TINY + ["stage2.iterations=3", "stage2.env_fixed=true", "stage2.env_init_fit=false"])
    train_stage2(ci_dataset, "city", run, cfg, seed=0, progress=False)
    ck = load_checkpoint(checkpoint_paths(run, 2)[-1][1], "cpu")
    env = ck["materials"]["env"]["log_radiance"]
    assert torch.equal(env, torch.full_like(env, float(torch.tensor(cfg["stage2"]["env_init"]).log())))
    assert "env" not in {g["name"] for g in ck["opt"]["param_groups"]}
    assert {"albedo", "roughness", "colour", "opacity"} <= {g["name"] for g in ck["opt"]["param_groups"]}


def test_predictions_relight_with_the_albedo_scaled_as_the_benchmark_aligns_it(ci_dataset, tiny_run):
    """relight_scaled/: the test views relit with the albedo multiplied per channel, before shading, by the
    scale the benchmark's albedo alignment finds on the same predictions (the authors' rule); the scale is
    in meta.json, and a scale of one gives the plain relight exactly (same directions, same traversals)."""
    import json

    import torch

    from benchmark.score import score
    from method.checkpoints import load_trained
    from method.config import load_method_config
    from method.data import load_scene
    from method.shading.deferred import render_pbr_view
    from method.shading.envmap import load_envmap

    pred = tiny_run / "predictions"
    meta = json.loads((pred / "meta.json").read_text())
    res = score(ci_dataset, pred, "city", "sunrise", protocol="lumimotion")
    assert meta["relight_albedo_scale"] == pytest.approx(res["metrics"]["albedo"]["scale"], rel=1e-9)
    assert res["metrics"]["relight"]["albedo_scale"] == meta["relight_albedo_scale"]
    assert abs(meta["relight_albedo_scale"][0] - 1.0) > 0.02  # the scale matters on this run
    for stem in ("r_0000", "r_0001"):
        a = (pred / "relight" / "sunrise" / f"{stem}.png").read_bytes()
        b = (pred / "relight_scaled" / "sunrise" / f"{stem}.png").read_bytes()
        assert a != b
    cfg = load_method_config("ci", TINY)
    scene, mats = load_trained(tiny_run, cfg, "cpu")
    v = load_scene(ci_dataset, "city", cfg["data"]["background"], "cpu").test[0]
    env = {"sunrise": load_envmap("sunrise", ci_dataset, height=None, width=None)}
    r = render_pbr_view(scene, mats, v.camera, v.time, torch.ones(3), cfg, env, 8, torch.Generator().manual_seed(0),
                        albedo_scale=torch.ones(3))
    assert torch.equal(r["relit:sunrise"], r["relit_scaled:sunrise"])


def test_diagnose_swaps_one_buffer_at_a_time_with_the_same_samples(ci_dataset, tiny_run, tmp_path, monkeypatch):
    """`python -m method diagnose`: every step shades the same pixels with the same directions (a step that
    swaps nothing equals "ours" exactly), and a swapped buffer is the one the step names."""
    import json

    import torch

    import method.diagnose as dg
    from method.__main__ import main

    # "gt_albedo_shaded" swaps the albedo through the full shading (the marker keeps it off the shortcut that
    # takes "gt_albedo" from the "ours" step's irradiance and specular parts): the two must agree
    monkeypatch.setattr(dg, "STEPS", dg.STEPS + (("ours_again", ()), ("gt_albedo_shaded", ("albedo", "shaded"))))
    out = tmp_path / "diag"
    assert main(["diagnose", "--run", str(tiny_run), "--test-light", "sunrise", "--views", "2", "--dirs", "8",
                 "--out", str(out)]) == 0
    rec = json.loads((out / "diagnose.json").read_text())
    assert (out / "sheet.png").is_file() and rec["views"] == 2
    steps = rec["per_view_psnr"]
    assert steps["ours_again"] == steps["ours"]
    assert steps["gt_albedo_shaded"] == pytest.approx(steps["gt_albedo"], abs=1e-9)
    assert steps["gt_albedo"] != steps["ours"] and steps["gt_all"] != steps["gt_albedo"]
    assert steps["ours_unshadowed"] != steps["ours"]  # our buffers, V = 1: the traced shadows are dropped

    real = dg._gt_buffers

    def black_albedo(*args):
        b = real(*args)
        return {**b, "albedo": torch.zeros_like(b["albedo"])}

    monkeypatch.setattr(dg, "_gt_buffers", black_albedo)
    rec2 = dg.diagnose(tiny_run, "sunrise", views=2, dirs=8, out=tmp_path / "d2", progress=False)
    assert rec2["per_view_psnr"]["gt_roughness"] == steps["gt_roughness"]  # only the albedo steps change
    assert rec2["per_view_psnr"]["ours_unshadowed"] == steps["ours_unshadowed"]  # no ground truth in it
    assert rec2["per_view_psnr"]["gt_albedo"] != steps["gt_albedo"]
    assert rec2["per_view_psnr"]["gt_all"] != steps["gt_all"]
