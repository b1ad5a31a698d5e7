"""Charts (matplotlib, Agg): quality vs training time (Pareto front), vs Gaussian count, seed stability, one
scene under each condition (a stress sweep's results: one column per configuration or '@' variant), and
where the relight error comes from (the relight diagnostic, when some result carries one).

Failed runs are drawn (a red cross in a row kept free under the data, counted in the legend), never
dropped silently; a run that diverged (training stopped on a non-finite value, method/train.py) is drawn
as such (a dark-red filled cross, "diverged" in the legend). Each cross sits at its run's x: its
(scene, configuration) column in the stability chart, its method's mean elsewhere; with few of them each
is labelled with its configuration and seed (:func:`failure_marks`, :func:`stability_data`). An external
method that has not been run is no failure: it draws nothing and is named under the chart as "not run".
The quality charts join the seeds of one (method, scene, configuration) with a thin line (their spread). Log axes carry plain numbers (0.1, 1, 10, 1k; 5k, 10k, 20k) on 1-2-5 or
decade positions and no minor labels; the legend sits outside the axes, shared by both panels. Each chart
works from result dictionaries only, so `make eval` rebuilds them from stored results. They are drawn from
the results of one protocol (the grid's primary one, see benchmark.outputs), named in each title.
"""
from __future__ import annotations

import re
import textwrap
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from lumibench.io import atomic_path

from .aggregate import gaussian_count, is_not_run, metric_value, training_clock

QUALITY = (("relight.psnr", "relight PSNR (dB) ↑", True), ("albedo.lpips", "albedo LPIPS ↓", False))
# the cause method/train.py's TrainingDiverged gives ("stage 1 stopped: non-finite loss at iteration 37; ...")
DIVERGED = re.compile(r"stopped: non-finite|\bdiverged\b", re.IGNORECASE)
FAILURE_STYLE = {"failed": {"marker": "x", "color": "red"}, "diverged": {"marker": "X", "color": "darkred"}}
MAX_FAILURE_LABELS = 12  # with more failed runs than this, the legend counts them and no cross is labelled


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _methods(results: Sequence[dict]) -> list[str]:
    """Methods in first-seen order, less those none of whose jobs has been run (see :func:`_not_run_note`)."""
    return list(dict.fromkeys(r["method"] for r in results if not is_not_run(r)))


def _not_run_note(results: Sequence[dict]) -> str | None:
    """One line naming the methods with jobs that were not run (external, no outputs yet), or None."""
    names = []
    for m in dict.fromkeys(r["method"] for r in results if is_not_run(r)):
        n = sum(1 for r in results if r["method"] == m and is_not_run(r))
        total = sum(1 for r in results if r["method"] == m)
        names.append(m if n == total else f"{m} ({n} of {total} jobs)")
    return f"not run (no outputs yet; not failures): {', '.join(names)}" if names else None


def _plain_number(v: float, unit: float = 1.0, suffix: str = "") -> str:
    if unit != 1.0:
        return f"{v / unit:.10g}{suffix}"
    return f"{v:,.0f}" if float(v).is_integer() else f"{v:,.10g}"


def _log_ticks(vmin: float, vmax: float) -> list[float]:
    """Readable major positions on a log axis: decades when it spans many, 1-2-5 when few, else even steps."""
    from matplotlib.ticker import MaxNLocator

    vmin, vmax = sorted((vmin, vmax))
    if not (np.isfinite(vmin) and np.isfinite(vmax)) or vmax <= 0:
        return []
    vmin = max(vmin, vmax * 1e-12)
    decades = np.log10(vmax / vmin)
    lo, hi = int(np.floor(np.log10(vmin))), int(np.ceil(np.log10(vmax)))

    def within(subs, every=1):
        eps = 1e-9 * vmax
        return [m * 10.0 ** e for e in range(lo, hi + 1) if (e - lo) % every == 0 for m in subs
                if vmin - eps <= m * 10.0 ** e <= vmax + eps]

    if decades > 2.2:
        return within((1,), every=int(np.ceil(decades / 6)))
    ticks = within((1, 2, 5))
    if len(ticks) >= 3:
        return ticks
    # under about half a decade: even steps (e.g. 19,940 19,950 19,960) rather than one lonely label
    return [float(t) for t in MaxNLocator(nbins=5, steps=[1, 2, 2.5, 5, 10]).tick_values(vmin, vmax)
            if vmin <= t <= vmax]


