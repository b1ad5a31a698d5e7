"""python -m baselines_adapters VERB: export a scene for an external method, import its outputs."""
import sys

from lumibench.cli import build_main

main = build_main(
    "python -m baselines_adapters",
    "Run external inverse-rendering methods (IRGS, R-3DGS, GI-GS, the authors' LumiMotion) on LumiBench scenes.",
    {
        "export": "baselines_adapters.commands.export",
        "import": "baselines_adapters.commands.importer",
    },
)

if __name__ == "__main__":
    sys.exit(main())
