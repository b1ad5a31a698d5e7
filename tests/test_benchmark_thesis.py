"""benchmark/thesis.py: dynamic (lumimotion) against static capture, per scene and over scenes, from results."""
from __future__ import annotations

import numpy as np
import pytest

from benchmark import thesis
from benchmark.outputs import build_outputs
from benchmark.results import write_result
from benchmark_fakes import fake_result

# per (scene, method): the seeds' albedo LPIPS and relight PSNR
VALUES = {
    ("a", "lumimotion"): {0: (0.04, 27.0), 1: (0.06, 28.0)},
    ("a", "static"): {0: (0.10, 26.0)},
    ("b", "lumimotion"): {0: (0.12, 27.0)},
    ("b", "static"): {0: (0.08, 26.5), 1: (0.10, 25.5)},
}


def _results():
    rs = []
    for (scene, method), seeds in VALUES.items():
        for seed, (lp, relight) in seeds.items():
            rs.append(fake_result(method, scene, seed=seed, lpips=lp, relight_psnr=relight))
    rs.append(fake_result("lumimotion", "c", seed=0))          # no static run on c: listed, not averaged
    rs.append(fake_result("static", "c", seed=0, status="failed"))
    rs.append(fake_result("lumimotion", "d", seed=0))          # static not run on d (yet): not a failure
    rs.append(fake_result("lit_as_albedo", "a", seed=0, lpips=0.5))  # other methods are ignored
    return rs


def test_per_scene_changes_and_the_mean_over_scenes_match_a_hand_computation():
    (comp,) = thesis.compare(_results())
    assert comp["configuration"] == ("city", "sunrise")
    rows = {r["scene"]: r for r in comp["scenes"]}
    assert rows["c"]["missing"] == "static" and rows["c"]["metrics"] == {}
    a = rows["a"]["metrics"]["albedo.lpips"]
    assert a["dynamic"] == pytest.approx((0.05, 0.01, 2)) and a["static"] == pytest.approx((0.10, 0.0, 1))
    assert a["change"] == pytest.approx(-50.0)                 # (0.05 - 0.10) / 0.10
    b = rows["b"]["metrics"]["albedo.lpips"]
    assert b["change"] == pytest.approx(100 * (0.12 - 0.09) / 0.09)
    assert rows["a"]["metrics"]["relight.psnr"]["change"] == pytest.approx(27.5 - 26.0)  # dB, not percent
    # the seeds: every seed of one method against every seed of the other
    assert a["seed_range"] == pytest.approx((-60.0, -40.0, 2))  # 0.04 and 0.06 against 0.10
    assert b["seed_range"] == pytest.approx((20.0, 50.0, 2))    # 0.12 against 0.10 and 0.08
    assert rows["a"]["metrics"]["relight.psnr"]["seed_range"] == pytest.approx((1.0, 2.0, 2))
    assert rows["b"]["metrics"]["relight.psnr"]["change"] == pytest.approx(27.0 - 26.0)
    o = comp["overall"]["albedo.lpips"]
    changes = [-50.0, 100 * (0.12 - 0.09) / 0.09]
    assert o["mean"] == pytest.approx(np.mean(changes)) and o["std"] == pytest.approx(np.std(changes))
    assert o["n_scenes"] == 2 and o["wins"] == 1               # lower LPIPS wins on a only
    assert comp["overall"]["relight.psnr"]["wins"] == 2        # higher PSNR wins on both


def test_markdown_names_missing_runs_and_the_paper_claims():
    text = thesis.markdown(thesis.compare(_results()), "lumimotion")
    assert "| c | no successful run of static |" in text
    assert "| d | static not run |" in text
    assert "0.100 → 0.050 ± 0.010 (**-50.0 %**; seeds -60.0 to -40.0 %)" in text
    assert "(**+1.00 dB**; seeds +0.50 to +1.50 dB)" in text   # b's relight: 27.0 against 26.5 and 25.5
    assert "+1.50 dB" in text and "better on 1 of 2" in text
    assert "-23 %" in text and "-15 %" in text


def test_no_thesis_files_without_both_methods(tmp_path):
    only_dynamic = [r for r in _results() if r["method"] != "static"]
    assert thesis.write(only_dynamic, tmp_path) == {}
    assert not (tmp_path / "thesis.md").exists()


def test_build_outputs_writes_the_thesis_table_chart_and_report_section(tmp_path):
    paths = []
    for i, r in enumerate(_results()):
        p = tmp_path / "runs" / f"{i}" / "results.json"
        write_result(p, r)
        paths.append(p)
    out = build_outputs(paths, tmp_path / "out", grids=False, published=False)
    assert (tmp_path / "out" / "thesis.md").is_file() and (tmp_path / "out" / "thesis.png").is_file()
    assert "thesis.md" in out
    html = (tmp_path / "out" / "report.html").read_text()
    assert "Dynamic against static capture" in html and "thesis.png" in html


def test_one_seed_each_gives_no_seed_range_in_the_table():
    rs = [fake_result("lumimotion", "a", lpips=0.05), fake_result("static", "a", lpips=0.10)]
    text = thesis.markdown(thesis.compare(rs), "lumimotion")
    assert "0.100 → 0.050 (**-50.0 %**)" in text and "; seeds" not in text
