"""A result names the predictions it scored (inputs.pred_meta_sha256), and the image grids are drawn only from
those: another run's predictions that later took the same folder are never drawn under the old scores."""
from __future__ import annotations

from pathlib import Path

import benchmark.outputs as outputs
from benchmark.results import write_result
from benchmark.score import predictions_hash
from benchmark_fakes import fake_result


def _build(tmp_path, result, out_name):
    calls = []

    def fake_grid(r, target):
        calls.append(r["method"])
        Path(target).parent.mkdir(parents=True, exist_ok=True)
        Path(target).write_bytes(b"png")
        return Path(target)

    path = tmp_path / out_name / "runs" / "results.json"
    write_result(path, result)
    orig = outputs.image_grid
    outputs.image_grid = fake_grid
    try:
        outputs.build_outputs([path], tmp_path / out_name, grids=True, published=False)
    finally:
        outputs.image_grid = orig
    return calls


def test_grids_only_from_the_predictions_the_result_scored(tmp_path, capsys):
    pred = tmp_path / "pred"
    pred.mkdir()
    (pred / "meta.json").write_text('{"method": "ours", "run": 1}')
    r = fake_result("ours", "a")
    r["inputs"] = {"scene_dir": str(tmp_path), "pred_dir": str(pred), "pred_meta_sha256": predictions_hash(pred)}
    assert r["inputs"]["pred_meta_sha256"] and len(r["inputs"]["pred_meta_sha256"]) == 64
    assert _build(tmp_path, r, "first") == ["ours"]
    (pred / "meta.json").write_text('{"method": "ours", "run": 2}')  # another run's predictions, same folder
    assert _build(tmp_path, r, "second") == []
    assert "the predictions it scored are not here" in capsys.readouterr().err
    del r["inputs"]["pred_meta_sha256"]  # results written before the hash existed: drawn as before
    assert _build(tmp_path, r, "third") == ["ours"]
    assert predictions_hash(tmp_path / "nowhere") is None
