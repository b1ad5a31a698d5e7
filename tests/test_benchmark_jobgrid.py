"""The job grid: resumes, records failures without stopping, renders missing scenes, runs on Ray."""
from __future__ import annotations

import subprocess
import sys
import types
from pathlib import Path

import pytest

from baselines_adapters import registry
from baselines_adapters.base import MethodAdapter
from benchmark.config import load_benchmark_config
from benchmark.jobgrid import Paths, result_path, run_grid
from benchmark.results import read_result
from benchmark_fakes import dataset_root, make_fake_scene

REPO = Path(__file__).resolve().parent.parent


class Broken(MethodAdapter):
    name = "broken"
    version = "1"

    def predict(self, *args, **kwargs):
        raise RuntimeError("diverged at iteration 3")


def _grid(tmp_path: Path, scenes, methods, seeds=(0,)) -> Path:
    path = tmp_path / "grid.yaml"
    path.write_text(f"profile: ci\nscenes: [{', '.join(scenes)}]\nconfigurations:\n  - {{train: city, test: sunrise}}\n"
                    f"methods: [{', '.join(methods)}]\nseeds: [{', '.join(map(str, seeds))}]\n")
    return path


def _paths(tmp_path: Path, data: Path) -> Paths:
    return Paths(data, tmp_path / "runs", tmp_path / "results", "ci")


def test_grid_records_failure_and_resumes(tmp_path, monkeypatch):
    monkeypatch.setitem(registry._FACTORIES, "broken", Broken)
    data = dataset_root(tmp_path, scenes=("fa",), res=24, n_test=2, n_train=2)
    config = load_benchmark_config(_grid(tmp_path, ["fa"], ["broken", "lit_as_albedo"]))
    paths = _paths(tmp_path, data)
    first = run_grid(config, paths, quiet=True)
    assert len(first.executed) == 2 and len(first.failed) == 1
    conf = config.configurations[0]
    bad = read_result(result_path(paths, "broken", "fa", conf, 0))
    assert bad["status"] == "failed" and "diverged at iteration 3" in bad["error"]
    assert "Traceback" in result_path(paths, "broken", "fa", conf, 0).with_name("error.log").read_text()
    good_path = result_path(paths, "lit_as_albedo", "fa", conf, 0)
    assert read_result(good_path)["status"] == "ok"
    stamp = good_path.stat().st_mtime_ns

    second = run_grid(config, paths, quiet=True)
    assert [j["method"] for j, _ in second.executed] == ["broken"]  # only the failed job is retried
    assert [j["method"] for j in second.skipped] == ["lit_as_albedo"]
    assert good_path.stat().st_mtime_ns == stamp


def test_grid_renders_missing_scene_through_the_generator(tmp_path, monkeypatch):
    calls = []

    def render_scene(scene, profile, data, jobs):
        calls.append((scene, profile, jobs))
        make_fake_scene(Path(data) / profile, name=scene, res=24, n_test=2, n_train=2)

    monkeypatch.setitem(sys.modules, "generator.pipeline", types.SimpleNamespace(render_scene=render_scene))
    monkeypatch.setattr("benchmark.jobgrid.known_scenes", lambda: ["newscene"])
    data = tmp_path / "data"
    config = load_benchmark_config(_grid(tmp_path, ["newscene"], ["mean_albedo"]))
    report = run_grid(config, _paths(tmp_path, data), quiet=True)
    assert calls == [("newscene", "ci", 1)]
    assert [o["status"] for _, o in report.rendered + report.executed] == ["ok", "ok"]
    # rendered now: a second grid renders nothing
    assert run_grid(config, _paths(tmp_path, data), quiet=True).rendered == []


def test_grid_refuses_unknown_unrendered_scene(tmp_path):
    from lumibench.errors import UserError

    config = load_benchmark_config(_grid(tmp_path, ["atlantis"], ["mean_albedo"]))
    with pytest.raises(UserError, match="atlantis neither rendered"):
        run_grid(config, _paths(tmp_path, tmp_path / "data"), quiet=True)


