"""Everything `make eval` shows, built from stored result files: tables, charts, image grids, report.

Results of several protocols (a grid's ``protocols``) give one table per protocol in table.md, table.tex,
table.csv and report.html, primary protocol first; charts and image grids are drawn from the primary
protocol's results (their titles name it). Nothing here scores: rebuilding reads result files only."""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Iterable, Sequence

from lumibench.errors import UserError
from lumibench.io import atomic_write_text

from . import budget, charts, tables, thesis
from .aggregate import load_results, protocol_tables, published_reference
from .grids import image_grid
from .report import write_report
from .score import predictions_hash


def build_outputs(result_paths: Iterable[str | Path], out_dir: str | Path, title: str = "LumiBench results",
                  grids: bool = True, published: bool = True,
                  protocols: Sequence[str] | None = None) -> dict[str, Path]:
    """Write table.md/.tex/.csv, charts, grids/ and report.html into ``out_dir``; return their paths.

    ``protocols``: the order of the per-protocol tables, the first being the primary one (charts, image
    grids); protocols present in the results but not named follow (lumimotion before strict).
    ``published``: append the paper's published rows (its own dataset and lights) to the lumimotion table
    (else the primary one) as labelled reference sections, never mixed into our means."""
    out = Path(out_dir)
    results = load_results(result_paths)
    if not results:
        raise UserError("no result files to build tables from")
    ptables = protocol_tables(results, protocols)
    primary = ptables[0].results
    written = {
        "table.md": out / "table.md", "table.tex": out / "table.tex", "table.csv": out / "table.csv",
    }
    reference = published_reference() if published else []
    atomic_write_text(written["table.md"], tables.markdown_tables(ptables, reference=reference))
    atomic_write_text(written["table.tex"], tables.latex_tables(ptables, reference=reference))
    atomic_write_text(written["table.csv"], tables.csv_tables(ptables, reference=reference))
    chart_paths = charts.all_charts(primary, out)
    thesis_paths = thesis.write(primary, out, ptables[0].protocol)  # dynamic against static, when both ran
    written.update({k: v for k, v in thesis_paths.items() if k.endswith(".md")})
    if "thesis.png" in thesis_paths:
        chart_paths["thesis"] = thesis_paths["thesis.png"]
    written.update(budget.write(primary, out, ptables[0].protocol))  # speed against accuracy, when variants ran
    grid_paths = []
    seen = set()
    for r in primary:  # one grid per (method, scene, configuration): the lowest seed that succeeded
        key = (r["method"], r["scene"], r["train_light"], r["test_light"])
        if r["status"] != "ok" or key in seen:
            continue
        seen.add(key)
        name = f"{r['method']}_{r['scene']}_{r['train_light']}_to_{r['test_light']}_seed{r['seed']}.png"
        target = out / "grids" / name
        scored = r["inputs"].get("pred_meta_sha256")
        if not grids or not Path(r["inputs"]["pred_dir"]).is_dir() or (
                scored and predictions_hash(Path(r["inputs"]["pred_dir"])) != scored):
            # Not drawn now (grids=False, or the tables are rebuilt from result files alone: a grid of other
            # machines' runs, runs/ cleaned, or another run's predictions in that folder now): the report
            # keeps a grid drawn earlier, and never fails for a missing one.
            if target.is_file():
                grid_paths.append(target)
            elif grids:
                print(f"note: no image grid for {name[:-4]}: the predictions it scored are not here "
                      f"({r['inputs']['pred_dir']})", file=sys.stderr)
            continue
        grid_paths.append(image_grid(r, target))
    report = write_report(out / "report.html", ptables, results, chart_paths, grid_paths,
                          {k: v for k, v in written.items()}, title, reference=reference)
    return {**written, **{v.name: v for v in chart_paths.values()}, "report.html": report,
            **{f"grids/{p.name}": p for p in grid_paths}}
