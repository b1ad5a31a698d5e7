"""python -m method VERB: train LumiMotion (stage 1, stage 2) and relight a trained run."""
import os
import sys

# before torch loads: with active OpenMP waiting, 2 threads on a busy 2-core box ran ~15x slower (measured)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

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
