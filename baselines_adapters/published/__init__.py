"""The paper's published numbers, stored as data (``lumimotion_cvpr2026.yaml``), as reference rows.

They were measured on the paper's own dataset, so they are shown beside our tables, labelled
"published, on the paper's dataset", and never mixed into our means or our bold. One row per
(paper configuration, method) merges the paper's tables: albedo and relight mean ± std from main
Table 1, NVS, roughness MSE (± std) and ΔPSNR from the supplementary table, the ablations from Table 2.
Where two tables print different means for the same cell (GI-GS, Dam Wall → Harbour Sunset, relight
PSNR: 18.434 in Table 1, 18.431 in the supplementary) Table 1 is shown and the row notes the other.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

DATA = Path(__file__).with_name("lumimotion_cvpr2026.yaml")
LABEL = "published, on the paper's dataset"
# merge order: later tables override earlier ones for the metrics they give
_ORDER = ("table2_ablation", "supplementary", "table1")


@dataclass
class PublishedRow:
    configuration: str                 # the paper's configuration label, e.g. "dam_wall->small_harbour_sunset"
    method: str                        # key in the YAML, e.g. "irgs_nosmooth"
    display: str                       # name shown in tables
    adapter: str                       # our registry name running that method's code
    metrics: dict[str, tuple[float, float]] = field(default_factory=dict)  # "albedo.psnr" -> (mean, std or nan)
    sources: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    paper_configuration: str = ""      # the paper's heading, e.g. "Dam Wall → Harbour Sunset"
    label: str = LABEL
    n: int = 5                         # scenes averaged by the paper


def load(path: str | Path = DATA) -> dict[str, Any]:
    import yaml

    with open(path, encoding="utf-8") as f:
        return yaml.safe_load(f)


def _value(v: Any) -> tuple[float, float]:
    if isinstance(v, (list, tuple)):
        return float(v[0]), float(v[1])
    return float(v), math.nan


def rows(path: str | Path = DATA) -> list[PublishedRow]:
    """Every published row, merged over the paper's tables, in the paper's order."""
    data = load(path)
    methods, confs = data["methods"], data["configurations"]
    merged: dict[tuple[str, str], PublishedRow] = {}
    order: list[tuple[str, str]] = []
    for table in _ORDER:
        block = data["tables"][table]
        for r in block["rows"]:
            key = (r["configuration"], r["method"])
            if key not in merged:
                m = methods[r["method"]]
                merged[key] = PublishedRow(r["configuration"], r["method"], m["display"], m["adapter"],
                                           paper_configuration=confs[r["configuration"]], label=data["label"])
                order.append(key)
            row = merged[key]
            row.sources.append(block["source"])
            for task, metrics in r.items():
                if task in ("configuration", "method"):
                    continue
                for name, v in metrics.items():
                    k = f"{task}.{name}"
                    new = _value(v)
                    old = row.metrics.get(k)
                    if old is not None and old[0] != new[0]:
                        row.notes.append(f"{k}: {new[0]:g} in {table}, {old[0]:g} in an earlier table")
                    row.metrics[k] = new if not (old and math.isnan(new[1]) and not math.isnan(old[1])) else \
                        (new[0], old[1])
    conf_order = list(confs)
    method_order = list(methods)
    order.sort(key=lambda k: (conf_order.index(k[0]), method_order.index(k[1])))
    return [merged[k] for k in order]


def published_rows(configurations: Sequence[str] | Mapping[str, str] | None = None,
                   methods: Sequence[str] | None = None, ablations: bool = False,
                   path: str | Path = DATA) -> list[PublishedRow]:
    """Reference rows to show in the tables.

    ``configurations``: None for all; a list of the paper's labels (``"golden_bay->dam_wall"``) to keep;
    or a mapping {our configuration label: paper label} to show each paper configuration inside our
    section (e.g. ``{"city->sunrise": "golden_bay->dam_wall"}``: strong sun -> low sun). ``methods``:
    YAML keys to keep (default: the five of the supplementary table); ``ablations`` adds Table 2's rows.
    """
    keep = list(methods) if methods else ["r3dgs", "gigs", "irgs", "irgs_nosmooth", "lumimotion"]
    if ablations and not methods:
        keep += ["wo_stage2", "wo_dc", "wo_P"]
    out = []
    all_rows = rows(path)
    known = {r.configuration for r in all_rows}
    if isinstance(configurations, Mapping):
        targets = [(ours, paper) for ours, paper in configurations.items()]
    elif configurations is not None:
        targets = [(c, c) for c in configurations]
    else:
        targets = [(c, c) for c in dict.fromkeys(r.configuration for r in all_rows)]
    for ours, paper in targets:
        if paper not in known:
            from lumibench.errors import UserError

            raise UserError(f"no published results for configuration '{paper}' (published: {', '.join(sorted(known))})")
        for r in all_rows:
            if r.configuration == paper and r.method in keep:
                copy = PublishedRow(**{**r.__dict__, "metrics": dict(r.metrics), "sources": list(r.sources),
                                       "notes": list(r.notes)})
                copy.configuration = ours
                if ours != paper:  # shown inside our section: say which of the paper's configurations it is
                    copy.display = f"{r.display} [{r.paper_configuration}]"
                out.append(copy)
    return out