def _readable_log_axis(axis) -> None:
    """Plain-number major labels at :func:`_log_ticks` positions; minor ticks unlabelled."""
    from matplotlib.ticker import Formatter, Locator, LogLocator, NullFormatter

    class _Locator(Locator):
        def __call__(self):
            return self.tick_values(*self.axis.get_view_interval())

        def tick_values(self, vmin, vmax):
            return _log_ticks(vmin, vmax)

    class _Formatter(Formatter):
        short = True

        def set_locs(self, locs):
            # thousands as "k" when every label from 1,000 up reads exactly so ("1k 10k", "5k 10k 20k");
            # otherwise all of them in full ("19,940 19,950"), never a mix of both
            super().set_locs(locs)
            big = [abs(v) for v in locs if abs(v) >= 1e3]
            self.short = all(abs(v / 100 - round(v / 100)) < 1e-6 for v in big)

        def __call__(self, x, pos=None):
            if self.short and abs(x) >= 1e6 and abs(x / 1e5 - round(x / 1e5)) < 1e-6:
                return _plain_number(x, 1e6, "M")
            if self.short and abs(x) >= 1e3:
                return _plain_number(x, 1e3, "k")
            return _plain_number(x)

    axis.set_major_locator(_Locator())
    axis.set_major_formatter(_Formatter())
    axis.set_minor_locator(LogLocator(subs=np.arange(2, 10)))
    axis.set_minor_formatter(NullFormatter())


def _reserve_failure_row(ax, n: int) -> None:
    """Lower the y-limit so that the data sits above the row of failure crosses (none cover a point)."""
    if n <= 0:
        return
    frac = min(_failure_heights(n)[-1] + 0.05, 0.3)
    lo, hi = ax.get_ylim()
    ax.set_ylim(lo - frac * (hi - lo) / (1 - frac), hi)


def _failure_heights(n: int) -> list[float]:
    step = min(0.04, 0.15 / max(n - 1, 1))
    return [0.03 + step * k for k in range(n)]


def _figure_legend(fig, axes) -> None:
    """One legend for all panels, outside them on the right, so that it covers no point."""
    seen: dict[str, Any] = {}
    for ax in np.atleast_1d(axes):
        for h, lab in zip(*ax.get_legend_handles_labels()):
            seen.setdefault(lab, h)
    if seen:
        fig.legend(list(seen.values()), list(seen.keys()), loc="outside right upper", fontsize=8)


def _figure_notes(fig, notes: Sequence[str | None]) -> None:
    notes = [n for n in notes if n]
    if notes:  # under the x labels; savefig(bbox_inches="tight") keeps it in the image
        fig.text(0.01, 0.0, "\n".join(notes), ha="left", va="top", fontsize=8, color="0.3")


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


def protocol_label(results: Sequence[dict]) -> str:
    """"protocol: <name>" of the results drawn (one protocol per chart), or "" for none or a mix."""
    names = {r.get("protocol") for r in results}
    return f"protocol: {names.pop()}" if len(names) == 1 else ""


def _titled(title: str, results: Sequence[dict]) -> str:
    label = protocol_label(results)
    return f"{title} [{label}]" if label else title


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
    fig, axes = plt.subplots(1, len(QUALITY), figsize=(5.2 * len(QUALITY) + 1.6, 4.2), layout="constrained")
    fig.suptitle(_titled(title, results))
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
                for sx, (lo, hi) in seed_spreads(results, m, xfun, key):  # the seeds of one point: their spread
                    ax.plot([sx, sx], [lo, hi], color=colours[m], alpha=0.5, lw=1, zorder=1)
                mx, my = float(np.mean(xs)), float(np.mean(ys))
                ax.scatter([mx], [my], s=70, color=colours[m], edgecolor="k", zorder=3, label=m)
                means.append((mx, my))
                xpos[m] = mx
        if front and len(means) > 1:
            fx, fy = np.array(pareto_front(means, higher)).T
            ax.step(fx, fy, where="post", color="0.3", lw=1, ls="--", label="Pareto front", zorder=2)
        marks = failure_marks(results, methods)
        for mk in marks:
            mk["x"] = xpos.get(mk["method"])
        _draw_failures(ax, marks, methods)
        _reserve_failure_row(ax, _max_failures(results))
        if means and min(x for x, _ in means) > 0:
            ax.set_xscale("log")
            _readable_log_axis(ax.xaxis)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if not means:
            ax.text(0.5, 0.5, f"no run reports {xlabel.split(' (')[0]}" +
                    (f"\n({', '.join(missing_x)} report none)" if missing_x else ""),
                    ha="center", va="center", transform=ax.transAxes, fontsize=9, color="0.35")
    _figure_legend(fig, axes)
    _figure_notes(fig, [f"not shown (no {xlabel.split(' (')[0]} reported): {', '.join(missing_x)}"
                        if missing_x and len(missing_x) < len(methods) else None, _not_run_note(results)])
    return _save(fig, path)


