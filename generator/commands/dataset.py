"""`python -m generator dataset` (`make dataset`): render DATA/PROFILE/<scene> for each scene, resumably."""
from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("dataset", help="render the dataset (both variants, train and test splits) of scenes",
                       description="Render DATA/PROFILE/<scene> and <scene>_statictimestepNNNN for each scene. "
                                   "Resumable: finished frames with the same spec hash and settings are skipped.")
    p.add_argument("--profile", default="ci", help="configs/profiles/<name>.yaml: ci, demo, small or full (default ci)")
    p.add_argument("--data", default="data", help="dataset root (default data)")
    p.add_argument("--jobs", type=int, default=1, help="worker processes, each building the scene once (default 1)")
    p.add_argument("--scenes", nargs="+", default=None, help="scene names or scene YAML paths (default: every configs/scenes/*.yaml)")
    p.add_argument("--lights", nargs="+", default=None,
                   help="light names from configs/lights.yaml or .hdr/.exr paths (default: the four default lights; "
                        "a light with default: false, e.g. city_sharp, only when named)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from generator import pipeline, spec as spec_mod
    from lumibench.errors import UserError
    from lumibench.profiles import load_profile

    if args.jobs < 1:
        raise UserError(f"--jobs must be at least 1, got {args.jobs}")
    load_profile(args.profile)
    scenes = args.scenes or spec_mod.available_scenes()
    for name in scenes:  # every mistake is reported before the first render
        pipeline.load_spec(name)
    pipeline.resolve_lights(args.lights)
    pipeline.check_writable(Path(args.data))
    for name in scenes:
        out = pipeline.render_scene(name, args.profile, Path(args.data), jobs=args.jobs, lights=args.lights,
                                    progress=not args.no_progress)
        print(f"{name}: {out}")
    return 0
