"""The authors' LumiMotion code on a LumiBench scene: export, commands, import.

Convention read from github.com/joaxkal/LumiMotion @ 65287461075a1a4c0f54845325cc22039bd14e7d:

* ``scene/dataset_readers.py`` ``readCamerasFromTransforms`` / ``readNerfSyntheticInfo`` (``--is_blender``):
  keys ``camera_angle_x``, ``frames[].file_path``, ``frames[].transform_matrix``, ``frames[].time`` (else
  idx / N); the image is ``<source>/<train_light_folder>/<file_path>.png`` (RGBA); frames are SORTED by the
  integer after the last "_" of the file name; a ``<source>/rgba/`` folder would override the images.
* ``utils/general_utils.py`` ``find_static_dataset``: ``glob(f"{source_path}_statictimestep*")``; the
  ``*_static`` scripts take the timestep from ``timestep(\\d+)`` in that name and use the time of the
  first camera whose image path contains it zero-padded to 4 digits (our train view ``r_NNNN``).
* ``scripts/scale_albedo_static.py``, ``eval_material_static.py``, ``eval_relight_static.py``,
  ``eval_nvs_static.py`` (and the ``_dynamic`` twins on ``<source>``): GT in FLAT
  ``<static>/albedo/`` (``render_name in f``), ``<static>/roughness/r_<last 4 digits>.png``,
  ``<static>/<test_light_folder>/`` (RGBA, alpha = mask, ``render_name in f``); relighting env map
  ``<source>/<test_light_folder>.hdr``. They write, with idx = sorted test order:
  ``<model>/eval_material_static/ours_<iter>/albedo_train_static<idx>.png`` (LINEAR, scaled),
  ``roughness_train_static<idx>.png`` (linear), ``<model>/eval_relight_static/ours_<iter>/render<idx>.png``
  and ``<model>/eval_nvs_static/ours_<iter>/render<idx>.png`` (sRGB, masked). The test light's name is not
  in any path: import one test light per model dir (evaluations overwrite each other).

Commands: ``bash_scripts/synthetic_results_from_paper.sh`` with ``--resolution 1`` (the paper used 2 on
800 px images; ours are <= 400 px) and one of the paper's per-scene separation weights.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from lumibench.errors import UserError

from .common import ExternalMethod, Importer, latest_iteration_dir, one_test_light

VARIANTS = ("static", "dynamic")


def commands(c: dict[str, str]) -> list[str]:
    common = (f"--source_path {c['DYNAMIC']} --model_path {c['RUN']} --is_blender --eval --resolution 1 "
              f"--train_light_folder {c['TRAIN']}")
    ev = f"{common} --load_iter 55000 --depth_ratio 0.0"
    return [
        "# github.com/joaxkal/LumiMotion, CUDA GPU",
        f"python -m scripts.train_stage1 {common} --gt_alpha_mask_as_scene_mask --iterations 35000 "
        "--densify_until_iter 20000 --lambda_separation 0.001 --d_xyz_loss_weight 0.001 --binarization_warm_up 1000 "
        "--depth_ratio 1.0 --d_color_reg_loss_weight 0.01   # lambda_separation 0.001|0.005 per scene (paper)",
        f"python -m scripts.train_stage2 {common} --gt_alpha_mask_as_scene_mask --iterations 55000 --load_iter 35000 "
        "--diffuse_sample_num 512 --depth_ratio 0.0",
        f"python -m scripts.scale_albedo_static {ev} --test_light_folder {c['TEST']}",
        f"python -m scripts.eval_material_static {ev} --test_light_folder {c['TEST']}",
        f"python -m scripts.eval_relight_static {ev} --test_light_folder {c['TEST']} --diffuse_sample_num 2048",
        f"python -m scripts.eval_nvs_static {ev} --diffuse_sample_num 2048",
    ]


def import_outputs(imp: Importer, run: Path, test_lights: list[str], variant: str = "static") -> dict[str, Any]:
    if variant not in VARIANTS:
        raise UserError(f"unknown LumiMotion evaluation variant '{variant}' (known: {', '.join(VARIANTS)})")
    n = len(imp.names.test_stems)
    info: dict[str, Any] = {"variant": variant}
    mat = latest_iteration_dir(run / f"eval_material_{variant}")
    if mat is not None:
        imp.kind("albedo", [mat / f"albedo_train_{variant}{j}.png" for j in range(n)], "linear")
        imp.kind("roughness", [mat / f"roughness_train_{variant}{j}.png" for j in range(n)], "scalar")
    nvs = latest_iteration_dir(run / f"eval_nvs_{variant}")
    if nvs is not None:
        imp.kind("nvs", [nvs / f"render{j}.png" for j in range(n)], "srgb")
    rel = latest_iteration_dir(run / f"eval_relight_{variant}")
    if rel is not None and (rel / "render0.png").is_file():
        light = one_test_light(SPEC, test_lights)
        if light is None:
            raise UserError("LumiMotion writes eval_relight_*/render<idx>.png without the light's name: pass "
                            "--test-light <the --test_light_folder given to eval_relight_static>")
        imp.kind("relight", [rel / f"render{j}.png" for j in range(n)], "srgb", light)
    return info


SPEC = ExternalMethod(
    name="lumimotion_official", title="LumiMotion (authors' code)", repo="github.com/joaxkal/LumiMotion",
    commit="65287461075a1a4c0f54845325cc22039bd14e7d", upstream="github.com/joaxkal/LumiMotion",
    trains_on="dynamic", relight_names_light=False, commands=commands, import_outputs=import_outputs)
