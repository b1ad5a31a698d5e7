"""python -m method VERB: train LumiMotion (stage 1, stage 2) and relight a trained run."""
import sys

from lumibench.threads import configure_threads

configure_threads()  # before torch or Numba load; the grid's workers inherit it (lumibench/threads.py)

from lumibench.cli import build_main

main = build_main(
    "python -m method",
    "LumiMotion: relightable dynamic 2D Gaussian splatting (train, relight, diagnose).",
    {
        "train": "method.commands.train",
        "relight": "method.commands.relight",
        "diagnose": "method.commands.diagnose",
        "demo": "method.commands.demo",
    },
)

if __name__ == "__main__":
    sys.exit(main())
