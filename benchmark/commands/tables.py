"""`python -m benchmark tables [DIR]`: rebuild a results folder's tables, charts and report from its stored
result files alone, without the dataset, the runs or a grid YAML (results from another machine, a
committed `results/<profile>/`, or a grid whose runs were cleaned)."""
from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "tables",
        help="rebuild tables, charts and report.html from the result files stored under a results folder",
        description="Read every result file under DIR/runs and write DIR/table.md/.tex/.csv, thesis.md, the "
        "charts and report.html, as `eval` does after a grid; nothing is trained or scored. Image grids "
        "are redrawn only where the scored predictions are still on this machine.",
    )
    p.add_argument("results", nargs="?", default="results/ci", metavar="DIR",
                   help="a profile's results folder, holding runs/ (default: %(default)s)")
    p.add_argument("--protocols", "--protocol", nargs="+", metavar="PROTOCOL",
                   help="the tables' order, the first being the primary one (default: lumimotion, then strict)")
    p.add_argument("--title", help="the report's title (default: named after the folder)")
    p.add_argument("--no-grids", action="store_true", help="do not redraw image grids")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from benchmark.jobgrid import stored_results
    from benchmark.outputs import build_outputs
    from benchmark.protocol import PROTOCOLS
    from lumibench.errors import UserError

    out = Path(args.results)
    if not out.is_dir():
        raise UserError(f"{out}: no such results folder (a profile's, e.g. results/small)")
    for p in args.protocols or []:
        if p not in PROTOCOLS:
            raise UserError(f"--protocols: unknown protocol '{p}' (known: {', '.join(PROTOCOLS)})")
    stored = stored_results(out)
    if not stored:
        raise UserError(f"{out}: no result files under {out / 'runs'} (run `python -m benchmark eval` first)")
    written = build_outputs(stored, out, title=args.title or f"LumiBench results: profile {out.name}",
                            grids=not args.no_grids, protocols=args.protocols)
    print(f"{len(stored)} result files; wrote {out}/: " + ", ".join(k for k in written if not k.startswith("grids/")))
    return 0
