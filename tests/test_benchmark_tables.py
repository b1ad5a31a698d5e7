"""Aggregation, tables, charts and report from result dictionaries (no scoring needed)."""
from __future__ import annotations

import csv
import io
import re

import numpy as np
import pytest

from benchmark import charts, tables
from benchmark.aggregate import COLUMNS, aggregate, check_consistent
from benchmark.results import write_result
from benchmark_fakes import fake_result
from lumibench.errors import UserError


def _results():
    rs = []
    for scene, shift in (("a", 0.0), ("b", 2.0)):
        for seed in (0, 1):
            rs.append(fake_result("ours", scene, seed=seed, albedo_psnr=28 + shift + seed, relight_psnr=26 + shift,
                                  lpips=0.05, mse=0.01, seconds=100 + seed, gaussians=5000))
            rs.append(fake_result("lit_as_albedo", scene, seed=seed, albedo_psnr=20 + shift, relight_psnr=27 + shift,
                                  lpips=0.2, mse=0.03, nvs_psnr=None, seconds=0.1))
    rs.append(fake_result("ours", "c", seed=0, status="failed"))
    rs.append(fake_result("ours", "a", train="courtyard", test="sunset", albedo_psnr=30))
    return rs


def test_mean_std_over_scenes_and_seeds_with_failures_counted():
    groups = {(g.configuration, g.method): g for g in aggregate(_results())}
    ours = groups[("city->sunrise", "ours")]
    vals = [28, 29, 30, 31]
    assert ours.stats["albedo.psnr"].mean == pytest.approx(np.mean(vals))
    assert ours.stats["albedo.psnr"].std == pytest.approx(np.std(vals))
    assert ours.n_ok == 4 and ours.n_failed == 1 and ours.failures[0]["scene"] == "c"
    assert ours.stats["time.seconds"].mean == pytest.approx(100.5)
    assert "nvs.psnr" not in groups[("city->sunrise", "lit_as_albedo")].stats
    assert groups[("courtyard->sunset", "ours")].n_ok == 1


def _row(md: str, conf: str, method: str) -> list[str]:
    block = md.split(f"### {conf}")[1].split("###")[0]
    line = next(l for l in block.splitlines() if l.startswith(f"| {method} |"))
    return [c.strip() for c in line.strip("|").split("|")]


def test_markdown_bold_is_direction_aware_and_states_protocol():
    rs = _results()
    md = tables.markdown(aggregate(rs), check_consistent(rs))
    assert "Protocol: lumimotion" in md and "abababababab" in md
    ours, lit = _row(md, "city → sunrise", "ours"), _row(md, "city → sunrise", "lit_as_albedo")
    col = {c.key: i + 1 for i, c in enumerate(COLUMNS)}
    assert ours[col["albedo.psnr"]].startswith("**29.50 ± 1.12")       # higher PSNR is better
    assert ours[col["albedo.lpips"]].startswith("**0.050")             # lower LPIPS is better
    assert ours[col["roughness.mse"]].startswith("**0.0100")
    assert lit[col["relight.psnr"]].startswith("**28.00")              # the floor wins a column: bold there
    assert not ours[col["relight.psnr"]].startswith("**")
    assert lit[col["nvs.psnr"]] == "–"
    assert ours[-1] == "4 ok, 1 failed"
    assert "### Failed runs" in md and "RuntimeError: boom" in md


def test_latex_and_csv():
    rs = _results()
    groups, meta = aggregate(rs), check_consistent(rs)
    tex = tables.latex(groups, meta)
    assert r"\mathbf{29.50} \pm 1.12" in tex and r"lit\_as\_albedo" in tex and "lumimotion" in tex
    assert tex.count(r"\begin{tabular}") == 1 and tex.count("&") > 40
    rows = list(csv.DictReader(io.StringIO(tables.csv_text(groups, meta))))
    ours = next(r for r in rows if r["method"] == "ours" and r["configuration"] == "city->sunrise")
    assert float(ours["albedo.psnr.mean"]) == pytest.approx(29.5) and ours["n_failed"] == "1"
    assert rows[0]["protocol"] == "lumimotion"


def test_mixed_protocols_are_refused():
    rs = _results()
    rs[0]["protocol"] = "strict"
    with pytest.raises(UserError, match="mix protocols"):
        check_consistent(rs)


def test_pareto_front():
    pts = [(1, 20), (2, 25), (3, 24), (4, 30), (0.5, 10)]
    assert charts.pareto_front(pts, higher_better=True) == [(0.5, 10), (1, 20), (2, 25), (4, 30)]
    assert charts.pareto_front([(1, 0.2), (2, 0.1), (3, 0.15)], higher_better=False) == [(1, 0.2), (2, 0.1)]


def test_charts_and_report_written(tmp_path):
    from benchmark.outputs import build_outputs

    paths = []
    for i, r in enumerate(_results()):
        p = tmp_path / "runs" / f"{i}" / "results.json"
        write_result(p, r)
        paths.append(p)
    out = build_outputs(paths, tmp_path / "out", grids=False)
    for name in ("table.md", "table.tex", "table.csv", "pareto.png", "quality_vs_gaussians.png", "stability.png", "report.html"):
        assert out[name].name == name
        assert out[name].is_file() and out[name].stat().st_size > 0, name
    assert out["pareto.png"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    html = out["report.html"].read_text()
    for link in ("pareto.png", "stability.png", "quality_vs_gaussians.png", "table.md", "table.tex", "table.csv",
                 "../runs/0/results.json"):
        assert link in html
    assert "Failed runs" in html and "RuntimeError: boom" in html
    assert re.search(r"<td class=best>29\.50 ± 1\.12</td>", html)


def test_chart_failure_marks_skip_methods_not_run():
    labels = []

    class Ax:  # records what _draw_failures would draw
        transAxes = None

        def scatter(self, *args, **kwargs):
            labels.append(kwargs["label"])

        def get_xaxis_transform(self):
            return None

    res = [{"method": "irgs", "status": "failed", "error": "not run: export the scene first"},
           {"method": "r3dgs", "status": "not_run"},
           {"method": "ours", "status": "failed", "error": "NaN at iteration 3"}]
    charts._draw_failures(Ax(), res, ["irgs", "r3dgs", "ours"], {})
    assert labels == ["ours: 1 failed (no value)"]


def test_outputs_rebuilt_without_predictions_keep_drawn_grids(tmp_path, capsys):
    """Result files alone rebuild everything (runs/ cleaned or from another machine): a grid drawn while
    the predictions were here is kept and linked, a missing one is skipped with a note, nothing fails."""
    from benchmark.outputs import build_outputs

    paths = []
    for i, r in enumerate(_results()):  # every pred_dir is /nowhere
        p = tmp_path / "runs" / f"{i}" / "results.json"
        write_result(p, r)
        paths.append(p)
    kept = tmp_path / "out" / "grids" / "ours_a_city_to_sunrise_seed0.png"
    kept.parent.mkdir(parents=True)
    kept.write_bytes(b"\x89PNG\r\n\x1a\nold")
    out = build_outputs(paths, tmp_path / "out", grids=True)
    assert out["grids/ours_a_city_to_sunrise_seed0.png"] == kept and kept.read_bytes().endswith(b"old")
    assert sorted(k for k in out if k.startswith("grids/")) == ["grids/ours_a_city_to_sunrise_seed0.png"]
    html = out["report.html"].read_text()
    assert "grids/ours_a_city_to_sunrise_seed0.png" in html
    assert "grids/ours_b_city_to_sunrise_seed0.png" not in html
    assert "no image grid for ours_b_city_to_sunrise_seed0" in capsys.readouterr().err
