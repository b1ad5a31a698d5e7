"""`python -m baselines_adapters import`: an external method's outputs -> our predictions folder."""
from __future__ import annotations

import argparse

METHODS = ("irgs", "r3dgs", "gigs", "lumimotion_official")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("import", help="turn an external method's outputs into a predictions folder",
                       description="Read the files an external method's render/eval scripts wrote (named as its "
                                   "repository writes them) and write our predictions layout "
                                   "(lumibench/predictions.py), meta.json last, ready for 'python -m benchmark score'.")
    p.add_argument("method", choices=METHODS)
    p.add_argument("--from", dest="source", required=True, help="the method's output (model) dir")
    p.add_argument("--out", required=True, help="predictions folder to write")
    p.add_argument("--data", default=None, help="our rendered scene dir (default: found through the export "
                                                "manifest named by <from>/cfg_args' source_path)")
    p.add_argument("--export", default=None, help="the dir written by 'export' (to find the scene without --data)")
    p.add_argument("--test-light", action="append", default=None,
                   help="light of the relit outputs (needed where the method's file names do not say it: "
                        "r3dgs, lumimotion_official); repeat to restrict the others")
    p.add_argument("--train-light", default=None, help="recorded in meta.json")
    p.add_argument("--seed", type=int, default=0, help="recorded in meta.json")
    p.add_argument("--variant", default="static", choices=["static", "dynamic"],
                   help="lumimotion_official: which evaluation scripts' outputs to read (default: static)")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from lumibench.predictions import write_meta

    from ..external import get_method
    from ..external.common import Importer, import_run, scene_for_import

    spec = get_method(args.method)
    source, out = Path(args.source), Path(args.out)
    names = scene_for_import(source, args.data, args.export)
    (out / "meta.json").unlink(missing_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    options = {"variant": args.variant} if spec.name == "lumimotion_official" else {}
    info = import_run(spec, Importer(names, out), source, list(args.test_light or []), **options)
    meta = {"method": spec.name, "version": spec.version, "seed": int(args.seed), "device": "external",
            "scene": names.name, "train_light": args.train_light, "test_lights": info["relit_lights"],
            "external": info}
    write_meta(out, meta)
    kinds = ", ".join(f"{k} ({v})" for k, v in sorted(info["kinds"].items()))
    print(f"wrote {out}: {kinds}")
    for light in info["relit_lights"]:
        print(f"score: python -m benchmark score --data {names.scene} --pred {out} "
              f"--train-light {args.train_light or '<train light>'} --test-light {light}")
    return 0
