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


def _fit_rare_sun(loss_name: str, steps: int = 4000) -> float:
    """Fit a scale theta of an estimator theta * X whose X is a rare bright hit (10 with probability 0.1,
    else 0; mean 1) to the target 1: the sun texel that few of a pixel's directions reach. The right
    answer is theta = 1."""
    import torch

    from method.stage2 import decorrelated_l2

    g = torch.Generator().manual_seed(0)
    theta = torch.tensor(0.5, requires_grad=True)
    opt = torch.optim.SGD([theta], lr=0.002)
    y = torch.ones(64)
    for _ in range(steps):
        xa = 10.0 * (torch.rand(64, generator=g) < 0.1).float()
        xb = 10.0 * (torch.rand(64, generator=g) < 0.1).float()
        if loss_name == "l1":
            loss = (theta * xa - y).abs().mean()
        elif loss_name == "l2":
            loss = ((theta * xa - y) ** 2).mean()
        elif loss_name == "same_samples":
            loss = decorrelated_l2(theta * xa, theta * xa, y)
        else:
            loss = decorrelated_l2(theta * xa, theta * xb, y)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return float(theta.detach())


def test_decorrelated_loss_learns_a_rare_bright_source_that_l1_and_l2_underestimate():
    import torch

    from method.stage2 import decorrelated_l2

    a, b, y = torch.tensor([0.2, 0.7]), torch.tensor([0.4, 0.1]), torch.tensor([0.3, 0.3])
    assert float(decorrelated_l2(a, b, y)) == pytest.approx(((-0.1 * 0.1) + (0.4 * -0.2)) / 2)
    assert _fit_rare_sun("decorrelated") == pytest.approx(1.0, abs=0.1)
    # L1 drives the median (a miss) to the target and plain L2 adds the estimator's variance: both settle
    # near theta = 0.1, which is how the learned env map lost its sun at 64 directions per pixel
    for name in ("l1", "l2", "same_samples"):
        assert _fit_rare_sun(name) < 0.3, name


def test_stage2_step_with_the_decorrelated_loss(ci_dataset, tiny_run):
    import torch

    from lumibench.errors import UserError
    from method.config import load_method_config
    from method.data import load_scene
    from method.stage2 import stage2_step_loss
    from method.checkpoints import load_trained

    cfg = load_method_config("ci", TINY + ["stage2.pbr_loss=l2_decorrelated"])
    scene, mats = load_trained(tiny_run, cfg, "cpu")
    data = load_scene(ci_dataset, "city", cfg["data"]["background"], "cpu")
    gen = torch.Generator().manual_seed(0)
    loss, terms, rays = stage2_step_loss(scene, mats, data.train[0], data.background, cfg, gen, {}, 0, 1)
    loss.backward()
    assert torch.isfinite(terms["pbr"]) and rays > 0
    assert next(mats.env.parameters()).grad.abs().sum() > 0 and mats.albedo_logit.grad.abs().sum() > 0
    with pytest.raises(UserError, match="stage2.pbr_loss"):
        load_method_config("ci", ["stage2.pbr_loss=l3"])


def test_stage2_records_its_own_settings_in_the_run_config(ci_dataset, tiny_run, tmp_path):
    import shutil

    import yaml

    from method.config import load_method_config
    from method.checkpoints import checkpoint_paths
    from method.train import train_stage2

    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    shutil.copy(checkpoint_paths(tiny_run, 1)[-1][1], run / "checkpoints")
    shutil.copy(tiny_run / "config.yaml", run / "config.yaml")
    before = yaml.safe_load((run / "config.yaml").read_text())
    cfg = load_method_config("ci", TINY + ["stage2.iterations=2", "stage2.lr_env=0.123", "stage1.lr_p=0.5"])
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


def test_stage2_material_rates_decay_to_the_final_factor(ci_dataset, tiny_run, tmp_path):
    import shutil

    from lumibench.errors import UserError
    from method.config import load_method_config
    from method.stage2 import material_lr_scale
    from method.checkpoints import checkpoint_paths, load_checkpoint
    from method.train import train_stage2

    assert material_lr_scale(0, 8, 0.01) == 1.0 and material_lr_scale(8, 8, 0.01) == pytest.approx(0.01)
    assert material_lr_scale(4, 8, 0.01) == pytest.approx(0.1)  # exponential: the geometric midpoint
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    shutil.copy(checkpoint_paths(tiny_run, 1)[-1][1], run / "checkpoints")
    shutil.copy(tiny_run / "config.yaml", run / "config.yaml")
    cfg = load_method_config("ci", TINY + ["stage2.iterations=4", "stage2.lr_final_factor=0.01"])
    train_stage2(ci_dataset, "city", run, cfg, seed=0, progress=False)
    lrs = {g["name"]: g["lr"] for g in load_checkpoint(checkpoint_paths(run, 2)[-1][1], "cpu")["opt"]["param_groups"]}
    k = 0.01 ** (3 / 4)  # the last step (iteration 4) used the rate of 3 / 4 of the way
    for name in ("albedo", "roughness", "env"):
        assert lrs[name] == pytest.approx(cfg["stage2"][f"lr_{name}"] * k), name
    assert lrs["colour"] == pytest.approx(cfg["stage1"]["lr_colour"] * cfg["stage2"]["finetune_factor"])
    with pytest.raises(UserError, match="stage2.lr_final_factor"):
        load_method_config("ci", ["stage2.lr_final_factor=0"])
