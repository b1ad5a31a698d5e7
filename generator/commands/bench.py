"""`python -m generator bench` (`make bench`): rendering speed per profile, persistent data and JOBS gains,
projected hours for the five scenes; writes a JSON file and prints the tables BENCHMARKS.md quotes."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="measure rendering speed and project dataset rendering hours",
                       description="Seconds per frame (ground-truth and lit pass) at ci, small and full; the gain "
                                   "from persistent data and JOBS=2; projected hours for the five scenes.")
    p.add_argument("--out", default="bench/generator.json", help="JSON output (default bench/generator.json)")


def run(args: argparse.Namespace) -> int:
    from generator.render_bench import markdown, run_bench
    from lumibench.errors import UserError
    from lumibench.io import atomic_write_json

    out = Path(args.out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create {out.parent}: {exc.strerror or exc}") from None
    doc = run_bench(out, progress_print=lambda msg: print(msg, file=sys.stderr, flush=True))
    atomic_write_json(out, doc)
    print(markdown(doc))
    print(f"wrote {out}")
    return 0
