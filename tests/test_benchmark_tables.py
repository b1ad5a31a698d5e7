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

        def annotate(self, *args, **kwargs):
            pass

    res = [{"method": "irgs", "status": "failed", "error": "not run: export the scene first"},
           {"method": "r3dgs", "status": "not_run"},
           {"method": "ours", "status": "failed", "error": "NaN at iteration 3"}]
    methods = ["irgs", "r3dgs", "ours"]
    charts._draw_failures(Ax(), charts.failure_marks(res, methods), methods)
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
    # without drawing (`--no-grids`), the report still links the grid drawn before, and says nothing of the rest
    html = build_outputs(paths, tmp_path / "out", grids=False)["report.html"].read_text()
    assert "grids/ours_a_city_to_sunrise_seed0.png" in html and kept.read_bytes().endswith(b"old")
    assert "no image grid" not in capsys.readouterr().err


# --- readable charts (issue 26): plain log ticks that do not overlap, "not run" is no failure, legends outside ---

def _drawn(monkeypatch, tmp_path, build, results):
    """Build a chart with ``build`` and return its figure, drawn (instead of writing the PNG)."""
    figs = []
    monkeypatch.setattr(charts, "_save", lambda fig, path: figs.append(fig) or path)
    build(results, tmp_path / "chart.png")
    (fig,) = figs
    fig.canvas.draw()
    return fig


def _shown_labels(ax, minor=False):
    """The x tick labels drawn inside the axis' view interval, with their bounding boxes on the canvas."""
    lo, hi = sorted(ax.get_xlim())
    renderer = ax.figure.canvas.get_renderer()
    out = []
    for lab in ax.get_xticklabels(minor=minor):
        x = lab.get_position()[0]
        if lab.get_visible() and lab.get_text() and lo * (1 - 1e-9) <= x <= hi * (1 + 1e-9):
            out.append((lab.get_text(), lab.get_window_extent(renderer)))
    return out


def _assert_no_overlap(labels):
    for i, (ta, a) in enumerate(labels):
        for tb, b in labels[i + 1:]:
            assert not a.overlaps(b), f"tick labels {ta!r} and {tb!r} overlap"


def _size_results(counts):
    return [fake_result(m, s, seed=seed, relight_psnr=24 + i + seed, lpips=0.1 - 0.01 * i, seconds=10 ** i,
                        gaussians=int(n * (1 + 0.05 * seed)))
            for i, (m, n) in enumerate(counts.items()) for s in ("a", "b") for seed in (0, 1)]


def test_gaussian_axis_ticks_are_plain_numbers_that_do_not_overlap(monkeypatch, tmp_path):
    import matplotlib.pyplot as plt

    res = _size_results({"small": 5200, "ours": 21000, "big": 190000})
    fig = _drawn(monkeypatch, tmp_path, charts.gaussians_chart, res)
    for ax in fig.axes:
        assert ax.get_xscale() == "log"
        labels = _shown_labels(ax)
        texts = [t for t, _ in labels]
        assert set(texts) <= {"5k", "10k", "20k", "50k", "100k", "200k"}, texts
        assert {"10k", "20k", "50k", "100k"} <= set(texts), texts
        assert _shown_labels(ax, minor=True) == []  # no minor labels
        _assert_no_overlap(labels)
    plt.close(fig)

    # a narrow range (the published small benchmark: 19,935 to 19,960 Gaussians) overlapped before
    res = [fake_result("static", s, relight_psnr=26 + k, gaussians=n)
           for k, (s, n) in enumerate((("a", 19935), ("b", 19960)))]
    fig = _drawn(monkeypatch, tmp_path, charts.gaussians_chart, res)
    for ax in fig.axes:
        labels = _shown_labels(ax)
        assert len(labels) >= 2
        assert all(re.fullmatch(r"\d{1,3}(,\d{3})*|\d+(\.\d+)?k", t) for t, _ in labels), labels
        assert _shown_labels(ax, minor=True) == []
        _assert_no_overlap(labels + _shown_labels(ax, minor=True))
    plt.close(fig)


