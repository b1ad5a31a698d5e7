"""External methods (their code is not ours and needs a CUDA GPU): export our scenes to the layout their
loaders read, print how to run them, import their outputs into our predictions layout.

``irgs`` (IRGS), ``r3dgs`` (R-3DGS), ``gigs`` (GI-GS), ``lumimotion_official`` (the authors' LumiMotion).
Each module's docstring says which repository file and commit its convention was read from.
"""
from __future__ import annotations

import importlib

from lumibench.errors import UserError

from .common import ExternalAdapter, ExternalMethod

MODULES = {"irgs": "irgs", "r3dgs": "r3dgs", "gigs": "gigs", "lumimotion_official": "lumimotion_official"}


def methods() -> list[str]:
    return list(MODULES)


def get_method(name: str) -> ExternalMethod:
    if name not in MODULES:
        raise UserError(f"unknown external method '{name}' (known: {', '.join(MODULES)})")
    return importlib.import_module(f"{__name__}.{MODULES[name]}").SPEC


def adapter(name: str) -> ExternalAdapter:
    return ExternalAdapter(get_method(name))


# zero-argument factories for the registry (not named like the submodules, which would shadow them)
def irgs_adapter() -> ExternalAdapter:
    return adapter("irgs")


def r3dgs_adapter() -> ExternalAdapter:
    return adapter("r3dgs")


def gigs_adapter() -> ExternalAdapter:
    return adapter("gigs")


def lumimotion_official_adapter() -> ExternalAdapter:
    return adapter("lumimotion_official")
