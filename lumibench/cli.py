"""`python -m <package> <verb>`: each verb is a module with ``register(subparsers)`` and ``run(args)``."""
from __future__ import annotations

import argparse
import importlib
from typing import Sequence

from .errors import run_cli


def build_main(prog: str, description: str, verbs: dict[str, str]):
    """Return ``main(argv)`` dispatching to verb modules, imported lazily (bpy and torch load slowly)."""

    def main(argv: Sequence[str] | None = None) -> int:
        parser = argparse.ArgumentParser(prog=prog, description=description)
        sub = parser.add_subparsers(dest="verb", metavar="VERB")
        modules = {}
        for verb, module_name in verbs.items():
            module = importlib.import_module(module_name)
            modules[verb] = module
            module.register(sub)
        args = parser.parse_args(argv)
        if args.verb is None:
            parser.print_help()
            return 2
        return modules[args.verb].run(args) or 0

    return lambda argv=None: run_cli(main, argv)
