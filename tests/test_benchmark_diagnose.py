"""Where the relight error comes from (issue 26): the in-project adapters run the relight diagnostic once per
(run, test light), results.json carries it, a chart shows it per scene and report.html has a section for it.

No training here: a run directory with the files a finished run leaves stands for one, its predictions are
the noisy oracle's, and method.diagnose.diagnose is replaced by a counting fake."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from baselines_adapters import lumimotion as lm
from baselines_adapters.registry import get_adapter
from benchmark import charts
from benchmark.results import read_result, validate, write_result
from benchmark_fakes import dataset_root, fake_result
from lumibench.io import atomic_write_json

STEP_NAMES = ("ours", "ours_unshadowed", "gt_albedo", "gt_roughness", "gt_normal", "gt_all", "gt_all_unshadowed")
OURS_PSNR = {"sunrise": 20.0, "courtyard": 21.0, "sunset": 22.0}  # per test light, to tell the blocks apart


def _record(test_light: str, views: int, dirs: int, steps=STEP_NAMES) -> dict:
    base = OURS_PSNR[test_light]
    return {"views": views, "dirs": dirs, "protocol": "lumimotion", "test_light": test_light,
            "steps": {n: {"psnr": base + 0.5 * i, "ssim": 0.9, "lpips": 0.2 - 0.01 * i, "psnr_gain": 0.5 * i}
                      for i, n in enumerate(steps)}}


@pytest.fixture
def calls(monkeypatch):
    """method.diagnose.diagnose replaced by a fake that counts its calls and writes the record as the real one."""
    import method.diagnose as dg

    seen = []

    def fake(run_dir, test_light, *, dirs=None, views=None, data=None, progress=True, **kw):
        seen.append({"run": Path(run_dir), "light": test_light, "dirs": dirs, "views": views, "data": data})
        rec = _record(test_light, 3, dirs)  # the fake scene has 3 test views
        atomic_write_json(Path(run_dir) / "diagnose" / test_light / "diagnose.json", rec)
        return rec

    monkeypatch.setattr(dg, "diagnose", fake)
    return seen


@pytest.fixture
def no_training(monkeypatch):
    """The adapter finds finished runs: it must not train; its predictions are written by the noisy oracle."""
    import method.predictions
    import method.train
    from baselines_adapters.trivial import NoisyGT
    from lumibench.predictions import write_meta

    def refuse(*args, **kwargs):
        raise AssertionError("the adapter trained a finished run")

    def write_predictions(run_dir, scene_dir, light, cfg, *, method="lumimotion", seed=0, test_lights=None, **kw):
        pred = Path(run_dir) / "predictions"
        NoisyGT().predict(Path(scene_dir), light, list(test_lights), seed, "ci", pred, None)
        write_meta(pred, {"method": method, "version": "2", "seed": seed, "timings": {"stage1": 1.0, "stage2": 1.0}})
        return pred

    monkeypatch.setattr(method.train, "train_stage1", refuse)
    monkeypatch.setattr(method.train, "train_stage2", refuse)
    monkeypatch.setattr(method.predictions, "write_predictions", write_predictions)


def _finished_run(run_dir: Path, dirs_eval: int = 256) -> Path:
    """The files of a run whose two stages are done (config.yaml as train writes it, in part)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    for stage in (1, 2):
        (run_dir / f"metrics_stage{stage}.json").write_text("{}")
    (run_dir / "config.yaml").write_text(f"run: {{light: city, seed: 0}}\nprofile: ci\nstage2: {{dirs_eval: {dirs_eval}}}\n")
    return run_dir


