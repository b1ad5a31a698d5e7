"""The stage-1 training loop: progress, checkpoints, resume, the NaN guard, timings and outputs.

Run directory (``runs/<profile>/<name>/<scene>/<light>/seed<k>/``)::

    config.yaml            the resolved configuration and the run's identity (scene, light, seed, device)
    checkpoints/stage1_<iteration>.pt   (every stage1.checkpoint_every and at the end; the last two kept)
    log_stage1.jsonl       one line per stage1.log_every iterations (loss terms, PSNR, Gaussian count)
    timings.json           seconds, iterations/s, peak memory, device, threads, where the time went
    metrics_stage1.json    test-view NVS metrics, separation score, Gaussian and parameter counts
    renders/stage1/<rgb|normal|depth|p>/r_NNNN.png, sheet_stage1.png
    predictions/p_map/train/r_NNNN.png   P of the training views (benchmark predictions layout)
    failure.json           written when training stops on a non-finite value (the benchmark shows it)

Resuming from a checkpoint restores every tensor, the optimiser moments, the density statistics and
the random generator, so on the CPU a resumed run equals an uninterrupted one.
"""
from __future__ import annotations

import dataclasses
import json
import math
import platform
import resource
import time
from pathlib import Path

import torch
import yaml

from lumibench.errors import UserError
from lumibench.io import atomic_path, atomic_write_json, atomic_write_text
from method import losses
from method.data import SceneData, load_scene
from method.model.deform import DeformNet
from method.model.density import DensityStats, densify_and_prune, reset_opacity
from method.model.gaussians import GaussianAdam, Gaussians
from method.splat.camera import Camera
from method.splat.backend import resolve as resolve_backend
from method.stage1 import DynamicScene, assign_p_from_motion, render, stage1_loss


class TrainingDiverged(UserError):
    """A non-finite loss, gradient or parameter: the run stops, its last good checkpoint stays."""

    exit_code = 3


def default_run_dir(runs: str | Path, profile: str, name: str, scene: str, light: str, seed: int) -> Path:
    return Path(runs) / profile / name / scene / light / f"seed{seed}"


def expon_lr(step: int, total: int, lr0: float, lr1: float) -> float:
    """Log-linear decay from lr0 at step 0 to lr1 at ``total`` (3DGS's exponential schedule)."""
    t = min(max(step / max(total, 1), 0.0), 1.0)
    return math.exp(math.log(lr0) * (1 - t) + math.log(lr1) * t)


def mlp_lr(iteration: int, total: int, s1: dict) -> float:
    """The deformation network's rate: exponential decay from ``lr_mlp`` to ``lr_mlp * lr_mlp_final``, on the
    base ``lr_mlp_warmup`` instead during the P = 1 warm-up when that is set (> 0): a slow warm-up keeps the
    static Gaussians' wobble small for the split by motion, a faster rate afterwards lets the dynamic ones
    catch fast motion (BENCHMARKS.md, session 11)."""
    base = s1["lr_mlp"]
    if s1["lr_mlp_warmup"] > 0 and iteration <= s1["warmup"]:
        base = s1["lr_mlp_warmup"]
    return expon_lr(iteration, total, base, base * s1["lr_mlp_final"])


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def peak_memory_bytes(device: torch.device) -> int:
    if device.type == "cuda":
        return int(torch.cuda.max_memory_allocated(device))
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024  # Linux: KiB


def device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return platform.processor() or platform.machine() or "cpu"


# --------------------------------------------------------------------------------------------- init

def carve(points: torch.Tensor, data: SceneData, fraction: float = 0.5) -> torch.Tensor:
    """Keep points that fall inside the foreground (alpha > 0.5) of at least ``fraction`` of the training
    views that see them (a visual hull; moving objects blur it, density control does the rest)."""
    inside = torch.zeros(points.shape[0])
    seen = torch.zeros(points.shape[0])
    for v in data.train:
        cam = v.camera
        p = points.to(cam.w2c) @ cam.w2c[:3, :3].T + cam.w2c[:3, 3]
        z = p[:, 2]
        x = cam.focal * p[:, 0] / z.clamp_min(1e-6) + cam.cx
        y = cam.focal * p[:, 1] / z.clamp_min(1e-6) + cam.cy
        ok = (z > 1e-3) & (x >= 0) & (x < cam.width) & (y >= 0) & (y < cam.height)
        xi = x.clamp(0, cam.width - 1).long()
        yi = y.clamp(0, cam.height - 1).long()
        a = v.alpha[yi.to(v.alpha.device), xi.to(v.alpha.device)].cpu()
        seen += ok.cpu().float()
        inside += (ok.cpu() & (a > 0.5)).float()
    return (seen > 0) & (inside >= fraction * seen.clamp_min(1))


