"""`python -m generator demo` (`make demo`): the ci dataset of the default scene and its contact sheet."""
from __future__ import annotations

import argparse
from pathlib import Path

# Primitives only (fastest to build and render), four balls whose shadows sweep a checkered plate.
DEMO_SCENE = "spheres"
DEMO_PROFILE = "ci"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help=f"render the {DEMO_PROFILE} dataset of '{DEMO_SCENE}' and a contact sheet",
                       description=f"Render DATA/{DEMO_PROFILE}/{DEMO_SCENE} (resumable) and write a contact sheet PNG: "
                                   "a few frames x (lit under each light, albedo, roughness, normals, dynamic mask).")
    p.add_argument("--data", default="data", help="dataset root (default data)")
    p.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    p.add_argument("--scene", default=DEMO_SCENE, help=f"scene to show (default {DEMO_SCENE})")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from generator import pipeline
    from generator.contact_sheet import make_contact_sheet
    from lumibench.errors import UserError

    if args.jobs < 1:
        raise UserError(f"--jobs must be at least 1, got {args.jobs}")
    scene_dir = pipeline.render_scene(args.scene, DEMO_PROFILE, Path(args.data), jobs=args.jobs,
                                      progress=not args.no_progress)
    sheet = make_contact_sheet(scene_dir, scene_dir.parent / f"contact_sheet_{args.scene}.png")
    print(f"dataset:       {scene_dir}")
    print(f"contact sheet: {sheet}")
    return 0