def _failed(results: Sequence[dict]) -> list[dict]:
    return [r for r in results if r["status"] != "ok" and not is_not_run(r)]


def failure_kind(result: dict) -> str:
    """"diverged" when the run stopped on a non-finite value (its cause says so), else "failed"."""
    return "diverged" if DIVERGED.search(str(result.get("error") or "")) else "failed"


def failure_marks(results: Sequence[dict], methods: Sequence[str] | None = None) -> list[dict]:
    """One mark per failed run of ``methods`` (all when None; a job of a method not run is no failure):
    method, scene, configuration, seed, kind ("failed" or "diverged"), cause, and a short ``label``
    (configuration and seed, the scene first when the results hold several) drawn beside its cross; the
    charts add its ``x``."""
    out = []
    several = len({r.get("scene") for r in results if not is_not_run(r)}) > 1  # then the label names the scene
    for r in _failed(results):
        if methods is not None and r["method"] not in methods:
            continue
        out.append({"method": r["method"], "scene": r.get("scene"), "train_light": r.get("train_light"),
                    "test_light": r.get("test_light"), "seed": r.get("seed"), "kind": failure_kind(r),
                    "cause": str(r.get("error") or ""),
                    "label": (f"{r.get('scene')} " if several else "")
                    + f"{r.get('train_light')}→{r.get('test_light')} s{r.get('seed')}"})
    return out


def _max_failures(results: Sequence[dict]) -> int:
    counts: dict[str, int] = {}
    for r in _failed(results):
        counts[r["method"]] = counts.get(r["method"], 0) + 1
    return max(counts.values(), default=0)


def seed_spreads(results: Sequence[dict], method: str, xfun: Callable[[dict], float | None],
                 key: str) -> list[tuple[float, tuple[float, float]]]:
    """Per (scene, configuration) of ``method`` with two or more seeds that report x and ``key``: (mean x,
    (min, max) of the metric over the seeds), the spread the quality charts draw as a line."""
    cells: dict[tuple, list[tuple[float, float]]] = {}
    for r in results:
        if r["method"] != method or r["status"] != "ok":
            continue
        x, y = xfun(r), metric_value(r, key)
        if x is not None and y is not None:
            cells.setdefault((r["scene"], r["train_light"], r["test_light"]), []).append((x, y))
    return [(float(np.mean([x for x, _ in v])), (min(y for _, y in v), max(y for _, y in v)))
            for v in cells.values() if len(v) > 1]


