"""Scene building is a pure function of the spec, in every process.

Cycles on CPU renders identical meshes to identical bytes, so the dataset's determinism rests on the
builder: the same spec must give the same vertices, the same face-corner order and the same normals in
any process, whatever its memory layout. (Blender's own UV-sphere operator did not: its corner order
followed addresses, and renders of moving spheres differed in the last bit between processes.)
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("bpy")
pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parent.parent

# Prints one digest per mesh object of every benchmark scene and per primitive: vertex positions,
# face-corner vertex order, corner normals, and the world matrix at a few times.
_DIGEST_SCRIPT = r"""
import hashlib, json, sys
import numpy as np
import bpy
from generator.blender.build import build_scene, make_mesh, reset_blender
from generator.spec import PRIMITIVES, load_scene_spec

def mesh_digest(me, h):
    co = np.zeros(len(me.vertices) * 3, np.float32); me.vertices.foreach_get("co", co)
    lv = np.zeros(len(me.loops), np.int32); me.loops.foreach_get("vertex_index", lv)
    cn = np.zeros(len(me.loops) * 3, np.float32); me.corner_normals.foreach_get("vector", cn)
    for a in (co, lv, cn):
        h.update(a.tobytes())

out = {}
scene = reset_blender()
for prim in PRIMITIVES:
    if prim != "rig":
        h = hashlib.sha256(); mesh_digest(make_mesh(prim, prim, (0.7, 0.5, 0.9)), h); out[prim] = h.hexdigest()
for name in sys.argv[1:]:
    scene = reset_blender()
    built = build_scene(scene, load_scene_spec(name))
    hs = {}
    for t in (0.0, 0.37, 1.0):
        built.set_time(t)
        dg = bpy.context.evaluated_depsgraph_get()
        for ob in scene.objects:
            if ob.type != "MESH":
                continue
            h = hs.setdefault(ob.name, hashlib.sha256())
            h.update(np.array(ob.evaluated_get(dg).matrix_world, np.float32).tobytes())
    for ob in scene.objects:
        if ob.type == "MESH":
            mesh_digest(ob.evaluated_get(bpy.context.evaluated_depsgraph_get()).data, hs[ob.name])
    out.update({f"{name}/{k}": h.hexdigest() for k, h in hs.items()})
print(json.dumps(out))
"""


def _digests(scenes: list[str], pad: int) -> dict[str, str]:
    """Digests from a fresh interpreter whose environment (and so its memory layout) grows with ``pad``."""
    env = dict(os.environ, LUMIBENCH_LAYOUT_PAD="x" * pad)
    proc = subprocess.run([sys.executable, "-c", _DIGEST_SCRIPT, *scenes], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_meshes_are_identical_across_processes():
    scenes = ["spheres", "jumpingjacks", "hook", "mouse", "standup"]
    runs = [_digests(scenes, pad) for pad in (0, 37, 4099)]
    assert len(runs[0]) > 20
    for other in runs[1:]:
        differ = sorted(k for k in runs[0] if runs[0][k] != other.get(k))
        assert not differ, f"meshes built differently in another process: {differ[:8]}"