def test_time_axis_ticks_are_plain_numbers(monkeypatch, tmp_path):
    import matplotlib.pyplot as plt

    fig = _drawn(monkeypatch, tmp_path, charts.pareto_chart, _size_results({"a": 1, "b": 1, "c": 1, "d": 1, "e": 1}))
    for ax in fig.axes:  # seconds from 1 to 10,000 (and a little more)
        texts = [t for t, _ in _shown_labels(ax)]
        assert texts == ["1", "10", "100", "1k", "10k"], texts
        _assert_no_overlap(_shown_labels(ax))
    plt.close(fig)


def _with_not_run():
    rs = [fake_result("ours", s, seed=seed, relight_psnr=26 + seed, seconds=100, gaussians=20000)
          for s in ("a", "b") for seed in (0, 1)]
    rs.append(fake_result("ours", "c", status="failed"))  # a crash: stays a failure
    for s in ("a", "b"):  # external methods without outputs, in both forms a not-run job is recorded
        rs.append(fake_result("irgs", s, status="failed") | {"error": "not run: run IRGS and put its outputs in x"})
        rs.append(fake_result("r3dgs", s, status="failed") | {"status": "not_run", "error": "not run: no outputs"})
    return rs


@pytest.mark.parametrize("build", ["pareto_chart", "gaussians_chart", "stability_chart"])
def test_method_not_run_is_named_not_drawn_as_failure(monkeypatch, tmp_path, build):
    import matplotlib.pyplot as plt

    fig = _drawn(monkeypatch, tmp_path, getattr(charts, build), _with_not_run())
    notes = " ".join(t.get_text() for t in fig.texts)
    assert re.search(r"not run\b.*: irgs, r3dgs", notes), notes
    legend_labels = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
    assert "ours: 1 failed" in legend_labels
    for ax in fig.axes:
        labels = [c.get_label() for c in ax.collections]
        assert not [lab for lab in labels if "irgs" in lab or "r3dgs" in lab], labels
        crosses = [c for c in ax.collections if "failed" in c.get_label()]
        assert sum(len(c.get_offsets()) for c in crosses) == 1  # the crash only
        assert not {"irgs", "r3dgs"} & {t.get_text() for t in ax.get_xticklabels()}  # no empty column
    plt.close(fig)


@pytest.mark.parametrize("build", ["pareto_chart", "gaussians_chart", "stability_chart"])
def test_legend_outside_axes_and_failures_below_the_data(monkeypatch, tmp_path, build):
    import matplotlib.pyplot as plt

    fig = _drawn(monkeypatch, tmp_path, getattr(charts, build), _with_not_run())
    renderer = fig.canvas.get_renderer()
    assert fig.legends, "one legend for the figure"
    for ax in fig.axes:
        assert ax.get_legend() is None
        box = ax.get_window_extent(renderer)
        for leg in fig.legends:
            assert not leg.get_window_extent(renderer).overlaps(box), "the legend covers a panel"
        # every failure cross sits below every data point, with room for the markers (no cross covers a point)
        cross_y, data_y = [], []
        for c in ax.collections:
            ys = c.get_offset_transform().transform(c.get_offsets())[:, 1]
            (cross_y if "failed" in c.get_label() else data_y).extend(ys)
        assert cross_y and data_y
        assert min(data_y) - max(cross_y) > 0.04 * box.height
    plt.close(fig)


def test_report_lists_methods_not_run_as_not_run_not_as_failures(tmp_path):
    from benchmark.outputs import build_outputs

    paths = []
    stored = [r | {"status": "failed"} if r["status"] == "not_run" else r for r in _with_not_run()]  # a result file stores not-run as failed + "not run:"
    for i, r in enumerate(stored):
        p = tmp_path / "runs" / f"{i}" / "results.json"
        write_result(p, r)
        paths.append(p)
    html = build_outputs(paths, tmp_path / "out", grids=False)["report.html"].read_text()
    failed = html.split("<h2 class=fail>Failed runs</h2>", 1)[1].split("</ul>", 1)[0]
    assert "ours" in failed and "irgs" not in failed and "r3dgs" not in failed  # only the crash
    assert "5 runs, 1 failed, 4 jobs of methods not run here (not failures)" in html
    listed = html.split("<h2>Per-run result files</h2>", 1)[1]
    assert listed.count("not run</li>") == 4 and listed.count("<span class=fail>failed</span>") == 1


