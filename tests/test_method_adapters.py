"""In-project adapters end to end on the ci dataset (train, predict, score), at a tenth of the ci budget:
the same code paths as a full run (both stages, predictions, the benchmark's scorer), in seconds."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from baselines_adapters.registry import get_adapter, is_known
from benchmark.score import score
from lumibench.errors import UserError

BUDGET = "0.1+cap1500"


def test_budget_variants_parse_and_reject_nonsense():
    a = get_adapter("lumimotion@0.25+cap10000")
    ov = a.overrides("small")
    assert "stage1.max_gaussians=10000" in ov and any(o.startswith("stage1.iterations=") for o in ov)
    # every iteration-indexed setting shrinks with the budget, the coarse-to-fine schedule too
    from method.config import load_method_config

    full = load_method_config("small")["stage1"]
    assert f"stage1.iterations={round(full['iterations'] * 0.25)}" in ov
    assert f"stage1.c2f_until={round(full['c2f_until'] * 0.25)}" in ov
    assert not any(o.startswith("stage1.c2f_until=") for o in get_adapter("lumimotion@0.5").overrides("ci"))
    assert full["time_window_until"] > 0  # the small profile sets it, so it must shrink too
    assert f"stage1.time_window_until={round(full['time_window_until'] * 0.25)}" in ov
    assert is_known("static@0.5") and is_known("wo_P") and not is_known("static@fast") and not is_known("nope@0.5")
    with pytest.raises(UserError, match="unknown budget"):
        get_adapter("lumimotion@fast")


@pytest.mark.parametrize("profile", ["ci", "demo", "small", "full"])
def test_every_variant_loads_its_settings_at_every_profile(profile):
    """Each in-project variant's overrides make a valid configuration at each profile: small moves the
    Gaussians by rigid motion bases fitted at the P split, which wo_P (no split) must turn off, or its every
    grid job fails on the settings before training."""
    from baselines_adapters.lumimotion import VARIANTS
    from method.config import load_method_config

    for base in VARIANTS:
        for name in (base, f"{base}@cap2000", f"{base}@0.5"):
            cfg = load_method_config(profile, get_adapter(name).overrides(profile))
            if base == "wo_P":
                assert not cfg["model"]["separation"] and cfg["model"]["motion_bases"] == 0
    assert load_method_config("small")["model"]["motion_bases"] > 0  # so the wo_P case above guards something


def test_one_stages_budget_scales_that_stage_alone():
    """`make demo`'s lumimotion@s1x8: stage 1 at 8x ci's schedule, stage 2 at ci's own."""
    from method.config import ITERATION_KEYS, load_method_config

    ci = load_method_config("ci")
    ov = get_adapter("lumimotion@s1x8").overrides("ci")
    for key in ITERATION_KEYS["stage1"]:
        if ci["stage1"][key] > 0:
            assert f"stage1.{key}={ci['stage1'][key] * 8}" in ov, key
    assert not any(o.startswith("stage2.") for o in ov)
    # composed with the common fraction: 8x both, stage 2 back to 1x
    assert sorted(get_adapter("lumimotion@8+s2x0.125").overrides("ci")) == sorted(ov)
    ov2 = get_adapter("lumimotion@s2x0.5").overrides("ci")
    assert ov2 == [f"stage2.iterations={ci['stage2']['iterations'] // 2}"]
    for bad, msg in (("s3x2", "unknown budget"), ("s1x9", r"stage1 runs at 9x .* \(0, 8\]"),
                     ("4+s1x4", r"stage1 runs at 16x"), ("s1x2+s1x4", "stage-1 fraction twice"), ("s2x0", "stage2 runs at 0x")):
        with pytest.raises(UserError, match=msg) as exc:
            get_adapter(f"lumimotion@{bad}")
        assert "\n" not in str(exc.value), bad