def test_adapter_diagnoses_each_test_light_once_and_reuses_the_record(tmp_path, calls, no_training):
    scene = dataset_root(tmp_path) / "ci" / "fake"
    runs = tmp_path / "runs"
    run = _finished_run(runs / "lumimotion" / "fake" / "city" / "seed0")
    adapter = get_adapter("lumimotion")
    adapter.run(scene, "city", ["sunrise", "courtyard"], 0, "ci", run / "predictions", runs)
    # once per test light the grid scores, all test views, the run's dirs_eval capped at 128, on the scored scene
    assert [c["light"] for c in calls] == ["sunrise", "courtyard"]
    assert all(c["run"] == run and c["dirs"] == lm.DIAGNOSE_MAX_DIRS == 128 and c["views"] is None
               and Path(c["data"]) == scene for c in calls)
    meta = json.loads((run / "predictions" / "meta.json").read_text())
    assert set(meta["diagnose"]) == {"sunrise", "courtyard"}
    block = meta["diagnose"]["courtyard"]
    assert block["views"] == 3 and block["dirs"] == 128 and set(block["steps"]) == set(STEP_NAMES)
    assert block["steps"]["ours"] == {"psnr": 21.0, "lpips": 0.2}

    # predicting again (a rescore, another grid over the same run) reuses the stored records
    adapter.run(scene, "city", ["courtyard", "sunrise"], 0, "ci", run / "predictions", runs)
    assert len(calls) == 2
    assert json.loads((run / "predictions" / "meta.json").read_text())["diagnose"] == meta["diagnose"]

    # a record with other steps (an older diagnostic) or of fewer views (--views 2) is computed again
    atomic_write_json(run / "diagnose" / "sunset" / "diagnose.json", _record("sunset", 3, 64, STEP_NAMES[:-1]))
    adapter.run(scene, "city", ["sunset"], 0, "ci", run / "predictions", runs)
    atomic_write_json(run / "diagnose" / "sunset" / "diagnose.json", _record("sunset", 2, 64))
    adapter.run(scene, "city", ["sunset"], 0, "ci", run / "predictions", runs)
    assert [c["light"] for c in calls[2:]] == ["sunset", "sunset"]

    # a record made under another test-time normal filter than the run's record says is computed again
    # (predictions written again with stage2.normal_filter record the new value in config.yaml)
    rec = _record("sunset", 3, 64)
    atomic_write_json(run / "diagnose" / "sunset" / "diagnose.json", rec)
    adapter.run(scene, "city", ["sunset"], 0, "ci", run / "predictions", runs)
    assert len(calls) == 4  # no filter either side (a record from before the setting): reused
    (run / "config.yaml").write_text("run: {light: city, seed: 0}\nprofile: ci\n"
                                     "stage2: {dirs_eval: 256, normal_filter: 1.0}\n")
    adapter.run(scene, "city", ["sunset"], 0, "ci", run / "predictions", runs)
    assert len(calls) == 5
    atomic_write_json(run / "diagnose" / "sunset" / "diagnose.json", {**rec, "normal_filter": 1.0})
    adapter.run(scene, "city", ["sunset"], 0, "ci", run / "predictions", runs)
    assert len(calls) == 5
    # the same for the relit indirect light (stage2.relight_indirect): a record without it is not reused
    # once the run shades with it, one with it is
    (run / "config.yaml").write_text("run: {light: city, seed: 0}\nprofile: ci\n"
                                     "stage2: {dirs_eval: 256, normal_filter: 1.0, relight_indirect: true}\n")
    adapter.run(scene, "city", ["sunset"], 0, "ci", run / "predictions", runs)
    assert len(calls) == 6
    atomic_write_json(run / "diagnose" / "sunset" / "diagnose.json",
                      {**rec, "normal_filter": 1.0, "relight_indirect": True})
    adapter.run(scene, "city", ["sunset"], 0, "ci", run / "predictions", runs)
    assert len(calls) == 6
    _finished_run(run)

    # a small dirs_eval is not raised to the cap
    small = _finished_run(runs / "wo_dc" / "fake" / "city" / "seed0", dirs_eval=64)
    get_adapter("wo_dc").run(scene, "city", ["sunrise"], 0, "ci", small / "predictions", runs)
    assert calls[-1]["run"] == small and calls[-1]["dirs"] == 64


def test_no_diagnostic_without_stage_2(tmp_path, calls, no_training):
    scene = dataset_root(tmp_path) / "ci" / "fake"
    run = _finished_run(tmp_path / "runs" / "wo_stage2" / "fake" / "city" / "seed0")
    get_adapter("wo_stage2").run(scene, "city", ["sunrise"], 0, "ci", run / "predictions", tmp_path / "runs")
    assert calls == [] and "diagnose" not in json.loads((run / "predictions" / "meta.json").read_text())


