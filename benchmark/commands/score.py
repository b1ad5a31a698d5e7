"""`python -m benchmark score`: score one predictions folder on one scene -> one result file."""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from lumibench.errors import UserError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("score", help="score a predictions folder (layout: lumibench/predictions.py)",
                       description="Score one method's predictions for one scene and train -> test light pair.")
    p.add_argument("--data", required=True, help="the rendered scene directory (DATA/PROFILE/<scene>)")
    p.add_argument("--pred", required=True, help="the predictions folder")
    p.add_argument("--train-light", required=True)
    p.add_argument("--test-light", required=True)
    p.add_argument("--protocol", default="lumimotion", choices=["lumimotion", "strict"])
    p.add_argument("--lpips-net", default="vgg", choices=["vgg", "alex"])
    p.add_argument("--profile", default=None, help="profile name recorded in the result (default: from meta.json)")
    p.add_argument("--out", default=None, help="result file to write (default: <pred>/results_<train>_to_<test>.json)")


def check_out(out: Path, given: bool) -> None:
    """Before any metric runs: the result file can be written (one line naming it otherwise)."""
    hint = "choose another --out" if given else "the predictions folder is not writable: give --out"
    if out.is_dir():
        raise UserError(f"--out {out} is a directory; give the result file's path, e.g. {out / 'results.json'}")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=out.parent, prefix=".write-test-"):
            pass
    except OSError as exc:
        raise UserError(f"cannot write the result file {out}: {exc.strerror or exc} ({hint})") from None


def run(args: argparse.Namespace) -> int:
    from benchmark.results import write_result
    from benchmark.score import score
    from lumibench.layout import parse_light

    args.train_light, _ = parse_light(args.train_light)  # a light file is its stem, the dataset's folder
    args.test_light, _ = parse_light(args.test_light)
    out = Path(args.out) if args.out else Path(args.pred) / f"results_{args.train_light}_to_{args.test_light}.json"
    if args.out or Path(args.pred).is_dir():  # a missing --pred folder is score()'s error to name
        check_out(out, bool(args.out))
    res = score(args.data, args.pred, args.train_light, args.test_light, args.protocol, args.lpips_net,
                args.profile)
    try:
        write_result(out, res)
    except OSError as exc:
        raise UserError(f"cannot write the result file {out}: {exc.strerror or exc}") from None
    summary = {task: res["metrics"][task] for task in ("nvs", "albedo", "roughness", "relight", "delta_psnr",
                                                        "separation") if res["metrics"].get(task)}
    print(json.dumps(summary, indent=1))
    print(f"wrote {out}")
    return 0
