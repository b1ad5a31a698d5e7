"""`python -m benchmark score`: score one predictions folder on one scene -> one result file."""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("score", help="score a predictions folder (layout: benchmark/predictions.py)",
                       description="Score one method's predictions for one scene and train -> test light pair.")
    p.add_argument("--data", required=True, help="the rendered scene directory (DATA/PROFILE/<scene>)")
    p.add_argument("--pred", required=True, help="the predictions folder")
    p.add_argument("--train-light", required=True)
    p.add_argument("--test-light", required=True)
    p.add_argument("--protocol", default="lumimotion", choices=["lumimotion", "strict"])
    p.add_argument("--lpips-net", default="vgg", choices=["vgg", "alex"])
    p.add_argument("--profile", default=None, help="profile name recorded in the result (default: from meta.json)")
    p.add_argument("--out", default=None, help="result file to write (default: <pred>/results_<train>_to_<test>.json)")


def run(args: argparse.Namespace) -> int:
    from benchmark.results import write_result
    from benchmark.score import score

    res = score(args.data, args.pred, args.train_light, args.test_light, args.protocol, args.lpips_net,
                args.profile)
    out = Path(args.out) if args.out else Path(args.pred) / f"results_{args.train_light}_to_{args.test_light}.json"
    write_result(out, res)
    summary = {task: res["metrics"][task] for task in ("nvs", "albedo", "roughness", "relight", "delta_psnr",
                                                        "separation") if res["metrics"].get(task)}
    print(json.dumps(summary, indent=1))
    print(f"wrote {out}")
    return 0
