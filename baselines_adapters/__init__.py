"""One adapter per method the benchmark can score, all behind one protocol.

``baselines_adapters.base.MethodAdapter`` is the protocol, ``baselines_adapters.registry`` maps names to
adapters. The trivial methods (``lit_as_albedo``, ``mean_albedo``) are the floors every method must beat;
``noisy_gt`` (ground truth plus Gaussian noise of a known sigma) is a sanity row and a test oracle.
"""
from .registry import available, get_adapter, register

__all__ = ["available", "get_adapter", "register"]
