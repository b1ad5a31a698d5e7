"""Tables in Markdown, LaTeX and CSV laid out like the paper's supplementary table (its Table 1 columns).

Rows are grouped by train -> test configuration; columns are NVS, albedo and relight PSNR / SSIM /
LPIPS, roughness MSE and the PSNR drop from NVS to relight (percent of the NVS PSNR, lower is better).
Cells are mean +- std over scenes and seeds; the best mean per configuration and column is bold, in the
metric's direction; a method without a task shows "–". Every table states its protocol and metric
configuration, and the number of successful and failed runs per row.

Optional reference rows (``reference=``: groups from ``aggregate.reference_groups``, e.g. the paper's
published numbers) are listed after our rows of the same configuration, or in their own section when the
configuration is not ours; they are marked with their label ("published, on the paper's dataset"), show
their std only where one was published, are never bold and never enter our means. An external method
that has not been run shows "not run" in the Runs column (and under "Not run"), not as a failure.

A grid scored under several protocols gets one table per protocol (``markdown_tables``, ``latex_tables``,
``csv_tables``: same layout, each stating its protocol; the primary one first; the floors are rows of
each); the published reference rows go with the ``lumimotion`` table (the paper's code's conventions),
or with the primary one when there is none.
"""
from __future__ import annotations

import csv
import io
import math
from typing import Any, Sequence

from .aggregate import COLUMNS, EXTRA_COLUMNS, SHORT_GROUP, Column, Group, ProtocolTable, best_methods

DASH = "–"


def _configurations(groups: Sequence[Group]) -> list[str]:
    return list(dict.fromkeys(g.configuration for g in groups))


def _sections(groups: Sequence[Group], reference: Sequence[Group]) -> list[tuple[str, list[Group], list[Group]]]:
    """(configuration, our rows, reference rows): our configurations first, then reference-only ones."""
    confs = _configurations(list(groups) + list(reference))
    return [(c, [g for g in groups if g.configuration == c], [g for g in reference if g.configuration == c])
            for c in confs]


def _pretty(conf: str) -> str:
    train, test = conf.split("->")
    return f"{train} → {test}"


def _runs(g: Group) -> str:
    if g.reference:
        return "reference"
    n_not_run = len(getattr(g, "not_run", ()))
    if n_not_run and not g.n_ok and not g.n_failed:
        return "not run"
    return (f"{g.n_ok} ok" + (f", {g.n_failed} failed" if g.n_failed else "")
            + (f", {n_not_run} not run" if n_not_run else ""))


def _method(g: Group) -> str:
    return f"{g.method} ({g.reference})" if g.reference else g.method


def _cell_text(g: Group, col: Column) -> str | None:
    """"mean ± std", or the mean alone where a reference row has no published std."""
    cell = _cell(g, col)
    if cell is None:
        return None
    st = g.stats[col.key]
    return cell[0] if math.isnan(st.std) else f"{cell[0]} ± {cell[1]}"


def _fmt(value: float, digits: int) -> str:
    text = f"{value:.{digits}f}"
    return text[1:] if text.startswith("-") and float(text) == 0 else text  # no "-0.0"


def _cell(g: Group, col: Column) -> tuple[str, str] | None:
    st = g.stats.get(col.key)
    if st is None:
        return None
    return _fmt(st.mean, col.digits), (DASH if math.isnan(st.std) else _fmt(st.std, col.digits))


def _columns(groups: Sequence[Group]) -> list[Column]:
    """The paper's columns, plus separation / normal columns when any method reports them."""
    extra = [c for c in EXTRA_COLUMNS if any(c.key in g.stats for g in groups)]
    return list(COLUMNS) + extra


def caption(meta: dict[str, Any], groups: Sequence[Group], reference: Sequence[Group] = ()) -> str:
    mc = meta.get("metric_config") or {}
    weights = (mc.get("lpips_weights") or {}).get("sha256", "?")
    scenes = sorted(set().union(*(g.scenes for g in groups))) if groups else []
    seeds = sorted(set().union(*(g.seeds for g in groups))) if groups else []
    return (f"Protocol: {meta.get('protocol')} ({mc.get('masking', '')}). LPIPS-{mc.get('lpips_net', '?')} "
            f"(weights sha256 {weights[:12]}). Albedo aligned by a per-channel median ratio in linear space. "
            f"Mean ± std over scenes ({', '.join(scenes)}) and seeds ({', '.join(map(str, seeds))}). "
            f"Best per configuration in bold. ΔPSNR = (NVS PSNR - relight PSNR) / NVS PSNR."
            + _reference_note(reference))


def _reference_note(reference: Sequence[Group]) -> str:
    labels = sorted({g.reference for g in reference if g.reference})
    return "".join(f" Rows marked \"{label}\" are reference numbers as published (not our runs, not comparable "
                   f"image for image, never in our means or bold)." for label in labels)


