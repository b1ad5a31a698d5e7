"""python -m generator VERB: dataset rendering, the demo and generator benchmarks."""
import sys

from lumibench.cli import build_main

main = build_main(
    "python -m generator",
    "Render the LumiBench synthetic dataset with Blender (Cycles, CPU).",
    {"dataset": "generator.commands.dataset", "demo": "generator.commands.demo", "bench": "generator.commands.bench"},
)

if __name__ == "__main__":
    sys.exit(main())
