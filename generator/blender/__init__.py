"""The thin Blender layer: the only package that imports bpy (Cycles settings, camera, world).

Import the submodules from code that already runs Blender work; importing this package itself does not
import bpy, so the rest of the generator stays importable (and testable) without it.
"""
