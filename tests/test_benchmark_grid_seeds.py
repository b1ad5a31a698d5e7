"""A configuration's own seeds, and one train -> test pair split between method sets (benchmark/config.py,
method_jobs): the published grid runs its main methods with three seeds and the ablations with one."""
from __future__ import annotations

from pathlib import Path

import pytest

from benchmark.config import load_benchmark_config
from benchmark.jobgrid import Paths, method_jobs
from lumibench.errors import UserError

GRID = """profile: ci
scenes: [spheres]
configurations:
  - {train: city, test: sunrise, methods: [lumimotion, lit_as_albedo]}
  - {train: city, test: sunrise, methods: [wo_dc], seeds: [0]}
  - {train: city, test: sunset, methods: [lumimotion], seeds: [1]}
  - {train: sunrise, test: city, methods: [lumimotion, wo_dc], seeds: [0]}
methods: [lumimotion, wo_dc, lit_as_albedo]
seeds: [0, 1, 2]
"""


def _jobs(tmp_path, text=GRID):
    path = tmp_path / "grid.yaml"
    path.write_text(text)
    cfg = load_benchmark_config(path)
    return {(j["method"], j["train"], j["seed"]): j["tests"]
            for j in method_jobs(cfg, Paths(tmp_path / "d", tmp_path / "r", tmp_path / "o", cfg.profile))}


def test_jobs_follow_each_configurations_methods_and_seeds(tmp_path):
    expected = {  # brute force: (method, train, seed) -> the tests that run it
        ("lumimotion", "city", 0): ["sunrise"],
        ("lumimotion", "city", 1): ["sunrise", "sunset"],
        ("lumimotion", "city", 2): ["sunrise"],
        ("lumimotion", "sunrise", 0): ["city"],
        ("wo_dc", "city", 0): ["sunrise"],
        ("wo_dc", "sunrise", 0): ["city"],
        ("lit_as_albedo", "city", 0): ["sunrise"],  # not seed-dependent: the first seed only
    }
    assert _jobs(tmp_path) == expected


@pytest.mark.parametrize("conf, needle", [
    ("{train: city, test: sunrise, methods: [lumimotion], seeds: [0]}", "repeats the configuration"),
    ("{train: city, test: sunrise}", "repeats the configuration"),
    ("{train: city, test: courtyard, seeds: [3]}", "not one of the grid's seeds"),
    ("{train: city, test: courtyard, seeds: []}", "non-negative integers"),
])
def test_bad_configuration_seeds_and_repeated_pairs_name_the_key(tmp_path, conf, needle):
    text = GRID.replace("methods: [lumimotion, wo_dc], seeds: [0]}\n",
                        "methods: [lumimotion, wo_dc], seeds: [0]}\n  - " + conf + "\n")
    assert conf in text
    with pytest.raises(UserError, match=needle):
        _jobs(tmp_path, text)
