"""Time training steps from a run's checkpoint: the A/B measure for speed work on the method.

Whole trainings on a shared machine move by 20 % or more with the hour (BENCHMARKS.md, sessions 39-40), so a
code change is measured by alternating short runs of the old and the new code on the same late steps:

    python -m method.step_bench RUN_DIR --steps 100             # stage 1 from its last checkpoint
    python -m method.step_bench RUN_DIR --iteration 4000 --profile prof.txt
    # old and new code alternated, each from its own checkout (git worktree add ../old <commit>):
    for r in 1 2 3; do for d in ../old .; do (cd $d && python -m method.step_bench $RUN --iteration 4000 --tag "$d r$r"); done; done

It runs the training loop's own step (``train.training_step``) on the run's recorded scene, light and
settings, from the chosen stage-1 checkpoint, with torch and the kernels on the threads a training alone
gets, and prints one line: wall and CPU ms a step and each part of it. The optimisers run as a fresh run
of this code would build them (a checkpoint keeps the Adam settings it was written with). Nothing is
written to the run: the NaN guard's failure record, if any, goes to a temporary folder.
"""
from __future__ import annotations

import argparse
import contextlib
import sys
import tempfile
import time
from pathlib import Path

import torch

from lumibench.errors import UserError


def bench_steps(run_dir: str | Path, *, iteration: int | None = None, steps: int = 100, warm: int = 10,
                profile_out: str | Path | None = None, device: str = "cpu") -> dict:
    """Run ``warm`` untimed then ``steps`` timed stage-1 steps from ``run_dir``'s checkpoint at
    ``iteration`` (None: the last); return {"ms_per_step", "cpu_ms_per_step", "parts_ms", "iteration",
    "steps", "last_loss"} (the last step's loss: the training's own, step for step)."""
    from method import run_record
    from method.checkpoints import checkpoint_paths
    from method.config import load_method_config
    from method.devices import check_device
    from method.optim import fused_supported
    from method.splat.backend import kernels_take_the_threads
    from method.stage1 import Stage1
    from method.train import Timer, denormals_flushed, load_training_scene, training_step

    run_dir = Path(run_dir)
    rec = run_record.read_record(run_dir)
    if rec is None or not isinstance(rec.get("run"), dict):
        raise UserError(f"{run_dir}: no config.yaml with a run record; point step_bench at a run directory")
    paths = checkpoint_paths(run_dir, 1)
    if not paths:
        raise UserError(f"{run_dir}: no stage-1 checkpoint to start from")
    chosen = paths[-1] if iteration is None else next((p for p in paths if p[0] == iteration), None)
    if chosen is None:
        raise UserError(f"{run_dir}: no stage-1 checkpoint at iteration {iteration} "
                        f"(there are: {', '.join(str(p[0]) for p in paths)})")
    if steps < 1 or warm < 0:
        raise UserError("--steps must be at least 1 and --warm at least 0")
    ident = rec["run"]
    cfg = load_method_config(str(rec.get("profile", "small")), [])
    for section in ("model", "data", "stage1"):  # the settings the run trained with
        cfg[section] = {**cfg[section], **rec.get(section, {})}
    dev = check_device(device)
    with kernels_take_the_threads(dev), denormals_flushed(dev):
        data = load_training_scene(ident["scene"], ident["light"], cfg, dev)
        stage = Stage1(data, cfg, static=bool(ident.get("static")), device=dev)
        ck = torch.load(chosen[1], map_location=dev, weights_only=False)
        stage.resume(ck)
        for opt in (stage.gopt.opt, stage.nopt):
            for grp in (opt.param_groups if opt is not None else []):
                grp["fused"], grp["foreach"] = (True, None) if fused_supported(grp["params"]) else (None, None)
        gen = torch.Generator()
        gen.set_state(ck["rng"])
        total, it = int(ck.get("total_iterations", cfg["stage1"]["iterations"])), int(ck["iteration"])
        if it + warm + steps > total:
            raise UserError(f"{run_dir}: {warm} + {steps} steps from iteration {it} pass the run's {total}; "
                            f"choose an earlier checkpoint (--iteration) or fewer steps")
        timer = Timer(dev)
        with tempfile.TemporaryDirectory() as scratch:
            for _ in range(warm):
                it += 1
                training_step(stage, Path(scratch), it, total, gen, timer, lambda rec: None)
            timer.sums.clear()
            profiler = contextlib.nullcontext()
            if profile_out is not None:
                from torch.profiler import ProfilerActivity, profile

                profiler = profile(activities=[ProfilerActivity.CPU], record_shapes=True)
            with profiler as prof:
                t0, c0 = time.perf_counter(), time.process_time()
                for _ in range(steps):
                    it += 1
                    loss, _ = training_step(stage, Path(scratch), it, total, gen, timer, lambda rec: None)
                wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            if profile_out is not None:
                averages = prof.key_averages(group_by_input_shape=True)
                Path(profile_out).write_text(averages.table(sort_by="self_cpu_time_total", row_limit=80))
    return {"ms_per_step": 1000 * wall / steps, "cpu_ms_per_step": 1000 * cpu / steps,
            "parts_ms": {k: 1000 * v / steps for k, v in timer.sums.items()}, "iteration": int(ck["iteration"]),
            "steps": steps, "last_loss": float(loss.detach())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m method.step_bench", description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="a run directory with stage-1 checkpoints (e.g. runs/small/lumimotion/spheres/city/seed0)")
    ap.add_argument("--iteration", type=int, default=None, help="the checkpoint to start from (default: the last)")
    ap.add_argument("--steps", type=int, default=100, help="timed steps (default 100)")
    ap.add_argument("--warm", type=int, default=10, help="untimed steps first (default 10)")
    ap.add_argument("--profile", default=None, help="also write torch.profiler's table of the timed steps here")
    ap.add_argument("--tag", default="", help="a label printed first (which code, which round)")
    args = ap.parse_args(argv)
    try:
        res = bench_steps(args.run, iteration=args.iteration, steps=args.steps, warm=args.warm,
                          profile_out=args.profile)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    parts = " ".join(f"{k} {v:.1f}" for k, v in res["parts_ms"].items())
    print(f"{args.tag} ms/step {res['ms_per_step']:.1f} cpu {res['cpu_ms_per_step']:.1f} | {parts} "
          f"({res['steps']} steps from iteration {res['iteration']})".strip())
    return 0


if __name__ == "__main__":
    sys.exit(main())