def markdown(groups: Sequence[Group], meta: dict[str, Any], reference: Sequence[Group] = ()) -> str:
    cols = _columns(groups)
    head = ["Method"] + [f"{SHORT_GROUP.get(c.group, c.group)} {c.label} {'↑' if c.higher_better else '↓'}"
                         for c in cols] + ["Runs"]
    lines = [f"**{caption(meta, groups, reference)}**", ""]
    for conf, rows, refs in _sections(groups, reference):
        bold = {c.key: best_methods(list(groups), conf, c) for c in cols}
        title = _pretty(conf) + ("" if rows else f" ({', '.join(sorted({g.reference for g in refs}))})")
        lines += [f"### {title}", "", "| " + " | ".join(head) + " |",
                  "|" + "|".join([":--"] + ["--:"] * (len(cols) + 1)) + "|"]
        for g in rows + refs:
            cells = [f"*{_method(g)}*" if g.reference else g.method]
            for c in cols:
                text = _cell_text(g, c)
                if text is None:
                    cells.append(DASH)
                    continue
                cells.append(f"**{text}**" if not g.reference and g.method in bold[c.key] else text)
            cells.append(_runs(g))
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    failed = [(g, f) for g in groups for f in g.failures]
    if failed:
        lines += ["### Failed runs", ""]
        lines += [f"- {g.method} {_pretty(g.configuration)} {f['scene']} seed {f['seed']}: {f['error']}"
                  for g, f in failed]
        lines.append("")
    not_run = [(g, f) for g in groups for f in getattr(g, "not_run", ())]
    if not_run:
        lines += ["### Not run", ""]
        lines += [f"- {g.method} {_pretty(g.configuration)} {f['scene']}: {f['error']}" for g, f in not_run]
        lines.append("")
    mixed = [g for g in groups if not g.reference and g.mixed_provenance()]
    if mixed:
        lines += ["### Rows that mix runs", "",
                  "Each row below averages runs of more than one adapter version or training setting (a stored "
                  "result is never recomputed; delete the stale ones' result files, or their runs, to redo them):", ""]
        lines += [f"- {g.method} {_pretty(g.configuration)}: " + "; ".join(
            f"version {v}, settings {h[:12] if h else 'not recorded'} on {', '.join(sorted(sc))}"
            for (v, h), sc in sorted(g.provenance.items(), key=lambda kv: (kv[0][0], kv[0][1] or ""))) for g in mixed]
        lines.append("")
    mixed_data = [(g, sc) for g in groups if not g.reference for sc in g.mixed_datasets()]
    if mixed_data:
        lines += ["### Rows that mix datasets", "",
                  "In each row below, a scene's runs were scored on more than one version of its dataset (the "
                  "generator's spec hash differs: re-render, then delete the older results to score them again):",
                  ""]
        lines += [f"- {g.method} {_pretty(g.configuration)}: {sc} (" + ", ".join(
            h[:12] for h in sorted(g.datasets[sc])) + ")" for g, sc in mixed_data]
        lines.append("")
    notes = [(g, n) for g in reference for n in getattr(g, "notes", ())]
    if notes:
        lines += ["### Notes on the reference rows", ""]
        lines += [f"- {g.method} {_pretty(g.configuration)}: {n}" for g, n in notes]
        lines.append("")
    return "\n".join(lines)


def _tex_escape(text: str) -> str:
    for a, b in (("\\", r"\textbackslash{}"), ("_", r"\_"), ("%", r"\%"), ("&", r"\&"), ("#", r"\#"),
                 ("$", r"\$"), ("{", r"\{"), ("}", r"\}"), ("→", r"$\rightarrow$"), ("±", r"$\pm$"),
                 ("Δ", r"$\Delta$"), ("°", r"$^\circ$")):
        text = text.replace(a, b)
    return text


