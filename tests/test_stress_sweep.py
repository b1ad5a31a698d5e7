"""Issue 26's stress sweep, its mechanisms: a share of the training frames (``@frames0.25``), a light at its own
map resolution (``city_sharp``, 128 x 64) with everything downstream of a GT map that is not 32 x 16, the
grids (every file in configs/benchmark/ loads; a configuration may name its methods), and failed or diverged
runs drawn where they belong in the charts."""
from __future__ import annotations

import dataclasses
import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from benchmark_fakes import fake_result, make_fake_scene
from lumibench.errors import UserError

ROOT = Path(__file__).resolve().parents[1]
TINY = ["stage1.iterations=6", "stage1.init_points=300", "stage1.max_gaussians=0", "stage1.warmup=2",
        "stage1.densify_from=100", "stage1.eval_every=0", "stage1.checkpoint_every=6",
        "stage2.iterations=2", "stage2.dirs_train=8", "stage2.dirs_eval=8", "stage2.rays_per_iteration=512"]


# ------------------------------------------------------------------- a share of the training frames

def _max_min_gap_subsets(times: list[float], m: int) -> list[tuple[int, ...]]:
    """Brute force: the m-frame subsets holding the first and the last time whose smallest gap between
    consecutive times is the largest possible (what "evenly over time" means)."""
    order = sorted(range(len(times)), key=lambda i: (times[i], i))
    best, found = -1.0, []
    for combo in itertools.combinations(range(len(order)), m):
        if combo[0] != 0 or combo[-1] != len(order) - 1:
            continue
        gap = min(times[order[b]] - times[order[a]] for a, b in zip(combo, combo[1:]))
        if gap > best + 1e-12:
            best, found = gap, [combo]
        elif abs(gap - best) <= 1e-12:
            found.append(combo)
    return [tuple(sorted(order[k] for k in c)) for c in found]


def test_even_subset_keeps_the_evenly_spaced_frames():
    from method.data import even_subset

    for n in (16, 17, 60, 100):
        assert even_subset(n, 1.0) == list(range(n))
        for f in (0.1, 0.25, 0.5, 0.75):
            idx = even_subset(n, f)
            assert len(idx) == round(f * n) and idx[0] == 0 and idx[-1] == n - 1
            gaps = np.diff(idx)
            assert gaps.max() - gaps.min() <= 1, (n, f, idx)  # evenly: every 1/f-th frame, give or take one
    # the quarter of ci's 16 frames and of a 13-frame capture: the unique most even choices
    for n in (16, 13):
        assert [tuple(even_subset(n, 0.25))] == _max_min_gap_subsets([i / (n - 1) for i in range(n)], round(n / 4))
    assert even_subset(3, 0.1) == [0, 2]  # never fewer than the first and the last time


def test_loader_keeps_the_frames_evenly_over_time_not_file_order(tmp_path):
    """A capture listed out of order whose times do not follow the file numbers: the frames kept are the
    evenly spaced ones over time (brute force), and their images alone are read."""
    from method.data import load_scene

    scene = make_fake_scene(tmp_path, "shuffled", lights=("city",), n_train=16, n_test=1, res=8)
    tf = scene / "transforms_train.json"
    doc = json.loads(tf.read_text())
    perm = np.random.default_rng(3).permutation(16)
    for f, k in zip(doc["frames"], perm):
        f["time"] = float(k) / 15.0
    doc["frames"] = doc["frames"][::-1]
    tf.write_text(json.dumps(doc))
    times = {f["file_path"].split("/")[-1]: f["time"] for f in doc["frames"]}
    stems = sorted(times)
    (expected,) = _max_min_gap_subsets([times[s] for s in stems], 4)
    # a frame that is not kept may even be unreadable: it is never opened
    dropped = [s for i, s in enumerate(stems) if i not in expected]
    (scene / "city" / "train" / f"{dropped[0]}.png").write_bytes(b"not a png")
    data = load_scene(scene, "city", train_frames=0.25, load_test=False)
    assert [v.stem for v in data.train] == [stems[i] for i in expected]
    assert sorted(v.time for v in data.train) == pytest.approx([0.0, 5 / 15, 10 / 15, 1.0])
    with pytest.raises(UserError, match="cannot read image"):
        load_scene(scene, "city", load_test=False)


