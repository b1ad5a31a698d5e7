"""A run's checkpoints, written and read here only.

``RUN/checkpoints/stage<k>_<iteration>.pt`` (atomic; the last two of each stage are kept). Every
checkpoint holds the model (``scene_state``: Gaussians, network, scene box, P temperature and the
architecture it was built with), the stage's own state (optimisers, density statistics, materials),
the random generator, and the loop's bookkeeping (iteration, total iterations, seconds so far).
"""
from __future__ import annotations

from pathlib import Path

import torch

from lumibench.errors import UserError
from lumibench.io import atomic_path
from method.model.deform import DeformNet
from method.model.gaussians import Gaussians
from method.model.materials import Materials
from method.model.motion_basis import MotionBasis
from method.model.nodes import MotionNodes
from method.model.scene import DynamicScene

KEEP = 2  # checkpoints kept per stage


def checkpoint_paths(run_dir: str | Path, stage: int = 1) -> list[tuple[int, Path]]:
    """(iteration, path) of the stage's checkpoints, oldest first."""
    d = Path(run_dir) / "checkpoints"
    out = []
    if d.is_dir():
        for p in d.glob(f"stage{stage}_*.pt"):
            tail = p.stem.split("_", 1)[1]
            if tail.isdigit():
                out.append((int(tail), p))
    return sorted(out)


def save_checkpoint(run_dir: str | Path, stage: int, iteration: int, state: dict) -> Path:
    """Write ``state`` as the stage's checkpoint at ``iteration`` and drop all but the last KEEP."""
    path = Path(run_dir) / "checkpoints" / f"stage{stage}_{iteration:06d}.pt"
    with atomic_path(path) as tmp:
        torch.save(state, tmp)
    for _, old in checkpoint_paths(run_dir, stage)[:-KEEP]:
        old.unlink(missing_ok=True)
    return path


def load_checkpoint(path: str | Path, device) -> dict:
    try:
        return torch.load(path, map_location=device, weights_only=False)
    except Exception as exc:  # truncated or foreign file
        raise UserError(f"cannot read checkpoint {path}: {type(exc).__name__}: {exc}") from None


def latest_checkpoint(run_dir: str | Path, stage: int, device) -> dict | None:
    cks = checkpoint_paths(run_dir, stage)
    return load_checkpoint(cks[-1][1], device) if cks else None


def scene_state(scene: DynamicScene) -> dict:
    """The model part of a checkpoint."""
    return {"gaussians": scene.g.state(), "net": None if scene.net is None else scene.net.state_dict(),
            "center": scene.center.cpu(), "extent": scene.extent, "temperature": scene.temperature,
            "model": dict(scene.model_cfg), "nodes": None if scene.nodes is None else scene.nodes.state(),
            "basis": None if scene.basis is None else scene.basis.state()}


def build_net(m: dict) -> DeformNet:
    """The deformation network of a ``model`` configuration section (a checkpoint from before
    ``mlp_precision`` existed was trained in fp32)."""
    return DeformNet(m["mlp_depth"], m["mlp_width"], m["mlp_skip"], m["pos_freqs"], m["time_freqs"],
                     m["time_net_width"], m["time_net_out"], m.get("mlp_precision", "fp32"))


def scene_from_checkpoint(ck: dict, cfg: dict, device) -> DynamicScene:
    """The model a checkpoint holds (for stage 2, relighting and evaluation)."""
    g = Gaussians({k: v.to(device) for k, v in ck["gaussians"].items()})
    m = ck.get("model") or cfg["model"]  # the architecture the checkpoint was trained with
    net = None
    if ck["net"] is not None:
        net = build_net(m).to(device)
        net.load_state_dict(ck["net"])
    scene = DynamicScene(g, net, ck["center"].to(device), ck["extent"], ck["temperature"], m["delta_colour"],
                         m["separation"])
    scene.model_cfg = dict(m)
    if net is not None and ck.get("nodes") is not None:
        scene.nodes = MotionNodes.from_state(ck["nodes"], device)
    if ck.get("basis") is not None:
        scene.basis = MotionBasis.from_state(ck["basis"]).to(device)
    return scene


def final_stage1(run_dir: str | Path, device) -> dict:
    """The last stage-1 checkpoint of a run whose stage 1 has finished (what stage 2 starts from)."""
    ck = latest_checkpoint(run_dir, 1, device)
    if ck is None:
        raise UserError(f"no stage-1 checkpoint in {run_dir}: train stage 1 first (make train STAGE=1 ...)")
    if int(ck["iteration"]) < int(ck.get("total_iterations", ck["iteration"])):
        raise UserError(f"stage 1 in {run_dir} stopped at iteration {ck['iteration']} of {ck['total_iterations']}: "
                        f"finish it first (make train STAGE=1 RESUME=1 ...)")
    return ck


def load_trained(run_dir: str | Path, cfg: dict, device) -> tuple:
    """(scene, materials) of the run's last stage-2 checkpoint."""
    ck = latest_checkpoint(run_dir, 2, device)
    if ck is None:
        raise UserError(f"no stage-2 checkpoint in {run_dir}: train stage 2 first (make train STAGE=2 ...)")
    return scene_from_checkpoint(ck, cfg, device), Materials.from_state(ck["materials"], cfg, device)
