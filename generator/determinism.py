"""Bit-exact renders: start Blender workers with address-space randomisation off.

Measured with bpy 5.0.1 (Cycles, CPU): the same scene, seed and settings rendered in two fresh
processes differ in a few silhouette pixels by ~1e-7 (Normal and Combined passes), with 1 thread as
with 2, with Embree as with BVH2; under ``setarch -R`` (no ASLR) every run is bit-identical. Some
ordering inside Blender follows memory addresses. Linux keeps the ADDR_NO_RANDOMIZE personality flag
across exec, so setting it in the parent while the worker processes start gives them fixed layouts.
"""
from __future__ import annotations

import contextlib
import ctypes
import sys
from typing import Iterator

ADDR_NO_RANDOMIZE = 0x0040000
_QUERY = 0xFFFFFFFF


def _personality():
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.personality
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_ulong]
    fn.restype = ctypes.c_int
    return fn


@contextlib.contextmanager
def no_aslr_children() -> Iterator[bool]:
    """Processes exec'd inside the block start without ASLR; yields whether that could be arranged."""
    fn = _personality()
    old = fn(_QUERY) if fn is not None else -1
    if old < 0:
        yield False
        return
    ok = fn(old | ADDR_NO_RANDOMIZE) >= 0 and (fn(_QUERY) & ADDR_NO_RANDOMIZE) != 0
    try:
        yield ok
    finally:
        fn(old)