def _draw_failures(ax, marks: Sequence[dict], methods: Sequence[str]) -> None:
    """A cross per failed run along the lower edge, so failures stay visible: red x when it failed, a
    dark-red filled X when it diverged, at its mark's ``x`` (data coordinates; marks without one go on
    the left, one slot per method), stacked where several share an x, and labelled with its configuration
    and seed when there are few. An external method that has not been run is not a failure (the tables
    list it as "not run")."""
    per_method: dict[str, int] = {}
    for mk in marks:
        per_method[mk["method"]] = per_method.get(mk["method"], 0) + 1
    heights = _failure_heights(max(per_method.values(), default=0))
    label_each = len(marks) <= MAX_FAILURE_LABELS
    stack: dict[Any, int] = {}
    for i, m in enumerate(methods):
        for kind, style in FAILURE_STYLE.items():
            mine = [mk for mk in marks if mk["method"] == m and mk["kind"] == kind]
            for placed in (True, False):
                group = [mk for mk in mine if (mk.get("x") is not None) == placed]
                if not group:
                    continue
                transform = ax.get_xaxis_transform() if placed else ax.transAxes
                xs, ys = [], []
                for mk in group:
                    slot = ("x", mk["x"]) if placed else ("method", i)
                    k = stack.get(slot, 0)
                    stack[slot] = k + 1
                    xs.append(mk["x"] if placed else 0.04 + 0.05 * i)
                    ys.append(heights[min(k, len(heights) - 1)])
                ax.scatter(xs, ys, transform=transform, s=40, clip_on=False, zorder=4,
                           label=f"{m}: {len(group)} {kind}" + ("" if placed else " (no value)"), **style)
                if label_each:
                    for x, y, mk in zip(xs, ys, group):
                        ax.annotate(mk["label"], (x, y), xycoords=transform, xytext=(4, 0),
                                    textcoords="offset points", fontsize=6, color=style["color"],
                                    va="center", ha="left", annotation_clip=False)


def pareto_chart(results: Sequence[dict], path: Path) -> Path:
    seconds, clock = training_clock(results)
    return _quality_vs(results, seconds, f"training time (s, {clock} clock, sum of reported stages)",
                       "Quality vs training time (large markers: mean per method)", path, front=True)


def gaussians_chart(results: Sequence[dict], path: Path) -> Path:
    return _quality_vs(results, gaussian_count, "number of Gaussians",
                       "Quality vs model size", path, front=True)


def stability_data(results: Sequence[dict], key: str) -> dict[str, Any]:
    """What the stability chart draws for ``key``: the methods (one column each), and per (method, scene,
    configuration) cell its x (spread inside the method's column) and the (seed, value) of each successful
    run; ``marks``: :func:`failure_marks` with each failed or diverged run at its own cell's x."""
    methods = _methods(results)
    cells, xs = [], {}
    for i, m in enumerate(methods):
        runs = [r for r in results if r["method"] == m and not is_not_run(r)]
        keys = sorted({(r["scene"], r["train_light"], r["test_light"]) for r in runs})
        for j, cell in enumerate(keys):
            x = i + (j - (len(keys) - 1) / 2) * (0.6 / max(len(keys), 1))
            xs[(m, *cell)] = x
            vals = [(r["seed"], metric_value(r, key)) for r in runs
                    if (r["scene"], r["train_light"], r["test_light"]) == cell and r["status"] == "ok"]
            cells.append({"method": m, "scene": cell[0], "train_light": cell[1], "test_light": cell[2], "x": x,
                          "values": [(s, v) for s, v in vals if v is not None]})
    marks = failure_marks(results, methods)
    for mk in marks:
        mk["x"] = xs.get((mk["method"], mk["scene"], mk["train_light"], mk["test_light"]))
    return {"methods": methods, "cells": cells, "marks": marks,
            "seeds": sorted({r["seed"] for r in results if r["status"] == "ok"})}


def stability_chart(results: Sequence[dict], path: Path) -> Path:
    """Per method and (scene, configuration): the value of every seed, so spread across seeds shows; a
    failed or diverged run is a cross at its own (scene, configuration) column (:func:`stability_data`)."""
    plt = _plt()
    methods = _methods(results)
    fig, axes = plt.subplots(1, len(QUALITY), figsize=(5.2 * len(QUALITY) + 1.2, 4.4), layout="constrained")
    fig.suptitle(_titled("Stability across seeds", results)
                 + "\none column per method; dots: seeds, bar: min-max per scene/config; x: failed or diverged")
    seeds = sorted({r["seed"] for r in results if r["status"] == "ok"})
    viridis = plt.get_cmap("viridis")

    def cmap(t: float):  # viridis without its pale yellow end, which is hard to see on white
        return viridis(0.85 * t)

    for ax, (key, label, _) in zip(np.atleast_1d(axes), QUALITY):
        data = stability_data(results, key)
        for cell in data["cells"]:
            if cell["values"]:
                x, vs = cell["x"], [v for _, v in cell["values"]]
                ax.plot([x, x], [min(vs), max(vs)], color="0.6", lw=1)
                ax.scatter([x] * len(vs), vs, s=16, zorder=3,
                           color=[cmap(seeds.index(s) / max(len(seeds) - 1, 1)) for s, _ in cell["values"]])
        for k, s in enumerate(seeds):  # legend entries only (the figure legend collects them)
            ax.plot([], [], ls="", marker="o", color=cmap(k / max(len(seeds) - 1, 1)), label=f"seed {s}")
        _draw_failures(ax, data["marks"], methods)
        _reserve_failure_row(ax, _max_failures(results))
        ax.set_xticks(range(len(methods)), methods, rotation=30, ha="right", rotation_mode="anchor", fontsize=8)
        ax.set_xlim(-0.6, len(methods) - 0.4)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3, axis="y")
    _figure_legend(fig, axes)
    _figure_notes(fig, [_not_run_note(results)])
    return _save(fig, path)


