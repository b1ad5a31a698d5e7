"""Differentiable 2D Gaussian rasterizer and ray tracer: pure PyTorch (CPU and CUDA), with compiled CPU
kernels (Numba: raster_numba.py, trace_numba.py) behind the same functions (backend.py).

    from method.splat.camera import Camera          # pinhole camera from camera_angle_x + OpenGL c2w
    from method.splat.rasterize import rasterize    # -> RasterOutput (features, alpha, normal, depths, ...)
    from method.splat.trace import TraceAccel, trace  # grid once per splat set; transmittance + features

(Nothing is re-exported here: the function names equal their module names.)
"""
