"""`python -m baselines_adapters export`: our scene in the layout an external method's code reads."""
from __future__ import annotations

import argparse

METHODS = ("irgs", "r3dgs", "gigs", "lumimotion_official")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="write a scene in the layout an external method reads",
                       description="Write both variants of a rendered scene (dynamic and _statictimestepNNNN) "
                                   "in the layout the external method's loader and evaluation scripts read, "
                                   "and print the commands that train and evaluate it.")
    p.add_argument("method", choices=METHODS)
    p.add_argument("--data", required=True, help="the rendered scene directory (DATA/PROFILE/<scene>)")
    p.add_argument("--out", required=True, help="export root: writes OUT/<scene> and OUT/<scene>_statictimestepNNNN")
    p.add_argument("--train-light", default=None, help="fills the printed commands (all lights are exported)")
    p.add_argument("--test-light", default=None, help="fills the printed commands")
    p.add_argument("--run", default=None, help="the method's model dir in the printed commands "
                                               "(default: where the benchmark grid looks for it)")


def run(args: argparse.Namespace) -> int:
    from lumibench.errors import UserError

    from ..external import get_method
    from ..external.common import default_run_hint, export_paper_layout

    spec = get_method(args.method)
    names, dirs = export_paper_layout(args.data, args.out, spec.name)
    for role, light in (("train", args.train_light), ("test", args.test_light)):
        if light is not None and light not in names.lights:
            raise UserError(f"unknown {role} light '{light}' (exported: {', '.join(names.lights)})")
    print(f"exported {names.name} for {spec.title} ({spec.repo}@{spec.commit[:12]}):")
    print(f"  dynamic variant: {dirs['dynamic']}")
    print(f"  static variant:  {dirs['static']}   ({spec.title} trains on the {spec.trains_on} variant)")
    print(f"  lights: {', '.join(names.lights)}; test views {', '.join(names.test_stems)} are named "
          f"{', '.join(names.test_names)} there")
    print("then, in a checkout of that repository:")
    cmds = spec.command_lines(names, dirs, args.train_light, args.test_light, args.run)
    for line in cmds:
        print(f"  {line}")
    run_dir = args.run or default_run_hint(spec.name, names, args.train_light,
                                           None if spec.relight_names_light else args.test_light)
    light = f" --test-light {args.test_light or '<test light>'}" if not spec.relight_names_light else ""
    print("and import its outputs for scoring:")
    print(f"  python -m baselines_adapters import {spec.name} --from {run_dir} --data {names.scene}{light} --out PRED")
    return 0