def c2f_factor(iteration: int, levels: int, until: int) -> int:
    """Image downscale factor at ``iteration`` of a coarse-to-fine schedule: 2^levels at the start, halving
    at evenly spaced iterations, 1 (full resolution) after ``until``; 1 throughout when either is 0.

    Why: the balls of `spheres` move by many pixels between frames, and a splat only receives gradient
    from pixels it covers; on a coarse image the same motion is a few pixels and a splat covers more of
    the object (the classic coarse-to-fine answer to large displacements), and a coarse step is cheaper."""
    if levels <= 0 or until <= 0 or iteration > until:
        return 1
    return 2 ** (levels - (max(iteration, 1) - 1) * levels // until)


def time_window_views(times: list[float], iteration: int, start: float, until: int,
                      front: bool = False) -> list[int]:
    """Indices of the training views a time-window curriculum may draw at ``iteration``: those whose time
    lies in the first ``start`` of the time range at iteration 1, the window growing linearly to the whole
    range at ``until``; every view when ``until`` is 0 or passed.

    Why: with one view per time, a Gaussian on a fast object at one time sits elsewhere at the others, so
    it only survives if the deformation already carries it along. Opening the times in order lets the
    network follow the object from a time it has fitted to the next, a small step, instead of having to
    find every position at once (spheres' small bouncing ball).

    ``front``: only the window's newest ``start`` share of the range (the times just opened), so that a
    caller can give them more draws than their share of a wide window."""
    if until <= 0 or iteration >= until:
        return list(range(len(times)))
    lo, hi = min(times), max(times)
    frac = start + (1.0 - start) * max(iteration - 1, 0) / until
    limit = lo + frac * (hi - lo)
    order = sorted(range(len(times)), key=lambda k: times[k])
    window = [k for k in order if times[k] <= limit + 1e-9]
    chosen = [k for k in window if times[k] >= limit - start * (hi - lo) - 1e-9] if front else window
    return chosen or window[-1:] or order[:1]


def downsampled(view, factor: int):
    """The view at 1/factor resolution: area-averaged image and alpha, the same camera with its focal
    length and size divided (pixel centres stay consistent since cx = width / 2)."""
    if factor == 1:
        return view
    cam = view.camera
    if cam.width % factor or cam.height % factor:
        return view
    pool = torch.nn.functional.avg_pool2d
    rgb = pool(view.rgb.permute(2, 0, 1)[None], factor)[0].permute(1, 2, 0).contiguous()
    alpha = pool(view.alpha[None, None], factor)[0, 0]
    small = Camera(cam.width // factor, cam.height // factor, cam.focal / factor, cam.w2c, cam.c2w)
    return dataclasses.replace(view, camera=small, rgb=rgb, alpha=alpha, dynamic_mask=None)


def init_points(data: SceneData, cfg: dict, gen: torch.Generator) -> torch.Tensor:
    s = cfg["stage1"]
    n = s["init_points"]
    c, e = data.center.cpu(), data.extent
    if not s["init_carve"]:
        return c + (torch.rand(n, 3, generator=gen) * 2 - 1) * e
    kept, tries = [], 0
    total = 0
    while total < n and tries < 20:
        cand = c + (torch.rand(4 * n, 3, generator=gen) * 2 - 1) * e
        k = cand[carve(cand, data)]
        kept.append(k)
        total += k.shape[0]
        tries += 1
    pts = torch.cat(kept)[:n] if total else c + (torch.rand(n, 3, generator=gen) * 2 - 1) * e
    return pts


def build_scene(data: SceneData, cfg: dict, static: bool, gen: torch.Generator, device: torch.device) -> DynamicScene:
    m = cfg["model"]
    pts = init_points(data, cfg, gen)
    g = Gaussians.from_points(pts, cfg["stage1"]["init_opacity"], m["p_init_logit"], gen,
                              scale_factor=cfg["stage1"]["init_scale"]).to(device)
    net = None
    if not static:
        net = DeformNet(m["mlp_depth"], m["mlp_width"], m["mlp_skip"], m["pos_freqs"], m["time_freqs"],
                        m["time_net_width"], m["time_net_out"]).to(device)
    scene = DynamicScene(g, net, data.center.to(device), data.extent, m["p_temperature"], m["delta_colour"],
                         m["separation"])
    scene.model_cfg = dict(m)
    return scene


def make_optimisers(scene: DynamicScene, cfg: dict) -> tuple[GaussianAdam, torch.optim.Optimizer | None]:
    s = cfg["stage1"]
    lrs = {"means": s["lr_position"] * scene.extent, "quats": s["lr_rotation"], "log_scales": s["lr_scaling"],
           "opacity_logit": s["lr_opacity"], "colour_logit": s["lr_colour"], "p_logit": s["lr_p"]}
    gopt = GaussianAdam(scene.g, lrs)
    nopt = torch.optim.Adam(scene.net.parameters(), lr=s["lr_mlp"], eps=1e-15) if scene.net is not None else None
    return gopt, nopt


# --------------------------------------------------------------------------------------- checkpoints

def checkpoint_paths(run_dir: Path, stage: int = 1) -> list[tuple[int, Path]]:
    d = Path(run_dir) / "checkpoints"
    out = []
    if d.is_dir():
        for p in d.glob(f"stage{stage}_*.pt"):
            tail = p.stem.split("_", 1)[1]
            if tail.isdigit():
                out.append((int(tail), p))
    return sorted(out)


def save_checkpoint(path: Path, iteration: int, scene: DynamicScene, gopt: GaussianAdam, nopt, stats: DensityStats,
                    gen: torch.Generator, extra: dict) -> None:
    state = {
        "iteration": iteration, "gaussians": scene.g.state(), "net": None if scene.net is None else scene.net.state_dict(),
        "gopt": gopt.state_dict(), "nopt": None if nopt is None else nopt.state_dict(), "density": stats.state(),
        "rng": gen.get_state(), "center": scene.center.cpu(), "extent": scene.extent,
        "temperature": scene.temperature, "model": dict(scene.model_cfg), **extra,
    }
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def load_checkpoint(path: Path, device) -> dict:
    try:
        return torch.load(path, map_location=device, weights_only=False)
    except Exception as exc:  # truncated or foreign file
        raise UserError(f"cannot read checkpoint {path}: {type(exc).__name__}: {exc}") from None


def scene_from_checkpoint(ck: dict, cfg: dict, device) -> DynamicScene:
    """The model a checkpoint holds (for stage 2, relighting and evaluation)."""
    g = Gaussians({k: v.to(device) for k, v in ck["gaussians"].items()})
    net = None
    m = ck.get("model") or cfg["model"]  # the architecture the checkpoint was trained with
    if ck["net"] is not None:
        net = DeformNet(m["mlp_depth"], m["mlp_width"], m["mlp_skip"], m["pos_freqs"], m["time_freqs"],
                        m["time_net_width"], m["time_net_out"]).to(device)
        net.load_state_dict(ck["net"])
    scene = DynamicScene(g, net, ck["center"].to(device), ck["extent"], ck["temperature"], m["delta_colour"],
                         m["separation"])
    scene.model_cfg = dict(m)
    return scene


# ------------------------------------------------------------------------------------------ the loop

def _finite_or_raise(run_dir: Path, iteration: int, what: str, value: torch.Tensor, stage: int = 1) -> None:
    if not bool(torch.isfinite(value).all()):
        record = {"status": "failed", "stage": stage, "iteration": iteration, "term": what,
                  "cause": f"non-finite {what} at iteration {iteration}", "time": time.time()}
        atomic_write_json(Path(run_dir) / "failure.json", record)
        last = checkpoint_paths(run_dir, stage)
        keep = f"; last good checkpoint: {last[-1][1]}" if last else "; no checkpoint was written yet"
        raise TrainingDiverged(f"stage {stage} stopped: non-finite {what} at iteration {iteration}{keep}")


def evaluate_test(scene: DynamicScene, data: SceneData) -> float | None:
    """Mean PSNR of the test views (inference P, at each view's time), for the log and the bar."""
    if not data.test:
        return None
    vals = []
    with torch.no_grad():
        for v in data.test:
            out = render(scene.deform(v.time, p_mode="inference"), v.camera, data.background)
            vals.append(losses.psnr(out.features[..., :3].clamp(0, 1), v.rgb))
    return float(sum(vals) / len(vals))


class Timer:
    def __init__(self, device):
        self.device = device
        self.sums: dict[str, float] = {}
        self._t = 0.0

    def start(self):
        _sync(self.device)
        self._t = time.perf_counter()

    def lap(self, name: str):
        _sync(self.device)
        t = time.perf_counter()
        self.sums[name] = self.sums.get(name, 0.0) + (t - self._t)
        self._t = t


def train_stage1(scene_dir: str | Path, light: str, run_dir: str | Path, cfg: dict, *, seed: int = 0,
                 device: str = "cpu", static: bool | None = None, resume: bool = False, progress: bool = True,
                 write_outputs: bool = True) -> dict:
    """Train stage 1 into ``run_dir``; return the metrics dict (also in metrics_stage1.json)."""
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise UserError("DEVICE=cuda asked for, but this torch has no CUDA device (use DEVICE=cpu)")
    run_dir = Path(run_dir)
    s = cfg["stage1"]
    data = load_scene(scene_dir, light, cfg["data"]["background"], dev)
    static = data.static if static is None else static
    existing = checkpoint_paths(run_dir, 1)
    if existing and not resume:
        raise UserError(f"{run_dir} already has stage-1 checkpoints: pass --resume to continue it, or choose "
                        f"another run directory (--run-dir) or seed")
    if resume and not existing:
        raise UserError(f"no stage-1 checkpoint to resume in {run_dir} (train without --resume to start it)")
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "failure.json").unlink(missing_ok=True)
    identity = {"scene": str(Path(scene_dir).resolve()), "scene_name": Path(scene_dir).name, "light": light,
                "seed": seed, "device": str(dev), "static": bool(static)}
    total = s["iterations"]
    start_it = 0
    prior_seconds = 0.0
    if existing:
        ck = load_checkpoint(existing[-1][1], dev)
        scene = scene_from_checkpoint(ck, cfg, dev)
        gopt, nopt = make_optimisers(scene, cfg)
        gopt.load_state_dict(ck["gopt"])
        if nopt is not None:
            nopt.load_state_dict(ck["nopt"])
        stats = DensityStats(len(scene.g), dev)
        stats.load(ck["density"])
        gen.set_state(ck["rng"])
        start_it = int(ck["iteration"])
        prior_seconds = float(ck.get("seconds", 0.0))
        total = int(ck.get("total_iterations", total))
    else:
        scene = build_scene(data, cfg, static, gen, dev)
        gopt, nopt = make_optimisers(scene, cfg)
        stats = DensityStats(len(scene.g), dev)
    atomic_write_text(run_dir / "config.yaml", yaml.safe_dump({**cfg, "run": identity}, sort_keys=False))

    timer = Timer(dev)
    log_path = run_dir / "log_stage1.jsonl"
    if start_it == 0:
        log_path.unlink(missing_ok=True)
        if s["eval_every"]:
            first = evaluate_test(scene, data)  # the baseline the learning curve starts from
            if first is not None:
                with open(log_path, "a") as fh:
                    fh.write(json.dumps({"iteration": 0, "test_psnr": first, "gaussians": len(scene.g)}) + "\n")
    H, W = data.resolution
    n_views = len(data.train)
    train_times = sorted({float(v.time) for v in data.train})
    view_times = [float(v.time) for v in data.train]
    coarse: dict = {}  # (view, factor) -> the downsampled view of the coarse-to-fine schedule
    t0 = time.perf_counter()
    c0 = time.process_time()
    last_psnr = None
    ema_loss = None
    from lumibench.progress import make_progress

    with make_progress(disable=not progress) as bar:
        task = bar.add_task("stage 1", total=total, completed=start_it, rate="")
        for it in range(start_it + 1, total + 1):
            timer.start()
            gopt.set_lr("means", expon_lr(it, total, s["lr_position"] * scene.extent,
                                          s["lr_position"] * scene.extent * s["lr_position_final"]))
            if nopt is not None:
                for grp in nopt.param_groups:
                    grp["lr"] = mlp_lr(it, total, s)
            if s["time_window_until"] and it < s["time_window_until"]:
                front = s["time_window_front"] > 0 and float(torch.rand(1, generator=gen)) < s["time_window_front"]
                pool = time_window_views(view_times, it, s["time_window_start"], s["time_window_until"], front)
                k_view = pool[int(torch.randint(len(pool), (1,), generator=gen))]
            else:
                k_view = int(torch.randint(n_views, (1,), generator=gen))
            factor = c2f_factor(it, s["c2f_levels"], s["c2f_until"])
            if factor == 1:
                view = data.train[k_view]
            else:
                if (k_view, factor) not in coarse:
                    coarse[(k_view, factor)] = downsampled(data.train[k_view], factor)
                view = coarse[(k_view, factor)]
            H, W = view.camera.height, view.camera.width
            if s["p_from_motion"] and it == s["warmup"] + 1 and not scene.static and scene.separation:
                info = assign_p_from_motion(scene, train_times, s["p_motion_threshold"] or None,
                                            s["p_from_motion_logit"], s["p_motion_relative"])
                gopt.reset_values("p_logit", scene.g.t["p_logit"].detach())
                with open(log_path, "a") as fh:
                    fh.write(json.dumps({"iteration": it, "p_from_motion": info}) + "\n")
            warm = it <= s["warmup"]
            d = scene.deform(view.time, p_mode="ones" if warm else "sample", generator=gen)
            timer.lap("deform")
            densify_now = s["densify_from"] <= it <= s["densify_until"]
            offsets = torch.zeros(len(scene.g), 2, device=dev, requires_grad=True) if densify_now else None
            out = render(d, view.camera, data.background, screen_offsets=offsets)
            timer.lap("rasterize")
            loss, terms = stage1_loss(out, d, view.rgb, view.alpha, s, it, warm)
            for name, val in terms.items():
                _finite_or_raise(run_dir, it, f"loss term '{name}'", val)
            _finite_or_raise(run_dir, it, "loss", loss)
            timer.lap("loss")
            gopt.zero_grad()
            if nopt is not None:
                nopt.zero_grad(set_to_none=True)
            loss.backward()
            timer.lap("backward")
            for name, t in scene.g.t.items():
                if t.grad is not None:
                    _finite_or_raise(run_dir, it, f"gradient of {name}", t.grad.sum())
            if scene.net is not None:
                gsum = sum(p.grad.sum() for p in scene.net.parameters() if p.grad is not None)
                _finite_or_raise(run_dir, it, "gradient of the deformation network", torch.as_tensor(gsum))
            gopt.step()
            if nopt is not None:
                nopt.step()
            for name, t in scene.g.t.items():
                _finite_or_raise(run_dir, it, f"parameter {name}", t.detach().sum())
            timer.lap("step")
            if densify_now:
                stats.add(offsets.grad, out.visible, out.radii, W, H)
                if it % s["densify_every"] == 0 and it < s["densify_until"]:
                    max_screen = 20.0 * max(H, W) / 800.0 if it > s["opacity_reset_every"] else None
                    densify_and_prune(scene.g, gopt, stats, grad_threshold=s["densify_grad_threshold"],
                                      percent_dense=s["percent_dense"], extent=scene.extent,
                                      min_opacity=s["prune_opacity"], max_gaussians=s["max_gaussians"],
                                      max_screen_radius=max_screen, generator=gen)
                if it % s["opacity_reset_every"] == 0:
                    reset_opacity(scene.g, gopt)
            timer.lap("density")
            lval = float(loss.detach())
            ema_loss = lval if ema_loss is None else 0.9 * ema_loss + 0.1 * lval
            if it % s["log_every"] == 0 or it == total:
                train_psnr = losses.psnr(out.features[..., :3].detach().clamp(0, 1), view.rgb)
                rec = {"iteration": it, "loss": lval, "train_psnr": train_psnr, "gaussians": len(scene.g),
                       "seconds": prior_seconds + time.perf_counter() - t0,
                       **{k: float(v.detach()) for k, v in terms.items()}}
                if not scene.static:  # how far the separation has gone: share of Gaussians with P > 0.5
                    rec["p_dynamic_share"] = float((scene.p_inference().detach() > 0.5).float().mean())
                if s["eval_every"] and (it % s["eval_every"] == 0 or it == total):
                    last_psnr = evaluate_test(scene, data)
                    rec["test_psnr"] = last_psnr
                with open(log_path, "a") as fh:
                    fh.write(json.dumps(rec) + "\n")
            elapsed = time.perf_counter() - t0
            rate = (it - start_it) / max(elapsed, 1e-9)
            bar.update(task, completed=it, rate=f"{rate:.1f} it/s",
                       description=f"stage 1  loss {ema_loss:.4f}" + (f"  test PSNR {last_psnr:.2f}" if last_psnr else "")
                       + f"  N {len(scene.g)}")
            if it % s["checkpoint_every"] == 0 or it == total:
                save_checkpoint(run_dir / "checkpoints" / f"stage1_{it:06d}.pt", it, scene, gopt, nopt, stats, gen,
                                {"seconds": prior_seconds + time.perf_counter() - t0, "total_iterations": total,
                                 "static": scene.static})
                for _, old in checkpoint_paths(run_dir, 1)[:-2]:
                    old.unlink(missing_ok=True)
    seconds = prior_seconds + time.perf_counter() - t0
    iters_run = total - start_it
    timings = {
        "stage1": {"seconds": seconds, "iterations": total, "iterations_per_s": total / max(seconds, 1e-9),
                   "cpu_seconds_this_session": time.process_time() - c0,
                   "breakdown_s": {k: round(v, 4) for k, v in timer.sums.items()},
                   "breakdown_iterations": iters_run},
        "device": device_name(dev), "device_type": dev.type, "threads": torch.get_num_threads(),
        "splat_backend": resolve_backend(None, dev),
        "peak_memory_bytes": peak_memory_bytes(dev),
    }
    _merge_json(run_dir / "timings.json", timings)
    metrics = {"iterations": total, "gaussians": len(scene.g), "parameters": scene.num_parameters(),
               "gaussian_parameters": scene.g.num_parameters(),
               "network_parameters": 0 if scene.net is None else scene.net.num_parameters(),
               "static": scene.static, "seconds": seconds}
    if write_outputs:
        metrics.update(stage1_outputs(scene, data, run_dir))
    atomic_write_json(run_dir / "metrics_stage1.json", metrics)
    return metrics


def stage1_outputs(scene: DynamicScene, data: SceneData, run_dir: Path) -> dict:
    """Test renders + sheet, NVS metrics, separation score, P maps; returns the metrics."""
    from benchmark.metrics import lpips, psnr, ssim
    from method.outputs import separation, write_p_maps, write_test_renders

    out: dict = {}
    renders, sheet = write_test_renders(scene, data, run_dir / "renders" / "stage1", "stage1")
    if renders:
        ps, ss, lp = [], [], []
        for r, v in zip(renders, data.test):
            gt = v.rgb.cpu().numpy()
            ps.append(psnr(r["rgb"], gt))
            ss.append(ssim(r["rgb"], gt))
            lp.append(lpips(r["rgb"], gt, net="vgg", input_range="[0,1]"))
        out["test"] = {"psnr": sum(ps) / len(ps), "ssim": sum(ss) / len(ss), "lpips_vgg": sum(lp) / len(lp),
                       "views": len(ps), "note": "test views under the train light, composited on the background"}
        out["sheet"] = str(sheet) if sheet else None
    sep = separation(scene, data) if not scene.static else None
    if sep is not None:
        out["separation"] = sep
    if not scene.static:
        write_p_maps(scene, data, run_dir / "predictions")
    return out


def _merge_json(path: Path, new: dict) -> None:
    old = {}
    if path.is_file():
        try:
            old = json.loads(path.read_text())
        except json.JSONDecodeError:
            old = {}
    old.update(new)
    atomic_write_json(path, old)