def test_frames_budget_parses_and_bad_values_are_one_line():
    from baselines_adapters.lumimotion import Budget, parse_budget
    from baselines_adapters.registry import get_adapter, is_known

    assert parse_budget("frames0.25") == Budget(frames=0.25)
    assert parse_budget("0.5+cap2000+frames0.5") == Budget(0.5, 2000, 0.5)
    assert get_adapter("lumimotion@frames0.25").overrides("small") == ["data.train_frames=0.25"]
    ov = get_adapter("static@frames0.25+cap2000").overrides("small")
    assert "data.train_frames=0.25" in ov and "stage1.max_gaussians=2000" in ov
    assert is_known("static@frames0.25") and not is_known("lumimotion@frames2")
    for bad in ("frames0", "frames1.5", "framesx", "frames", "frames0.5+frames0.25"):
        with pytest.raises(UserError) as exc:
            get_adapter(f"lumimotion@{bad}")
        assert "\n" not in str(exc.value) and "frames" in str(exc.value), bad
    from method.config import load_method_config

    for bad in ("0", "1.5", "-0.25"):
        with pytest.raises(UserError, match=r"data\.train_frames"):
            load_method_config("ci", [f"data.train_frames={bad}"])


def test_ci_run_records_the_share_and_trains_on_the_kept_frames(ci_dataset, tmp_path):
    """A ci run of lumimotion@frames0.25: config.yaml holds data.train_frames and the stems it trains on, the
    frames are the evenly spaced quarter of the 16 (brute force), and stage 2 or a resume with another share
    is refused (runs of different shares are never mixed)."""
    import torch

    from baselines_adapters.registry import get_adapter
    from method.config import load_method_config
    from method.train import load_training_scene, train_stage1, train_stage2

    torch.set_num_threads(1)
    cfg = load_method_config("ci", TINY + get_adapter("lumimotion@frames0.25").overrides("ci"))
    run = tmp_path / "run"
    train_stage1(ci_dataset, "city", run, cfg, seed=0, progress=False)
    rec = yaml.safe_load((run / "config.yaml").read_text())
    assert rec["data"]["train_frames"] == 0.25
    frames = json.loads((ci_dataset / "transforms_train.json").read_text())["frames"]
    times = {Path(f["file_path"]).name: f["time"] for f in frames}
    stems = sorted(times)
    (expected,) = _max_min_gap_subsets([times[s] for s in stems], 4)
    assert rec["run"]["train_views"] == [stems[i] for i in expected] == ["r_0000", "r_0005", "r_0010", "r_0015"]
    assert [v.stem for v in load_training_scene(ci_dataset, "city", cfg, "cpu").train] == rec["run"]["train_views"]
    # stage 1 drew P for the frames it trained on; the predictions hold every training view's (the benchmark
    # scores the separation on all of them)
    from method.predictions import write_predictions

    assert len(list((run / "predictions" / "p_map" / "train").glob("*.png"))) == 4
    pred = write_predictions(run, ci_dataset, "city", cfg, seed=0, test_lights=[], albedo_from_colour=True)
    assert sorted(p.stem for p in (pred / "p_map" / "train").glob("*.png")) == stems
    other = load_method_config("ci", TINY + ["data.train_frames=0.5"])
    with pytest.raises(UserError, match=r"data\.train_frames=0\.25"):
        train_stage2(ci_dataset, "city", run, other, seed=0, progress=False)
    full = load_method_config("ci", TINY)
    assert full["data"]["train_frames"] == 1.0
    run_full = tmp_path / "full"
    train_stage1(ci_dataset, "city", run_full, full, seed=0, progress=False, write_outputs=False)
    assert "train_views" not in yaml.safe_load((run_full / "config.yaml").read_text())["run"]


# --------------------------------------------------------------------------- a light at 128 x 64