@pytest.mark.slow
@pytest.mark.parametrize("method", ["lumimotion", "wo_stage2", "wo_dc", "wo_P", "static"])
def test_in_project_adapter_end_to_end(ci_dataset, tmp_path, method, monkeypatch):
    import baselines_adapters.lumimotion as lm

    monkeypatch.setattr(lm, "DIAGNOSE_MAX_DIRS", 16)  # the relight diagnostic's real path, at a quarter of ci's cost
    name = f"{method}@{BUDGET}"
    runs = tmp_path / "runs" / "ci"
    out = runs / name / ci_dataset.name / "city" / "seed0" / "predictions"
    adapter = get_adapter(name)
    adapter.run(ci_dataset, "city", ["sunrise"], 0, "ci", out, runs)
    meta = json.loads((out / "meta.json").read_text())
    assert meta["method"] == name and meta["model_size"]["gaussians"] <= 1500
    run_dir = out.parent
    assert (run_dir / "metrics_stage1.json").is_file()
    assert (run_dir / "metrics_stage2.json").is_file() == (method != "wo_stage2")
    assert (out / "envmap" / "city.hdr").is_file() == (method != "wo_stage2")
    # P maps only where there is a deformation network; all lights but the train one are relit
    assert (out / "p_map" / "train").is_dir() == (method != "static")
    assert sorted(p.name for p in (out / "relight").iterdir()) == ["courtyard", "sunrise", "sunset"]
    # and relit again with the albedo scaled as the benchmark aligns it (the lumimotion protocol's relight)
    assert sorted(p.name for p in (out / "relight_scaled").iterdir()) == ["courtyard", "sunrise", "sunset"]
    assert len(meta["relight_albedo_scale"]) == 3
    res = score(ci_dataset, out, "city", "sunrise")
    assert res["metrics"]["relight"]["albedo_scale"] == meta["relight_albedo_scale"]
    # the result names the settings the run was trained with (a table tells when its rows mix them)
    from method.run_record import settings_hash

    assert res["inputs"]["method_settings_sha256"] == meta["settings_sha256"] == settings_hash(run_dir)
    for kind in ("albedo", "relight", "nvs"):
        assert np.isfinite(res["metrics"][kind]["psnr"]), kind
    assert res["metrics"]["roughness"]["mse"] >= 0
    # the relight diagnostic of the test light, for the variants with a stage 2, carried into results.json
    if method == "wo_stage2":
        assert "diagnose" not in meta and "diagnose" not in res
    else:
        block = res["diagnose"]
        assert block == meta["diagnose"]["sunrise"] and block["dirs"] == 16
        assert block["views"] == len(list((out / "albedo").glob("*.png")))
        assert (run_dir / "diagnose" / "sunrise" / "diagnose.json").is_file()
        assert block["steps"]["ours"]["psnr"] == pytest.approx(res["metrics"]["relight"]["psnr"], abs=1.0)
    # a finished run is reused: predicting again trains nothing (the checkpoints stay as they are)
    cks = sorted((run_dir / "checkpoints").iterdir())
    stamp = [p.stat().st_mtime_ns for p in cks]
    adapter.run(ci_dataset, "city", ["sunset"], 0, "ci", out, runs)
    assert [p.stat().st_mtime_ns for p in sorted((run_dir / "checkpoints").iterdir())] == stamp


@pytest.mark.slow
def test_wo_stage2_takes_lumimotions_stage1_only_when_it_is_the_same(ci_dataset, tmp_path, monkeypatch):
    """w/o stage 2 is LumiMotion's stage 1: with a finished one of the same scene, light, seed and settings
    beside it, the ablation trains nothing and scores that very checkpoint; any difference trains its own."""
    import baselines_adapters.lumimotion as lm
    from method.checkpoints import checkpoint_paths
    from method.config import load_method_config
    from method.run_record import read_record
    from method.train import share_stage1, train_stage1

    runs = tmp_path / "runs" / "ci"
    cfg = load_method_config("ci", get_adapter(f"lumimotion@{BUDGET}").overrides("ci"))
    src = runs / f"lumimotion@{BUDGET}" / ci_dataset.name / "city" / "seed0"
    train_stage1(ci_dataset, "city", src, cfg, seed=0, progress=False)

    # anything stage 1 depends on differs: nothing is shared, nothing written
    other = load_method_config("ci", get_adapter(f"lumimotion@{BUDGET}").overrides("ci") + ["stage1.lr_opacity=0.04"])
    for kw, c in (({"seed": 1}, cfg), ({"light": "sunset"}, cfg), ({}, other)):
        dst = tmp_path / "no" / str(len(kw))
        args = {"scene": ci_dataset.name, "light": "city", "seed": 0, **kw}
        assert not share_stage1(src, dst, c, **args), kw
        assert not (dst / "metrics_stage1.json").exists() and not checkpoint_paths(dst, 1)
    # how often a run logs or checkpoints does not change what it trains, and a record made before a setting
    # existed counts it at its profile's value
    import yaml

    rec = read_record(src)
    del rec["data"]["train_frames"]
    (src / "config.yaml").write_text(yaml.safe_dump(rec, sort_keys=False))
    noisy = load_method_config("ci", get_adapter(f"lumimotion@{BUDGET}").overrides("ci") + ["stage1.log_every=7"])
    assert share_stage1(src, tmp_path / "yes", noisy, scene=ci_dataset.name, light="city", seed=0)

    def no_training(*a, **k):
        raise AssertionError("wo_stage2 trained a stage 1 of its own")

    monkeypatch.setattr("method.train.train_stage1", no_training)
    out = runs / f"wo_stage2@{BUDGET}" / ci_dataset.name / "city" / "seed0" / "predictions"
    get_adapter(f"wo_stage2@{BUDGET}").run(ci_dataset, "city", ["sunrise"], 0, "ci", out, runs)
    dst = out.parent
    (_, a), (_, b) = checkpoint_paths(src, 1)[-1], checkpoint_paths(dst, 1)[-1]
    assert a.name == b.name and a.read_bytes() == b.read_bytes()
    assert read_record(dst)["run"]["stage1_shared_from"] == str(src.resolve())
    metrics = [json.loads((d / "metrics_stage1.json").read_text()) for d in (src, dst)]
    assert metrics[0] == metrics[1]
    assert not (dst / "metrics_stage2.json").exists() and (out / "albedo").is_dir()
    assert lm.VARIANTS["wo_stage2"]["overrides"] == []  # the premise: the ablation's stage 1 is LumiMotion's
