"""Pinhole camera built from the dataset's conventions (camera_angle_x + OpenGL camera-to-world).

Internally the rasterizer works in the "vision" camera frame (x right, y down, z forward), so that a
pixel (i, j) with centre (x, y) = (j + 0.5, i + 0.5) maps to the direction ((x - cx) / f, (y - cy) / f, 1).
The OpenGL frame (x right, y up, looking down -z) differs from it by diag(1, -1, -1), a proper rotation.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

_GL_TO_CV = torch.tensor([[1.0, 0, 0, 0], [0, -1.0, 0, 0], [0, 0, -1.0, 0], [0, 0, 0, 1.0]], dtype=torch.float64)


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: square pixels, principal point at the image centre."""

    width: int
    height: int
    focal: float  # pixels (fx = fy)
    w2c: torch.Tensor  # 4 x 4 world -> vision-camera (x right, y down, z forward)
    c2w: torch.Tensor  # its inverse

    @property
    def cx(self) -> float:
        return 0.5 * self.width

    @property
    def cy(self) -> float:
        return 0.5 * self.height

    @property
    def center(self) -> torch.Tensor:
        """Camera position in world space, shape (3,)."""
        return self.c2w[:3, 3]

    @property
    def device(self) -> torch.device:
        return self.w2c.device

    @property
    def dtype(self) -> torch.dtype:
        return self.w2c.dtype

    @staticmethod
    def from_blender(camera_angle_x: float, c2w_gl, width: int, height: int,
                     device: torch.device | str | None = None, dtype: torch.dtype = torch.float32) -> "Camera":
        """Camera from the dataset: horizontal FOV in radians and an OpenGL camera-to-world 4 x 4."""
        if not (0.0 < float(camera_angle_x) < math.pi):
            raise ValueError(f"camera_angle_x must be in (0, pi) radians, got {camera_angle_x}")
        if int(width) <= 0 or int(height) <= 0:
            raise ValueError(f"image size must be positive, got {width} x {height}")
        m = torch.as_tensor(np.asarray(c2w_gl, dtype=np.float64) if not torch.is_tensor(c2w_gl) else c2w_gl,
                            dtype=torch.float64).cpu()
        if m.shape != (4, 4):
            raise ValueError(f"c2w must be 4 x 4, got {tuple(m.shape)}")
        c2w_cv = m @ _GL_TO_CV  # columns: camera x, -y_gl (down), -z_gl (forward), position
        w2c_cv = torch.linalg.inv(c2w_cv)
        focal = 0.5 * int(width) / math.tan(0.5 * float(camera_angle_x))
        return Camera(int(width), int(height), focal,
                      w2c_cv.to(device=device, dtype=dtype), c2w_cv.to(device=device, dtype=dtype))

    @staticmethod
    def look_at(eye, target, width: int, height: int, camera_angle_x: float = 0.6911112070083618,
                up=(0.0, 0.0, 1.0), device=None, dtype: torch.dtype = torch.float32) -> "Camera":
        """Convenience for tests and benchmarks: an OpenGL-convention camera at ``eye`` looking at ``target``."""
        eye = np.asarray(eye, dtype=np.float64)
        fwd = np.asarray(target, dtype=np.float64) - eye
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, np.asarray(up, dtype=np.float64))
        if np.linalg.norm(right) < 1e-9:
            right = np.cross(fwd, np.array([0.0, 1.0, 0.0]))
        right /= np.linalg.norm(right)
        true_up = np.cross(right, fwd)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, -fwd, eye
        return Camera.from_blender(camera_angle_x, c2w, width, height, device=device, dtype=dtype)

    def to(self, device=None, dtype: torch.dtype | None = None) -> "Camera":
        dtype = dtype or self.dtype
        return Camera(self.width, self.height, self.focal, self.w2c.to(device=device, dtype=dtype),
                      self.c2w.to(device=device, dtype=dtype))

    def pixel_rays(self) -> tuple[torch.Tensor, torch.Tensor]:
        """World-space origins and unit directions through every pixel centre, each (H, W, 3)."""
        dev, dt = self.device, self.dtype
        ys = torch.arange(self.height, device=dev, dtype=dt) + 0.5
        xs = torch.arange(self.width, device=dev, dtype=dt) + 0.5
        y, x = torch.meshgrid(ys, xs, indexing="ij")
        d_cam = torch.stack([(x - self.cx) / self.focal, (y - self.cy) / self.focal, torch.ones_like(x)], -1)
        d = d_cam @ self.c2w[:3, :3].T
        d = d / d.norm(dim=-1, keepdim=True)
        return self.center.expand_as(d), d
