"""`python -m benchmark eval` (`make eval`): run or resume the grid, then build tables, charts, report."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("eval", help="run/resume the benchmark grid and build tables, charts and report.html",
                       description="Render missing scenes, run and score every (method, scene, configuration, "
                                   "seed) job not yet finished, each under every protocol of the grid from the same "
                                   "predictions, then write RESULTS/PROFILE/: per-run results.json (lumimotion) and "
                                   "results_<protocol>.json (others), then table.md/.tex/.csv (one table per protocol), "
                                   "charts and report.html from every result stored under RESULTS/PROFILE/runs "
                                   "(earlier grids' too: delete a result file to drop it).")
    p.add_argument("--profile", default="ci", help="grid configs/benchmark/<profile>.yaml (default ci)")
    p.add_argument("--config", default=None, help="a grid YAML to use instead of the profile's")
    p.add_argument("--data", default="data", help="dataset root (scenes at DATA/PROFILE/<scene>)")
    p.add_argument("--runs", default="runs", help="method runs root (predictions at RUNS/PROFILE/<method>/...)")
    p.add_argument("--results", default="results", help="output root (writes RESULTS/PROFILE/)")
    p.add_argument("--executor", default="local", choices=["local", "ray"],
                   help="local process pool, or Ray (RAY_ADDRESS honoured)")
    p.add_argument("--jobs", type=int, default=1, help="parallel jobs (default 1)")
    p.add_argument("--methods", nargs="+", default=None, help="override the grid's methods")
    p.add_argument("--scenes", nargs="+", default=None, help="override the grid's scenes")
    p.add_argument("--seeds", nargs="+", type=int, default=None, help="override the grid's seeds")
    p.add_argument("--protocols", "--protocol", dest="protocols", nargs="+", default=None,
                   choices=["lumimotion", "strict"], metavar="PROTOCOL",
                   help="override the grid's protocols, the first being the primary one (lumimotion, strict; "
                        "each has its own result files: nothing stored is re-scored)")
    p.add_argument("--no-render", action="store_true", help="fail instead of rendering missing scenes")
    p.add_argument("--no-grids", action="store_true", help="skip the GT-vs-prediction image grids")
    p.add_argument("--keep-going", action="store_true",
                   help="exit 0 even when jobs failed (by default: exit 1 after writing every table and chart; "
                        "make eval KEEP_GOING=1)")


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from baselines_adapters.base import is_not_run_message
    from benchmark.config import load_benchmark_config
    from benchmark.jobgrid import Paths, failure_summary, iter_results, job_label, method_jobs, run_grid, stored_results
    from benchmark.outputs import build_outputs
    from lumibench.errors import UserError

    if args.jobs < 1:
        raise UserError(f"--jobs must be >= 1, got {args.jobs}")
    config = load_benchmark_config(args.config or args.profile).with_methods(args.methods)
    if args.config is None and config.profile != args.profile:
        raise UserError(f"{config.source}: key 'profile' is '{config.profile}', expected '{args.profile}'")
    if args.scenes:
        config = replace(config, scenes=tuple(args.scenes))
    if args.seeds:
        config = replace(config, seeds=tuple(args.seeds))
    config = config.with_protocols(args.protocols)
    paths = Paths(Path(args.data), Path(args.runs), Path(args.results), config.profile)
    report = run_grid(config, paths, args.executor, args.jobs, render=not args.no_render)
    for job, outcome in report.failed:
        print(f"failed: {job_label(job)}: {outcome.get('error')}")
    # the tables show every result stored for the profile, this grid's and earlier grids' (stored_results)
    stored = stored_results(paths.out)
    ours = {p.resolve() for p in iter_results(method_jobs(config, paths)) if p.is_file()}
    if len(stored) > len(ours):
        print(f"tables from all {len(stored)} result files under {paths.out / 'runs'} "
              f"({len(ours)} of them from this grid)")
    written = build_outputs(stored, paths.out,
                            title=f"LumiBench results: profile {config.profile}", grids=not args.no_grids,
                            protocols=config.protocols)
    n_done = len(report.executed)
    print(f"{n_done} jobs run, {len(report.skipped)} already finished, {len(report.failed)} failed")
    print(f"wrote {paths.out}/: " + ", ".join(k for k in written if not k.startswith("grids/")), flush=True)
    # an external method not run yet is shown as "not run" in the tables, not counted as a failure
    failed = [(j, o) for j, o in report.failed if not is_not_run_message(o.get("error"))]
    if failed:
        total = len(report.rendered) + len(report.executed)
        print(f"{'warning' if args.keep_going else 'error'}: {failure_summary(failed, total)}; "
              f"tables and report written to {paths.out}/"
              + ("" if args.keep_going else " (KEEP_GOING=1 or --keep-going exits 0)"), file=sys.stderr)
        return 0 if args.keep_going else 1
    return 0
