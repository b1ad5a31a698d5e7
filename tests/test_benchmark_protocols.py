"""Both protocols in one grid (issue 26): every run is scored under `lumimotion` and `strict` from the same
predictions, side by side (results.json and results_strict.json), one table per protocol with the floors
in each; a re-run recomputes nothing, and a result of one protocol never counts as finished for the other."""
from __future__ import annotations

import csv
import io
from pathlib import Path

import pytest

from baselines_adapters import registry
from baselines_adapters.trivial import LitAsAlbedo
from benchmark.config import load_benchmark_config
from benchmark.jobgrid import Paths, result_path, run_grid
from benchmark.results import is_finished, read_result, result_filename, write_result
from benchmark_fakes import dataset_root
from lumibench.errors import UserError

BOTH = ("lumimotion", "strict")
FLOORS = ("lit_as_albedo", "mean_albedo")


class CountingLit(LitAsAlbedo):
    """lit_as_albedo that counts its runs (the adapter's work, which must not repeat per protocol)."""

    name = "counting_lit"
    version = "1"
    seed_dependent = True
    runs: list = []

    def predict(self, *args, **kwargs):
        CountingLit.runs.append(args[1])  # the train light
        return super().predict(*args, **kwargs)


@pytest.fixture
def counting(monkeypatch):
    monkeypatch.setitem(registry._FACTORIES, "counting_lit", CountingLit)
    monkeypatch.setattr(CountingLit, "runs", [])
    monkeypatch.setattr(CountingLit, "version", "1")  # restored after a test that moves it on
    return CountingLit


def _grid(tmp_path: Path, methods, protocol_line: str = "protocols: [lumimotion, strict]",
          tests=("sunrise",), name: str = "grid.yaml") -> Path:
    path = tmp_path / name
    confs = "".join(f"  - {{train: city, test: {t}}}\n" for t in tests)
    path.write_text(f"profile: ci\n{protocol_line}\nscenes: [fa]\nconfigurations:\n{confs}"
                    f"methods: [{', '.join(methods)}]\nseeds: [0]\n")
    return path


def _setup(tmp_path: Path):
    data = dataset_root(tmp_path, scenes=("fa",), res=24, n_test=2, n_train=2)
    return Paths(data, tmp_path / "runs", tmp_path / "results", "ci")


def _files(paths: Paths, config, methods) -> dict[tuple[str, str, str], Path]:
    return {(m, c.test, p): result_path(paths, m, "fa", c, 0, p)
            for m in methods for c in config.configurations for p in config.protocols}


def _stamps(files) -> dict:
    return {k: p.stat().st_mtime_ns for k, p in files.items()}


# ------------------------------------------------------------------------------------------ grid YAML

def test_grid_names_both_protocols_and_old_key_still_loads(tmp_path):
    both = load_benchmark_config(_grid(tmp_path, FLOORS))
    assert both.protocols == BOTH and both.protocol == "lumimotion"  # the first is the primary one
    old = load_benchmark_config(_grid(tmp_path, FLOORS, "protocol: strict", name="old.yaml"))
    assert old.protocols == ("strict",)
    bare = load_benchmark_config(_grid(tmp_path, FLOORS, "", name="bare.yaml"))
    assert bare.protocols == ("lumimotion",)
    assert both.with_protocols(["strict", "lumimotion"]).protocols == ("strict", "lumimotion")
    with pytest.raises(UserError, match="--protocols: unknown protocol 'loose'"):
        both.with_protocols(["loose"])


@pytest.mark.parametrize("line, key, needle", [
    ("protocols: [lumimotion, loose]", "'protocols'", "unknown protocol 'loose' (known: lumimotion, strict)"),
    ("protocols: [strict, strict]", "'protocols'", "twice"),
    ("protocols: []", "'protocols'", "non-empty list"),
    ("protocols: strict", "'protocols'", "must be a list"),
    ("protocol: loose", "'protocol'", "must be one of lumimotion, strict"),
    ("protocol: strict\nprotocols: [lumimotion]", "'protocol'", "cannot be given with 'protocols'"),
])
def test_bad_protocols_name_the_key(tmp_path, line, key, needle):
    path = _grid(tmp_path, FLOORS, line)
    with pytest.raises(UserError) as err:
        load_benchmark_config(path)
    assert str(path) in str(err.value) and f"key {key}" in str(err.value) and needle in str(err.value)