def test_grid_results_carry_the_diagnostic_of_their_test_light(tmp_path, calls, no_training):
    from benchmark.config import load_benchmark_config
    from benchmark.jobgrid import Paths, result_path, run_grid

    data = dataset_root(tmp_path)
    grid = tmp_path / "grid.yaml"
    grid.write_text("profile: ci\nscenes: [fake]\nconfigurations:\n  - {train: city, test: sunrise}\n"
                    "  - {train: city, test: courtyard}\nmethods: [lumimotion, wo_stage2]\nseeds: [0]\n")
    config = load_benchmark_config(grid)
    paths = Paths(data, tmp_path / "runs", tmp_path / "results", "ci")
    for m in ("lumimotion", "wo_stage2"):
        _finished_run(paths.runs / "ci" / m / "fake" / "city" / "seed0")
    report = run_grid(config, paths, quiet=True)
    assert not report.failed, report.failed
    assert sorted(c["light"] for c in calls) == ["courtyard", "sunrise"]  # one job, both test lights
    files = {(m, c.test): result_path(paths, m, "fake", c, 0) for m in ("lumimotion", "wo_stage2")
             for c in config.configurations}
    for (m, test), path in files.items():
        res = read_result(path)  # validated on read
        if m == "wo_stage2":
            assert "diagnose" not in res
            continue
        block = res["diagnose"]
        assert block["views"] == 3 and block["dirs"] == 128 and block["protocol"] == "lumimotion"
        assert block["steps"]["ours"]["psnr"] == OURS_PSNR[test]  # this result's own test light
        assert set(block["steps"]) == set(STEP_NAMES)
        assert all(set(s) == {"psnr", "lpips"} for s in block["steps"].values())

    # rescored from scratch (results and predictions' meta.json gone): nothing is diagnosed again
    for path in files.values():
        path.unlink()
    (paths.runs / "ci" / "lumimotion" / "fake" / "city" / "seed0" / "predictions" / "meta.json").unlink()
    assert not run_grid(config, paths, quiet=True).failed
    assert len(calls) == 2
    assert read_result(files["lumimotion", "sunrise"])["diagnose"]["steps"]["ours"]["psnr"] == 20.0


def test_both_protocols_diagnose_once_and_an_added_protocol_diagnoses_nothing(tmp_path, calls, no_training,
                                                                              monkeypatch):
    """The diagnostic is the adapter's work: one per (run, test light) whatever the number of protocols; a
    protocol added to a grid later is scored from the stored predictions (even after an adapter version
    bump), with neither a prediction nor a diagnostic."""
    import method.predictions
    from benchmark.config import load_benchmark_config
    from benchmark.jobgrid import Paths, result_path, run_grid

    data = dataset_root(tmp_path)
    body = ("profile: ci\nscenes: [fake]\nconfigurations:\n  - {train: city, test: sunrise}\n"
            "  - {train: city, test: courtyard}\nmethods: [lumimotion]\nseeds: [0]\n")
    both, old = tmp_path / "both.yaml", tmp_path / "old.yaml"
    both.write_text("protocols: [lumimotion, strict]\n" + body)
    old.write_text("protocol: lumimotion\n" + body)
    predicted = []
    real = method.predictions.write_predictions
    monkeypatch.setattr(method.predictions, "write_predictions", lambda *a, **k: predicted.append(1) or real(*a, **k))

    # one grid, both protocols: one diagnostic per test light, carried into both protocols' results
    config = load_benchmark_config(both)
    paths = Paths(data, tmp_path / "runs", tmp_path / "results", "ci")
    _finished_run(paths.runs / "ci" / "lumimotion" / "fake" / "city" / "seed0")
    assert not run_grid(config, paths, quiet=True).failed
    assert sorted(c["light"] for c in calls) == ["courtyard", "sunrise"] and len(predicted) == 1
    for c in config.configurations:
        blocks = [read_result(result_path(paths, "lumimotion", "fake", c, 0, p))["diagnose"] for p in config.protocols]
        assert blocks[0] == blocks[1] and blocks[0]["steps"]["ours"]["psnr"] == OURS_PSNR[c.test]

    # an old grid (lumimotion only), then the same grid with strict added after the adapter moved on
    paths = Paths(data, tmp_path / "runs2", tmp_path / "results2", "ci")
    _finished_run(paths.runs / "ci" / "lumimotion" / "fake" / "city" / "seed0")
    assert not run_grid(load_benchmark_config(old), paths, quiet=True).failed
    assert len(calls) == 4 and len(predicted) == 2
    before = lm.LumiMotionAdapter.version
    monkeypatch.setattr(lm.LumiMotionAdapter, "version", "99")
    report = run_grid(config, paths, quiet=True)
    assert len(report.executed) == 1 and not report.failed
    assert len(calls) == 4 and len(predicted) == 2  # nothing predicted, nothing diagnosed
    strict = read_result(result_path(paths, "lumimotion", "fake", config.configurations[0], 0, "strict"))
    assert strict["adapter_version"] == before and strict["diagnose"]["steps"]["ours"]["psnr"] == OURS_PSNR["sunrise"]


@pytest.mark.parametrize("mutate, field", [
    (lambda d: d.update(views=0), "diagnose.views"),
    (lambda d: d.update(dirs="many"), "diagnose.dirs"),
    (lambda d: d.update(steps={"gt_all": {"psnr": 1.0, "lpips": 0.1}}), "diagnose.steps"),
    (lambda d: d["steps"]["gt_normal"].update(psnr=float("nan")), "diagnose.steps.gt_normal.psnr"),
    (lambda d: d["steps"]["ours"].pop("lpips"), "diagnose.steps.ours.lpips"),
])
def test_schema_accepts_the_block_and_names_a_bad_field(tmp_path, mutate, field):
    from lumibench.errors import UserError

    res = fake_result("lumimotion") | {"diagnose": _block("sunrise")}
    write_result(tmp_path / "results.json", res)
    assert read_result(tmp_path / "results.json")["diagnose"] == res["diagnose"]
    validate(fake_result("lumimotion") | {"diagnose": None})  # absent or null: fine (other methods)
    mutate(res["diagnose"])
    with pytest.raises(UserError, match=field.replace(".", r"\.")):
        validate(res, "r.json")


