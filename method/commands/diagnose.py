"""`python -m method diagnose`: where a trained run's relighting error is (method/diagnose.py)."""
from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("diagnose", help="relight the test views with our buffers replaced by the ground truth",
                       description="Relight a trained run's test views under a test light with, in turn, our albedo, "
                                   "roughness and normals replaced by the ground truth (then all three), and score "
                                   "each step as the benchmark's relight: RUN/diagnose/<light>/diagnose.json and "
                                   "sheet.png.")
    p.add_argument("--run", required=True, help="run directory (with checkpoints/stage2_*.pt)")
    p.add_argument("--test-light", required=True, help="a light rendered for the scene's test views")
    p.add_argument("--dirs", type=int, default=None, help="directions per pixel (default the profile's dirs_eval)")
    p.add_argument("--views", type=int, default=None, help="only the first N test views (default all)")
    p.add_argument("--data", default=None, help="where the run's scene is now, if the dataset moved")
    p.add_argument("--out", default=None, help="output folder (default RUN/diagnose/<test light>)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--seed", type=int, default=0)


def run(args: argparse.Namespace) -> int:
    from lumibench.layout import parse_light
    from method.diagnose import diagnose

    light, _ = parse_light(args.test_light)  # a light file is its stem: the dataset's folder, RUN/diagnose/<light>
    rec = diagnose(args.run, light, dirs=args.dirs, views=args.views, device=args.device, seed=args.seed,
                   data=args.data, out=args.out)
    print(f"{rec['scene']}: {rec['train_light']} -> {rec['test_light']}, {rec['views']} views, "
          f"relight PSNR (lumimotion)")
    for name, s in rec["steps"].items():
        print(f"  {name:17s} {s['psnr']:6.2f} dB  ({s['psnr_gain']:+.2f})  SSIM {s['ssim']:.3f}  "
              f"LPIPS {s['lpips']:.3f}")
    return 0
