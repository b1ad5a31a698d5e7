"""Shared fixtures: one rendered ci dataset per test session (generator, benchmark and method tests reuse it)."""
from __future__ import annotations

import os

# before torch loads: active OpenMP waiting made 2 torch threads ~15x slower on a busy 2-core box
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from pathlib import Path

import pytest

CI_SCENE = "spheres"  # the demo's default scene (generator/commands/demo.py)


@pytest.fixture(scope="session")
def ci_profile():
    """The ci dataset profile (resolution, frames, test views, spp, static timestep)."""
    from lumibench.profiles import load_profile

    return load_profile("ci").dataset


@pytest.fixture(scope="session")
def ci_dataset(tmp_path_factory) -> Path:
    """DATA/ci/<CI_SCENE> rendered once (both variants, all four lights); returns the dynamic scene dir.

    Treat it as read-only: copy it before changing anything.
    """
    from generator.pipeline import render_scene

    data = tmp_path_factory.mktemp("ci_data")
    return render_scene(CI_SCENE, "ci", data, jobs=2, progress=False)


@pytest.fixture(params=["torch", "numba"])
def splat_backend(request, monkeypatch):
    """Tests that use it run on the torch reference and on the compiled CPU backend (as 'auto': CUDA tensors
    in the GPU tests still take the torch path)."""
    import method.splat.backend as backend_mod

    if request.param == "numba" and not backend_mod.numba_available():
        pytest.skip("numba is not installed")
    monkeypatch.setattr(backend_mod, "_default", "auto" if request.param == "numba" else "torch")
    return request.param
