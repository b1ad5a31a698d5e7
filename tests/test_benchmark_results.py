"""Result files: written atomically and valid, malformed ones refused with the file and field named."""
from __future__ import annotations

import copy
import json

import pytest

from benchmark.results import is_finished, read_result, validate, write_result
from benchmark_fakes import fake_result
from lumibench.errors import UserError


def test_roundtrip_and_finished(tmp_path):
    path = tmp_path / "r" / "results.json"
    write_result(path, fake_result("m"))
    assert read_result(path)["method"] == "m"
    assert is_finished(path)
    write_result(path, fake_result("m", status="failed"))
    assert read_result(path)["error"] == "RuntimeError: boom"
    assert not is_finished(path)  # failed runs are retried on resume
    assert not is_finished(tmp_path / "absent.json")
    assert [p.name for p in path.parent.iterdir()] == ["results.json"]  # no temporary file left behind


@pytest.mark.parametrize("mutate, field", [
    (lambda r: r.pop("schema_version"), "schema_version"),
    (lambda r: r.update(status="done"), "status"),
    (lambda r: r.update(seed="0"), "seed"),
    (lambda r: r.pop("scene"), "scene"),
    (lambda r: r["metrics"]["albedo"].update(psnr="high"), "metrics.albedo.psnr"),
    (lambda r: r["metrics"]["relight"].update(lpips=float("nan")), "metrics.relight.lpips"),
    (lambda r: r["metrics"]["albedo"].update(scale=[1, 2]), "metrics.albedo.scale"),
    (lambda r: r["metrics"].update(shadows={"x": 1}), "metrics.shadows"),
    (lambda r: r["metric_config"]["lpips_weights"].pop("sha256"), "metric_config.lpips_weights.sha256"),
    (lambda r: r.update(timings={"stage1": "long"}), "timings"),
    (lambda r: r.update(cpu_timings={"stage1": None}), "cpu_timings"),
])
def test_malformed_result_names_file_and_field(tmp_path, mutate, field):
    res = copy.deepcopy(fake_result("m"))
    mutate(res)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(res))
    with pytest.raises(UserError) as err:
        read_result(path)
    assert str(path) in str(err.value) and f"'{field}'" in str(err.value)
    assert not is_finished(path)


def test_failed_result_needs_a_cause_and_write_refuses_invalid(tmp_path):
    res = fake_result("m", status="failed")
    res["error"] = ""
    with pytest.raises(UserError, match="'error'"):
        validate(res, "x")
    with pytest.raises(UserError, match="'metrics'"):
        write_result(tmp_path / "r.json", fake_result("m") | {"metrics": None})
    assert not (tmp_path / "r.json").exists()


def test_corrupt_json_is_named(tmp_path):
    path = tmp_path / "results.json"
    path.write_text("{not json")
    with pytest.raises(UserError, match="results.json: corrupt JSON"):
        read_result(path)


def test_result_of_another_protocol_is_not_finished(tmp_path):
    path = tmp_path / "results.json"
    write_result(path, fake_result("m"))  # lumimotion, vgg
    assert is_finished(path, "lumimotion", "vgg")
    assert not is_finished(path, "strict", "vgg")
    assert not is_finished(path, "lumimotion", "alex")
