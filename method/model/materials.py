"""Stage 2's materials: per-Gaussian albedo and roughness, and the learnable environment map.

Albedo is stored display-encoded through a sigmoid and initialised from the canonical colour (linearised
and clamped to [albedo_min, albedo_max] when shading); roughness through a sigmoid, init 0.75 (paper).
"""
from __future__ import annotations

import torch

from method.model.gaussians import inverse_sigmoid
from method.model.scene import DynamicScene
from method.shading.envmap import LearnableEnvMap


class Materials:
    """Per-Gaussian albedo and roughness logits, and the learnable env map."""

    def __init__(self, albedo_logit: torch.Tensor, roughness_logit: torch.Tensor, env: LearnableEnvMap):
        self.albedo_logit = albedo_logit.detach().clone().requires_grad_(True)
        self.roughness_logit = roughness_logit.detach().clone().requires_grad_(True)
        self.env = env

    @staticmethod
    def init_from(scene: DynamicScene, cfg: dict) -> "Materials":
        s = cfg["stage2"]
        n = len(scene.g)
        col = scene.g.colours.detach()
        rough = torch.full((n,), float(s["roughness_init"]), device=col.device)
        env = LearnableEnvMap(s["env_height"], s["env_width"], s["env_init"]).to(col.device)
        return Materials(inverse_sigmoid(col), inverse_sigmoid(rough), env)

    def albedo_display(self) -> torch.Tensor:
        return torch.sigmoid(self.albedo_logit)

    def roughness(self) -> torch.Tensor:
        return torch.sigmoid(self.roughness_logit)

    def state(self) -> dict:
        return {"albedo_logit": self.albedo_logit.detach().cpu(), "roughness_logit": self.roughness_logit.detach().cpu(),
                "env": self.env.state_dict()}

    @staticmethod
    def from_state(st: dict, cfg: dict, device) -> "Materials":
        s = cfg["stage2"]
        env = LearnableEnvMap(s["env_height"], s["env_width"], s["env_init"]).to(device)
        env.load_state_dict(st["env"])
        return Materials(st["albedo_logit"].to(device), st["roughness_logit"].to(device), env)

    def num_parameters(self) -> int:
        env = sum(p.numel() for p in self.env.parameters())
        return self.albedo_logit.numel() + self.roughness_logit.numel() + env
