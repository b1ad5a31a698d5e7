"""Benchmark entry point: bad input is one line with exit code 2; the scene generator is deterministic."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch

from method.splat.bench import make_scene, make_trace_queries


def test_bench_rejects_bad_device():
    res = subprocess.run([sys.executable, "-m", "method.splat.bench", "--device", "tpu", "--out", "/tmp/x.json"],
                         capture_output=True, text=True)
    assert res.returncode == 2
    assert res.stderr.strip().count("\n") == 0 and "--device" in res.stderr


def test_bench_scene_is_deterministic_and_plausible():
    a = make_scene(500, 100, seed=3)
    b = make_scene(500, 100, seed=3)
    for x, y in zip(a[:5], b[:5]):
        assert torch.equal(x, y)
    means, quats, scales = a[0], a[1], a[2]
    focal = a[5].focal
    sigma_px = float(scales.median()) * focal / 4.0
    assert 0.5 < sigma_px < 2.0  # typical footprints of a few pixels
    o, d = make_trace_queries(means, quats, scales, 16, 8)
    assert o.shape == (128, 3) and torch.allclose(d.norm(dim=1), torch.ones(128))


def test_deform_bench_times_both_precisions_and_the_nodes_on_the_profiles_network(tmp_path):
    from method.model.bench import main

    out = tmp_path / "deform.json"
    assert main(["--out", str(out), "--profile", "ci", "--gaussians", "300", "--repeats", "2", "--threads", "1",
                 "--nodes", "40"]) == 0
    res = json.loads(out.read_text())
    assert set(res["seconds"]) == {"fp32", "bf16", "fp32_nodes40"} and res["architecture"]["mlp_width"] == 64  # ci's width
    assert res["bf16_speedup"] == pytest.approx(res["seconds"]["fp32"] / res["seconds"]["bf16"])
    assert res["nodes_speedup"] == pytest.approx(res["seconds"]["fp32"] / res["seconds"]["fp32_nodes40"])
    assert res["nodes_choose_seconds"] > 0
