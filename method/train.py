"""The training loop shared by both stages: progress, checkpoints, resume, the NaN guard, timings.

A stage (``method.stage1.Stage1``, ``method.stage2.Stage2``) says what it optimises and how one step goes;
the loop runs the steps and owns everything around them. Run directory
(``runs/<profile>/<name>/<scene>/<light>/seed<k>/``)::

    config.yaml            the resolved configuration and the run's identity (method/run_record.py)
    checkpoints/stage<k>_<iteration>.pt   every stage<k>.checkpoint_every and at the end; the last two kept
    log_stage<k>.jsonl     one line per stage<k>.log_every iterations (loss terms, PSNR, Gaussian count)
    timings.json           seconds (wall) and cpu_seconds (all threads, over every session the stage ran in),
                           iterations/s, peak memory, device, threads (kernels, torch), where the time went
    metrics_stage<k>.json  what the finished stage reports (method/stage1.py, method/stage2.py)
    renders/, predictions/ the stages' outputs
    failure.json           written when training stops on a non-finite value (the benchmark shows it)

Resuming restores every tensor, the optimiser moments, the stage's statistics and the random generator,
so on the CPU a resumed run equals an uninterrupted one (tests/test_training_loop.py).
"""
from __future__ import annotations

import contextlib
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from lumibench.errors import UserError
from lumibench.io import atomic_write_json
from method import run_record
from method.checkpoints import checkpoint_paths, latest_checkpoint, save_checkpoint
from method.data import SceneData, load_scene
from method.devices import check_device, cpu_has_native_bf16, device_name, peak_memory_bytes, sync
from method.splat.backend import kernels_take_the_threads, resolve as resolve_backend
from method.stage1 import Stage1
from method.stage2 import Stage2


class TrainingDiverged(UserError):
    """A non-finite loss, gradient or parameter: the run stops, its last good checkpoint stays."""

    exit_code = 3


def default_run_dir(runs: str | Path, profile: str, name: str, scene: str, light: str, seed: int) -> Path:
    return Path(runs) / profile / name / scene / light / f"seed{seed}"


@contextlib.contextmanager
def denormals_flushed(device: torch.device):
    """Within, on the CPU: denormal floats (float32 below 1.2e-38, float64 below 2.2e-308) read and written as
    zero by this thread (FTZ / DAZ; autograd's CPU backward and a one-thread torch run here; the compiled
    kernels' float64 sums never come near that range).

    Why: Adam's second moment of the motion bases' blend logits decays into that range (62 % of its 200k
    entries at iteration 4,000 of a `small` stage 1, every scene), and the CPU's slow path on such numbers
    made the optimiser step 2.4x slower (6.0-7.2 -> 2.5-2.8 ms of a ~75 ms step, BENCHMARKS.md, issue 23,
    session 53). A moment that small moves no parameter. torch has no getter for the mode, so the default
    (off) is put back after. numpy works out its float limits on first use and warns that the smallest
    subnormal is zero when that first use falls inside, so they are worked out before."""
    if device.type != "cpu":
        yield
        return
    for t in (np.float16, np.float32, np.float64):
        np.finfo(t)
    flushing = torch.set_flush_denormal(True)  # False where the CPU cannot: nothing to put back
    try:
        yield
    finally:
        if flushing:
            torch.set_flush_denormal(False)


class Timer:
    """Seconds per named phase of a step, summed over the run (synchronising CUDA at each lap)."""

    def __init__(self, device):
        self.device = device
        self.sums: dict[str, float] = {}
        self._t = 0.0

    def start(self):
        sync(self.device)
        self._t = time.perf_counter()

    def lap(self, name: str):
        sync(self.device)
        t = time.perf_counter()
        self.sums[name] = self.sums.get(name, 0.0) + (t - self._t)
        self._t = t