@pytest.mark.parametrize("grid", ["small", "small_lumimotion", "small_diagnose", "full", "ci", "demo"])
def test_default_grids_publish_both_protocols(grid):
    assert load_benchmark_config(grid).protocols == BOTH


# ------------------------------------------------------------------------------------- grid and tables

def test_grid_with_both_protocols_writes_both_results_and_tables_and_reruns_nothing(tmp_path, counting,
                                                                                    monkeypatch):
    from benchmark import charts
    from benchmark.jobgrid import iter_results, method_jobs
    from benchmark.outputs import build_outputs

    paths = _setup(tmp_path)
    methods = ("counting_lit", "mean_albedo")
    config = load_benchmark_config(_grid(tmp_path, methods, tests=("sunrise", "courtyard")))
    report = run_grid(config, paths, quiet=True)
    assert not report.failed and len(report.executed) == 2
    assert counting.runs == ["city"]  # the adapter ran once for both configurations and both protocols
    files = _files(paths, config, methods)
    for (m, test, protocol), path in files.items():
        assert path.name == result_filename(protocol) == ("results.json" if protocol == "lumimotion"
                                                          else "results_strict.json")
        res = read_result(path)
        assert res["status"] == "ok" and res["protocol"] == protocol and res["test_light"] == test
        twin = read_result(files[m, test, "strict" if protocol == "lumimotion" else "lumimotion"])
        assert res["inputs"]["pred_dir"] == twin["inputs"]["pred_dir"]  # the same predictions

    drawn = []
    real = charts.all_charts
    monkeypatch.setattr(charts, "all_charts", lambda results, out: drawn.extend(results) or real(results, out))
    out = build_outputs(iter_results(method_jobs(config, paths)), paths.out, grids=True, protocols=config.protocols)
    md = out["table.md"].read_text()
    lm, st = md.index("## Protocol lumimotion (primary"), md.index("## Protocol strict")
    assert lm < st and md.count("**Protocol: lumimotion") == 1 and md.count("**Protocol: strict") == 1
    for section in (md[lm:st], md[st:]):  # the floors beside each protocol's rows, both configurations
        assert "### city → sunrise" in section and "### city → courtyard" in section
        assert section.count("| mean_albedo |") == 2 and section.count("| counting_lit |") == 2
    assert "(published, on the paper's dataset)" in md[lm:st] and "published" not in md[st:]
    rows = list(csv.DictReader(io.StringIO(out["table.csv"].read_text())))
    ours = [(r["protocol"], r["configuration"], r["method"]) for r in rows if not r["reference"]]
    assert sorted(ours) == sorted((p, f"city->{t}", m) for p in BOTH for t in ("sunrise", "courtyard")
                                  for m in methods)
    tex = out["table.tex"].read_text()
    assert tex.count(r"\begin{table*}") == 2 and r"\label{tab:lumibench-strict}" in tex
    assert tex.index(r"\caption{Protocol: lumimotion") < tex.index(r"\caption{Protocol: strict")
    html = out["report.html"].read_text()
    assert "Table: Protocol lumimotion (primary" in html and "Table: Protocol strict" in html
    assert html.count("<table>") == 3  # two tables of ours, one of the published references
    # charts and image grids from the primary protocol only
    assert drawn and {r["protocol"] for r in drawn} == {"lumimotion"}
    assert len(list((paths.out / "grids").glob("*.png"))) == 4  # 2 methods x 2 configurations, not x 2

    # re-run: nothing to do, nothing rewritten
    stamps = _stamps(files)
    again = run_grid(config, paths, quiet=True)
    assert again.executed == [] and len(again.skipped) == 2
    assert counting.runs == ["city"] and _stamps(files) == stamps