def _with_provenance(r: dict, version: str = "1", settings: str | None = None) -> dict:
    r = dict(r, adapter_version=version)
    r["inputs"] = dict(r["inputs"], **({"method_settings_sha256": settings} if settings else {}))
    return r


def test_rows_that_mix_adapter_versions_or_settings_are_named():
    a, b = "aa" * 32, "bb" * 32
    same = [_with_provenance(fake_result("ours", scene=s), settings=a) for s in ("s1", "s2")]
    md = tables.markdown(aggregate(same), check_consistent(same))
    assert "Rows that mix runs" not in md
    mixed = same + [_with_provenance(fake_result("ours", scene="s3"), settings=b)]
    md = tables.markdown(aggregate(mixed), check_consistent(mixed))
    block = md.split("### Rows that mix runs")[1]
    assert f"settings {a[:12]} on s1, s2" in block and f"settings {b[:12]} on s3" in block
    assert "ours city → sunrise" in block
    # another adapter version with the same settings is named too, and a result recording no settings
    versions = same + [_with_provenance(fake_result("ours", scene="s3"), version="2", settings=a),
                       _with_provenance(fake_result("ours", scene="s4"))]
    block = tables.markdown(aggregate(versions), check_consistent(versions)).split("### Rows that mix runs")[1]
    assert "version 2, settings aaaaaaaaaaaa on s3" in block and "settings not recorded on s4" in block
    only_version = same + [_with_provenance(fake_result("ours", scene="s3"), version="2", settings=a)]
    assert "version 2, settings aaaaaaaaaaaa on s3" in tables.markdown(aggregate(only_version),
                                                                         check_consistent(only_version))
    # a result that records no settings (scored before they were recorded) is not a mix by itself
    unrecorded = same + [_with_provenance(fake_result("ours", scene="s3"))]
    assert "Rows that mix runs" not in tables.markdown(aggregate(unrecorded), check_consistent(unrecorded))
    # failed runs do not count: they have no settings to mix
    with_failure = same + [fake_result("ours", scene="s3", status="failed")]
    assert "Rows that mix runs" not in tables.markdown(aggregate(with_failure), check_consistent(with_failure))


def test_a_scene_scored_on_two_versions_of_its_dataset_is_named():
    def on(r: dict, dataset: str) -> dict:
        return dict(r, inputs=dict(r["inputs"], dataset_spec_hash=dataset))

    a, b = "cc" * 32, "dd" * 32
    # two scenes on their own datasets (each scene has its own hash): not a mix
    same = [on(fake_result("ours", scene="s1", seed=k), a) for k in (0, 1)] + [on(fake_result("ours", scene="s2"), b)]
    assert "Rows that mix datasets" not in tables.markdown(aggregate(same), check_consistent(same))
    # s1's third seed scored after the dataset changed
    mixed = same + [on(fake_result("ours", scene="s1", seed=2), b)]
    block = tables.markdown(aggregate(mixed), check_consistent(mixed)).split("### Rows that mix datasets")[1]
    assert f"ours city → sunrise: s1 ({a[:12]}, {b[:12]})" in block and "s2" not in block.split("###")[0]


# --- `python -m benchmark tables DIR`: the tables rebuilt from a results folder alone ---