def finite_or_raise(run_dir: Path, stage: int, iteration: int, checks: list[tuple[str, torch.Tensor]]) -> None:
    """The NaN guard: the first non-finite value of ``checks`` (what, tensor) writes failure.json and stops
    the run naming the last good checkpoint. One test over all of them (their sums, stacked), the
    one-by-one search only when it fails (a sum that overflows over finite values passes then): the guard
    ran ~30 separate tests a step (~1 ms of a `demo` step)."""
    if not checks:
        return
    sums = [v.detach().sum() for _, v in checks]  # each in its own dtype (a float64 sum would copy the tensor)
    if len({t.dtype for t in sums}) > 1:
        sums = [t.double() for t in sums]
    if bool(torch.isfinite(torch.stack(sums)).all()):
        return
    what = next((w for w, v in checks if not bool(torch.isfinite(v).all())), None)
    if what is None:
        return
    record = {"status": "failed", "stage": stage, "iteration": iteration, "term": what,
              "cause": f"non-finite {what} at iteration {iteration}", "time": time.time()}
    atomic_write_json(Path(run_dir) / "failure.json", record)
    last = checkpoint_paths(run_dir, stage)
    keep = f"; last good checkpoint: {last[-1][1]}" if last else "; no checkpoint was written yet"
    raise TrainingDiverged(f"stage {stage} stopped: non-finite {what} at iteration {iteration}{keep}")


def training_step(stage, run_dir: Path, it: int, total: int, gen: torch.Generator, timer: Timer, log):
    """One iteration of ``stage``: forward, the NaN guard on the loss terms, backward, the guard on the
    gradients, the optimiser step, the guard on the parameters, then the stage's after-step work (density
    control). Timed into ``timer``'s laps; returns (loss, terms). The training loop and the step benchmark
    (method/step_bench.py) both run this."""
    k = stage.number
    timer.start()
    loss, terms = stage.forward(it, total, gen, timer, log)
    finite_or_raise(run_dir, k, it, [(f"loss term '{name}'", val) for name, val in terms.items()] + [("loss", loss)])
    timer.lap(stage.forward_lap)
    stage.zero_grad()
    loss.backward()
    timer.lap("backward")
    guarded = stage.guarded()
    finite_or_raise(run_dir, k, it, [(f"gradient of {name}", t.grad) for name, tensors in guarded
                                     for t in tensors if t.grad is not None])
    stage.optimiser_step(it, total)
    finite_or_raise(run_dir, k, it, [(f"parameter {name}", t) for name, tensors in guarded for t in tensors])
    timer.lap("step")
    stage.after_step(it, gen, timer)
    return loss, terms