def test_ray_executor_with_a_local_instance(tmp_path):
    ray = pytest.importorskip("ray")
    data = dataset_root(tmp_path, scenes=("ra", "rb"), res=24, n_test=2, n_train=2)
    (data / "ci" / "rb" / "city" / "test" / "r_0001.png").write_bytes(b"not a png")  # rb's job must fail
    config = load_benchmark_config(_grid(tmp_path, ["ra", "rb"], ["lit_as_albedo"]))
    paths = _paths(tmp_path, data)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:
        report = run_grid(config, paths, executor="ray", workers=2, quiet=True)
    finally:
        ray.shutdown()
    status = {j["scene"]: o["status"] for j, o in report.executed}
    assert status == {"ra": "ok", "rb": "failed"}
    conf = config.configurations[0]
    assert read_result(result_path(paths, "lit_as_albedo", "ra", conf, 0))["status"] == "ok"
    failed = read_result(result_path(paths, "lit_as_albedo", "rb", conf, 0))
    assert failed["status"] == "failed" and "r_0001.png" in failed["error"]


def test_eval_cli_builds_tables_and_report(tmp_path):
    data = dataset_root(tmp_path, scenes=("fe",), res=24, n_test=2, n_train=2)
    grid = _grid(tmp_path, ["fe"], ["lit_as_albedo", "noisy_gt"])
    cmd = [sys.executable, "-m", "benchmark", "eval", "--config", str(grid), "--data", str(data), "--runs",
           str(tmp_path / "runs"), "--results", str(tmp_path / "results"), "--jobs", "2"]  # a process pool
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    out = tmp_path / "results" / "ci"
    for name in ("table.md", "table.tex", "table.csv", "pareto.png", "stability.png", "report.html",
                 "runs/noisy_gt/fe/city_to_sunrise/seed0/results.json"):
        assert (out / name).is_file(), name
    assert len(list((out / "grids").glob("*.png"))) == 2
    md = (out / "table.md").read_text()
    noisy = next(l for l in md.splitlines() if l.startswith("| noisy_gt |"))
    lit = next(l for l in md.splitlines() if l.startswith("| lit_as_albedo |"))
    assert noisy.count("**") >= 2 * 7 and "**" not in lit  # the near-GT row wins every shared column
    # resumed: nothing to run the second time
    proc = subprocess.run(cmd + ["--no-grids"], capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 0 and "0 jobs run, 2 already finished" in proc.stdout
    bad = subprocess.run(cmd[:4] + ["--methods", "nope"], capture_output=True, text=True, cwd=REPO)
    assert bad.returncode == 2 and "unknown method 'nope'" in bad.stderr and "Traceback" not in bad.stderr


def test_seed_independent_methods_run_once(tmp_path):
    from benchmark.jobgrid import method_jobs

    config = load_benchmark_config(_grid(tmp_path, ["a", "b"], ["lit_as_albedo", "noisy_gt"], seeds=(0, 1, 2)))
    jobs = method_jobs(config, _paths(tmp_path, tmp_path / "data"))
    assert sorted((j["method"], j["scene"], j["seed"]) for j in jobs) == [
        ("lit_as_albedo", "a", 0), ("lit_as_albedo", "b", 0),
        ("noisy_gt", "a", 0), ("noisy_gt", "a", 1), ("noisy_gt", "a", 2),
        ("noisy_gt", "b", 0), ("noisy_gt", "b", 1), ("noisy_gt", "b", 2)]


def test_eval_exits_non_zero_after_writing_everything_when_a_job_failed(tmp_path):
    data = dataset_root(tmp_path, scenes=("ok", "bad"), res=24, n_test=2, n_train=2)
    (data / "ci" / "bad" / "city" / "test" / "r_0001.png").write_bytes(b"not a png")  # bad's job fails
    grid = _grid(tmp_path, ["ok", "bad"], ["lit_as_albedo"])
    cmd = [sys.executable, "-m", "benchmark", "eval", "--config", str(grid), "--data", str(data), "--runs",
           str(tmp_path / "runs"), "--results", str(tmp_path / "results"), "--no-grids"]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 1, proc.stderr[-2000:]
    out = tmp_path / "results" / "ci"
    for name in ("table.md", "table.csv", "report.html", "stability.png"):  # written before exiting
        assert (out / name).is_file(), name
    assert "Traceback" not in proc.stderr
    err = proc.stderr.strip().splitlines()[-1]  # the summary: one line, last (a progress bar may precede it)
    log = out / "runs" / "lit_as_albedo" / "bad" / "city_to_sunrise" / "seed0" / "error.log"
    assert err.startswith("error: 1 of 2 jobs run failed: lit_as_albedo bad city->sunrise seed 0")
    assert f"(log: {log})" in err and "--keep-going" in err and log.is_file()
    # --keep-going: the same summary as a warning, exit 0 (the failed job is retried, the other kept)
    proc = subprocess.run(cmd + ["--keep-going"], capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines()[-1].startswith("warning: 1 of 1 jobs run failed: lit_as_albedo bad")
    # make eval passes KEEP_GOING=1 on as --keep-going (and nothing for KEEP_GOING=0 or unset)
    dry = {v: subprocess.run(["make", "-n", "eval"] + ([f"KEEP_GOING={v}"] if v else []), capture_output=True,
                             text=True, cwd=REPO).stdout for v in ("1", "0", "")}
    assert "--keep-going" in dry["1"] and "--keep-going" not in dry["0"] + dry[""]


def test_failed_render_is_logged(tmp_path, monkeypatch):
    from benchmark.jobgrid import failure_summary

    def render_scene(scene, profile, data, jobs):
        raise RuntimeError("Cycles crashed")

    monkeypatch.setitem(sys.modules, "generator.pipeline", types.SimpleNamespace(render_scene=render_scene))
    monkeypatch.setattr("benchmark.jobgrid.known_scenes", lambda: ["newscene"])
    config = load_benchmark_config(_grid(tmp_path, ["newscene"], ["mean_albedo"]))
    paths = _paths(tmp_path, tmp_path / "data")
    report = run_grid(config, paths, quiet=True)
    assert [o["status"] for _, o in report.rendered + report.executed] == ["failed", "failed"]
    log = paths.out / "logs" / "render_newscene.log"
    assert "Cycles crashed" in log.read_text()
    summary = failure_summary(report.failed, 2)
    assert summary.startswith(f"2 of 2 jobs run failed: render ci/newscene (log: {log}); mean_albedo newscene")
    assert "error.log" in summary


def test_eval_does_not_count_a_method_not_run_as_failed(tmp_path, monkeypatch, capsys):
    from baselines_adapters.base import MethodNotRun
    from benchmark.__main__ import main

    class NotRun(MethodAdapter):
        name = "notrun"
        version = "1"

        def predict(self, *args, **kwargs):
            raise MethodNotRun("run the external code first and put its output in /somewhere")

    monkeypatch.setitem(registry._FACTORIES, "notrun", NotRun)
    data = dataset_root(tmp_path, scenes=("fn",), res=24, n_test=2, n_train=2)
    rc = main(["eval", "--config", str(_grid(tmp_path, ["fn"], ["notrun", "mean_albedo"])), "--data", str(data),
               "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "results"), "--no-grids"])
    err = capsys.readouterr().err
    assert rc == 0 and "jobs run failed" not in err, err
    assert (tmp_path / "results" / "ci" / "table.md").is_file()


def test_grid_on_light_files_uses_their_stems_and_writes_nothing_beside_them(tmp_path):
    """Issue 26: configurations given as .hdr paths run like named lights (the dataset's light folders are the
    files' stems), and nothing is written outside --runs and --results (nothing beside the user's HDRIs)."""
    import numpy as np

    from benchmark.__main__ import main
    from generator.envmap import write_hdr

    hdri = tmp_path / "my_hdris"
    for name in ("attic", "harbour"):
        write_hdr(hdri / f"{name}.hdr", np.full((16, 32, 3), 0.5, np.float32))
    before = sorted(p.relative_to(hdri) for p in hdri.rglob("*"))
    data = tmp_path / "data"
    make_fake_scene(data / "ci", name="fp", lights=("attic", "harbour"), res=24, n_test=2, n_train=2)
    grid = tmp_path / "grid.yaml"
    grid.write_text(f"profile: ci\nscenes: [fp]\nconfigurations:\n"
                    f"  - {{train: {hdri / 'attic.hdr'}, test: {hdri / 'harbour.hdr'}}}\n"
                    f"methods: [lit_as_albedo, mean_albedo]\nseeds: [0]\n")
    runs, results = tmp_path / "runs", tmp_path / "results"
    rc = main(["eval", "--config", str(grid), "--data", str(data), "--runs", str(runs), "--results", str(results),
               "--no-grids"])
    assert sorted(p.relative_to(hdri) for p in hdri.rglob("*")) == before  # nothing new beside the HDRIs
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "grid.yaml", "my_hdris", "results", "runs"]
    assert rc == 0
    for method in ("lit_as_albedo", "mean_albedo"):
        res = read_result(results / "ci" / "runs" / method / "fp" / "attic_to_harbour" / "seed0" / "results.json")
        assert res["status"] == "ok" and (res["train_light"], res["test_light"]) == ("attic", "harbour")
        assert (runs / "ci" / method / "fp" / "attic" / "seed0" / "predictions").is_dir()
    table = (results / "ci" / "table.md").read_text()
    assert "attic" in table and str(hdri) not in table


def test_grid_renders_its_light_files_with_the_named_lights(tmp_path, monkeypatch):
    calls = []

    def render_scene(scene, profile, data, jobs, lights=None):
        calls.append(lights)
        make_fake_scene(Path(data) / profile, name=scene, lights=("city", "attic"), res=24, n_test=2, n_train=2)

    fake = types.SimpleNamespace(render_scene=render_scene, default_lights=lambda: ["city", "sunrise"])
    monkeypatch.setitem(sys.modules, "generator.pipeline", fake)
    monkeypatch.setattr("benchmark.jobgrid.known_scenes", lambda: ["newscene"])
    grid = tmp_path / "grid.yaml"
    grid.write_text(f"profile: ci\nscenes: [newscene]\nconfigurations:\n"
                    f"  - {{train: city, test: {tmp_path}/attic.hdr}}\nmethods: [mean_albedo]\n")
    report = run_grid(load_benchmark_config(grid), _paths(tmp_path, tmp_path / "data"), quiet=True)
    assert calls == [["city", "sunrise", f"{tmp_path}/attic.hdr"]]
    assert [o["status"] for _, o in report.rendered + report.executed] == ["ok", "ok"]


def test_eval_tables_keep_the_results_of_earlier_grids(tmp_path, capsys):
    """results/<profile>/ is filled by several grids (a seed today, a light tomorrow): a grid's eval writes the
    tables from every stored result of the profile, so a later grid on a subset never drops published rows."""
    from benchmark.__main__ import main

    data = dataset_root(tmp_path, scenes=("fa", "fb"), res=24, n_test=2, n_train=2)
    common = ["--data", str(data), "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "results"),
              "--no-grids"]
    assert main(["eval", "--config", str(_grid(tmp_path, ["fa"], ["mean_albedo"])), *common]) == 0
    assert main(["eval", "--config", str(_grid(tmp_path, ["fb"], ["lit_as_albedo"])), *common]) == 0
    out = capsys.readouterr().out
    assert "tables from all 2 result files" in out and "(1 of them from this grid)" in out, out
    rows = (tmp_path / "results" / "ci" / "table.csv").read_text().splitlines()
    for method in ("mean_albedo", "lit_as_albedo"):  # one scene each, both in the table
        assert any(line.startswith(f"lumimotion,city->sunrise,{method},1,0,") for line in rows), (method, rows)