def test_adding_a_protocol_scores_only_it_from_the_stored_predictions(tmp_path, counting):
    paths = _setup(tmp_path)
    old = load_benchmark_config(_grid(tmp_path, ["counting_lit"], "protocol: lumimotion", name="old.yaml"))
    run_grid(old, paths, quiet=True)
    conf = old.configurations[0]
    lm_path = result_path(paths, "counting_lit", "fa", conf, 0)
    strict_path = result_path(paths, "counting_lit", "fa", conf, 0, "strict")
    assert lm_path.is_file() and not strict_path.exists() and counting.runs == ["city"]
    stamp = lm_path.stat().st_mtime_ns

    # the adapter has moved on since: the new protocol is still scored from the predictions the stored
    # result describes, without running the adapter (for the in-project methods: no prediction, no diagnose)
    counting.version = "2"
    both = load_benchmark_config(_grid(tmp_path, ["counting_lit"]))
    report = run_grid(both, paths, quiet=True)
    assert [j["method"] for j, _ in report.executed] == ["counting_lit"] and not report.failed
    assert counting.runs == ["city"]  # not run again
    assert lm_path.stat().st_mtime_ns == stamp  # the stored result is not recomputed
    res = read_result(strict_path)
    assert res["protocol"] == "strict" and res["adapter_version"] == "1"  # the stored predictions' version
    assert res["inputs"]["pred_dir"] == read_result(lm_path)["inputs"]["pred_dir"]

    # a configuration with no result at all needs the adapter's current predictions
    wider = load_benchmark_config(_grid(tmp_path, ["counting_lit"], tests=("sunrise", "courtyard"), name="w.yaml"))
    run_grid(wider, paths, quiet=True)
    assert counting.runs == ["city", "city"] and lm_path.stat().st_mtime_ns == stamp
    new = read_result(result_path(paths, "counting_lit", "fa", wider.configurations[1], 0, "strict"))
    assert new["adapter_version"] == "2"


def test_a_result_of_the_other_protocol_is_not_finished(tmp_path, counting):
    paths = _setup(tmp_path)
    config = load_benchmark_config(_grid(tmp_path, ["counting_lit"]))
    run_grid(config, paths, quiet=True)
    conf = config.configurations[0]
    lm_path = result_path(paths, "counting_lit", "fa", conf, 0)
    strict_path = result_path(paths, "counting_lit", "fa", conf, 0, "strict")
    lm, st = read_result(lm_path), read_result(strict_path)
    assert is_finished(lm_path, "lumimotion") and not is_finished(lm_path, "strict")
    assert is_finished(strict_path, "strict") and not is_finished(strict_path, "lumimotion")

    # each file swapped for the other protocol's result (an old `--protocol strict` run in results.json, a
    # copy gone wrong): both are scored again under their own protocol, from the stored predictions
    write_result(lm_path, st)
    write_result(strict_path, lm)
    report = run_grid(config, paths, quiet=True)
    assert len(report.executed) == 1 and not report.failed and counting.runs == ["city"]
    assert read_result(lm_path)["protocol"] == "lumimotion" and read_result(strict_path)["protocol"] == "strict"
    assert read_result(lm_path)["metrics"]["albedo"] == lm["metrics"]["albedo"]

    # a failed strict result is retried alone; the finished lumimotion one stays as it is
    from benchmark.results import failed_result

    stamp = lm_path.stat().st_mtime_ns
    write_result(strict_path, failed_result(dict(st, protocol="strict"), "RuntimeError: boom"))
    report = run_grid(config, paths, quiet=True)
    assert len(report.executed) == 1 and read_result(strict_path)["status"] == "ok"
    assert lm_path.stat().st_mtime_ns == stamp


def test_strict_and_lumimotion_differ_where_they_should(tmp_path):
    """Same predictions, two protocols: the floors' full-image scores (lumimotion: background pixels count
    as zero error) are higher than their foreground-only scores (strict), LPIPS differs with its input range,
    and what does not depend on the protocol (albedo alignment, roughness MSE over the foreground) agrees."""
    paths = _setup(tmp_path)
    config = load_benchmark_config(_grid(tmp_path, FLOORS))
    run_grid(config, paths, quiet=True)
    conf = config.configurations[0]
    for m in FLOORS:
        lm = read_result(result_path(paths, m, "fa", conf, 0))["metrics"]
        st = read_result(result_path(paths, m, "fa", conf, 0, "strict"))["metrics"]
        for task in ("albedo", "relight"):
            # the fake scene's disc covers about 55 % of the image: about 2.6 dB from the background alone
            assert lm[task]["psnr"] > st[task]["psnr"] + 1.5, (m, task)
            assert lm[task]["lpips"] != pytest.approx(st[task]["lpips"], abs=1e-4), (m, task)
        assert lm["albedo"]["scale"] == st["albedo"]["scale"]
        assert lm["roughness"]["mse"] == st["roughness"]["mse"]