def run_stage(stage, run_dir: Path, ident: dict, cfg: dict, *, seed: int, resume: bool, progress: bool = True,
              write_outputs: bool = True) -> dict:
    """Train ``stage`` into ``run_dir`` from scratch or from its last checkpoint; return its metrics."""
    k = stage.number
    s = cfg[f"stage{k}"]
    dev = stage.device
    what = f"stage {k}"
    with run_record.RunLock(run_dir), kernels_take_the_threads(dev) as kernel_threads, denormals_flushed(dev):
        existing = checkpoint_paths(run_dir, k)
        if existing and not resume:
            raise UserError(f"{run_dir} already has stage-{k} checkpoints: pass --resume to continue it, or choose "
                            f"another run directory (--run-dir) or seed")
        if resume and not existing:
            raise UserError(f"no stage-{k} checkpoint to resume in {run_dir} (train without --resume to start it)")
        run_record.check_identity(run_dir, ident, what)
        torch.manual_seed(seed)
        gen = torch.Generator().manual_seed(seed + stage.generator_offset)
        log_path = run_dir / f"log_stage{k}.jsonl"

        def log(rec: dict) -> None:
            with open(log_path, "a") as fh:
                fh.write(json.dumps(rec) + "\n")

        total, start_it, prior, prior_cpu = s["iterations"], 0, 0.0, 0.0
        if existing:
            run_record.check_settings(run_dir, cfg, k, f"resuming {what}")
            ck = latest_checkpoint(run_dir, k, dev)
            stage.resume(ck)
            gen.set_state(ck["rng"])
            start_it, prior = int(ck["iteration"]), float(ck.get("seconds", 0.0))
            prior_cpu = ck.get("cpu_seconds")  # absent in checkpoints from before it was kept: then unknown
            total = int(ck.get("total_iterations", total))
            run_record.truncate_log(log_path, start_it)
        else:
            if k == 1:
                run_record.write_record(run_dir, cfg, ident)
            else:
                run_record.check_settings(run_dir, cfg, 1, what)
                run_record.record_stage2(run_dir, cfg)
            log_path.unlink(missing_ok=True)
            stage.start(gen, log)
            prior, prior_cpu = stage.prior_seconds, stage.prior_cpu_seconds
        (run_dir / "failure.json").unlink(missing_ok=True)

        timer = Timer(dev)
        t0, c0 = time.perf_counter(), time.process_time()

        def cpu_total() -> float | None:  # the stage's CPU seconds (all threads) over every session it ran in
            return None if prior_cpu is None else float(prior_cpu) + time.process_time() - c0

        ema = None
        from lumibench.progress import make_progress

        with make_progress(disable=not progress) as bar:
            task = bar.add_task(what, total=total, completed=start_it, rate="")
            for it in range(start_it + 1, total + 1):
                loss, terms = training_step(stage, run_dir, it, total, gen, timer, log)
                lval = float(loss.detach())
                ema = lval if ema is None else 0.9 * ema + 0.1 * lval
                if it % s["log_every"] == 0 or it == total:
                    log({"iteration": it, "loss": lval, "seconds": prior + time.perf_counter() - t0,
                         **{n: float(v.detach()) for n, v in terms.items()}, **stage.log_fields(it, total)})
                rate = (it - start_it) / max(time.perf_counter() - t0, 1e-9)
                bar.update(task, completed=it, rate=f"{rate:.1f} it/s",
                           description=f"{what}  loss {ema:.4f}{stage.describe()}")
                if it % s["checkpoint_every"] == 0 or it == total:
                    save_checkpoint(run_dir, k, it, {
                        "iteration": it, "total_iterations": total, "rng": gen.get_state(),
                        "seconds": prior + time.perf_counter() - t0, "cpu_seconds": cpu_total(), **stage.state()})
        seconds = prior + time.perf_counter() - t0
        run_record.merge_json(run_dir / "timings.json", {
            f"stage{k}": {"seconds": seconds, "iterations": total, "iterations_per_s": total / max(seconds, 1e-9),
                          "cpu_seconds_this_session": time.process_time() - c0,
                          **({} if (cpu := cpu_total()) is None else {"cpu_seconds": cpu}),
                          "breakdown_s": {n: round(v, 4) for n, v in timer.sums.items()},
                          "breakdown_iterations": total - start_it, **stage.timing_fields()},
            "device": device_name(dev), "device_type": dev.type, "threads": kernel_threads,
            "torch_threads": torch.get_num_threads(), "splat_backend": resolve_backend(None, dev),
            "peak_memory_bytes": peak_memory_bytes(dev)})
        metrics = stage.finish(run_dir, seconds, write_outputs, gen)
        atomic_write_json(run_dir / f"metrics_stage{k}.json", metrics)
    return metrics


