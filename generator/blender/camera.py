"""Place the scene camera from an OpenGL camera-to-world matrix and a horizontal field of view."""
from __future__ import annotations

import numpy as np

import bpy
from mathutils import Matrix

CAMERA_NAME = "LumiBenchCamera"


def set_camera(bpy_scene, c2w, camera_angle_x: float):
    """Create (once) or update the scene camera: matrix_world = c2w, sensor fit horizontal, angle_x.

    Blender cameras already look down their local -Z with +Y up, the same convention as the dataset's
    transform_matrix, so the matrix is used as is (it must be a rigid transform: no scale).
    """
    m = np.asarray(c2w, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"c2w must be 4 x 4, got {m.shape}")
    rot = m[:3, :3]
    if not np.allclose(rot.T @ rot, np.eye(3), atol=1e-5) or np.linalg.det(rot) < 0:
        raise ValueError("c2w rotation must be orthonormal and right-handed (no scale or mirror)")
    obj = bpy_scene.objects.get(CAMERA_NAME)
    if obj is None or obj.type != "CAMERA":
        data = bpy.data.cameras.new(CAMERA_NAME)
        obj = bpy.data.objects.new(CAMERA_NAME, data)
        bpy_scene.collection.objects.link(obj)
    cam = obj.data
    cam.type = "PERSP"
    cam.sensor_fit = "HORIZONTAL"
    cam.shift_x = 0.0
    cam.shift_y = 0.0
    cam.angle_x = float(camera_angle_x)
    cam.clip_start = 1e-3
    cam.clip_end = 1e4
    obj.rotation_mode = "QUATERNION"
    obj.matrix_world = Matrix([[float(v) for v in row] for row in m])
    bpy_scene.camera = obj
    return obj
