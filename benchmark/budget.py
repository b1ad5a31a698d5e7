"""Speed against accuracy and model size for one method run at several budgets (issue 26): which variant to
run at a given training time, and the smallest model within a tolerance of the largest.

A method's budget variants are its runs under ``<method>@<budget>`` (baselines_adapters: a fraction of the
iterations, ``@0.25``; a Gaussian cap, ``@cap10000``; or both), the plain name being the full budget. Variants
that keep a share of the training frames (``@frames0.25``) change the data, not the cost, and are left out.
Per configuration, every variant is averaged over the same scenes (those on which all of them have a
successful run; the others are named), each scene weighted alike (the mean of its seeds' mean), so a
variant's mean is never over easier scenes than another's. The recommendation is the Pareto front of training time against relight PSNR: at a time budget
T, run the front's best variant whose mean time is at most T. Built from result files only.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from lumibench.io import atomic_write_text

from .aggregate import gaussian_count, metric_value, training_clock

TOLERANCE_DB = 0.3  # issue 26: "the smallest model within 0.3 dB of the largest" (relight PSNR)
KEY = "relight.psnr"  # the quality the recommendation ranks by (higher is better)
COLUMNS = (("nvs.psnr", "NVS PSNR", 2), ("albedo.psnr", "albedo PSNR", 2), ("albedo.lpips", "albedo LPIPS", 3),
           (KEY, "relight PSNR", 2), ("relight.lpips", "relight LPIPS", 3))


def family(method: str) -> str:
    return method.split("@", 1)[0]


def is_budget_variant(method: str) -> bool:
    """The plain method or a variant at an iteration fraction and/or a Gaussian cap (not a share of frames)."""
    return "@" not in method or not any(p.strip().startswith("frames") for p in method.split("@", 1)[1].split("+"))


def _mean(values: Sequence[float | None]) -> float | None:
    vals = [v for v in values if v is not None]
    return float(np.mean(vals)) if vals else None


def pareto_variants(points: dict[str, tuple[float | None, float | None]]) -> list[str]:
    """Names not dominated (another variant at most as slow and at least as good, one of them strictly),
    fastest first; variants without a time or a quality are never on the front."""
    have = {n: p for n, p in points.items() if p[0] is not None and p[1] is not None}
    front = [n for n, (t, q) in have.items()
             if not any((t2 <= t and q2 >= q) and (t2 < t or q2 > q) for m, (t2, q2) in have.items() if m != n)]
    return sorted(front, key=lambda n: have[n][0])


def smallest_within(variants: dict[str, dict], tolerance: float = TOLERANCE_DB) -> tuple[str, str] | None:
    """(the largest model, the smallest model whose relight PSNR is within ``tolerance`` dB of it), by mean
    Gaussian count; None when fewer than two variants report a count and the quality."""
    have = {n: v for n, v in variants.items() if v["gaussians"] is not None and v["metrics"].get(KEY) is not None}
    if len(have) < 2:
        return None
    largest = max(have, key=lambda n: (have[n]["gaussians"], have[n]["metrics"][KEY]))
    floor = have[largest]["metrics"][KEY] - tolerance
    ok = [n for n, v in have.items() if v["metrics"][KEY] >= floor]
    return largest, min(ok, key=lambda n: (have[n]["gaussians"], -have[n]["metrics"][KEY]))


def compare(results: Sequence[dict]) -> list[dict]:
    """One entry per (method family, configuration) with at least two budget variants: {family,
    configuration, scenes (those every variant ran), left_out (scenes some variant lacks), variants: {name:
    {runs, seconds, gaussians, metrics: {key: mean}, per_scene: {scene: relight PSNR}}} fastest first, front
    (names, fastest first), size: (largest, smallest within the tolerance) or None, clock: "CPU" when the
    seconds are CPU seconds (every run reports them), else "wall"}."""
    ok = [r for r in results if r["status"] == "ok" and is_budget_variant(r["method"])]
    out = []
    for fam in sorted({family(r["method"]) for r in ok}):
        for conf in sorted({(r["train_light"], r["test_light"]) for r in ok if family(r["method"]) == fam}):
            runs = [r for r in ok if family(r["method"]) == fam and (r["train_light"], r["test_light"]) == conf]
            names = sorted({r["method"] for r in runs}, key=lambda n: (n != fam, n))
            if len(names) < 2:
                continue
            scene_sets = [{r["scene"] for r in runs if r["method"] == n} for n in names]
            common = sorted(set.intersection(*scene_sets))
            left_out = sorted(set.union(*scene_sets) - set(common))
            if not common:
                continue
            variants = {}
            seconds, clock = training_clock([r for r in runs if r["scene"] in common])
            for n in names:
                rs = [r for r in runs if r["method"] == n and r["scene"] in common]

                def over_scenes(value) -> float | None:  # the mean over scenes of each scene's seed mean
                    return _mean([_mean([value(r) for r in rs if r["scene"] == s]) for s in common])

                variants[n] = {
                    "runs": len(rs),
                    "seconds": over_scenes(seconds),
                    "gaussians": over_scenes(gaussian_count),
                    "metrics": {k: over_scenes(lambda r, k=k: metric_value(r, k)) for k, _, _ in COLUMNS},
                    "per_scene": {s: _mean([metric_value(r, KEY) for r in rs if r["scene"] == s]) for s in common},
                }
            variants = dict(sorted(variants.items(), key=lambda kv: (kv[1]["seconds"] is None, kv[1]["seconds"] or 0.0)))
            front = pareto_variants({n: (v["seconds"], v["metrics"][KEY]) for n, v in variants.items()})
            out.append({"family": fam, "configuration": conf, "clock": clock, "scenes": common, "left_out": left_out,
                        "variants": variants, "front": front, "size": smallest_within(variants)})
    return out


def _num(v: float | None, digits: int) -> str:
    return "–" if v is None else f"{v:.{digits}f}"


def _time(seconds: float | None) -> str:
    if seconds is None:
        return "–"
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.1f} min"


def markdown(comparisons: Sequence[dict], protocol: str | None = None) -> str:
    lines = ["# Speed against accuracy: budget variants", "",
             f"Protocol: {protocol or '?'}. Each variant's mean over the scenes every variant ran (of each scene's mean over its seeds); "
             f"training time is the sum of the reported stages, in CPU seconds (all threads) where every run "
             f"reports them, which a loaded machine does not inflate, else in wall seconds. On the front: no "
             f"other variant is at most as slow and at least as good in relight PSNR. At a time budget T, run the "
             f"front's last variant whose time is "
             f"at most T. Model size: the smallest model whose relight PSNR is within {TOLERANCE_DB} dB of the "
             f"largest model's."]
    for c in comparisons:
        train, test = c["configuration"]
        lines += ["", f"## {c['family']}, {train} → {test}", "",
                  f"Scenes: {', '.join(c['scenes'])}" + (f" (left out, not run by every variant: "
                                                         f"{', '.join(c['left_out'])})" if c["left_out"] else "") + ".",
                  "", f"| variant | runs | training time ({c['clock']}) | Gaussians | "
                  + " | ".join(label for _, label, _ in COLUMNS)
                  + " | " + " | ".join(f"{s} relight PSNR" for s in c["scenes"]) + " | on the front |",
                  "|:--|--:|--:|--:|" + "--:|" * (len(COLUMNS) + len(c["scenes"])) + ":-:|"]
        for n, v in c["variants"].items():
            cells = [_num(v["metrics"][k], d) for k, _, d in COLUMNS]
            scenes = [_num(v["per_scene"][s], 2) for s in c["scenes"]]
            g = "–" if v["gaussians"] is None else f"{v['gaussians']:,.0f}"
            lines.append(f"| {n} | {v['runs']} | {_time(v['seconds'])} | {g} | " + " | ".join(cells + scenes)
                         + f" | {'yes' if n in c['front'] else ''} |")
        if c["front"]:
            lines += ["", "At a time budget of:"]
            for i, n in enumerate(c["front"]):
                v = c["variants"][n]
                upto = (f" (under {_time(c['variants'][c['front'][i + 1]]['seconds'])})" if i + 1 < len(c["front"])
                        else "")
                lines.append(f"- from {_time(v['seconds'])}{upto}: **{n}** (relight PSNR "
                             f"{_num(v['metrics'][KEY], 2)} dB)")
        if c["size"]:
            largest, small = c["size"]
            vl, vs = c["variants"][largest], c["variants"][small]
            if small == largest:
                lines += ["", f"Model size: no smaller variant is within {TOLERANCE_DB} dB of the largest, {largest} "
                              f"({vl['gaussians']:,.0f} Gaussians, {_num(vl['metrics'][KEY], 2)} dB)."]
            else:
                lines += ["", f"Model size: **{small}** ({vs['gaussians']:,.0f} Gaussians, "
                              f"{_num(vs['metrics'][KEY], 2)} dB) is within {TOLERANCE_DB} dB of the largest, "
                              f"{largest} ({vl['gaussians']:,.0f} Gaussians, {_num(vl['metrics'][KEY], 2)} dB)."]
    return "\n".join(lines) + "\n"


def write(results: Sequence[dict], out_dir: Path, protocol: str | None = None) -> dict[str, Path]:
    """budget.md in ``out_dir`` when some method has two or more budget variants; {} otherwise."""
    comps = compare(results)
    if not comps:
        return {}
    path = Path(out_dir) / "budget.md"
    atomic_write_text(path, markdown(comps, protocol))
    return {"budget.md": path}