def _block(test_light: str, gain: float = 1.0) -> dict:
    rec = _record(test_light, 20, 128)
    return {"views": 20, "dirs": 128, "protocol": "lumimotion",
            "steps": {n: {"psnr": s["psnr"] * gain, "lpips": s["lpips"]} for n, s in rec["steps"].items()}}


def _diagnosed_results():
    rs = []
    for train, test in (("city", "sunrise"), ("sunrise", "city")):
        for scene in ("spheres", "jumpingjacks", "mouse"):
            for k, m in enumerate(("lumimotion", "static")):
                rs.append(fake_result(m, scene, train, test) | {"diagnose": _block("sunrise", 1 + 0.02 * k)})
            rs.append(fake_result("lit_as_albedo", scene, train, test))
    rs.append(fake_result("static", "hook", "city", "sunrise", status="failed"))
    return rs


def test_relight_error_chart_lists_scenes_and_is_absent_without_diagnostics(monkeypatch, tmp_path):
    import matplotlib.pyplot as plt

    out = charts.all_charts(_diagnosed_results(), tmp_path / "with")
    assert out["relight_error_sources"] == tmp_path / "with" / "relight_error_sources.png"
    assert out["relight_error_sources"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    plain = [fake_result(m, s) for m in ("lumimotion", "lit_as_albedo") for s in ("a", "b")]
    out = charts.all_charts(plain, tmp_path / "without")
    assert "relight_error_sources" not in out and not (tmp_path / "without" / "relight_error_sources.png").exists()

    figs = []
    monkeypatch.setattr(charts, "_save", lambda fig, path: figs.append(fig) or path)
    charts.relight_error_sources_chart(_diagnosed_results(), tmp_path / "chart.png")
    (fig,) = figs
    fig.canvas.draw()
    assert [ax.get_title() for ax in fig.axes] == ["city → sunrise", "sunrise → city"]  # a panel per configuration
    renderer = fig.canvas.get_renderer()
    # the scenes with a run in each configuration, under their groups (hook: static failed there)
    assert [[t.get_text() for t in ax.texts] for ax in fig.axes] == [["spheres", "jumpingjacks", "mouse", "hook"],
                                                                     ["spheres", "jumpingjacks", "mouse"]]
    for ax in fig.axes:
        ticks = [t.get_text() for t in ax.get_xticklabels()]
        assert "lumimotion\n20.0 dB" in ticks and "static\n20.4 dB" in ticks  # the method and its own PSNR
        assert not any("lit_as_albedo" in t for t in ticks)  # no diagnostic, no group
        # six bars per diagnosed group: the gains of the steps over "ours"
        assert len(ax.patches) == 6 * 6
        # the gains over "ours": lumimotion's steps 0.5 dB apart, static's 2 % more
        heights = sorted(round(p.get_height(), 6) for p in ax.patches)
        assert heights[-6:] == [3.0] * 3 + [3.06] * 3 and heights[0] == 0.5
        for leg in fig.legends:
            assert not leg.get_window_extent(renderer).overlaps(ax.get_window_extent(renderer))
    assert "static\nfailed" in [t.get_text() for t in fig.axes[0].get_xticklabels()]
    legend = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
    assert legend == ["GT albedo", "GT roughness", "GT normals", "GT albedo + roughness + normals",
                      "ours without our shadows", "all three GT, without our shadows"]
    plt.close(fig)


def test_report_has_the_relight_error_section(tmp_path):
    from benchmark.outputs import build_outputs

    def build(results, name):
        paths = []
        for i, r in enumerate(results):
            write_result(tmp_path / name / "runs" / str(i) / "results.json", r)
            paths.append(tmp_path / name / "runs" / str(i) / "results.json")
        return build_outputs(paths, tmp_path / name / "out", grids=False)

    out = build(_diagnosed_results(), "with")
    html = out["report.html"].read_text()
    section = html.split("<h2>Where the relight error comes from</h2>", 1)[1].split("<h2", 1)[0]
    assert "relight_error_sources.png" in section and "replaced by the ground truth" in section
    assert html.count("relight_error_sources.png") == 2  # the link and the image, in that section only
    html = build([fake_result("lumimotion", s) for s in ("a", "b")], "without")["report.html"].read_text()
    assert "Where the relight error comes from" not in html
