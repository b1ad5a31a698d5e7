"""Registry of method adapters by name; later methods register themselves here (``register``)."""
from __future__ import annotations

import importlib
from typing import Callable

from lumibench.errors import UserError

from .base import MethodAdapter

# name -> "module:attribute" of a zero-argument factory, imported lazily (a method may pull in torch)
_FACTORIES: dict[str, str | Callable[[], MethodAdapter]] = {
    "lit_as_albedo": "baselines_adapters.trivial:LitAsAlbedo",
    "mean_albedo": "baselines_adapters.trivial:MeanAlbedo",
    "noisy_gt": "baselines_adapters.trivial:NoisyGT",
}


def register(name: str, factory: str | Callable[[], MethodAdapter]) -> None:
    """Add a method: ``factory`` is a callable or a "module:attribute" string resolved on first use."""
    _FACTORIES[name] = factory


def available() -> list[str]:
    return sorted(_FACTORIES)


def get_adapter(name: str) -> MethodAdapter:
    if name not in _FACTORIES:
        raise UserError(f"unknown method '{name}' (known: {', '.join(available())})")
    factory = _FACTORIES[name]
    if isinstance(factory, str):
        module_name, attr = factory.split(":")
        factory = getattr(importlib.import_module(module_name), attr)
    adapter = factory()
    if not isinstance(adapter, MethodAdapter):
        raise TypeError(f"factory for '{name}' returned {type(adapter).__name__}, not a MethodAdapter")
    return adapter


# --- external methods (appended): scored from their own outputs; "not run" until someone runs them ---
for _name in ("irgs", "r3dgs", "gigs", "lumimotion_official"):
    register(_name, f"baselines_adapters.external:{_name}_adapter")
del _name


# --- in-project methods: LumiMotion, its ablations, the static baseline; "<method>@<budget>" variants ---
_IN_PROJECT = ("lumimotion", "wo_stage2", "wo_dc", "wo_P", "static")
for _name in _IN_PROJECT:
    register(_name, f"baselines_adapters.lumimotion:{_name}_factory")
del _name


def _budget_variant(name: str):
    """'lumimotion@0.25' etc.: an in-project method at a budget (see baselines_adapters/lumimotion.py)."""
    base, sep, budget = name.partition("@")
    if not sep or base not in _IN_PROJECT:
        return None
    from .lumimotion import LumiMotionAdapter, parse_budget

    parse_budget(budget)  # validates, one-line error
    return lambda: LumiMotionAdapter(base, budget)


_get_adapter_plain = get_adapter


def get_adapter(name: str) -> MethodAdapter:  # noqa: F811  (extends the lookup with budget variants)
    if "@" in name and name not in _FACTORIES:
        factory = _budget_variant(name)
        if factory is not None:
            return factory()
    return _get_adapter_plain(name)


def is_known(name: str) -> bool:
    """A registered method or a valid budget variant of an in-project one."""
    if name in _FACTORIES:
        return True
    try:
        return _budget_variant(name) is not None
    except UserError:
        return False