def share_stage1(source: str | Path, run_dir: str | Path, cfg: dict, *, scene: str, light: str, seed: int) -> bool:
    """Give ``run_dir`` the finished stage 1 of ``source`` when that run trained exactly this stage 1: the same
    scene, light, seed, dynamic capture and every stage-1 setting (``cfg``'s profile, model, data, stage1
    sections as :func:`run_record.recorded_settings` reads them). Its checkpoint is linked (copied across file
    systems), its log, renders, timings and metrics copied, and the record names the source
    (``run.stage1_shared_from``), so an ablation
    that differs from its source only after stage 1 (``wo_stage2``) compares the very same stage 1 and does
    not pay for it twice. False, with nothing written, when the source is unfinished or differs in anything."""
    import os
    import shutil

    src, dst = Path(source), Path(run_dir)
    rec = run_record.read_record(src)
    ident = (rec or {}).get("run")
    if (not rec or not isinstance(ident, dict) or not (src / "metrics_stage1.json").is_file()
            or not checkpoint_paths(src, 1)):
        return False
    if (str(ident.get("scene_name")), str(ident.get("light")), str(ident.get("seed")), ident.get("static")) != (
            Path(scene).name, light, str(seed), False):
        return False
    if run_record.recorded_settings(rec, 1) != run_record.recorded_settings(cfg, 1):
        return False
    with run_record.RunLock(dst):
        if checkpoint_paths(dst, 1) or (dst / "metrics_stage1.json").is_file():
            return False  # this run has a stage 1 of its own (or a partial one to resume)
        _, ck = checkpoint_paths(src, 1)[-1]
        (dst / "checkpoints").mkdir(parents=True, exist_ok=True)
        tmp = dst / "checkpoints" / f".{ck.name}.tmp"
        tmp.unlink(missing_ok=True)
        try:
            os.link(ck, tmp)
        except OSError:
            shutil.copyfile(ck, tmp)
        os.replace(tmp, dst / "checkpoints" / ck.name)
        if (src / "log_stage1.jsonl").is_file():
            shutil.copyfile(src / "log_stage1.jsonl", dst / "log_stage1.jsonl")
        for part in ("renders/stage1", "renders/sheet_stage1.png"):
            if (src / part).is_dir():
                shutil.copytree(src / part, dst / part, dirs_exist_ok=True)
            elif (src / part).is_file():
                (dst / part).parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(src / part, dst / part)
        run_record.write_record(dst, cfg, {**ident, "stage1_shared_from": str(src.resolve())})
        try:
            times = json.loads((src / "timings.json").read_text())
        except (OSError, ValueError):
            times = {}
        run_record.merge_json(dst / "timings.json", {**{k: v for k, v in times.items() if k != "stage2"},
                                                     "stage1_shared_from": str(src.resolve())})
        atomic_write_json(dst / "metrics_stage1.json", json.loads((src / "metrics_stage1.json").read_text()))
    return True


def load_training_scene(scene_dir: str | Path, light: str, cfg: dict, device) -> SceneData:
    """The scene as a run of ``cfg`` trains on it: the training frames its ``data.train_frames`` keeps."""
    return load_scene(scene_dir, light, cfg["data"]["background"], device, train_frames=cfg["data"]["train_frames"])


def kept_views(data: SceneData, cfg: dict) -> list[str] | None:
    """The stems of the training views a run trains on, recorded in config.yaml when it keeps a share of
    them (``data.train_frames`` < 1); None when it trains on all."""
    return [v.stem for v in data.train] if cfg["data"]["train_frames"] < 1 else None


def train_stage1(scene_dir: str | Path, light: str, run_dir: str | Path, cfg: dict, *, seed: int = 0,
                 device: str = "cpu", static: bool | None = None, resume: bool = False, progress: bool = True,
                 write_outputs: bool = True) -> dict:
    """Train stage 1 into ``run_dir``; return the metrics dict (also in metrics_stage1.json)."""
    dev = check_device(device)
    data = load_training_scene(scene_dir, light, cfg, dev)
    static = data.static if static is None else static
    bf16 = cfg["model"]["mlp_precision"] == "bf16" and not static
    if bf16 and dev.type == "cpu" and cpu_has_native_bf16() is False:
        print("note: model.mlp_precision=bf16 on a CPU without AVX512-BF16 or AMX: bf16 is emulated and slower than "
              "fp32 here; pass model.mlp_precision=fp32 (BENCHMARKS.md, 'The deformation network in bf16')",
              file=sys.stderr)
    stage = Stage1(data, cfg, static=static, device=dev)
    ident = run_record.identity(Path(scene_dir), light, seed, dev, static, train_views=kept_views(data, cfg))
    return run_stage(stage, Path(run_dir), ident, cfg, seed=seed, resume=resume, progress=progress,
                     write_outputs=write_outputs)


def train_stage2(scene_dir: str | Path, light: str, run_dir: str | Path, cfg: dict, *, seed: int = 0,
                 device: str = "cpu", resume: bool = False, progress: bool = True,
                 data: SceneData | None = None) -> dict:
    """Train stage 2 on the run's finished stage 1; return the metrics dict (also in metrics_stage2.json)."""
    dev = check_device(device)
    data = data or load_training_scene(scene_dir, light, cfg, dev)
    stage = Stage2(data, cfg, Path(run_dir), device=dev)
    ident = run_record.identity(Path(scene_dir), light, seed, dev, data.static, train_views=kept_views(data, cfg))
    return run_stage(stage, Path(run_dir), ident, cfg, seed=seed, resume=resume, progress=progress)
