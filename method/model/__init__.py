"""LumiMotion's model: canonical 2D Gaussians with density control, and the deformation network."""
