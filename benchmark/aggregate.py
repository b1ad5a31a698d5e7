"""Aggregation of result files: mean +- std over scenes and seeds per (configuration, method).

Failed runs are counted per group (and listed) but never averaged in and never silently dropped: every
table row and chart says how many runs failed. The std is the population std (numpy's default, ddof=0)
over all successful (scene, seed) runs of the group.

An external method that has not been run yet (its adapter raised ``baselines_adapters.base.MethodNotRun``)
is counted as "not run", not as failed: a result with status "not_run", or a failed result whose error
starts with "not run: " (what the job grid records today from that exception's message).
Reference rows (the paper's published numbers, :func:`reference_groups`) are separate groups with a
``reference`` label: they are never averaged with, nor compared against, our runs.

One table states one protocol (:func:`check_consistent` refuses a mix); results of several protocols (a
grid with ``protocols: [lumimotion, strict]``) are split into one table each by :func:`protocol_tables`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from lumibench.errors import UserError

from .results import read_result


@dataclass(frozen=True)
class Column:
    key: str            # "task.metric" inside result["metrics"]
    group: str          # table header group
    label: str          # column label
    higher_better: bool
    digits: int


SHORT_GROUP = {"Novel View Synthesis": "NVS", "ΔPSNR NVS→Relight": "ΔPSNR"}

# laid out like the paper's supplementary table: NVS, albedo, roughness, relight, Delta PSNR
COLUMNS = (
    Column("nvs.psnr", "Novel View Synthesis", "PSNR", True, 2),
    Column("nvs.ssim", "Novel View Synthesis", "SSIM", True, 3),
    Column("nvs.lpips", "Novel View Synthesis", "LPIPS", False, 3),
    Column("albedo.psnr", "Albedo", "PSNR", True, 2),
    Column("albedo.ssim", "Albedo", "SSIM", True, 3),
    Column("albedo.lpips", "Albedo", "LPIPS", False, 3),
    Column("roughness.mse", "Roughness", "MSE", False, 4),
    Column("relight.psnr", "Relight", "PSNR", True, 2),
    Column("relight.ssim", "Relight", "SSIM", True, 3),
    Column("relight.lpips", "Relight", "LPIPS", False, 3),
    Column("delta_psnr.percent", "ΔPSNR NVS→Relight", "%", False, 1),
)
EXTRA_COLUMNS = (
    Column("separation.iou", "Separation", "IoU", True, 3),
    Column("separation.balanced_accuracy", "Separation", "bal. acc.", True, 3),
    Column("separation.dynamic_recall", "Separation", "moving recall", True, 3),  # the class that fails first
    Column("nvs_moving.gap_db", "Moving objects", "NVS gap dB", False, 1),  # whole image's PSNR - moving pixels'
    Column("normal.mae_deg", "Normal", "MAE °", False, 1),
)


def metric_value(result: dict[str, Any], key: str) -> float | None:
    task, name = key.split(".")
    block = (result.get("metrics") or {}).get(task)
    if not isinstance(block, dict):
        return None
    value = block.get(name)
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else None


def training_seconds(result: dict[str, Any]) -> float | None:
    """Total of the per-stage timings a method reported (None when it reported none)."""
    timings = result.get("timings")
    return float(sum(timings.values())) if timings else None


def training_cpu_seconds(result: dict[str, Any]) -> float | None:
    """Total CPU seconds (all threads) of the stages a method reported, when it reported them for every
    timed stage (None otherwise: older results and external methods report wall time only)."""
    wall, cpu = result.get("timings"), result.get("cpu_timings")
    if not wall or not cpu or set(cpu) != set(wall):
        return None
    return float(sum(cpu.values()))


def training_clock(results: Sequence[dict[str, Any]]) -> tuple[Callable[[dict[str, Any]], float | None], str]:
    """How to time the successful runs of ``results`` alike: (CPU seconds, "CPU") when every one that reports a
    wall time also reports its CPU seconds, else (wall seconds, "wall"). CPU seconds do not grow with the
    load of a shared machine; a chart or table never mixes the two clocks."""
    timed = [r for r in results if r.get("status") == "ok" and training_seconds(r) is not None]
    if timed and all(training_cpu_seconds(r) is not None for r in timed):
        return training_cpu_seconds, "CPU"
    return training_seconds, "wall"


def gaussian_count(result: dict[str, Any]) -> float | None:
    size = result.get("model_size") or {}
    return float(size["gaussians"]) if "gaussians" in size else None


@dataclass
class Stat:
    mean: float
    std: float
    n: int


@dataclass
class Group:
    configuration: str
    method: str
    stats: dict[str, Stat] = field(default_factory=dict)
    n_ok: int = 0
    failures: list[dict[str, Any]] = field(default_factory=list)
    scenes: set[str] = field(default_factory=set)
    seeds: set[int] = field(default_factory=set)
    not_run: list[dict[str, Any]] = field(default_factory=list)
    reference: str | None = None  # e.g. "published, on the paper's dataset": not our runs
    notes: list[str] = field(default_factory=list)
    # provenance of the successful runs: (adapter version, training settings' sha256 or None) -> scenes
    provenance: dict[tuple[str, str | None], set[str]] = field(default_factory=dict)
    # per scene, the dataset spec hashes its successful runs were scored on (benchmark.score.dataset_inputs)
    datasets: dict[str, set[str]] = field(default_factory=dict)

    def mixed_datasets(self) -> list[str]:
        """The scenes whose runs in this row were scored on more than one version of the scene's dataset
        (e.g. before and after a ground-truth change of the generator): their mean mixes two references."""
        return sorted(sc for sc, hashes in self.datasets.items() if len(hashes) > 1)

    def mixed_provenance(self) -> bool:
        """True when the row's runs come from more than one adapter version or recorded training setting
        (results scored before settings were recorded, session 18, count as any setting)."""
        return (len({v for v, _ in self.provenance}) > 1
                or len({h for _, h in self.provenance if h is not None}) > 1)

    @property
    def n_failed(self) -> int:
        return len(self.failures)

    @property
    def n_not_run(self) -> int:
        return len(self.not_run)


NOT_RUN_STATUS = "not_run"
NOT_RUN_PREFIX = "not run: "  # the message prefix of baselines_adapters.base.MethodNotRun


def is_not_run(result: dict[str, Any]) -> bool:
    """A job whose external method has not been run (shown as "not run", not as a failure)."""
    if result.get("status") == NOT_RUN_STATUS:
        return True
    err = result.get("error")
    return result.get("status") == "failed" and isinstance(err, str) and err.startswith(NOT_RUN_PREFIX)


def configuration_label(result: dict[str, Any]) -> str:
    return f"{result['train_light']}->{result['test_light']}"


def load_results(paths: Iterable[str | Path]) -> list[dict[str, Any]]:
    """Read and validate result files; a missing one is an error naming it (the grid writes every one)."""
    out = []
    for p in paths:
        if not Path(p).is_file():
            raise UserError(f"result file missing: {p} (run the grid again: it resumes)")
        out.append(read_result(p) | {"_path": str(p)})
    return out


def check_consistent(results: list[dict[str, Any]]) -> dict[str, Any]:
    """All results of one table must share protocol, LPIPS net and weights; return that config."""
    ok = [r for r in results if r["status"] == "ok"]
    protocols = {r["protocol"] for r in results}
    if len(protocols) > 1:
        raise UserError(f"results mix protocols {sorted(protocols)}: one table states one protocol")
    nets = {(r["metric_config"]["lpips_net"], r["metric_config"]["lpips_weights"]["sha256"]) for r in ok}
    if len(nets) > 1:
        raise UserError(f"results mix LPIPS networks or weights: {sorted(nets)}")
    first = ok[0]["metric_config"] if ok else {}
    return {"protocol": next(iter(protocols)) if protocols else None, "metric_config": first}


@dataclass
class ProtocolTable:
    """The results of one protocol, aggregated: one table of the outputs."""
    protocol: str
    results: list[dict[str, Any]]
    groups: list[Group]
    meta: dict[str, Any]
    primary: bool = False  # the grid's first protocol: the charts and image grids are drawn from its results


def protocol_tables(results: list[dict[str, Any]], order: Iterable[str] | None = None) -> list[ProtocolTable]:
    """One :class:`ProtocolTable` per protocol present in ``results``, in ``order`` (the grid's protocols,
    primary first), then any other present protocol in the order of benchmark.protocol.PROTOCOLS. All
    tables must share the LPIPS network and weights (only masking, averaging and input range differ)."""
    from .protocol import PROTOCOLS

    present = list(dict.fromkeys(r["protocol"] for r in results))
    names = [p for p in dict.fromkeys(list(order or ()) + list(PROTOCOLS) + present) if p in present]
    ok = [r for r in results if r["status"] == "ok"]
    nets = {(r["metric_config"]["lpips_net"], r["metric_config"]["lpips_weights"]["sha256"]) for r in ok}
    if len(nets) > 1:
        raise UserError(f"results mix LPIPS networks or weights: {sorted(nets)}")
    out = []
    for i, name in enumerate(names):
        rs = [r for r in results if r["protocol"] == name]
        out.append(ProtocolTable(name, rs, aggregate(rs), check_consistent(rs), primary=i == 0))
    return out


def aggregate(results: list[dict[str, Any]]) -> list[Group]:
    """Groups in first-seen order of configuration, then method."""
    groups: dict[tuple[str, str], Group] = {}
    values: dict[tuple[str, str], dict[str, list[float]]] = {}
    for r in results:
        key = (configuration_label(r), r["method"])
        g = groups.setdefault(key, Group(*key))
        vals = values.setdefault(key, {})
        g.scenes.add(r["scene"])
        g.seeds.add(r["seed"])
        if is_not_run(r):
            g.not_run.append({"scene": r["scene"], "seed": r["seed"], "error": r.get("error")})
            continue
        if r["status"] != "ok":
            g.failures.append({"scene": r["scene"], "seed": r["seed"], "error": r.get("error")})
            continue
        g.n_ok += 1
        settings = (r.get("inputs") or {}).get("method_settings_sha256")
        g.provenance.setdefault((str(r["adapter_version"]), settings), set()).add(r["scene"])
        if isinstance(dataset := (r.get("inputs") or {}).get("dataset_spec_hash"), str):
            g.datasets.setdefault(r["scene"], set()).add(dataset)
        for col in COLUMNS + EXTRA_COLUMNS:
            v = metric_value(r, col.key)
            if v is not None:
                vals.setdefault(col.key, []).append(v)
        t = training_seconds(r)
        if t is not None:
            vals.setdefault("time.seconds", []).append(t)
        n = gaussian_count(r)
        if n is not None:
            vals.setdefault("model.gaussians", []).append(n)
    for key, g in groups.items():
        for metric, vs in values[key].items():
            arr = np.asarray(vs, dtype=np.float64)
            g.stats[metric] = Stat(float(arr.mean()), float(arr.std()), int(arr.size))
    return list(groups.values())


def best_methods(groups: list[Group], configuration: str, column: Column) -> set[str]:
    """Methods holding the best mean of ``column`` in ``configuration`` (ties all bold), by direction."""
    cands = [(g.stats[column.key].mean, g.method) for g in groups
             if g.configuration == configuration and column.key in g.stats]
    if len(cands) < 2:
        return set()
    rounded = [(round(v, column.digits), m) for v, m in cands]  # a tie as displayed is a tie
    best = max(v for v, _ in rounded) if column.higher_better else min(v for v, _ in rounded)
    return {m for v, m in rounded if v == best}


def reference_groups(rows: Iterable[Any]) -> list[Group]:
    """Groups for reference rows (``baselines_adapters.published.PublishedRow`` or alike: ``configuration``,
    ``display``, ``metrics`` {key: (mean, std)}, ``label``, ``n``). A NaN std means "not published"."""
    out = []
    for r in rows:
        g = Group(r.configuration, r.display, reference=r.label, notes=list(getattr(r, "notes", [])))
        for key, (mean, std) in r.metrics.items():
            g.stats[key] = Stat(float(mean), float(std), int(getattr(r, "n", 0)))
        out.append(g)
    return out


def published_reference(configurations: Any = None, **kwargs: Any) -> list[Group]:
    """The paper's published rows as reference groups (see ``baselines_adapters.published.published_rows``)."""
    from baselines_adapters.published import published_rows

    return reference_groups(published_rows(configurations, **kwargs))
