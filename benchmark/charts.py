"""Charts (matplotlib, Agg): quality vs training time (Pareto front), vs Gaussian count, seed stability.

Failed runs are drawn (a red cross on the lower edge of the axes, counted in the legend), never dropped
silently. Each chart works from result dictionaries only, so `make eval` rebuilds them from stored results.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from lumibench.io import atomic_path

from .aggregate import gaussian_count, is_not_run, metric_value, training_seconds

QUALITY = (("relight.psnr", "relight PSNR (dB) ↑", True), ("albedo.lpips", "albedo LPIPS ↓", False))


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _methods(results: Sequence[dict]) -> list[str]:
    return list(dict.fromkeys(r["method"] for r in results))


def _colours(methods: Sequence[str]) -> dict[str, Any]:
    plt = _plt()
    cmap = plt.get_cmap("tab10")
    return {m: cmap(i % 10) for i, m in enumerate(methods)}


def pareto_front(points: Sequence[tuple[float, float]], higher_better: bool) -> list[tuple[float, float]]:
    """Points not dominated by another one that is at least as fast and at least as good (sorted by x)."""
    front, best = [], -np.inf
    for x, y in sorted(points, key=lambda p: (p[0], -p[1] if higher_better else p[1])):
        score = y if higher_better else -y
        if score > best:
            front.append((x, y))
            best = score
    return front


def _save(fig, path: Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    _plt().close(fig)
    return path


def _quality_vs(results: Sequence[dict], xfun: Callable[[dict], float | None], xlabel: str, title: str,
                path: Path, front: bool) -> Path:
    plt = _plt()
    methods = _methods(results)
    colours = _colours(methods)
    fig, axes = plt.subplots(1, len(QUALITY), figsize=(5.2 * len(QUALITY), 4.2))
    fig.suptitle(title)
    # methods with successful runs none of which reports x: named under the chart, not dropped silently
    missing_x = [m for m in methods if not any(r["method"] == m and r["status"] == "ok" and xfun(r) is not None
                                               for r in results)
                 and any(r["method"] == m and r["status"] == "ok" for r in results)]
    for ax, (key, label, higher) in zip(np.atleast_1d(axes), QUALITY):
        means, xpos = [], {}
        for m in methods:
            pts = [(xfun(r), metric_value(r, key)) for r in results
                   if r["method"] == m and r["status"] == "ok"]
            pts = [(x, y) for x, y in pts if x is not None and y is not None]
            if pts:
                xs, ys = np.array(pts).T
                ax.scatter(xs, ys, s=14, alpha=0.35, color=colours[m])
                mx, my = float(np.mean(xs)), float(np.mean(ys))
                ax.scatter([mx], [my], s=70, color=colours[m], edgecolor="k", zorder=3, label=m)
                means.append((mx, my))
                xpos[m] = mx
        if front and len(means) > 1:
            fx, fy = np.array(pareto_front(means, higher)).T
            ax.step(fx, fy, where="post", color="0.3", lw=1, ls="--", label="Pareto front", zorder=2)
        _draw_failures(ax, results, methods, colours, xpos)
        if means and min(x for x, _ in means) > 0:
            ax.set_xscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if not means:
            ax.text(0.5, 0.5, f"no run reports {xlabel.split(' (')[0]}" +
                    (f"\n({', '.join(missing_x)} report none)" if missing_x else ""),
                    ha="center", va="center", transform=ax.transAxes, fontsize=9, color="0.35")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7, loc="best")
    if missing_x and len(missing_x) < len(methods):
        fig.text(0.01, -0.02, f"not shown (no {xlabel.split(' (')[0]} reported): {', '.join(missing_x)}",
                 fontsize=8, color="0.35")
    return _save(fig, path)


def _draw_failures(ax, results: Sequence[dict], methods: Sequence[str], colours: dict,
                   xpos: dict[str, float] | None = None) -> None:
    """A red cross per failed run on the lower edge, so failures stay visible.

    ``xpos`` gives a method's x in data coordinates (its mean); methods without one go on the left.
    An external method that has not been run is not a failure (the tables list it as "not run").
    """
    failed = [r for r in results if r["status"] != "ok" and not is_not_run(r)]
    for i, m in enumerate(methods):
        n = sum(1 for r in failed if r["method"] == m)
        if not n:
            continue
        if xpos and m in xpos:
            ax.scatter([xpos[m]] * n, [0.03 + 0.04 * k for k in range(n)], transform=ax.get_xaxis_transform(),
                       marker="x", color="red", s=40, clip_on=False, label=f"{m}: {n} failed", zorder=4)
        else:
            ax.scatter([0.04 + 0.05 * i] * n, [0.03 + 0.04 * k for k in range(n)], transform=ax.transAxes,
                       marker="x", color="red", s=40, clip_on=False, label=f"{m}: {n} failed (no value)", zorder=4)


def pareto_chart(results: Sequence[dict], path: Path) -> Path:
    return _quality_vs(results, training_seconds, "training time (s, sum of reported stages)",
                       "Quality vs training time (large markers: mean per method)", path, front=True)


def gaussians_chart(results: Sequence[dict], path: Path) -> Path:
    return _quality_vs(results, gaussian_count, "number of Gaussians",
                       "Quality vs model size", path, front=True)


def stability_chart(results: Sequence[dict], path: Path) -> Path:
    """Per method and (scene, configuration): the value of every seed, so spread across seeds shows."""
    plt = _plt()
    methods = _methods(results)
    fig, axes = plt.subplots(1, len(QUALITY), figsize=(5.2 * len(QUALITY), 4.2))
    fig.suptitle("Stability across seeds (one column per method; dots: seeds, bar: min-max per scene/config)")
    seeds = sorted({r["seed"] for r in results})
    cmap = plt.get_cmap("viridis")
    for ax, (key, label, _) in zip(np.atleast_1d(axes), QUALITY):
        for i, m in enumerate(methods):
            runs = [r for r in results if r["method"] == m]
            cells = sorted({(r["scene"], r["train_light"], r["test_light"]) for r in runs})
            for j, cell in enumerate(cells):
                x = i + (j - (len(cells) - 1) / 2) * (0.6 / max(len(cells), 1))
                vals = [(r["seed"], metric_value(r, key)) for r in runs
                        if (r["scene"], r["train_light"], r["test_light"]) == cell and r["status"] == "ok"]
                vals = [(s, v) for s, v in vals if v is not None]
                if vals:
                    vs = [v for _, v in vals]
                    ax.plot([x, x], [min(vs), max(vs)], color="0.6", lw=1)
                    ax.scatter([x] * len(vs), vs, s=16, zorder=3,
                               color=[cmap(seeds.index(s) / max(len(seeds) - 1, 1)) for s, _ in vals])
        _draw_failures(ax, results, methods, _colours(methods), {m: float(i) for i, m in enumerate(methods)})
        ax.set_xticks(range(len(methods)), methods, rotation=20, fontsize=8)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3, axis="y")
        handles = [plt.Line2D([], [], ls="", marker="o", color=cmap(k / max(len(seeds) - 1, 1)), label=f"seed {s}")
                   for k, s in enumerate(seeds)]
        ax.legend(handles=handles + [h for h in ax.get_legend_handles_labels()[0]], fontsize=7, loc="best")
    return _save(fig, path)


def all_charts(results: Sequence[dict], out_dir: Path) -> dict[str, Path]:
    out_dir = Path(out_dir)
    return {
        "pareto": pareto_chart(results, out_dir / "pareto.png"),
        "gaussians": gaussians_chart(results, out_dir / "quality_vs_gaussians.png"),
        "stability": stability_chart(results, out_dir / "stability.png"),
    }
