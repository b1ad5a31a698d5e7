"""report.html: one self-contained page (relative links) with the tables (one per protocol, each stating it),
charts and image grids (of the primary protocol), and failures."""
from __future__ import annotations

import html
import os
from pathlib import Path
from typing import Any, Sequence

from lumibench.io import atomic_write_text

from .aggregate import Group, ProtocolTable, best_methods, is_not_run
from .results import now_iso
from .tables import (DASH, _cell, _cell_text, _columns, _configurations, _method, _pretty, _runs, caption,
                     protocol_heading, reference_index)

_CSS = """
body{font-family:system-ui,sans-serif;margin:24px;color:#222;max-width:1400px}
table{border-collapse:collapse;font-size:13px;margin-bottom:18px}
th,td{border:1px solid #ccc;padding:3px 7px;text-align:right} td{white-space:nowrap}
th{background:#f0f0f0} td:first-child,th:first-child{text-align:left}
td.best{font-weight:bold;background:#e8f5e9} tr.conf td{background:#fafafa;font-weight:bold;text-align:center}
.fail{color:#b00} img{max-width:100%;border:1px solid #ddd;margin:6px 0}
.grids img{max-width:560px} code{background:#f4f4f4;padding:1px 3px}
"""


def _rel(path: Path, base: Path) -> str:
    return html.escape(os.path.relpath(path, base).replace(os.sep, "/"))


def html_table(groups: Sequence[Group]) -> str:
    cols = _columns(groups)
    spans: list[list[Any]] = []
    for c in cols:
        if spans and spans[-1][0] == c.group:
            spans[-1][1] += 1
        else:
            spans.append([c.group, 1])
    out = ["<table>", "<tr><th rowspan=2>Method</th>" +
           "".join(f"<th colspan={k}>{html.escape(g)}</th>" for g, k in spans) + "<th rowspan=2>Runs</th></tr>",
           "<tr>" + "".join(f"<th>{html.escape(c.label)} {'↑' if c.higher_better else '↓'}</th>" for c in cols)
           + "</tr>"]
    for conf in _configurations(groups):
        out.append(f"<tr class=conf><td colspan={len(cols) + 2}>{html.escape(_pretty(conf))}</td></tr>")
        bold = {c.key: best_methods(list(groups), conf, c) for c in cols}
        for g in [g for g in groups if g.configuration == conf]:
            cells = []
            for c in cols:
                cell = _cell(g, c)
                if cell is None:
                    cells.append(f"<td>{DASH}</td>")
                else:
                    cls = " class=best" if g.method in bold[c.key] else ""
                    cells.append(f"<td{cls}>{cell[0]} ± {cell[1]}</td>")
            runs = html.escape(_runs(g))
            runs = f"<span class=fail>{runs}</span>" if g.n_failed else runs
            out.append(f"<tr><td>{html.escape(g.method)}</td>{''.join(cells)}<td>{runs}</td></tr>")
    out.append("</table>")
    return "\n".join(out)


def reference_table(reference: Sequence[Group]) -> str:
    """The published rows, per configuration of the paper, in italics: never bold, never in our means."""
    cols = _columns(reference)
    out = ["<table>", "<tr><th>Method</th>" + "".join(
        f"<th>{html.escape(c.group)} {html.escape(c.label)} {'↑' if c.higher_better else '↓'}</th>" for c in cols)
        + "</tr>"]
    for conf in _configurations(reference):
        out.append(f"<tr class=conf><td colspan={len(cols) + 1}>{html.escape(_pretty(conf))}</td></tr>")
        for g in [g for g in reference if g.configuration == conf]:
            cells = "".join(f"<td>{html.escape(_cell_text(g, c) or DASH)}</td>" for c in cols)
            out.append(f"<tr><td><i>{html.escape(_method(g))}</i></td>{cells}</tr>")
    out.append("</table>")
    return "\n".join(out)


def _failure_items(results: Sequence[dict]) -> list[str]:
    """One line per failed run, its protocols joined (a run that failed fails under each protocol)."""
    seen: dict[tuple, list[str]] = {}
    for r in results:
        key = (r["method"], r["scene"], r["train_light"], r["test_light"], r["seed"], str(r.get("error")))
        seen.setdefault(key, []).append(r["protocol"])
    return [f"{html.escape(m)} {html.escape(sc)} {html.escape(tr)} → {html.escape(te)} seed {seed} "
            f"[{html.escape(', '.join(ps))}]: {html.escape(err)}" for (m, sc, tr, te, seed, err), ps in seen.items()]


