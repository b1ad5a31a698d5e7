"""The question the benchmark was built for: does training on the dynamic capture beat training the same
pipeline on a static one? (DESIGN.md: the paper claims -23 % albedo LPIPS and -15 % relight LPIPS against the
best static baseline.)

Per (configuration, scene) where both methods have successful runs: each method's mean +- std over its seeds
for albedo and relight LPIPS and PSNR and roughness MSE, and the change from static to dynamic (relative, in
percent, for LPIPS and MSE; a difference in dB for PSNR); then, per configuration, the mean +- std over scenes
of those per-scene changes and the number of scenes on which the dynamic method is better. Scenes where one of
the two was not run, or has no successful run, are listed as such (a run not yet in the grid is not a
failure), never averaged in. Built from result files only.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from lumibench.io import atomic_write_text

from .aggregate import metric_value

DYNAMIC, STATIC = "lumimotion", "static"


@dataclass(frozen=True)
class ThesisMetric:
    key: str
    label: str
    relative: bool       # change in percent of the static value (else a difference, in the metric's unit)
    higher_better: bool
    digits: int


METRICS = (
    ThesisMetric("albedo.lpips", "Albedo LPIPS", True, False, 3),
    ThesisMetric("relight.lpips", "Relight LPIPS", True, False, 3),
    ThesisMetric("albedo.psnr", "Albedo PSNR", False, True, 2),
    ThesisMetric("relight.psnr", "Relight PSNR", False, True, 2),
    ThesisMetric("roughness.mse", "Roughness MSE", True, False, 4),
)
PAPER_CLAIMS = {"albedo.lpips": -23.0, "relight.lpips": -15.0}  # percent, dynamic against the best static


def _values(results: Sequence[dict], method: str, conf: tuple[str, str], scene: str, key: str) -> list[float]:
    vals = [metric_value(r, key) for r in results
            if r["status"] == "ok" and r["method"] == method and r["scene"] == scene
            and (r["train_light"], r["test_light"]) == conf]
    return [v for v in vals if v is not None]


def _lacking(row: dict) -> str:
    """Why a scene has no comparison: a method not run there (not yet in the grid) is not one that failed."""
    parts = ([f"{', '.join(row['not_run'])} not run"] if row["not_run"] else []) + \
            ([f"no successful run of {', '.join(row['failed'])}"] if row["failed"] else [])
    return "; ".join(parts)


def change(dynamic: float, static: float, metric: ThesisMetric) -> float:
    """Static -> dynamic: percent of the static value (relative metrics) or the difference."""
    if metric.relative:
        return 100.0 * (dynamic - static) / static if static != 0 else float("nan")
    return dynamic - static


def better(delta: float, metric: ThesisMetric) -> bool:
    return delta > 0 if metric.higher_better else delta < 0


def compare(results: Sequence[dict], dynamic: str = DYNAMIC, static: str = STATIC) -> list[dict]:
    """One entry per configuration present in both methods' results: {configuration, scenes: [{scene,
    missing (a method without a successful run, or None), metrics: {key: {dynamic: (mean, std, n), static:
    (...), change, seed_range}}}], overall: {key: {mean, std, n_scenes, wins}}}.

    ``change`` compares the seed means; ``seed_range`` is (min, max, pairs) of the change taken between every
    seed of one method and every seed of the other, so a reader sees whether the sign survives the seeds."""
    confs = sorted({(r["train_light"], r["test_light"]) for r in results if r["method"] in (dynamic, static)})
    out = []
    for conf in confs:
        scenes = sorted({r["scene"] for r in results if r["method"] in (dynamic, static)
                         and (r["train_light"], r["test_light"]) == conf})
        rows, deltas = [], {m.key: [] for m in METRICS}
        for scene in scenes:
            row = {"scene": scene, "missing": None, "metrics": {}}
            have = {name: bool(_values(results, name, conf, scene, METRICS[0].key)) for name in (dynamic, static)}
            lacking = [name for name, ok in have.items() if not ok]
            if lacking:
                row["missing"] = ", ".join(lacking)
                tried = {r["method"] for r in results if r["scene"] == scene and (r["train_light"], r["test_light"]) == conf}
                row["not_run"] = [name for name in lacking if name not in tried]  # no result at all, not a failure
                row["failed"] = [name for name in lacking if name in tried]
                rows.append(row)
                continue
            for m in METRICS:
                d, s = _values(results, dynamic, conf, scene, m.key), _values(results, static, conf, scene, m.key)
                if not d or not s:
                    continue
                c = change(float(np.mean(d)), float(np.mean(s)), m)
                pairs = [change(x, y, m) for x in d for y in s]  # every dynamic seed against every static one
                row["metrics"][m.key] = {"dynamic": (float(np.mean(d)), float(np.std(d)), len(d)),
                                         "static": (float(np.mean(s)), float(np.std(s)), len(s)), "change": c,
                                         "seed_range": (float(min(pairs)), float(max(pairs)), len(pairs))}
                deltas[m.key].append(c)
            rows.append(row)
        overall = {k: {"mean": float(np.mean(v)), "std": float(np.std(v)), "n_scenes": len(v),
                       "wins": sum(better(x, m) for x in v)}
                   for m in METRICS for k, v in [(m.key, deltas[m.key])] if v}
        out.append({"configuration": conf, "scenes": rows, "overall": overall})
    return out


def _ms(t: tuple[float, float, int], digits: int) -> str:
    mean, std, n = t
    return f"{mean:.{digits}f}" + (f" ± {std:.{digits}f}" if n > 1 else "")


def _delta(c: float, m: ThesisMetric) -> str:
    return f"{c:+.1f} %" if m.relative else f"{c:+.2f} dB" if "psnr" in m.key else f"{c:+.{m.digits}f}"


def _seed_range(e: dict, m: ThesisMetric) -> str:
    lo, hi, n = e["seed_range"]
    if n < 2:
        return ""
    if m.relative:
        return f"; seeds {lo:+.1f} to {hi:+.1f} %"
    return f"; seeds {lo:+.{m.digits}f} to {hi:+.{m.digits}f}" + (" dB" if "psnr" in m.key else "")


def _spread(o: dict, m: ThesisMetric) -> str:
    if m.relative:
        return f"{o['mean']:+.1f} ± {o['std']:.1f} %"
    unit = " dB" if "psnr" in m.key else ""
    return f"{o['mean']:+.{m.digits}f} ± {o['std']:.{m.digits}f}{unit}"


def markdown(comparisons: Sequence[dict], protocol: str | None = None, dynamic: str = DYNAMIC,
             static: str = STATIC) -> str:
    """thesis.md: per configuration, a row per scene (static -> dynamic, change) and the mean over scenes."""
    lines = [f"# {dynamic} (dynamic capture) against {static} (the same pipeline on the static capture)", "",
             f"Protocol: {protocol or '?'}. Per scene: each method's mean ± std over its seeds (n), static → "
             f"dynamic, and the change of the means (LPIPS and MSE in percent of the static value, PSNR in dB; "
             f"negative LPIPS and MSE changes and positive PSNR changes favour the dynamic capture) with, where "
             f"a method has several seeds, the lowest and highest change between one seed of each. Last row: the mean ± std "
             f"over scenes of the per-scene change, and on how many scenes the dynamic capture is better. The "
             f"paper: albedo LPIPS {PAPER_CLAIMS['albedo.lpips']:+.0f} %, relight LPIPS "
             f"{PAPER_CLAIMS['relight.lpips']:+.0f} % against the best static baseline (its own dataset)."]
    for comp in comparisons:
        train, test = comp["configuration"]
        if all(r["missing"] for r in comp["scenes"]):
            lines += ["", f"## {train} → {test}", "",
                      "No scene has successful runs of both: " + "; ".join(
                          f"{r['scene']} ({_lacking(r)})" for r in comp["scenes"]) + "."]
            continue
        lines += ["", f"## {train} → {test}", "",
                  "| scene | seeds (dyn / static) | " + " | ".join(m.label for m in METRICS) + " |",
                  "|:--|:--|" + "--:|" * len(METRICS)]
        for row in comp["scenes"]:
            if row["missing"]:
                lines.append(f"| {row['scene']} | {_lacking(row)} |" + " – |" * len(METRICS))
                continue
            first = next(iter(row["metrics"].values()))
            cells = []
            for m in METRICS:
                e = row["metrics"].get(m.key)
                cells.append("–" if e is None else
                             f"{_ms(e['static'], m.digits)} → {_ms(e['dynamic'], m.digits)} "
                             f"(**{_delta(e['change'], m)}**{_seed_range(e, m)})")
            lines.append(f"| {row['scene']} | {first['dynamic'][2]} / {first['static'][2]} | " + " | ".join(cells) + " |")
        cells = []
        for m in METRICS:
            o = comp["overall"].get(m.key)
            cells.append("–" if o is None else f"{_spread(o, m)}; better on {o['wins']} of {o['n_scenes']}")
        lines.append("| **all scenes** | | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def chart(comparisons: Sequence[dict], path: Path, protocol: str | None = None) -> Path | None:
    """thesis.png: per configuration, the change of albedo and relight LPIPS per scene (bars, from the seed
    means; grey whisker: lowest to highest change between one seed of each method) and their mean over scenes
    (black whisker: std over scenes), the paper's claims as dashed lines."""
    comps = [c for c in comparisons if any(not r["missing"] for r in c["scenes"])]
    if not comps:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lumibench.io import atomic_path

    keys = [m for m in METRICS if m.key in PAPER_CLAIMS]
    # one y scale for every configuration, so the panels compare by eye
    fig, axes = plt.subplots(1, len(comps), figsize=(1.2 + 4.2 * len(comps), 4.2), squeeze=False,
                             sharey=True, layout="constrained")
    colours = {"albedo.lpips": "#1f77b4", "relight.lpips": "#ff7f0e"}
    for ax, comp in zip(axes[0], comps):
        rows = [r for r in comp["scenes"] if not r["missing"]]
        names = [r["scene"] for r in rows] + ["mean"]
        width = 0.8 / len(keys)
        for i, m in enumerate(keys):
            vals = [r["metrics"][m.key]["change"] if m.key in r["metrics"] else np.nan for r in rows]
            o = comp["overall"].get(m.key)
            vals.append(o["mean"] if o else np.nan)
            xs = np.arange(len(names)) + (i - (len(keys) - 1) / 2) * width
            ax.bar(xs, vals, width, color=colours[m.key], label=m.label)
            for x, r in zip(xs, rows):  # the seeds: lowest to highest change between one seed of each method
                e = r["metrics"].get(m.key)
                if e is not None and e["seed_range"][2] > 1:
                    lo, hi, _ = e["seed_range"]
                    ax.plot([x, x], [lo, hi], color="0.25", lw=1.2, solid_capstyle="butt")
                    ax.hlines([lo, hi], x - width / 4, x + width / 4, color="0.25", lw=1.2)
            if o and o["n_scenes"] > 1:
                ax.errorbar(xs[-1], o["mean"], yerr=o["std"], color="k", capsize=3, lw=1)
            ax.axhline(PAPER_CLAIMS[m.key], color=colours[m.key], ls="--", lw=1,
                       label=f"paper, {m.label} ({PAPER_CLAIMS[m.key]:+.0f} %)")
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xticks(range(len(names)), names, rotation=30, ha="right", rotation_mode="anchor", fontsize=8)
        seeds = sorted({r["metrics"][k][side][2] for r in rows for k in r["metrics"] for side in ("dynamic", "static")})
        seeds_note = f"{seeds[0]}" if len(seeds) == 1 else f"{seeds[0]}-{seeds[-1]}" if seeds else "0"
        ax.set_title(f"{comp['configuration'][0]} → {comp['configuration'][1]}"
                     f" ({seeds_note} seed{'s' if seeds_note != '1' else ''} per scene)", fontsize=10)
        if ax is axes[0][0]:
            ax.set_ylabel("change, dynamic vs static (%)\n< 0: the dynamic capture is better")
        ax.grid(alpha=0.3, axis="y")
    handles, labels = axes[0][0].get_legend_handles_labels()
    if any(e["seed_range"][2] > 1 for c in comps for r in c["scenes"] for e in r["metrics"].values()):
        from matplotlib.lines import Line2D

        handles.append(Line2D([], [], color="0.25", lw=1.2))
        labels.append("seeds: lowest to highest change between one seed of each method")
    fig.legend(handles, labels, loc="outside lower center", ncols=2, fontsize=8)
    fig.suptitle("Dynamic against static capture: LPIPS change per scene" + (f" [{protocol}]" if protocol else ""))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return Path(path)


def write(results: Sequence[dict], out_dir: Path, protocol: str | None = None) -> dict[str, Path]:
    """thesis.md and thesis.png in ``out_dir`` when both methods have results; {} otherwise."""
    comps = compare(results)
    if not any(not r["missing"] for c in comps for r in c["scenes"]):
        return {}
    out = {"thesis.md": Path(out_dir) / "thesis.md"}
    atomic_write_text(out["thesis.md"], markdown(comps, protocol))
    png = chart(comps, Path(out_dir) / "thesis.png", protocol)
    if png is not None:
        out["thesis.png"] = png
    return out
