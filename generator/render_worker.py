"""Worker-process entry points for the frame renders (ProcessPoolExecutor, spawn context).

This module must not import bpy at top level: the parent imports it to name the functions, and bpy
loaded in the parent would put Blender's script folders on the sys.path the spawned workers inherit,
which breaks ``import bpy`` there. Each worker imports bpy and builds the scene once, in init_worker.
"""
from __future__ import annotations

import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

_RENDERER = None
_SPEC_HASH = ""


def init_worker(spec, spec_hash: str, settings, hdr_paths: dict[str, str], threads: int,
                persistent_data: bool = True) -> None:
    global _RENDERER, _SPEC_HASH
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle (it stops the workers)
    _watch_parent()
    _silence_stdout()
    drop_blender_script_paths()
    from .blender.render_frame import FrameRenderer

    _RENDERER = FrameRenderer(spec, settings, hdr_paths, threads=threads, persistent_data=persistent_data)
    _SPEC_HASH = spec_hash


def render_job(job) -> dict[str, Any]:
    if _RENDERER is None:
        raise RuntimeError("render worker used before init_worker")
    return _RENDERER.render(job, _SPEC_HASH)


def drop_blender_script_paths() -> None:
    """Spawned workers inherit the parent's sys.path. If the parent imported bpy (a test process may), that
    path lists Blender's script folders, whose ``modules/bpy`` would shadow the real bpy extension module
    here; drop them, and bpy puts them back when it is imported."""
    def is_blender_scripts(p: str) -> bool:
        parts = Path(p).parts
        return "scripts" in parts and any(x in ("bpy", "blender") for x in parts[:parts.index("scripts")])

    if "bpy" not in sys.modules:
        sys.path[:] = [p for p in sys.path if not is_blender_scripts(p)]


def _silence_stdout() -> None:
    """Blender prints a line per saved file from C: send the worker's stdout to /dev/null (not stderr)."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.close(devnull)


def _watch_parent() -> None:
    """Exit when the parent dies: a killed run must not leave orphans rendering in the background."""
    parent = os.getppid()

    def watch() -> None:
        while True:
            time.sleep(0.5)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, daemon=True, name="watch-parent").start()
