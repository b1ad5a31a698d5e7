"""Benchmark grid YAML: the shipped grids load; mistakes are named by file and key."""
from __future__ import annotations

import pytest

from benchmark.config import Configuration, load_benchmark_config
from lumibench.errors import UserError

GOOD = """profile: ci
scenes: [a]
configurations:
  - {train: city, test: sunrise}
methods: [lit_as_albedo]
seeds: [0, 1]
"""


@pytest.mark.parametrize("profile", ["ci", "small", "full"])
def test_shipped_grids_load(profile):
    cfg = load_benchmark_config(profile)
    assert cfg.profile == profile
    pairs = [(c.train, c.test) for c in cfg.configurations]  # every default configuration, in this order
    defaults = [("city", "sunrise"), ("courtyard", "sunset"), ("sunrise", "courtyard")]
    assert [p for p in dict.fromkeys(pairs) if p in defaults] == defaults
    assert {"lit_as_albedo", "mean_albedo", "noisy_gt"} <= set(cfg.methods)


@pytest.mark.parametrize("text, key", [
    (GOOD.replace("seeds: [0, 1]", "seeds: [0, -1]"), "seeds"),
    (GOOD.replace("methods: [lit_as_albedo]", "methods: [magic]"), "methods"),
    (GOOD.replace("test: sunrise", "test: moon"), "configurations[0].test"),
    (GOOD.replace("test: sunrise", "test: city"), "configurations[0].test"),
    (GOOD.replace("{train: city, test: sunrise}", "{train: city, test: sunrise, tset: x}"), "configurations[0].tset"),
    (GOOD + "protocol: loose\n", "protocol"),
    (GOOD + "sceens: [b]\n", "sceens"),
    (GOOD.replace("profile: ci", "profile: huge"), "profile"),
    (GOOD.replace("scenes: [a]", "scenes: []"), "scenes"),
])
def test_bad_grid_names_the_key(tmp_path, text, key):
    path = tmp_path / "grid.yaml"
    path.write_text(text)
    with pytest.raises(UserError) as err:
        load_benchmark_config(path)
    assert str(path) in str(err.value) and key in str(err.value)


def test_unknown_profile_and_method_override(tmp_path):
    with pytest.raises(UserError, match="no benchmark grid for profile 'nope'"):
        load_benchmark_config("nope")
    path = tmp_path / "grid.yaml"
    path.write_text(GOOD)
    cfg = load_benchmark_config(path)
    assert cfg.with_methods(["noisy_gt"]).methods == ("noisy_gt",)
    with pytest.raises(UserError, match="--methods: unknown method 'x'"):
        cfg.with_methods(["x"])


def test_light_files_are_named_by_their_stem(tmp_path):
    path = tmp_path / "grid.yaml"
    path.write_text(GOOD.replace("{train: city, test: sunrise}",
                                 f"{{train: {tmp_path / 'hdri' / 'attic.hdr'}, test: ~/maps/Harbour.EXR}}"))
    cfg = load_benchmark_config(path)
    assert cfg.configurations == (Configuration("attic", "Harbour"),)
    assert cfg.configurations[0].slug == "attic_to_Harbour"


@pytest.mark.parametrize("light, needles", [
    ("moon", ["unknown light 'moon'", "city", "a path to an .hdr or .exr file"]),
    ("/maps/moon.png", ["/maps/moon.png", "a path to an .hdr or .exr file"]),
])
def test_unknown_light_says_a_file_path_is_accepted(tmp_path, light, needles):
    path = tmp_path / "grid.yaml"
    path.write_text(GOOD.replace("test: sunrise", f"test: {light}"))
    with pytest.raises(UserError) as err:
        load_benchmark_config(path)
    assert "configurations[0].test" in str(err.value)
    for needle in needles:
        assert needle in str(err.value)
