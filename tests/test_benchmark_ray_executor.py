"""Issue 26: the grid on a Ray cluster gives the local executor's results, in the same files.

A local two-node Ray cluster (ray.cluster_utils.Cluster: a head without CPUs and two worker nodes with one
CPU each, all on this machine) runs a floors-only grid; its result files and predictions must equal those
of the same grid run with the local executor, except for the fields that record when and how fast it ran
(``created``; ``timings``, ``cpu_timings`` in results and meta.json), and for float32 rounding in the last bits
of the scores: a Ray worker holding one CPU runs torch on one thread, and on some CPUs (a Xeon with AMX,
session 46) the LPIPS network's convolutions round differently on one thread than on two (relative 1e-7).
"""
from __future__ import annotations

import json
import math
import os
import shutil
import socket
from pathlib import Path

import pytest

from benchmark.config import load_benchmark_config
from benchmark.jobgrid import Paths, run_grid
from benchmark_fakes import dataset_root
from lumibench.errors import UserError

ray = pytest.importorskip("ray")

VARYING = {"results.json": ("created", "timings", "cpu_timings"),
           "results_strict.json": ("created", "timings", "cpu_timings"),
           "meta.json": ("timings", "cpu_timings")}  # when and how fast it ran


def _same(a: object, b: object, where: str = "") -> list[str]:
    """Where ``a`` and ``b`` differ: floats within a relative 1e-6 (float32 rounding) count as equal,
    everything else must be equal exactly."""
    if isinstance(a, float) and isinstance(b, float):
        return [] if math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-12) else [f"{where}: {a} != {b}"]
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            return [f"{where}: keys {sorted(set(a) ^ set(b))}"]
        return [d for k in a for d in _same(a[k], b[k], f"{where}/{k}")]
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{where}: lengths {len(a)} != {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _same(x, y, f"{where}[{i}]")]
    return [] if a == b else [f"{where}: {a!r:.80} != {b!r:.80}"]


def test_same_allows_float32_rounding_and_nothing_else():
    assert not _same({"x": [0.014683172106742859, "a"]}, {"x": [0.014683171641081572, "a"]})
    assert _same({"x": 0.0147}, {"x": 0.0146}) and _same({"x": "a"}, {"x": "b"}) and _same({"x": 1}, {"y": 1})
    assert _same(b"png", b"pnG") and _same([1.0], [1.0, 2.0])


def _tree(root: Path) -> dict[str, object]:
    """Every file under ``root`` by relative path: JSON without the varying fields, other files as bytes."""
    out: dict[str, object] = {}
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        rel = str(path.relative_to(root))
        if path.suffix == ".json":
            obj = json.loads(path.read_text())
            for key in VARYING.get(path.name, ()):
                obj.pop(key, None)
            if path.name in ("results.json", "results_strict.json"):  # the hash of a meta.json whose timings vary
                (obj.get("inputs") or {}).pop("pred_meta_sha256", None)
            out[rel] = obj
        else:
            out[rel] = path.read_bytes()
    return out


@pytest.fixture
def two_node_cluster():
    from ray.cluster_utils import Cluster

    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 0, "include_dashboard": False})
    nodes = [cluster.add_node(num_cpus=1) for _ in range(2)]
    ray.init(address=cluster.address, log_to_driver=False, configure_logging=False)
    try:
        cluster.wait_for_nodes()
        yield {n.node_id for n in nodes}
    finally:
        ray.shutdown()
        cluster.shutdown()


def test_ray_grid_on_two_nodes_equals_the_local_grid(tmp_path, monkeypatch, two_node_cluster):
    dataset_root(tmp_path, scenes=("ra",), res=16, n_test=2, n_train=2)
    grid = tmp_path / "grid.yaml"
    grid.write_text("profile: ci\nprotocols: [lumimotion, strict]\nscenes: [ra]\nconfigurations:\n"
                    "  - {train: city, test: sunrise}\n"
                    "  - {train: courtyard, test: sunset}\nmethods: [lit_as_albedo, mean_albedo, noisy_gt]\n"
                    "seeds: [0]\n")
    config = load_benchmark_config(grid)
    # relative paths, as `make eval` passes them: the Ray workers' own working directory is not this one
    monkeypatch.chdir(tmp_path)
    paths = Paths(Path("data"), Path("runs"), Path("results"), "ci")  # the same paths for both executors

    local = run_grid(config, paths, executor="local", workers=1, quiet=True)
    assert len(local.executed) == 6 and not local.failed
    expected = {"runs": _tree(paths.runs), "results": _tree(paths.results)}
    shutil.rmtree(paths.runs), shutil.rmtree(paths.results)

    report = run_grid(config, paths, executor="ray", workers=2, quiet=True)
    assert len(report.executed) == 6 and not report.failed, report.failed
    got = {"runs": _tree(paths.runs), "results": _tree(paths.results)}
    assert sorted(got["results"]) == sorted(expected["results"])  # every result file, no more
    assert sum(Path(k).name in ("results.json", "results_strict.json") for k in got["results"]) == 12
    assert not _same(got, expected)  # the same files and values, up to float32 rounding
    # the jobs ran on the two worker nodes, in Ray worker processes, not in this one
    nodes = {o["node"] for _, o in report.executed}
    assert nodes == two_node_cluster
    assert all(o["pid"] != os.getpid() for _, o in report.executed)


def test_unreachable_ray_address_is_one_line(monkeypatch, tmp_path):
    from benchmark.jobgrid import ray_connect

    assert not ray.is_initialized()
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setenv("RAY_ADDRESS", f"127.0.0.1:{port}")
    with pytest.raises(UserError, match=rf"cannot reach the Ray cluster at RAY_ADDRESS=127.0.0.1:{port} .*ray start"):
        ray_connect()
    assert not ray.is_initialized()
