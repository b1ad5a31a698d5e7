"""benchmark/budget.py: a method's budget variants against each other, from result files."""
from __future__ import annotations

import pytest

from benchmark import budget
from benchmark.outputs import build_outputs
from benchmark.results import write_result
from benchmark_fakes import fake_result

# variant: (training seconds, Gaussians, {scene: [relight PSNR per seed]})
RUNS = {
    "lumimotion": (100.0, 20000, {"a": [27.0], "b": [26.0]}),
    "lumimotion@0.25": (25.0, 19000, {"a": [25.0], "b": [24.0]}),
    "lumimotion@0.5": (50.0, 19500, {"a": [26.4, 26.8], "b": [26.0]}),     # two seeds on a (50 and 70 s)
    "lumimotion@cap5000": (80.0, 5000, {"a": [26.0], "b": [26.1]}),        # 26.05: 0.45 dB under the largest
    "lumimotion@cap10000": (90.0, 10000, {"a": [26.4], "b": [26.2]}),      # 26.3: within 0.3 dB of it
}


def _results():
    rs = []
    for method, (sec, gauss, scenes) in RUNS.items():
        for scene, psnrs in scenes.items():
            for seed, p in enumerate(psnrs):
                rs.append(fake_result(method, scene, seed=seed, relight_psnr=p, seconds=sec + 20 * seed,
                                      gaussians=gauss))
    rs.append(fake_result("lumimotion", "c", relight_psnr=40.0, seconds=100.0, gaussians=20000))  # only the full
    rs.append(fake_result("lumimotion@0.25", "a", seed=5, status="failed"))                       # ignored
    rs.append(fake_result("lumimotion@frames0.25", "a", relight_psnr=10.0, seconds=1.0))         # data, not cost
    rs.append(fake_result("static", "a", relight_psnr=30.0, seconds=1.0))                        # no variants
    return rs


def test_variants_are_compared_over_common_scenes_with_each_scene_weighted_alike():
    (c,) = budget.compare(_results())
    assert (c["family"], c["configuration"]) == ("lumimotion", ("city", "sunrise"))
    assert c["scenes"] == ["a", "b"] and c["left_out"] == ["c"]
    assert list(c["variants"]) == ["lumimotion@0.25", "lumimotion@0.5", "lumimotion@cap5000", "lumimotion@cap10000",
                                   "lumimotion"]  # fastest first
    v = c["variants"]
    assert v["lumimotion"]["metrics"]["relight.psnr"] == pytest.approx(26.5)      # scene c is not averaged in
    assert v["lumimotion@0.5"]["metrics"]["relight.psnr"] == pytest.approx(26.3)  # (26.6 + 26.0) / 2, not pooled
    assert v["lumimotion@0.5"]["per_scene"] == pytest.approx({"a": 26.6, "b": 26.0})
    assert v["lumimotion@0.5"]["runs"] == 3 and v["lumimotion"]["runs"] == 2
    assert v["lumimotion@0.5"]["seconds"] == pytest.approx(55.0)                  # (60 + 50) / 2, not 170 / 3
    assert v["lumimotion@0.25"]["seconds"] == pytest.approx(25.0)
    assert v["lumimotion@cap5000"]["gaussians"] == pytest.approx(5000)


def test_the_front_and_the_smallest_model_within_the_tolerance():
    (c,) = budget.compare(_results())
    # cap5000 (80 s, 26.05) and cap10000 (90 s, 26.3) are dominated by @0.5 (50 s, 26.3)
    assert c["front"] == ["lumimotion@0.25", "lumimotion@0.5", "lumimotion"]
    assert c["size"] == ("lumimotion", "lumimotion@cap10000")  # cap5000 is 0.45 dB under: outside 0.3 dB


def test_pareto_variants_needs_a_strict_gain_and_skips_missing_values():
    pts = {"a": (10.0, 20.0), "b": (10.0, 20.0), "c": (5.0, 19.0), "d": (None, 30.0), "e": (20.0, 20.0)}
    assert budget.pareto_variants(pts) == ["c", "a", "b"]  # ties both stay; e is slower for the same quality


def test_budget_md_is_written_by_build_outputs_only_when_variants_ran(tmp_path):
    paths = []
    for i, r in enumerate(_results()):
        p = tmp_path / "runs" / f"{i}.json"
        write_result(p, r)
        paths.append(p)
    written = build_outputs(paths, tmp_path / "out", grids=False, published=False)
    text = written["budget.md"].read_text()
    assert "## lumimotion, city → sunrise" in text and "left out, not run by every variant: c" in text
    assert "- from 25 s (under 55 s): **lumimotion@0.25**" in text and "- from 100 s: **lumimotion**" in text
    assert "**lumimotion@cap10000** (10,000 Gaussians, 26.30 dB) is within 0.3 dB" in text
    assert "frames" not in text and "static" not in text
    plain = build_outputs(paths[-1:], tmp_path / "plain", grids=False, published=False)
    assert "budget.md" not in plain and not (tmp_path / "plain" / "budget.md").exists()


def test_budget_times_are_cpu_seconds_only_when_every_run_reports_them(tmp_path):
    """A loaded machine stretches wall time, not CPU time: the comparison reads the CPU seconds when every run
    has them, and never mixes the two clocks (one run without them puts the whole comparison on the wall)."""
    rs = _results()
    for r in rs:
        if r["status"] == "ok":  # the CPU took 60 % of the wall time on every run
            r["cpu_timings"] = {k: 0.6 * v for k, v in r["timings"].items()}
    (c,) = budget.compare(rs)
    assert c["clock"] == "CPU"
    assert c["variants"]["lumimotion@0.5"]["seconds"] == pytest.approx(0.6 * 55.0)
    paths = []
    for i, r in enumerate(rs):
        write_result(tmp_path / "runs" / f"{i}.json", r)
        paths.append(tmp_path / "runs" / f"{i}.json")
    text = build_outputs(paths, tmp_path / "out", grids=False, published=False)["budget.md"].read_text()
    assert "| training time (CPU) |" in text and "- from 15 s (under 33 s): **lumimotion@0.25**" in text
    del next(r for r in rs if r["method"] == "lumimotion@cap5000")["cpu_timings"]
    (c,) = budget.compare(rs)
    assert c["clock"] == "wall" and c["variants"]["lumimotion@0.5"]["seconds"] == pytest.approx(55.0)
    # a run whose CPU seconds cover only some of its stages has none
    r = rs[0]
    r["cpu_timings"] = {"stage1": 1.0}
    from benchmark.aggregate import training_cpu_seconds

    assert training_cpu_seconds(r) is None


def test_an_adapter_that_times_its_own_stages_keeps_no_cpu_seconds_of_another_span(tmp_path):
    """The base adapter's CPU seconds cover its predict call; a method that reports its own stages' wall
    times without their CPU seconds must not be left with a CPU record of another span."""
    import json

    from baselines_adapters.base import MethodAdapter

    class Timed(MethodAdapter):
        name, version = "timed", "1"

        def __init__(self, extra):
            self.extra = extra

        def predict(self, *args):
            return self.extra

    for extra, want in (({}, {"predict"}), ({"timings": {"train": 5.0}}, None),
                        ({"timings": {"train": 5.0}, "cpu_timings": {"train": 4.0}}, {"train"})):
        out = Timed(extra).run(tmp_path, "city", ["sunrise"], 0, "ci", tmp_path / f"p{len(extra)}")
        meta = json.loads((out / "meta.json").read_text())
        assert (set(meta["cpu_timings"]) if "cpu_timings" in meta else None) == want, extra
