"""`python -m benchmark compare OLD NEW`: two results folders job by job (benchmark/compare.py)."""
from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "compare",
        help="two results folders side by side, job by job, with the mean change",
        description="Match the result files of two results folders (e.g. before and after a change to a "
        "method) by method, scene, train -> test light, seed and protocol; print a markdown table with "
        "each job's scores on both sides and the mean change over the jobs found on both. Jobs on one side "
        "only are listed, not averaged in.",
    )
    p.add_argument("old", help="the results folder before (holding runs/), e.g. results/small")
    p.add_argument("new", help="the results folder after")
    p.add_argument("--methods", nargs="+", help="only these methods (default: all)")
    p.add_argument("--protocol", default="lumimotion", help="which protocol's results (default: %(default)s)")
    p.add_argument("--out", help="also write the table to this markdown file")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from benchmark.compare import compare, markdown
    from benchmark.protocol import PROTOCOLS
    from lumibench.errors import UserError
    from lumibench.io import atomic_write_text

    if args.protocol not in PROTOCOLS:
        raise UserError(f"--protocol: unknown protocol '{args.protocol}' (known: {', '.join(PROTOCOLS)})")
    c = compare(args.old, args.new, methods=args.methods, protocol=args.protocol)
    if not c.pairs and not c.failed:
        raise UserError(f"no job is in both {args.old} and {args.new} (protocol {args.protocol}"
                        + (f", methods {' '.join(args.methods)}" if args.methods else "") + ")")
    text = markdown(c, Path(args.old).as_posix(), Path(args.new).as_posix())
    print(text, end="")
    if args.out:
        atomic_write_text(args.out, text)
    return 0