def condition_of(result: dict) -> tuple[str, str, str]:
    """(train light, test light, variant) of a result: the variant is the part of its method after '@'
    (a budget or stress variant, "" for none)."""
    return result["train_light"], result["test_light"], result["method"].partition("@")[2]


def condition_label(cond: tuple[str, str, str]) -> str:
    train, test, variant = cond
    return f"{train}→{test}" + (f"\n@{variant}" if variant else "")


def conditions_data(results: Sequence[dict], key: str) -> dict[str, Any]:
    """What the conditions chart draws for ``key`` on one scene: the conditions (one column each: the
    configuration and the variant, the most-run configuration without a variant first, then the other
    configurations, then the variants), the base methods (the part before '@', one colour each), and per
    (base method, condition) its x and the (seed, value) of each successful run; ``marks``: each failed or
    diverged run at its own cell's x (its ``method`` the base method)."""
    runs = [r for r in results if not is_not_run(r)]
    bases = list(dict.fromkeys(r["method"].partition("@")[0] for r in runs))
    count: dict[tuple, int] = {}
    for r in runs:
        c = condition_of(r)
        count[c] = count.get(c, 0) + 1
    conds = sorted(count, key=lambda c: (c[2] != "", -count[c] if not c[2] else 0, c[2], c[0], c[1]))
    width = 0.6 / max(len(bases), 1)
    cells, xs = [], {}
    for i, c in enumerate(conds):
        for k, b in enumerate(bases):
            mine = [r for r in runs if condition_of(r) == c and r["method"].partition("@")[0] == b]
            if not mine:
                continue
            x = i + (k - (len(bases) - 1) / 2) * width
            xs[(b, c)] = x
            vals = [(r["seed"], metric_value(r, key)) for r in mine if r["status"] == "ok"]
            cells.append({"method": b, "condition": c, "x": x, "values": [(sd, v) for sd, v in vals if v is not None]})
    marks = []
    for mk in failure_marks(runs):
        base = mk["method"].partition("@")[0]
        cond = (mk["train_light"], mk["test_light"], mk["method"].partition("@")[2])
        marks.append({**mk, "method": base, "x": xs.get((base, cond)), "label": f"s{mk['seed']}"})
    return {"conditions": conds, "methods": bases, "cells": cells, "marks": marks}


def has_conditions(results: Sequence[dict]) -> bool:
    """True for results of one scene under two or more conditions (a stress sweep's shape)."""
    runs = [r for r in results if not is_not_run(r)]
    return len({r["scene"] for r in runs}) == 1 and len({condition_of(r) for r in runs}) > 1


