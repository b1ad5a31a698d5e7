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
