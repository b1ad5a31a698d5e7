"""`python -m method relight`: a trained run's views at any time under any environment map."""
from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("relight", help="render a trained run under any environment map",
                       description="Render the test views (or an orbit) of a trained run at a time, under an env "
                                   "map given as an .hdr/.exr file or a light name, writing albedo (linear .npz "
                                   "and sRGB PNG), roughness, normals, the relit image and the estimated env map.")
    p.add_argument("--run", required=True, help="run directory (with checkpoints/stage2_*.pt)")
    p.add_argument("--envmap", required=True, help=".hdr/.exr file, or a light name (the scene's <light>.hdr or "
                                                  "configs/lights.yaml)")
    p.add_argument("--views", default="test", choices=["test", "orbit"], help="test cameras or an orbit")
    p.add_argument("--time", type=float, default=None, help="time in [0, 1] (default: each test view's own time; "
                                                             "orbit: 0)")
    p.add_argument("--frames", type=int, default=24, help="orbit frames (default 24)")
    p.add_argument("--dirs", type=int, default=None, help="directions per pixel (default the profile's dirs_eval)")
    p.add_argument("--out", default=None, help="output folder (default RUN/relight/<envmap name>)")
    p.add_argument("--data", default=None, metavar="DIR",
                   help="where the run's scene is now, if the dataset moved since training: the scene directory "
                        "itself or a data root holding <profile>/<scene> (default: the path in RUN/config.yaml)")
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default cpu)")
    p.add_argument("--splat-backend", default=None, choices=["auto", "torch", "numba"],
                   help="rasterizer/tracer implementation (default auto: compiled CPU kernels when available)")
    p.add_argument("--seed", type=int, default=0)


def run(args: argparse.Namespace) -> int:
    from method.commands.train import set_splat_backend
    from method.relight import relight

    set_splat_backend(args.splat_backend)
    out = relight(args.run, args.envmap, views=args.views, time=args.time, frames=args.frames, dirs=args.dirs,
                  out=args.out, device=args.device, seed=args.seed, data=args.data)
    print(f"relit: {out}")
    return 0
