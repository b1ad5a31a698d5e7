"""`python -m method train` (`make train`): stage 1 (and stage 2 once it exists) of one scene and light."""
from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train LumiMotion on one scene under one light",
                       description="Train LumiMotion on DATA/PROFILE/SCENE under the light LIGHT into "
                                   "RUNS/PROFILE/NAME/SCENE/LIGHT/seedK/ (checkpoints, logs, timings, renders). "
                                   "Any configuration key can be overridden: stage1.iterations=500.")
    p.add_argument("--scene", required=True, help="scene name under DATA/PROFILE, or a scene directory")
    p.add_argument("--light", default="city", help="training light (default city)")
    p.add_argument("--profile", default="ci", help="effort profile, configs/profiles/<name>.yaml: ci, demo, small, full (default ci)")
    p.add_argument("--stage", default="all", choices=["1", "2", "all"],
                   help="1, 2 (from the run's stage-1 checkpoint), or all: both, then the benchmark predictions (default)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--splat-backend", default=None, choices=["auto", "torch", "numba"],
                   help="rasterizer/tracer implementation: auto (default; compiled CPU kernels when numba is "
                        "installed and the device is the CPU), torch (the reference), numba")
    p.add_argument("--data", default="data", help="dataset root (default data)")
    p.add_argument("--runs", default="runs", help="runs root (default runs)")
    p.add_argument("--run-dir", default=None, help="explicit run directory (overrides --runs/--name)")
    p.add_argument("--name", default=None, help="method name in the run path (default lumimotion; static with --static)")
    p.add_argument("--static", action="store_true", help="no deformation network (the static pipeline)")
    p.add_argument("--resume", action="store_true", help="continue from the run's last checkpoint")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="configuration overrides, e.g. stage1.iterations=500 "
                   "(iterations=0 means the profile's number; negative numbers are refused)")


def resolve_scene(data: str, profile: str, scene: str) -> Path:
    from lumibench import layout
    from lumibench.errors import UserError

    as_path = Path(scene)
    if as_path.is_dir() and (as_path / "transforms_train.json").is_file():
        return as_path
    d = layout.scene_dir(data, profile, scene)
    if not d.is_dir():
        root = Path(data) / profile
        have = sorted(p.name for p in root.iterdir() if (p / "transforms_train.json").is_file()) if root.is_dir() else []
        raise UserError(f"unknown scene '{scene}': no {d} (rendered under {root}: {', '.join(have) or 'none'}; "
                        f"render it with `make dataset PROFILE={profile} SCENES={scene}`)")
    return d


def set_splat_backend(name: str | None) -> None:
    """--splat-backend: the process-wide rasterizer/tracer implementation (None: LUMIBENCH_SPLAT_BACKEND or auto)."""
    from method.splat.backend import set_backend

    if name is not None:
        set_backend(name)


def run(args: argparse.Namespace) -> int:
    from lumibench.errors import UserError
    from lumibench.layout import parse_light
    from method.checkpoints import checkpoint_paths
    from method.config import load_method_config
    from method.predictions import write_predictions
    from method.devices import check_device
    from method.train import default_run_dir, train_stage1, train_stage2

    check_device(args.device)
    set_splat_backend(args.splat_backend)
    args.light, _ = parse_light(args.light)  # a light file is its stem: the dataset's folder, the run's name
    cfg = load_method_config(args.profile, args.overrides)
    scene_dir = resolve_scene(args.data, args.profile, args.scene)
    name = args.name or ("static" if args.static else "lumimotion")
    run_dir = Path(args.run_dir) if args.run_dir else default_run_dir(args.runs, args.profile, name, scene_dir.name,
                                                                       args.light, args.seed)
    if args.static and not _is_static_capture(scene_dir):
        raise UserError(f"--static trains the static pipeline on a static capture, but {scene_dir.name} is dynamic: "
                        f"use --scene {scene_dir.name}_statictimestep0000 (rendered beside it by make dataset), "
                        f"or leave out --static")
    metrics = {}
    stage1_done = bool(checkpoint_paths(run_dir, 1)) and (run_dir / "metrics_stage1.json").is_file()
    if args.stage == "1" or (args.stage == "all" and not (args.resume and stage1_done)):
        metrics = train_stage1(scene_dir, args.light, run_dir, cfg, seed=args.seed, device=args.device,
                               static=True if args.static else None, resume=args.resume,
                               progress=not args.no_progress)
        _report_stage1(run_dir, metrics)
    if args.stage in ("2", "all"):
        m2 = train_stage2(scene_dir, args.light, run_dir, cfg, seed=args.seed, device=args.device,
                          # --resume continues stage 2 where it has checkpoints, else starts it (a resumed
                          # stage 1 goes on into stage 2); without --resume, `all` still picks up its own
                          resume=(args.resume or args.stage == "all") and bool(checkpoint_paths(run_dir, 2)),
                          progress=not args.no_progress)
        print(f"stage 2:     PBR PSNR (train views) {m2['pbr_psnr']:.2f} dB"
              + (f"  albedo PSNR (aligned) {m2['albedo_psnr_aligned']:.2f} dB" if "albedo_psnr_aligned" in m2 else "")
              + f"  {m2['seconds']:.1f} s")
        pred = write_predictions(run_dir, scene_dir, args.light, cfg, method=name, device=args.device,
                                 seed=args.seed, progress=not args.no_progress)
        print(f"predictions: {pred}  (python -m benchmark score --data {scene_dir} --pred {pred} "
              f"--train-light {args.light} --test-light <light>)")
    return 0


def _is_static_capture(scene_dir: Path) -> bool:
    import json

    frames = json.loads((scene_dir / "transforms_train.json").read_text()).get("frames", [])
    return len({float(f.get("time", 0.0)) for f in frames}) <= 1


def _report_stage1(run_dir, metrics) -> None:
    test = metrics.get("test", {})
    sep = metrics.get("separation")
    print(f"run:         {run_dir}")
    if test:
        print(f"test views:  PSNR {test['psnr']:.2f} dB  SSIM {test['ssim']:.3f}  LPIPS {test['lpips_vgg']:.3f}")
    if sep:
        print(f"separation:  dynamic {sep['dynamic_recall']:.3f}  static {sep['static_recall']:.3f}")
    print(f"model:       {metrics['gaussians']} Gaussians, {metrics['parameters']} parameters, "
          f"{metrics['seconds']:.1f} s")
    if metrics.get("sheet"):
        print(f"sheet:       {metrics['sheet']}")
