"""Everything `make eval` shows, built from stored result files: tables, charts, image grids, report."""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Iterable

from lumibench.errors import UserError
from lumibench.io import atomic_write_text

from . import charts, tables
from .aggregate import aggregate, check_consistent, load_results, published_reference
from .grids import image_grid
from .report import write_report


def build_outputs(result_paths: Iterable[str | Path], out_dir: str | Path, title: str = "LumiBench results",
                  grids: bool = True, published: bool = True) -> dict[str, Path]:
    """Write table.md/.tex/.csv, charts, grids/ and report.html into ``out_dir``; return their paths.

    ``published``: append the paper's published rows (its own dataset and lights) to the tables as
    labelled reference sections, never mixed into our means."""
    out = Path(out_dir)
    results = load_results(result_paths)
    if not results:
        raise UserError("no result files to build tables from")
    meta = check_consistent(results)
    groups = aggregate(results)
    written = {
        "table.md": out / "table.md", "table.tex": out / "table.tex", "table.csv": out / "table.csv",
    }
    reference = published_reference() if published else []
    atomic_write_text(written["table.md"], tables.markdown(groups, meta, reference=reference))
    atomic_write_text(written["table.tex"], tables.latex(groups, meta, reference=reference))
    atomic_write_text(written["table.csv"], tables.csv_text(groups, meta, reference=reference))
    chart_paths = charts.all_charts(results, out)
    grid_paths = []
    if grids:
        seen = set()
        for r in results:  # one grid per (method, scene, configuration): the lowest seed that succeeded
            key = (r["method"], r["scene"], r["train_light"], r["test_light"])
            if r["status"] != "ok" or key in seen:
                continue
            seen.add(key)
            name = f"{r['method']}_{r['scene']}_{r['train_light']}_to_{r['test_light']}_seed{r['seed']}.png"
            target = out / "grids" / name
            if not Path(r["inputs"]["pred_dir"]).is_dir():
                # The tables are rebuilt from result files alone (a grid of other machines' runs, or runs/
                # cleaned): keep the grid drawn when the predictions were here, and never fail for it.
                if target.is_file():
                    grid_paths.append(target)
                else:
                    print(f"note: no image grid for {name[:-4]}: its predictions are not here "
                          f"({r['inputs']['pred_dir']})", file=sys.stderr)
                continue
            grid_paths.append(image_grid(r, target))
    report = write_report(out / "report.html", groups, meta, results, chart_paths, grid_paths,
                          {k: v for k, v in written.items()}, title, reference=reference)
    return {**written, **{v.name: v for v in chart_paths.values()}, "report.html": report,
            **{f"grids/{p.name}": p for p in grid_paths}}