def conditions_chart(results: Sequence[dict], path: Path) -> Path:
    """One scene under each condition (a stress sweep: fewer frames, a Gaussian cap, another light), the
    methods side by side in each column: every seed a dot, the seeds' range a bar, the mean a tick, a
    failed or diverged run a cross in its column, so where a method breaks and how much its seeds spread
    show at a glance."""
    plt = _plt()
    runs = [r for r in results if not is_not_run(r)]
    scene = runs[0]["scene"] if runs else ""
    fig, axes = plt.subplots(1, len(QUALITY), figsize=(5.6 * len(QUALITY) + 1.4, 4.6), layout="constrained")
    fig.suptitle(_titled(f"{scene}: each condition, the methods side by side", results)
                 + "\ndots: seeds, bar: min-max, tick: mean; x: failed or diverged")
    for ax, (key, label, _) in zip(np.atleast_1d(axes), QUALITY):
        data = conditions_data(results, key)
        colours = _colours(data["methods"])
        for cell in data["cells"]:
            vs = [v for _, v in cell["values"]]
            if not vs:
                continue
            x, col = cell["x"], colours[cell["method"]]
            ax.plot([x, x], [min(vs), max(vs)], color=col, lw=1, alpha=0.6)
            ax.scatter([x] * len(vs), vs, s=18, color=col, zorder=3)
            ax.plot([x - 0.08, x + 0.08], [float(np.mean(vs))] * 2, color=col, lw=2, zorder=3)
        for m in data["methods"]:  # legend entries only (the figure legend collects them)
            ax.plot([], [], ls="", marker="o", color=colours[m], label=m)
        _draw_failures(ax, data["marks"], data["methods"])
        counts: dict[str, int] = {}
        for mk in data["marks"]:
            counts[mk["method"]] = counts.get(mk["method"], 0) + 1
        _reserve_failure_row(ax, max(counts.values(), default=0))
        ax.set_xticks(range(len(data["conditions"])), [condition_label(c) for c in data["conditions"]],
                      fontsize=8)
        ax.set_xlim(-0.6, len(data["conditions"]) - 0.4)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3, axis="y")
    _figure_legend(fig, axes)
    _figure_notes(fig, [_not_run_note(results)])
    return _save(fig, path)


# the relight diagnostic's steps (method/diagnose.py) drawn as gains over "ours": key, legend label, colour, hatch
DIAGNOSE_GAINS = (
    ("gt_albedo", "GT albedo", "#4c72b0", ""),
    ("gt_roughness", "GT roughness", "#64b5cd", ""),
    ("gt_normal", "GT normals", "#55a868", ""),
    ("gt_all", "GT albedo + roughness + normals", "#2f2f2f", ""),
    ("ours_unshadowed", "ours without our shadows", "#dd8452", "//"),
    ("gt_all_unshadowed", "all three GT, without our shadows", "#c44e52", "//"),
)


def has_diagnose(results: Sequence[dict]) -> bool:
    """True when some successful result carries a relight-diagnostic block (the chart is drawn then)."""
    return any(r["status"] == "ok" and isinstance(r.get("diagnose"), dict) for r in results)


def _diagnose_means(runs: Sequence[dict]) -> dict[str, float] | None:
    """Mean PSNR per step over the seeds of one (method, scene, configuration); None without a block."""
    blocks = [r["diagnose"]["steps"] for r in runs if r["status"] == "ok" and isinstance(r.get("diagnose"), dict)]
    if not blocks:
        return None
    names = set.intersection(*(set(b) for b in blocks))
    return {n: float(np.mean([b[n]["psnr"] for b in blocks])) for n in names}


