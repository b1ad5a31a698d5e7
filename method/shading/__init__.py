"""Physically based shading for stage 2: env maps, BRDF, direction sampling, Monte Carlo shading, tracing.

    from method.shading.envmap import load_envmap, lookup, LearnableEnvMap, lower_hemisphere_l2, resample
    from method.shading.render import shade               # G-buffer pixels (P, .) -> linear RGB (P, 3)
    from method.shading.visibility import GaussianTracer  # V and indirect light from the 2D Gaussians

Conventions: env maps are (H, W, 3) linear radiance in the generator's equirectangular orientation with
a nearest-texel lookup (as Blender renders the dataset: Environment Texture 'Closest', strength 1);
directions are world-space unit vectors; view_dirs point from the surface to the camera; colours linear.

Pinned to Blender by tests/test_shading.py::test_shading_matches_blender_on_calib_sphere (ci profile,
every interior pixel of the 16 train + 4 test views, 128 directions; relative error of the summed linear
radiance, "global" over all pixels / mean over world-normal sectors; Blender renders at 8 spp, so
single pixels are +-12..25 % noisy and only sums can be compared):

    diffuse weight          calib_sphere (roughness 0.4)             calib_sphere_glossy (0.15)
                            city   sunrise courtyard sunset          city   sunrise courtyard sunset
    1 - E_s(n.v) (default)  0.64   1.52    0.60     1.11 %           0.66   0.95    0.41     0.99 %
      sectors               0.94   1.53    2.14     1.68 %           0.75   1.23    1.89     1.50 %
    1 - F(v.h)              0.64   2.03    1.12     1.62 %           0.58   1.18    0.53     1.06 %
    none (paper's sum)      3.40   1.77    2.73     2.21 %           3.78   2.78    3.32     2.79 %
    default + env_quadrature 0.63  1.60    0.61     1.16 %           0.65   1.05    0.43     1.00 %
      sectors               0.97   1.57    2.09     1.69 %           0.76   1.22    1.90     1.52 %

Against 1024-spp Blender renders of a few views the default is within 1-1.5 % per pixel; the rest is the
paper's BRDF itself (Cycles uses a height-correlated Smith G, the exact dielectric Fresnel and
multiple-scattering GGX, 'MULTI_GGX', the Principled default the generator keeps): swapping those in
brings the residual to ~0.5 %, but the paper's BRDF is what stage 2 fits, so we keep it.

Estimator (render.py): MIS over a cosine lattice, GGX half vectors and env texels, against the
cosine-weighted lattice alone (the paper's lattice is uniform over the hemisphere). Mean per-pixel error
against 32768 directions, one calib_sphere test view (city with its 0.03 sr sun / courtyard, soft):

    directions per pixel          64       256      1024
    roughness 0.4,  cosine only   16.9 %   8.4 %    2.7 %   (courtyard 6.7 / 2.0 / 0.8 %)
                    MIS           3.7 %    1.0 %    0.4 %   (courtyard 4.8 / 1.6 / 0.6 %)
    roughness 0.15, cosine only   20.3 %   10.5 %   2.7 %
                    MIS           3.6 %    0.9 %    0.4 %
"""
