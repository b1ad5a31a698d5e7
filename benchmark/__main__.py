"""python -m benchmark VERB: metrics of two images, scoring a prediction folder, the evaluation grid."""
import sys

from lumibench.threads import configure_threads

configure_threads()  # before torch or Numba load; the grid's workers inherit it (lumibench/threads.py)

from lumibench.cli import build_main

main = build_main(
    "python -m benchmark",
    "Score inverse-rendering methods on the LumiBench train-light -> test-light protocol.",
    {
        "metrics": "benchmark.commands.metrics",
        "score": "benchmark.commands.score",
        "eval": "benchmark.commands.eval",
        "tables": "benchmark.commands.tables",
        "compare": "benchmark.commands.compare",
        "check-report": "benchmark.commands.check_report",
    },
)

if __name__ == "__main__":
    sys.exit(main())
