"""Differentiable 2D Gaussian rasterizer and ray tracer, pure PyTorch (CPU and CUDA)."""
