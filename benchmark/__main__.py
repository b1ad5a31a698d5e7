"""python -m benchmark VERB: metrics of two images, scoring a prediction folder, the evaluation grid."""
import os
import sys

# before torch or Numba load, in this process and the grid's workers (they inherit it): with active OpenMP
# waiting, each one-thread grid worker kept a second thread spinning, and two workers on a 2-core box ran
# stage 1 ~7x slower (1.1 s against 0.15 s per iteration, measured session 23)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from lumibench.cli import build_main

main = build_main(
    "python -m benchmark",
    "Score inverse-rendering methods on the LumiBench train-light -> test-light protocol.",
    {
        "metrics": "benchmark.commands.metrics",
        "score": "benchmark.commands.score",
        "eval": "benchmark.commands.eval",
        "check-report": "benchmark.commands.check_report",
    },
)

if __name__ == "__main__":
    sys.exit(main())