def relight_error_sources_chart(results: Sequence[dict], path: Path) -> Path:
    """Per configuration, per scene and method: our relight PSNR in the diagnostic (under the group) and the
    PSNR gained by each ground-truth swap or by dropping our shadows (bars), mean over seeds."""
    from matplotlib.patches import Patch

    plt = _plt()
    diag = [r for r in results if r["status"] == "ok" and isinstance(r.get("diagnose"), dict)]
    methods = list(dict.fromkeys(r["method"] for r in diag))
    confs = list(dict.fromkeys((r["train_light"], r["test_light"]) for r in diag))
    # per panel, the scenes where one of these methods has a run (a failed one too: it is named, not dropped)
    scenes_of = {c: list(dict.fromkeys(r["scene"] for r in results if r["method"] in methods and not is_not_run(r)
                                       and (r["train_light"], r["test_light"]) == c)) for c in confs}
    n_scenes = max(len(v) for v in scenes_of.values())
    n_groups = n_scenes * len(methods) + (n_scenes - 1) * 0.5
    fig_w = max(8.0, 1.15 * n_groups + 4.0)  # the legend takes about 2.5 in on the right
    fig, axes = plt.subplots(len(confs), 1, figsize=(fig_w, 3.3 * len(confs) + 0.8),
                             layout="constrained", sharey=True, squeeze=False)
    fig.get_layout_engine().set(h_pad=0.15)  # room for the scene names under each panel's labels
    # text wrapped to the figure's width, so that it never widens the image past the panels
    fig.suptitle(textwrap.fill("Where the relight error comes from: the relight PSNR gained when one of our buffers "
                               "is replaced by the ground truth, or when our traced shadows are dropped (bars); under "
                               "each group: the method and its own relight PSNR in the diagnostic ('ours')",
                               int((fig_w - 3.0) * 12)), fontsize=10, x=0.01, ha="left")
    width = 0.8 / len(DIAGNOSE_GAINS)
    for ax, (train, test) in zip(axes[:, 0], confs):
        ticks, labels, scenes = [], [], scenes_of[train, test]
        for i, scene in enumerate(scenes):
            for j, m in enumerate(methods):
                x = i * (len(methods) + 0.5) + j
                runs = [r for r in results if (r["method"], r["scene"], r["train_light"], r["test_light"])
                        == (m, scene, train, test) and not is_not_run(r)]
                means = _diagnose_means(runs)
                ticks.append(x)
                if means is None or "ours" not in means:
                    labels.append(f"{m}\n{'failed' if runs and all(r['status'] != 'ok' for r in runs) else 'no data'}")
                    continue
                labels.append(f"{m}\n{means['ours']:.1f} dB")
                for k, (key, label, colour, hatch) in enumerate(DIAGNOSE_GAINS):
                    if key in means:
                        ax.bar(x + (k - (len(DIAGNOSE_GAINS) - 1) / 2) * width, means[key] - means["ours"], width,
                               color=colour, hatch=hatch, edgecolor="white" if not hatch else "0.95", lw=0.5)
            centre = i * (len(methods) + 0.5) + (len(methods) - 1) / 2
            ax.annotate(scene, xy=(centre, 0), xycoords=("data", "axes fraction"), xytext=(0, -30),
                        textcoords="offset points", ha="center", va="top", fontsize=10, fontweight="bold")
            if i:
                ax.axvline(i * (len(methods) + 0.5) - 0.75, color="0.8", lw=0.8)
        ax.axhline(0, color="0.3", lw=0.8)
        ax.set_xticks(ticks, labels, fontsize=8)
        ax.set_xlim(-0.6, ticks[-1] + 0.6 if ticks else 0.6)
        ax.set_ylabel("PSNR gain over ours (dB)")
        ax.set_title(f"{train} → {test}", fontsize=10)
        ax.grid(alpha=0.3, axis="y")
    handles = [Patch(facecolor=c, hatch=h, edgecolor="0.95" if h else c, label=l) for _, l, c, h in DIAGNOSE_GAINS]
    fig.legend(handles=handles, loc="outside right upper", fontsize=8, title="bar: PSNR gain with", title_fontsize=8)
    used = sorted({(r["diagnose"]["views"], r["diagnose"]["dirs"]) for r in diag})
    seeds = len({r["seed"] for r in diag})
    note = ("ours: our albedo (scaled as the lumimotion protocol scales it), roughness and normals, with our traced "
            "shadows; GT: the ground truth's buffer where it has a surface. "
            + "; ".join(f"{v} test views, {d} directions per pixel" for v, d in used)
            + (f"; mean over {seeds} seeds" if seeds > 1 else "") + ".")
    _figure_notes(fig, ["\n" + textwrap.fill(note, int(fig_w * 15)), _not_run_note(results)])
    return _save(fig, path)


def all_charts(results: Sequence[dict], out_dir: Path) -> dict[str, Path]:
    out_dir = Path(out_dir)
    charts = {
        "pareto": pareto_chart(results, out_dir / "pareto.png"),
        "gaussians": gaussians_chart(results, out_dir / "quality_vs_gaussians.png"),
        "stability": stability_chart(results, out_dir / "stability.png"),
    }
    if has_conditions(results):
        charts["conditions"] = conditions_chart(results, out_dir / "conditions.png")
    if has_diagnose(results):
        charts["relight_error_sources"] = relight_error_sources_chart(results, out_dir / "relight_error_sources.png")
    return charts
