"""`python -m benchmark check-report [REPORT] [--screenshot PNG]`: open a report in headless Chromium and list
what a reader would find broken (images that do not load, console errors); exit 1 if anything is."""
from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "check-report",
        help="open report.html in headless Chromium: broken images, console errors, a screenshot",
        description="Load a report in headless Chromium (Debian's `chromium` package, or $LUMIBENCH_CHROMIUM), "
        "list every image that does not load and every console error, and optionally save a full-page "
        "screenshot. Exit 1 when anything is broken.",
    )
    p.add_argument("report", nargs="?", default="results/ci/report.html", help="the report (default: %(default)s)")
    p.add_argument("--screenshot", metavar="PNG", help="write a full-page screenshot here")


def run(args: argparse.Namespace) -> int:
    from benchmark.browser_check import check_page

    res = check_page(args.report, screenshot=args.screenshot)
    print(f"{args.report}: {len(res.images)} images, {len(res.images) - len(res.broken_images)} loaded")
    for src in res.broken_images:
        print(f"  broken image: {src}")
    for err in res.console_errors:
        print(f"  {err}")
    if res.screenshot:
        print(f"screenshot: {res.screenshot}")
    return 0 if res.ok else 1