def test_tables_verb_rebuilds_from_stored_results_alone(tmp_path, capsys):
    """No dataset, no runs, no grid YAML: the verb reads DIR/runs and rewrites a stale table with every
    stored result, the strict protocol's in its own table."""
    from benchmark.__main__ import main

    out = tmp_path / "small"
    for scene, a in (("a", 27.0), ("b", 29.0)):
        r = fake_result("ours", scene, albedo_psnr=a)
        write_result(out / "runs" / "ours" / scene / "results.json", r)
        write_result(out / "runs" / "ours" / scene / "results_strict.json",
                     r | {"protocol": "strict", "metrics": r["metrics"] | {"albedo": r["metrics"]["albedo"] | {"psnr": a - 6}}})
    (out / "table.md").write_text("stale\n")
    assert main(["tables", str(out), "--no-grids"]) == 0
    md = (out / "table.md").read_text()
    assert "stale" not in md and "Protocol lumimotion" in md and "Protocol strict" in md
    assert "28.00 ± 1.00" in md  # the two scenes' albedo PSNR, lumimotion
    assert "22.00 ± 1.00" in md  # and strict
    assert (out / "report.html").is_file()
    assert "4 result files" in capsys.readouterr().out


def test_tables_verb_refuses_a_folder_without_results(tmp_path, capsys):
    from benchmark.__main__ import main

    assert main(["tables", str(tmp_path)]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no result files" in err[0]
    assert main(["tables", str(tmp_path / "nope")]) != 0
    assert "no such results folder" in capsys.readouterr().err


# --- `python -m benchmark compare OLD NEW`: job by job ---

def test_compare_matches_jobs_by_identity_and_counts_improvements_by_direction(tmp_path, capsys):
    """Pairs by (method, scene, lights, seed, protocol), never by position; LPIPS lower is better; a job on
    one side only or failed on one side is listed and kept out of the means."""
    from benchmark.__main__ import main
    from benchmark.compare import compare

    def put(side, r, name="results.json"):
        write_result(tmp_path / side / "runs" / r["method"] / r["scene"] / f"seed{r['seed']}" / name, r)

    put("old", fake_result("ours", "a", albedo_psnr=25.0, lpips=0.10))
    put("new", fake_result("ours", "a", albedo_psnr=26.0, lpips=0.12))      # PSNR better, LPIPS worse
    put("old", fake_result("ours", "b", albedo_psnr=30.0, lpips=0.10))
    put("new", fake_result("ours", "b", albedo_psnr=29.0, lpips=0.11))      # both worse
    put("old", fake_result("ours", "b", seed=1, albedo_psnr=10.0))          # only before
    put("old", fake_result("ours", "c", albedo_psnr=20.0))
    put("new", fake_result("ours", "c", status="failed"))                    # failed after
    put("new", fake_result("ours", "a", albedo_psnr=99.0) | {"protocol": "strict"}, "results_strict.json")
    c = compare(tmp_path / "old", tmp_path / "new")
    assert [(o["scene"], n["scene"]) for o, n in c.pairs] == [("a", "a"), ("b", "b")]
    assert c.summary("albedo.psnr") == (0.0, 1, 2)
    mean, better, n = c.summary("albedo.lpips")
    assert abs(mean - (0.02 + 0.01) / 2) < 1e-12 and (better, n) == (0, 2)  # higher LPIPS is worse
    assert [i[1] for i in c.only_old] == ["b"] and c.failed == [(("ours", "c", "city", "sunrise", 0, "lumimotion"), "new")]
    strict = compare(tmp_path / "old", tmp_path / "new", protocol="strict")
    assert not strict.pairs and [i[1] for i in strict.only_new] == ["a"]
    assert main(["compare", str(tmp_path / "old"), str(tmp_path / "new"), "--out", str(tmp_path / "c.md")]) == 0
    out = capsys.readouterr().out
    assert "| ours | a | city -> sunrise | 0 |" in out and "25.00 -> 26.00" in out and "+0.00 (better 1 of 2)" in out
    assert "failed on new side" in out and "only in" in out and (tmp_path / "c.md").read_text() == out
    assert main(["compare", str(tmp_path / "old"), str(tmp_path / "new"), "--methods", "theirs"]) != 0
    assert "no job is in both" in capsys.readouterr().err
