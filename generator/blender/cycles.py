"""Cycles render settings shared by every dataset render, and an atomic still render."""
from __future__ import annotations

import contextlib
import os
from pathlib import Path

import bpy


def configure(bpy_scene, *, resolution: int, spp: int, seed: int, threads: int = 0,
              persistent_data: bool = True) -> None:
    """Cycles on CPU with a fixed seed, exactly ``spp`` samples, OIDN denoising only above 8 spp.

    Colour management is plain: "Standard" view transform (sRGB transfer, no tone curve), no look,
    exposure 0, gamma 1; film transparent so that alpha is the coverage of the scene. Output: PNG RGBA
    8-bit at resolution x resolution, 100 %, no metadata stamps (deterministic bytes). Adaptive sampling
    is off so every pixel gets ``spp``.
    """
    if resolution < 1 or spp < 1 or threads < 0:
        raise ValueError(f"bad render settings: resolution={resolution}, spp={spp}, threads={threads}")
    r = bpy_scene.render
    r.engine = "CYCLES"
    c = bpy_scene.cycles
    c.device = "CPU"
    c.samples = int(spp)
    c.use_adaptive_sampling = False
    c.use_denoising = spp > 8
    if c.use_denoising:
        c.denoiser = "OPENIMAGEDENOISE"
    c.seed = int(seed)
    c.use_animated_seed = False
    c.use_preview_denoising = False
    r.threads_mode = "AUTO" if threads == 0 else "FIXED"
    if threads:
        r.threads = int(threads)
    r.use_persistent_data = bool(persistent_data)
    r.film_transparent = True
    r.resolution_x = int(resolution)
    r.resolution_y = int(resolution)
    r.resolution_percentage = 100
    r.pixel_aspect_x = 1.0
    r.pixel_aspect_y = 1.0
    r.use_border = False
    vs = bpy_scene.view_settings
    bpy_scene.display_settings.display_device = "sRGB"
    vs.view_transform = "Standard"
    vs.look = "None"
    vs.exposure = 0.0
    vs.gamma = 1.0
    vs.use_curve_mapping = False
    _no_stamps(r)
    set_png_output(bpy_scene)


def _no_stamps(render) -> None:
    """No date, render time, host or file name in the written files: same inputs, same bytes."""
    for prop in render.bl_rna.properties:
        if prop.identifier.startswith("use_stamp") and prop.type == "BOOLEAN" and not prop.is_readonly:
            setattr(render, prop.identifier, False)


def set_png_output(bpy_scene) -> None:
    """Still output as PNG, RGBA, 8 bits per channel (display-referred, view transform applied)."""
    ims = bpy_scene.render.image_settings
    ims.media_type = "IMAGE"
    ims.file_format = "PNG"
    ims.color_mode = "RGBA"
    ims.color_depth = "8"
    ims.compression = 15


def set_exr_output(bpy_scene, *, multilayer: bool = False, half: bool = False) -> None:
    """Still output as linear OpenEXR (scene-referred: no view transform), RGBA or multilayer."""
    ims = bpy_scene.render.image_settings
    ims.media_type = "MULTI_LAYER_IMAGE" if multilayer else "IMAGE"
    ims.file_format = "OPEN_EXR_MULTILAYER" if multilayer else "OPEN_EXR"
    if not multilayer:
        ims.color_mode = "RGBA"
    ims.color_depth = "16" if half else "32"
    ims.exr_codec = "ZIP"


def render_still(bpy_scene, path) -> Path:
    """Render the scene's current frame to ``path``, atomically: temp name beside it, then rename.

    The temporary name keeps the extension and starts with '.tmp-', so an interrupted render never
    leaves a file that looks finished.
    """
    path = Path(path).resolve()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".tmp-{path.stem}-{os.getpid()}{path.suffix}")
    r = bpy_scene.render
    old = (r.filepath, r.use_file_extension)
    r.filepath = str(tmp)
    r.use_file_extension = False
    try:
        with _context_scene(bpy_scene):
            bpy.ops.render.render(write_still=True, scene=bpy_scene.name)
        if not tmp.is_file():
            raise RuntimeError(f"Blender did not write {tmp}")
        if path.suffix.lower() == ".png":
            _strip_png_text(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
    finally:
        r.filepath, r.use_file_extension = old
    return path


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_DROP = {b"tEXt", b"zTXt", b"iTXt", b"tIME"}


def _strip_png_text(path: Path) -> None:
    """Drop PNG text/time chunks: Cycles stamps its render time there even with every stamp option
    off, which would make identical renders differ in bytes. Pixel chunks are copied untouched."""
    data = path.read_bytes()
    if not data.startswith(_PNG_SIGNATURE):
        raise RuntimeError(f"{path} is not a PNG file")
    out = [_PNG_SIGNATURE]
    pos = len(_PNG_SIGNATURE)
    while pos + 12 <= len(data):
        length = int.from_bytes(data[pos:pos + 4], "big")
        kind = data[pos + 4:pos + 8]
        end = pos + 12 + length
        if kind not in _PNG_DROP:
            out.append(data[pos:end])
        pos = end
        if kind == b"IEND":
            break
    path.write_bytes(b"".join(out))


@contextlib.contextmanager
def _context_scene(bpy_scene):
    """Make ``bpy_scene`` the window's scene for the operator (a no-op when it already is)."""
    window = bpy.context.window
    if window is None or bpy.context.scene == bpy_scene:
        yield
        return
    previous = window.scene
    window.scene = bpy_scene
    try:
        yield
    finally:
        window.scene = previous