def test_city_sharp_is_city_at_128_by_64_same_energy_and_sun():
    """The shipped sharp-shadow light is city's light: the same total energy, its 32 x 16 downsampling is
    city's map (block averaging nests), and the sun sits inside city's sun texel; its sun is in texels 16x
    smaller, so its peak is far higher."""
    from generator import envmap as em
    from generator.lights import default_light_names, load_lights, prepare_envmap

    lights = load_lights()
    city, sharp = lights["city"], lights["city_sharp"]
    assert (sharp.source, sharp.rotation_deg, sharp.strength) == (city.source, city.rotation_deg, city.strength)
    assert sharp.resolution == (128, 64) and city.resolution == (32, 16)
    assert "city_sharp" not in default_light_names() and default_light_names() == ["city", "sunrise", "courtyard",
                                                                                     "sunset"]
    a, b = prepare_envmap(city), prepare_envmap(sharp)
    assert a.shape == (16, 32, 3) and b.shape == (64, 128, 3) and b.dtype == np.float32
    np.testing.assert_allclose(em.mean_radiance(b), em.mean_radiance(a), rtol=1e-6)  # measured 3e-8
    np.testing.assert_allclose(em.downsample_envmap(b, 32, 16), a, rtol=1e-5, atol=1e-7)  # measured 1.2e-7
    lum = lambda x: x @ np.array([0.2126, 0.7152, 0.0722], np.float32)  # noqa: E731
    r, c = np.unravel_index(int(np.argmax(lum(b))), (64, 128))
    assert (r // 4, c // 4) == np.unravel_index(int(np.argmax(lum(a))), (16, 32))
    az_a, el_a = em.brightest_direction(a)
    az_b, el_b = em.brightest_direction(b)
    assert abs(az_b - az_a) < 6 and abs(el_b - el_a) < 6  # within city's 11.25 x 11.25 deg sun texel
    assert lum(b).max() > 4 * lum(a).max()


@pytest.mark.parametrize("value", ["[128, 128]", "[128]", "[0, 0]", "[128.0, 64.0]", "128", "[4096, 2048]",
                                   "[true, 1]"])
def test_light_resolution_is_validated_naming_the_key(tmp_path, value):
    from generator.lights import load_lights

    y = tmp_path / "lights.yaml"
    y.write_text(f"lights:\n  city:\n    source: a.hdr\n    resolution: {value}\n")
    with pytest.raises(UserError) as exc:
        load_lights(y)
    assert "lights.city.resolution" in str(exc.value) and "\n" not in str(exc.value)
    y.write_text("lights:\n  city:\n    source: a.hdr\n    default: maybe\n")
    with pytest.raises(UserError, match=r"lights\.city\.default"):
        load_lights(y)


def test_prepare_envmap_at_the_lights_resolution(tmp_path):
    from generator import envmap as em
    from generator.lights import LightSpec, prepare_envmap

    img = np.random.default_rng(0).lognormal(0, 1, (64, 128, 3)).astype(np.float32)
    em.write_hdr(tmp_path / "m.hdr", img)
    src = em.read_envmap(tmp_path / "m.hdr")
    for res in ((32, 16), (64, 32), (128, 64)):
        out = prepare_envmap(LightSpec("m", tmp_path / "m.hdr", 0.0, 2.0, res))
        assert out.shape == (res[1], res[0], 3)
        np.testing.assert_allclose(em.mean_radiance(out), 2.0 * em.mean_radiance(src), rtol=1e-5)


def test_shading_under_a_finer_map_is_the_same_function(tmp_path):
    """A 16 x 32 map and the same map repeated onto 64 x 128 texels are one light: the shading gives the same
    value with and without the env quadrature (its cells are the same: 4 x 4 per texel of the coarse map, one
    per texel of the fine one), and a view relit under maps of both sizes shares one proposal (the mixture
    on the fine grid, its pdf looked up on its own grid)."""
    import torch

    from method.shading.deferred import common_grid, sampling_mixture
    from method.shading.render import quadrature_sub, shade

    assert quadrature_sub(16) == 4 and quadrature_sub(64) == 1 and quadrature_sub(8) == 8
    g = torch.Generator().manual_seed(0)
    P = 64
    n = torch.nn.functional.normalize(torch.randn(P, 3, generator=g, dtype=torch.float64), dim=-1)
    v = torch.nn.functional.normalize(n + 0.5 * torch.randn(P, 3, generator=g, dtype=torch.float64), dim=-1)
    a = torch.rand(P, 3, generator=g, dtype=torch.float64) * 0.8 + 0.1
    r = torch.rand(P, generator=g, dtype=torch.float64) * 0.7 + 0.2
    coarse = torch.rand(16, 32, 3, generator=g, dtype=torch.float64) + 0.05
    coarse[4, 9] = 80.0
    fine = coarse.repeat_interleave(4, 0).repeat_interleave(4, 1)
    assert torch.equal(common_grid([coarse, fine])[0], fine)
    mix = sampling_mixture([coarse, fine])
    assert mix.shape == (64, 128, 3)
    vis = lambda o, d: (d[:, 1] >= -0.2).to(d)  # noqa: E731  (a wall: the quadrature's sampled correction too)
    pts = torch.zeros(P, 3, dtype=torch.float64)
    for quad in (False, True):
        out = [shade(pts, n, v, a, r, env, 64, torch.Generator().manual_seed(5), visibility=vis, sampling_env=mix,
                     env_quadrature=quad) for env in (coarse, fine)]
        torch.testing.assert_close(out[0], out[1], rtol=1e-9, atol=1e-12)
    # unbiased with a proposal on another grid: a 16 x 32 map sampled from a 64 x 128 mixture agrees with
    # its own proposal at many directions
    other = torch.rand(64, 128, 3, generator=g, dtype=torch.float64) + 0.05
    other[10, 70] = 300.0
    mix2 = sampling_mixture([coarse, other])
    ref = shade(None, n, v, a, r, coarse, 8192, torch.Generator().manual_seed(1))
    alt = shade(None, n, v, a, r, coarse, 8192, torch.Generator().manual_seed(2), sampling_env=mix2)
    assert abs(float(alt.sum() / ref.sum()) - 1) < 0.01
    assert sampling_mixture([coarse, torch.ones(24, 48, 3, dtype=torch.float64)]) is None  # sizes that do not nest


def test_benchmark_grid_and_demo_sheet_show_a_finer_true_map(tmp_path):
    """A scene whose <light>.hdr is 64 x 128: the image grid and the demo sheet draw it (and the estimated
    map of another size beside it), and the scorer is indifferent to it."""
    from baselines_adapters.registry import get_adapter
    from benchmark.grids import _true_envmap, image_grid
    from benchmark.score import score
    from generator.envmap import write_hdr
    from lumibench import layout
    from method.commands.demo import demo_sheet

    scene = make_fake_scene(tmp_path, "fine", lights=("city", "sunrise"), n_train=2, n_test=2, res=16)
    env = np.full((64, 128, 3), 0.3, np.float32)
    env[10:12, 40:42] = 200.0
    write_hdr(layout.envmap_path(scene, "city"), env)
    pred = tmp_path / "pred"
    get_adapter("noisy_gt").run(scene, "city", ["sunrise"], 0, "ci", pred, tmp_path / "runs")
    assert _true_envmap(scene, "city").shape == (64, 128, 3)
    res = score(scene, pred, "city", "sunrise")
    out = image_grid(res, tmp_path / "grid.png")
    assert out.is_file() and out.read_bytes()[:4] == b"\x89PNG"
    sheet = demo_sheet(scene, pred, "city", "sunrise", tmp_path / "sheet.png")
    assert sheet.is_file() and sheet.stat().st_size > 0


# ------------------------------------------------------------------------------------------- grids

@pytest.mark.parametrize("path", sorted((ROOT / "configs" / "benchmark").glob("*.yaml")), ids=lambda p: p.name)
def test_every_shipped_grid_loads(path):
    from benchmark.config import load_benchmark_config

    grid = load_benchmark_config(path)
    assert grid.methods and grid.configurations and grid.seeds


def test_stress_and_budget_grids_plan_the_issue_26_jobs(tmp_path):
    from benchmark.config import load_benchmark_config
    from benchmark.jobgrid import Paths, method_jobs, render_jobs

    paths = Paths(tmp_path / "data", tmp_path / "runs", tmp_path / "results", "small")
    stress = load_benchmark_config(ROOT / "configs" / "benchmark" / "small_stress.yaml")
    assert stress.scenes == ("spheres",) and len(stress.seeds) >= 2
    planned = {(j["method"], j["train"], tuple(j["tests"])) for j in method_jobs(stress, paths)}
    full = {(m, "city", ("sunrise",)) for m in ("lumimotion", "static")}
    budget = {(f"{m}@{b}", "city", ("sunrise",)) for m in ("lumimotion", "static") for b in ("frames0.25", "cap2000")}
    lights = {(m, t, (x,)) for m in ("lumimotion", "static") for t, x in (("city_sharp", "sunrise"), ("sunrise", "city"))}
    assert planned == full | budget | lights
    assert len(method_jobs(stress, paths)) == len(planned) * len(stress.seeds)
    assert render_jobs(stress, paths) == [{"kind": "render", "scene": "spheres", "profile": "small",
                                           "data": str(tmp_path / "data"), "light_names": ["city_sharp"]}]
    small_budget = load_benchmark_config(ROOT / "configs" / "benchmark" / "small_budget.yaml")
    assert set(small_budget.methods) == {"lumimotion", "lumimotion@0.25", "lumimotion@0.5", "lumimotion@cap5000",
                                         "lumimotion@cap10000"}
    assert len(small_budget.scenes) == 2 and small_budget.seeds == (0,)
    assert [(c.train, c.test) for c in small_budget.configurations] == [("city", "sunrise")]
    from method.config import load_method_config

    assert load_method_config("small")["stage1"]["max_gaussians"] == 20000  # so lumimotion is the 20k cap


@pytest.mark.parametrize("conf,key", [
    ("{train: city, test: sunrise, methods: [nope]}", "configurations[0].methods"),
    ("{train: city, test: sunrise, methods: []}", "configurations[0].methods"),
    ("{train: city, test: sunrise, methods: lit_as_albedo}", "configurations[0].methods"),
    ("{train: city, test: sunrise, method: [lit_as_albedo]}", "configurations[0].method"),
])
def test_configuration_methods_are_validated(tmp_path, conf, key):
    from benchmark.config import load_benchmark_config

    grid = tmp_path / "g.yaml"
    grid.write_text(f"profile: ci\nscenes: [s]\nconfigurations:\n  - {conf}\nmethods: [lit_as_albedo]\n")
    with pytest.raises(UserError) as exc:
        load_benchmark_config(grid)
    assert key in str(exc.value) and "\n" not in str(exc.value)


def test_a_method_no_configuration_runs_and_a_repeated_configuration_are_errors(tmp_path):
    from benchmark.config import load_benchmark_config

    grid = tmp_path / "g.yaml"
    grid.write_text("profile: ci\nscenes: [s]\nconfigurations:\n  - {train: city, test: sunrise, methods: "
                    "[mean_albedo]}\nmethods: [lit_as_albedo, mean_albedo]\n")
    with pytest.raises(UserError, match=r"key 'methods'.*lit_as_albedo"):
        load_benchmark_config(grid)
    grid.write_text("profile: ci\nscenes: [s]\nconfigurations:\n  - {train: city, test: sunrise}\n"
                    "  - {train: city, test: sunrise}\nmethods: [lit_as_albedo]\n")
    with pytest.raises(UserError, match=r"configurations\[1\].*repeats"):
        load_benchmark_config(grid)


def test_grid_renders_its_non_default_lights_and_refuses_a_scene_without_them(tmp_path, monkeypatch):
    import sys
    import types

    from benchmark.config import load_benchmark_config
    from benchmark.jobgrid import Paths, run_grid

    calls = []

    def render_scene(scene, profile, data, jobs, lights=None):
        calls.append(lights)
        make_fake_scene(Path(data) / profile, name=scene, lights=("city", "sunrise", "city_sharp"), res=16,
                        n_test=2, n_train=2)

    fake = types.SimpleNamespace(render_scene=render_scene, default_lights=lambda: ["city", "sunrise"])
    monkeypatch.setitem(sys.modules, "generator.pipeline", fake)
    monkeypatch.setattr("benchmark.jobgrid.known_scenes", lambda: ["newscene"])
    grid = tmp_path / "grid.yaml"
    grid.write_text("profile: ci\nscenes: [newscene]\nconfigurations:\n  - {train: city, test: sunrise}\n"
                    "  - {train: city_sharp, test: sunrise}\nmethods: [mean_albedo]\n")
    paths = Paths(tmp_path / "data", tmp_path / "runs", tmp_path / "results", "ci")
    report = run_grid(load_benchmark_config(grid), paths, quiet=True)
    assert calls == [["city", "sunrise", "city_sharp"]]
    assert [o["status"] for _, o in report.rendered + report.executed] == ["ok", "ok", "ok"]
    # a finished scene rendered without the light: one line before any job, naming the light and the way out
    old = make_fake_scene(tmp_path / "old" / "ci", name="newscene", lights=("city", "sunrise"), res=16,
                          n_test=2, n_train=2)
    with pytest.raises(UserError) as exc:
        run_grid(load_benchmark_config(grid), Paths(tmp_path / "old", tmp_path / "runs2", tmp_path / "res2", "ci"),
                 quiet=True)
    msg = str(exc.value)
    assert "city_sharp" in msg and str(old) in msg and "--data" in msg and "\n" not in msg
    assert not (tmp_path / "runs2").exists()


# ------------------------------------------------------------------------- failures in the charts

def _diverged(method, scene="s", train="city", test="sunrise", seed=0):
    return fake_result(method, scene, train, test, seed, status="failed") | {
        "error": "stage 1 stopped: non-finite loss at iteration 37; last good checkpoint: stage1_000000.pt"}


def _stress_results():
    rs = [fake_result(m, "spheres", tr, te, seed, relight_psnr=25 + seed, seconds=100 + i, gaussians=2000 + 10 * i)
          for i, m in enumerate(("lumimotion", "static")) for tr, te in (("city", "sunrise"), ("sunrise", "city"))
          for seed in (0, 1, 2)]
    rs = [r for r in rs if not (r["method"] == "lumimotion" and r["train_light"] == "sunrise" and r["seed"] == 2)]
    rs.append(_diverged("lumimotion", "spheres", "sunrise", "city", 2))
    rs.append(fake_result("static", "spheres", "city_sharp", "sunrise", 0, status="failed"))  # RuntimeError: boom
    return rs


def test_failure_marks_say_failed_or_diverged():
    from benchmark import charts

    marks = charts.failure_marks(_stress_results())
    assert [(m["method"], m["kind"], m["train_light"], m["seed"]) for m in marks] == [
        ("lumimotion", "diverged", "sunrise", 2), ("static", "failed", "city_sharp", 0)]
    assert marks[0]["label"] == "sunrise→city s2" and "non-finite" in marks[0]["cause"]
    two = _stress_results() + [fake_result("static", "mouse", "city", "sunrise", 0, status="failed")]
    assert [m["label"] for m in charts.failure_marks(two)] == ["spheres sunrise→city s2",
                                                               "spheres city_sharp→sunrise s0", "mouse city→sunrise s0"]


def test_stability_draws_each_failure_at_its_own_configuration():
    from benchmark import charts

    data = charts.stability_data(_stress_results(), "relight.psnr")
    assert data["methods"] == ["lumimotion", "static"]
    x = {(c["method"], c["train_light"]): c["x"] for c in data["cells"]}
    marks = {(m["method"], m["kind"]): m["x"] for m in data["marks"]}
    assert marks[("lumimotion", "diverged")] == x[("lumimotion", "sunrise")] != x[("lumimotion", "city")]
    assert marks[("static", "failed")] == x[("static", "city_sharp")]
    # the cell of a run that failed on every seed is kept (empty), so its cross has a column
    assert [c["values"] for c in data["cells"] if (c["method"], c["train_light"]) == ("static", "city_sharp")] == [[]]
    assert len([v for c in data["cells"] if (c["method"], c["train_light"]) == ("lumimotion", "sunrise")
                for v in c["values"]]) == 2


@pytest.mark.parametrize("build", ["pareto_chart", "stability_chart"])
def test_charts_draw_and_label_the_diverged_and_the_failed_run(monkeypatch, tmp_path, build):
    import matplotlib.pyplot as plt

    from benchmark import charts

    figs = []
    monkeypatch.setattr(charts, "_save", lambda fig, path: figs.append(fig) or path)
    getattr(charts, build)(_stress_results(), tmp_path / "c.png")
    (fig,) = figs
    legend = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
    assert "lumimotion: 1 diverged" in legend and "static: 1 failed" in legend
    for ax in fig.axes:
        crosses = {c.get_label(): c for c in ax.collections if c.get_label().endswith(("failed", "diverged"))}
        assert set(crosses) == {"lumimotion: 1 diverged", "static: 1 failed"}
        shapes = [crosses[k].get_paths()[0].vertices for k in ("lumimotion: 1 diverged", "static: 1 failed")]
        assert shapes[0].shape != shapes[1].shape or not np.allclose(*shapes)  # drawn as such: another marker
        texts = {t.get_text() for t in ax.texts}
        assert {"sunrise→city s2", "city_sharp→sunrise s0"} <= texts
        if build == "pareto_chart":  # at the method's mean training time (the failed run reports none)
            assert crosses["lumimotion: 1 diverged"].get_offsets()[0][0] == pytest.approx(100.0)
            assert crosses["static: 1 failed"].get_offsets()[0][0] == pytest.approx(101.0)
    plt.close(fig)


def test_quality_charts_draw_the_seeds_spread_per_point():
    from benchmark import charts
    from benchmark.aggregate import training_seconds

    rs = _stress_results()
    spreads = charts.seed_spreads(rs, "lumimotion", training_seconds, "relight.psnr")
    assert sorted(spreads) == [(100.0, (25.0, 26.0)), (100.0, (25.0, 27.0))]
    flat = [(x, lo, hi) for x, (lo, hi) in charts.seed_spreads(rs, "static", training_seconds, "relight.psnr")]
    assert flat == [pytest.approx((101.0, 25.0, 27.0))] * 2


def test_conditions_chart_puts_each_stress_in_its_own_column(monkeypatch, tmp_path):
    """One scene under several conditions (configurations and '@' variants): one column per condition, the
    most-run configuration without a variant first and the variants last, the base methods side by side in
    each, every seed's value in its own column and each failure at its own cell; drawn by all_charts for one
    scene only."""
    import matplotlib.pyplot as plt

    from benchmark import charts

    rs = _stress_results() + [fake_result(m, "spheres", "city", "sunrise", s, relight_psnr=20 + s)
                              for m in ("lumimotion@cap2000", "static@cap2000") for s in (0, 1)]
    rs.append(_diverged("static@cap2000", "spheres", "city", "sunrise", 2))
    data = charts.conditions_data(rs, "relight.psnr")
    assert data["conditions"] == [("city", "sunrise", ""), ("sunrise", "city", ""), ("city_sharp", "sunrise", ""),
                                  ("city", "sunrise", "cap2000")]
    assert data["methods"] == ["lumimotion", "static"]
    cell = {(c["method"], c["condition"]): c for c in data["cells"]}
    assert sorted(v for _, v in cell[("static", ("city", "sunrise", "cap2000"))]["values"]) == [20, 21]
    assert sorted(v for _, v in cell[("lumimotion", ("city", "sunrise", ""))]["values"]) == [25, 26, 27]
    assert 2.5 < cell[("static", ("city", "sunrise", "cap2000"))]["x"] < 3.5
    marks = {(m["method"], m["kind"]): m["x"] for m in data["marks"]}
    assert marks[("static", "diverged")] == cell[("static", ("city", "sunrise", "cap2000"))]["x"]
    assert marks[("lumimotion", "diverged")] == cell[("lumimotion", ("sunrise", "city", ""))]["x"]
    assert marks[("static", "failed")] == cell[("static", ("city_sharp", "sunrise", ""))]["x"]
    figs = []
    monkeypatch.setattr(charts, "_save", lambda fig, path: figs.append(fig) or path)
    assert "conditions" in charts.all_charts(rs, tmp_path)
    fig = figs[-1]
    ticks = [t.get_text() for t in fig.axes[0].get_xticklabels()]
    assert ticks == ["city→sunrise", "sunrise→city", "city_sharp→sunrise", "city→sunrise\n@cap2000"]
    for f in figs:
        plt.close(f)
    two = rs + [fake_result("static", "mouse", "city", "sunrise", 0)]
    assert not charts.has_conditions(two) and charts.has_conditions(rs)
