"""LumiMotion: relightable dynamic 2D Gaussian splatting in pure PyTorch."""
