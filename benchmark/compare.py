"""Two results folders side by side, job by job: what a change to a method did to each run it retrained.

Why: a change is judged on the runs it retrained against the same jobs before it (same method, scene,
train -> test light, seed, protocol), not on means over different sets of runs. Result files are matched by
that identity; jobs present on one side only are listed, never averaged in. Nothing is scored here."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from lumibench.errors import UserError

from .aggregate import COLUMNS, EXTRA_COLUMNS, Column, load_results, metric_value, training_seconds
from .jobgrid import stored_results

COMPARED = ("nvs.psnr", "nvs_moving.gap_db", "separation.balanced_accuracy", "albedo.psnr", "albedo.lpips",
            "roughness.mse", "relight.psnr", "relight.lpips")
TIME = Column("time.seconds", "Time", "training s", False, 0)
_BY_KEY = {c.key: c for c in COLUMNS + EXTRA_COLUMNS + (TIME,)}


def identity(result: dict[str, Any]) -> tuple:
    return (result["method"], result["scene"], result["train_light"], result["test_light"], int(result["seed"]),
            result["protocol"])


def value(result: dict[str, Any], key: str) -> float | None:
    return training_seconds(result) if key == TIME.key else metric_value(result, key)


@dataclass
class Comparison:
    pairs: list[tuple[dict, dict]]          # (old, new), both ok, sorted by identity
    failed: list[tuple[tuple, str]]         # (identity, "old" / "new" / "both") where a side did not succeed
    only_old: list[tuple]
    only_new: list[tuple]
    keys: tuple[str, ...]

    def summary(self, key: str) -> tuple[float, int, int] | None:
        """(mean of new - old, how many pairs improved, how many pairs have the metric on both sides)."""
        col = _BY_KEY[key]
        d = [(value(n, key), value(o, key)) for o, n in self.pairs]
        d = [b - a for b, a in d if b is not None and a is not None]
        if not d:
            return None
        better = sum(1 for x in d if (x > 0) == col.higher_better and x != 0)
        return sum(d) / len(d), better, len(d)


def compare(old_dir: str | Path, new_dir: str | Path, methods: Sequence[str] | None = None,
            protocol: str = "lumimotion", keys: Sequence[str] = COMPARED + (TIME.key,)) -> Comparison:
    """Match the result files stored under ``old_dir``/runs and ``new_dir``/runs (results folders of one
    profile) for ``protocol``, optionally for some methods only."""
    unknown = [k for k in keys if k not in _BY_KEY]
    if unknown:
        raise UserError(f"unknown metric {unknown[0]!r} (known: {', '.join(_BY_KEY)})")
    sides = []
    for d in (old_dir, new_dir):
        if not Path(d, "runs").is_dir():
            raise UserError(f"{d}: no runs/ folder of result files (a results folder, e.g. results/small)")
        rs = [r for r in load_results(stored_results(Path(d))) if r["protocol"] == protocol
              and (not methods or r["method"] in methods)]
        sides.append({identity(r): r for r in rs})
    old, new = sides
    pairs, failed = [], []
    for ident in sorted(set(old) & set(new)):
        o, n = old[ident], new[ident]
        if o["status"] == "ok" and n["status"] == "ok":
            pairs.append((o, n))
        else:
            failed.append((ident, "both" if o["status"] != "ok" and n["status"] != "ok" else
                           ("old" if o["status"] != "ok" else "new")))
    return Comparison(pairs, failed, sorted(set(old) - set(new)), sorted(set(new) - set(old)), tuple(keys))


def _fmt(x: float | None, digits: int) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def markdown(c: Comparison, old_label: str = "old", new_label: str = "new") -> str:
    """One row per matched job, each cell ``old -> new``; then the mean change over the pairs and how many
    improved (direction-aware: lower is better for LPIPS, MSE, the moving gap and time)."""
    cols = [_BY_KEY[k] for k in c.keys]
    head = ["method", "scene", "train -> test", "seed"] + [f"{k.group if k.group != 'Novel View Synthesis' else 'NVS'} "
                                                         f"{k.label} {'↑' if k.higher_better else '↓'}" for k in cols]
    lines = [f"{old_label} -> {new_label}, protocol {c.pairs[0][0]['protocol'] if c.pairs else '?'}: "
             f"{len(c.pairs)} jobs on both sides", "", "| " + " | ".join(head) + " |",
             "|" + "|".join(":--" if i < 4 else "--:" for i in range(len(head))) + "|"]
    for o, n in c.pairs:
        cells = [o["method"], o["scene"], f"{o['train_light']} -> {o['test_light']}", str(o["seed"])]
        for k in cols:
            cells.append(f"{_fmt(value(o, k.key), k.digits)} -> {_fmt(value(n, k.key), k.digits)}")
        lines.append("| " + " | ".join(cells) + " |")
    if c.pairs:
        cells = ["mean change", "", "", ""]
        for k in cols:
            s = c.summary(k.key)
            cells.append("–" if s is None else f"{s[0]:+.{k.digits}f} (better {s[1]} of {s[2]})")
        lines.append("| " + " | ".join(cells) + " |")
    for ident, side in c.failed:
        lines.append(f"\nnot compared, failed on {side} side(s): {' '.join(map(str, ident[:5]))}")
    for name, ids in ((old_label, c.only_old), (new_label, c.only_new)):
        if ids:
            lines.append(f"\nonly in {name} ({len(ids)}): " + "; ".join(" ".join(map(str, i[:5])) for i in ids))
    return "\n".join(lines) + "\n"
