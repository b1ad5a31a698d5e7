"""`python -m benchmark metrics A B [--json]`: PSNR, SSIM, LPIPS-VGG and LPIPS-Alex of two images.

A quick check outside the scoring protocol: no mask, RGB only (alpha dropped, grey replicated), values
clipped to [0, 1] (so linear EXR/NPZ files are compared as displayed), LPIPS inputs mapped to [-1, 1].
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from lumibench.errors import UserError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "metrics",
        help="PSNR / SSIM / LPIPS of two same-size images",
        description="Print PSNR, SSIM, LPIPS-VGG and LPIPS-Alex of image A against image B (any format "
        "lumibench reads: PNG, JPEG, EXR, NPZ). RGB only; values clipped to [0, 1]; no mask; LPIPS inputs "
        "mapped to [-1, 1] (the standard convention).",
    )
    p.add_argument("a", metavar="A", help="first image (e.g. the prediction)")
    p.add_argument("b", metavar="B", help="second image (e.g. the ground truth)")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object {psnr, ssim, lpips_vgg, lpips_alex}; psnr is null for identical images")


def load_rgb(path: str):
    """Read an image as H x W x 3 float64 in [0, 1]; the error names the file."""
    import numpy as np

    from lumibench.io import read_image

    try:
        img = read_image(path)
    except UserError as exc:  # decoder messages can span lines; the CLI contract is one line
        raise UserError(str(exc).strip().splitlines()[0]) from None
    c = img.shape[-1]
    if c in (3, 4):
        img = img[..., :3]
    elif c in (1, 2):
        img = np.repeat(img[..., :1], 3, axis=-1)
    else:
        raise UserError(f"image {path} has {c} channels; expected grey, grey+alpha, RGB or RGBA")
    if not np.isfinite(img).all():
        raise UserError(f"image {path} contains NaN or infinite values")
    return np.clip(img.astype(np.float64), 0.0, 1.0)


def compute(a, b) -> dict:
    from benchmark.metrics import lpips, psnr, ssim

    value = psnr(a, b)
    return {
        "psnr": value if math.isfinite(value) else None,
        "ssim": ssim(a, b),
        "lpips_vgg": lpips(a, b, net="vgg", input_range="[-1,1]"),
        "lpips_alex": lpips(a, b, net="alex", input_range="[-1,1]"),
    }


def run(args: argparse.Namespace) -> int:
    a, b = load_rgb(args.a), load_rgb(args.b)
    if a.shape != b.shape:
        raise UserError(f"image sizes differ: {args.a} is {a.shape[1]} x {a.shape[0]}, "
                        f"{args.b} is {b.shape[1]} x {b.shape[0]} (width x height)")
    result = compute(a, b)
    if args.json:
        print(json.dumps(result))
    else:
        psnr_text = "inf (identical)" if result["psnr"] is None else f"{result['psnr']:.4f} dB"
        print(f"A: {Path(args.a)}\nB: {Path(args.b)}  ({a.shape[1]} x {a.shape[0]})")
        print(f"PSNR        {psnr_text}")
        print(f"SSIM        {result['ssim']:.6f}")
        print(f"LPIPS-VGG   {result['lpips_vgg']:.6f}")
        print(f"LPIPS-Alex  {result['lpips_alex']:.6f}")
    sys.stdout.flush()
    return 0