def latex(groups: Sequence[Group], meta: dict[str, Any], reference: Sequence[Group] = (),
          label: str = "tab:lumibench") -> str:
    cols = _columns(groups)
    spans: list[tuple[str, int]] = []
    for c in cols:
        if spans and spans[-1][0] == c.group:
            spans[-1] = (c.group, spans[-1][1] + 1)
        else:
            spans.append((c.group, 1))
    n = len(cols) + 2
    out = [r"% generated by benchmark/tables.py; needs \usepackage{booktabs}",
           r"\begin{table*}", r"\centering", r"\small",
           r"\caption{" + _tex_escape(caption(meta, groups, reference)) + "}",
           r"\resizebox{\linewidth}{!}{",
           r"\begin{tabular}{l" + "c" * len(cols) + "c}", r"\toprule",
           r"\textbf{Method} & " + " & ".join(rf"\multicolumn{{{k}}}{{c}}{{\textbf{{{_tex_escape(name)}}}}}"
                                              for name, k in spans) + r" & Runs \\"]
    rules, start = [], 2
    for _, k in spans:
        rules.append(rf"\cmidrule(lr){{{start}-{start + k - 1}}}")
        start += k
    out.append(" ".join(rules))
    arrows = {True: r"$\uparrow$", False: r"$\downarrow$"}
    out.append(" & " + " & ".join(f"{_tex_escape(c.label)} {arrows[c.higher_better]}" for c in cols) + r" & \\")
    for conf, rows, refs in _sections(groups, reference):
        bold = {c.key: best_methods(list(groups), conf, c) for c in cols}
        out += [r"\midrule", rf"\multicolumn{{{n}}}{{c}}{{\textbf{{{_tex_escape(_pretty(conf))}}}}} \\", r"\midrule"]
        for g in rows + refs:
            cells = [rf"\textit{{{_tex_escape(_method(g))}}}" if g.reference else _tex_escape(g.method)]
            for c in cols:
                cell = _cell(g, c)
                if cell is None:
                    cells.append("--")
                elif g.reference and math.isnan(g.stats[c.key].std):
                    cells.append(rf"${cell[0]}$")
                elif not g.reference and g.method in bold[c.key]:
                    cells.append(rf"$\mathbf{{{cell[0]}}} \pm {cell[1]}$")
                else:
                    cells.append(rf"${cell[0]} \pm {cell[1]}$")
            cells.append(_tex_escape(_runs(g)))
            out.append(" & ".join(cells) + r" \\")
    out += [r"\bottomrule", r"\end{tabular}", "}", rf"\label{{{label}}}", r"\end{table*}", ""]
    return "\n".join(out)


def _csv_header(reference: bool) -> list[str]:
    header = ["protocol", "configuration", "method", "n_ok", "n_failed"]
    for key in [c.key for c in list(COLUMNS) + list(EXTRA_COLUMNS)] + list(_CSV_EXTRA):
        header += [f"{key}.mean", f"{key}.std", f"{key}.n"]
    return header + (["reference"] if reference else [])


_CSV_EXTRA = ("time.seconds", "model.gaussians")


def _csv_row(g: Group, protocol: str | None, reference: bool) -> list[Any]:
    row: list[Any] = [protocol if not g.reference else "", g.configuration, g.method, g.n_ok, g.n_failed]
    for key in [c.key for c in list(COLUMNS) + list(EXTRA_COLUMNS)] + list(_CSV_EXTRA):
        st = g.stats.get(key)
        if st is None:
            row += ["", "", 0]
        else:
            row += [f"{st.mean:.6g}", "" if math.isnan(st.std) else f"{st.std:.6g}", st.n]
    return row + ([g.reference or ""] if reference else [])


def csv_text(groups: Sequence[Group], meta: dict[str, Any], reference: Sequence[Group] = ()) -> str:
    """One row per (configuration, method): means, stds and counts, machine-readable (no bold).

    With reference rows, a last column "reference" holds their label (empty for our rows)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(_csv_header(bool(reference)))
    for g in list(groups) + list(reference):
        w.writerow(_csv_row(g, meta.get("protocol"), bool(reference)))
    return buf.getvalue()


# ------------------------------------------------------------------------------ one table per protocol

def reference_index(ptables: Sequence[ProtocolTable]) -> int:
    """Which table the published reference rows go with: ``lumimotion``'s, else the primary one."""
    return next((i for i, t in enumerate(ptables) if t.protocol == "lumimotion"), 0)


def protocol_heading(t: ProtocolTable, n_tables: int) -> str:
    return f"Protocol {t.protocol}" + (" (primary: charts and image grids)" if t.primary and n_tables > 1 else "")


def markdown_tables(ptables: Sequence[ProtocolTable], reference: Sequence[Group] = ()) -> str:
    """One Markdown table per protocol under a "## Protocol <name>" heading, primary first."""
    at = reference_index(ptables)
    parts = []
    for i, t in enumerate(ptables):
        parts += [f"## {protocol_heading(t, len(ptables))}", "",
                  markdown(t.groups, t.meta, reference=reference if i == at else ())]
    return "\n".join(parts)


def latex_tables(ptables: Sequence[ProtocolTable], reference: Sequence[Group] = ()) -> str:
    """One LaTeX table per protocol (label ``tab:lumibench-<protocol>``; a single one keeps ``tab:lumibench``)."""
    at = reference_index(ptables)
    return "\n".join(latex(t.groups, t.meta, reference=reference if i == at else (),
                           label="tab:lumibench" if len(ptables) == 1 else f"tab:lumibench-{t.protocol}")
                     for i, t in enumerate(ptables))


def csv_tables(ptables: Sequence[ProtocolTable], reference: Sequence[Group] = ()) -> str:
    """All protocols' rows in one CSV (the "protocol" column tells them apart), reference rows last."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(_csv_header(bool(reference)))
    for t in ptables:
        for g in t.groups:
            w.writerow(_csv_row(g, t.protocol, bool(reference)))
    for g in reference:
        w.writerow(_csv_row(g, None, True))
    return buf.getvalue()
