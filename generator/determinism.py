"""Reproducible renders: start Blender workers with address-space randomisation off.

Measured with bpy 5.0.1 (Cycles, CPU, this repository's scenes):
- the same frame rendered in two fresh processes differed in a few silhouette pixels by ~1e-7 (Normal
  and Combined passes), with 1 thread as with 2, with Embree as with BVH2; under ``setarch -R`` (no
  ASLR) fresh processes gave bit-identical passes: some ordering inside Blender follows addresses;
- even without ASLR, a frame's Normal pass still depends, in the last bit, on what the process rendered
  before it (with or without persistent data) and occasionally on thread timing; only pixels of moving
  objects were affected (normals within 6e-8). A fresh process per frame did not remove it completely
  (3 of 36 frames differed) and cost ~1.4 s of bpy start-up per frame, so the pipeline keeps one
  persistent worker per job and documents the bound instead: albedo, roughness and dynamic-mask files
  are byte-identical, normal .npz agree within 1e-5 (silhouette pixels divide by a small coverage),
  PNGs within one 8-bit step at rare pixels.
Tried later (lead, 2026-11-22) and dropped: a worker pinned to ONE core before bpy loads (Blender's task
scheduler and Embree's BVH build then single-threaded), started fresh for every frame with ASLR off. One
frame gave the same bytes in 6 of 6 runs and two whole-scene runs matched, but a kill-and-resume run in a
fresh clone still differed from an uninterrupted one in one normal .npz; normals also changed with the
parent's start-up (a `python -c` parent vs a script parent: the spawned worker's heap layout differs) and
with what the process rendered before a frame. It cost ~3x the ci render time for no guarantee.
Forking a worker after the scene is built (to give every frame the same history) deadlocks: Blender's
TBB thread pool does not survive fork.

Linux keeps the ADDR_NO_RANDOMIZE personality flag across exec (and threads inherit it), so setting it
while the worker processes start gives them fixed layouts.
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
