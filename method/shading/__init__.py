"""Physically based shading for stage 2: env maps, BRDF, direction sampling, Monte Carlo shading, tracing.

    from method.shading.envmap import load_envmap, lookup, LearnableEnvMap, lower_hemisphere_l2, resample
    from method.shading.render import shade            # (P,) G-buffer pixels -> linear RGB (P, 3)
    from method.shading.visibility import GaussianTracer  # V and indirect light from the 2D Gaussians

Conventions: env maps are (H, W, 3) linear radiance in the generator's equirectangular orientation with
a nearest-texel lookup (as Blender renders the dataset); directions are world-space unit vectors;
view_dirs point from the surface to the camera; colours are linear.

Pinned to Blender by tests/test_shading.py (calib_sphere, ci profile): see that file for the measured
errors of each diffuse weighting and the estimator choice.
"""