def write_report(path: Path, ptables: Sequence[ProtocolTable], results: Sequence[dict],
                 charts: dict[str, Path], grids: Sequence[Path], tables: dict[str, Path],
                 title: str = "LumiBench results", reference: Sequence[Group] = ()) -> Path:
    base = Path(path).parent
    primary = ptables[0]
    failed = [r for r in results if r["status"] != "ok" and not is_not_run(r)]
    runs = primary.results  # a run is counted once, under the primary protocol
    n_failed = sum(1 for r in runs if r["status"] != "ok" and not is_not_run(r))
    n_not_run = sum(1 for r in runs if is_not_run(r))
    names = [t.protocol for t in ptables]
    mc = primary.meta.get("metric_config") or {}
    weights = mc.get("lpips_weights") or {}
    parts = [f"<!doctype html><html><head><meta charset=utf-8><title>{html.escape(title)}</title>",
             f"<style>{_CSS}</style></head><body>", f"<h1>{html.escape(title)}</h1>",
             f"<p>LPIPS weights: <code>{html.escape(str(weights.get('file', '?')))}</code> from "
             f"<code>{html.escape(str(weights.get('package', '?')))}</code>, sha256 "
             f"<code>{html.escape(str(weights.get('sha256', '?')))}</code>. "
             f"{len(runs) - n_not_run} runs, {n_failed} failed"
             + (f", {n_not_run} jobs of methods not run here (not failures)" if n_not_run else "")
             + (f"; each scored under {len(names)} protocols ({', '.join(names)}) from the same predictions, one "
                f"table each; charts and image grids use the primary protocol, {primary.protocol}"
                if len(names) > 1 else "")
             + f". Generated {now_iso()}.</p>",
             "<p>Tables: " + ", ".join(f"<a href='{_rel(p, base)}'>{html.escape(p.name)}</a>"
                                       for p in tables.values()) + "</p>"]
    at = reference_index(ptables)
    for i, t in enumerate(ptables):
        heading = "Table" if len(ptables) == 1 else f"Table: {protocol_heading(t, len(ptables))}"
        parts += [f"<h2 id='table-{html.escape(t.protocol)}'>{html.escape(heading)}</h2>",
                  f"<p>{html.escape(caption(t.meta, t.groups, reference if i == at else ()))}</p>",
                  html_table(t.groups)]
    if reference:
        parts += ["<h2>Published numbers (reference, on the paper's own dataset and lights)</h2>",
                  "<p>As published, under the paper's code's conventions (those of the <code>lumimotion</code> "
                  "protocol); not our runs, not comparable row for row with the tables above.</p>",
                  reference_table(reference)]
    if failed:
        parts += ["<h2 class=fail>Failed runs</h2>", "<ul>"]
        parts += [f"<li class=fail>{item}</li>" for item in _failure_items(failed)]
        parts.append("</ul>")
    charts = dict(charts)
    sources = charts.pop("relight_error_sources", None)
    thesis_png = charts.pop("thesis", None)
    if thesis_png is not None:
        md = tables.get("thesis.md")
        parts += ["<h2>Dynamic against static capture</h2>",
                  "<p>The question the benchmark was built for: LumiMotion trained on the dynamic capture against the "
                  "same pipeline trained on the static capture, per scene (bars: the change of the seed means) and "
                  "over scenes (whisker: std over scenes); the paper's claims as dashed lines"
                  + (f"; every metric, per scene, with seeds: <a href='{_rel(md, base)}'>{html.escape(md.name)}</a>"
                     if md is not None else "") + ".</p>",
                  f"<a href='{_rel(thesis_png, base)}'><img src='{_rel(thesis_png, base)}' "
                  f"alt='dynamic against static capture'></a>"]
    parts.append("<h2>Charts</h2>")
    if len(ptables) > 1:
        parts.append(f"<p>Scored under the primary protocol, <code>{html.escape(primary.protocol)}</code>.</p>")
    for name, p in charts.items():
        parts.append(f"<h3>{html.escape(name)}</h3><a href='{_rel(p, base)}'><img src='{_rel(p, base)}' "
                     f"alt='{html.escape(name)}'></a>")
    if sources is not None:
        parts += ["<h2>Where the relight error comes from</h2>",
                  "<p>Each method's test views relit under the test light with, in turn, its albedo, roughness "
                  "and normals replaced by the ground truth (then all three), and with its traced shadows dropped "
                  "(V = 1): a bar is the relight PSNR gained by that step over the method's own relight "
                  "(<code>python -m method diagnose</code>, scored as the <code>lumimotion</code> protocol "
                  "scores relight), so a tall bar names where the error comes from and a negative shadow bar "
                  "says the method's shadows are better than none.</p>",
                  f"<a href='{_rel(sources, base)}'><img src='{_rel(sources, base)}' "
                  f"alt='where the relight error comes from'></a>"]
    if grids:
        parts.append("<h2>Ground truth vs prediction</h2><div class=grids>")
        parts += [f"<a href='{_rel(p, base)}'><img src='{_rel(p, base)}' alt='{html.escape(p.stem)}'></a>"
                  for p in grids]
        parts.append("</div>")
    parts += ["<h2>Per-run result files</h2>", "<ul>"]
    for r in results:
        rp = Path(r.get("_path", ""))
        status = ("ok" if r["status"] == "ok" else "not run" if is_not_run(r)
                  else "<span class=fail>failed</span>")
        parts.append(f"<li><a href='{_rel(rp, base)}'>{html.escape(r['method'])} / {html.escape(r['scene'])} / "
                     f"{html.escape(r['train_light'])}→{html.escape(r['test_light'])} / seed {r['seed']} / "
                     f"{html.escape(r['protocol'])}</a> {status}</li>")
    parts += ["</ul>", "</body></html>"]
    atomic_write_text(path, "\n".join(parts))
    return Path(path)
