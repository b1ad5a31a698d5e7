"""IRGS (Inter-Reflective Gaussian Splatting, CVPR 2025) on a LumiBench scene: export, commands, import.

Convention read from the authors' (LumiMotion's) fork that produced the paper's IRGS rows,
github.com/piotrmwojcik/IRGS @ 4aeea2518d12fe8e7403361c6dc325c9761ca196, itself based on
github.com/fudan-zvg/IRGS @ 1461869c0da84f26aebd8bb6d1caaa8a7bd91326:

* ``scene/dataset_readers.py`` ``readCamerasFromTransforms`` (Blender branch of ``scene/__init__.py``:
  a ``transforms_train.json`` and no "TensoIR"/"Synthetic4Relight" in the path): keys ``camera_angle_x``,
  ``frames[].file_path``, ``frames[].transform_matrix`` (OpenGL c2w); the image is
  ``<source>/$DATA_SUBDIR/<basename(file_path)>.png`` (RGBA; alpha > 0.5 is the mask). Frames are read
  in file order, the Scene is built with ``shuffle=False`` for rendering.
* ``eval_material_syn4.py`` / ``compute_albedo_scale_syn4.py``: ground truth in FLAT ``albedo/`` and
  ``roughness/``, found by ``f.startswith(splitext(file_path)[0])`` (the first in ``os.listdir`` order,
  so one albedo file per view) -> ``file_path`` must be a bare name; roughness is read under the albedo
  file's name and must have channels (``[..., :1]`` of an H x W x C array); GT and masks are resized to
  400 x 400 (hard-coded).
* ``eval_relighting_syn4.py``: env map from ``$MAP_PATH``, GT from ``<source>/$MAP_NAME/<name>.png``; writes
  ``<model>/test_lg0_rli_<MAP_NAME>[_<extra>]/env6/render/<idx>.png`` (sRGB, 400 x 400, idx = frame order).
* ``render.py``: ``<model>/test/ours_<iter>/{render,base_color,base_color_linear,roughness,rend_normal}/<idx:05d>.png``
  (render = NVS under the train light, sRGB; base_color_linear linear; roughness linear, grey as RGB;
  rend_normal world-space (n + 1) / 2; all multiplied by the GT mask).

Upstream fudan-zvg/IRGS reads ``<source>/<file_path>.png`` (no ``$DATA_SUBDIR``) and relights only under
its own hard-coded env maps, so run the fork (its training code is upstream's).

Training (the paper's ``train_stage1_spec_v5.sh``, ``train_stage2_spec_v5.sh``; IRGS† = without the
roughness smoothness term: ``--lambda_roughness_smooth 0``); we drop ``--resolution 2`` because our
images are at most 400 px (the paper's were 800 px).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from .common import ExternalMethod, Importer, latest_iteration_dir, match_light


def commands(c: dict[str, str]) -> list[str]:
    return [
        "# github.com/piotrmwojcik/IRGS (the LumiMotion authors' fork of fudan-zvg/IRGS), CUDA GPU",
        f"export DATA_SUBDIR={c['TRAIN']}",
        f"python train_refgaussian.py -s {c['STATIC']} -m {c['RUN']}/refgs --eval -w --lambda_mask_entropy 0.05",
        f"python train.py -s {c['STATIC']} -m {c['RUN']} --eval --iterations 20000 "
        f"--start_checkpoint_refgs {c['RUN']}/refgs/chkpnt50000.pth --envmap_resolution 128 "
        "--lambda_base_color_smooth 2 --lambda_roughness_smooth 2 --diffuse_sample_num 256 --envmap_cubemap_lr 0.01 "
        "--lambda_light_smooth 0.0005 --init_roughness_value 0.6 --lambda_light 0.1 --train_ray"
        "   # IRGS† (paper): --lambda_roughness_smooth 0",
        f"python render.py -m {c['RUN']} --eval --diffuse_sample_num 1024",
        f"python compute_albedo_scale_syn4.py -m {c['RUN']}",
        f"MAP_PATH={c['STATIC']}/{c['TEST']}.hdr MAP_NAME={c['TEST']} python eval_relighting_syn4.py -m {c['RUN']} "
        "--diffuse_sample_num 1024 --light_sample_num 0 --albedo_rescale 2 -e light   # once per test light",
    ]


def import_outputs(imp: Importer, run: Path, test_lights: list[str]) -> dict[str, Any]:
    n = len(imp.names.test_stems)
    info: dict[str, Any] = {}
    ours = latest_iteration_dir(run / "test", must_have="render")
    if ours is not None:
        info["render_dir"] = str(ours)
        seq = lambda sub: [ours / sub / f"{j:05d}.png" for j in range(n)]  # noqa: E731
        imp.kind("nvs", seq("render"), "srgb")
        if not imp.kind("albedo", seq("base_color_linear"), "linear"):
            imp.kind("albedo", seq("base_color"), "srgb")
        imp.kind("roughness", seq("roughness"), "scalar")
        imp.kind("normal", seq("rend_normal"), "normal")
    wanted = test_lights or list(imp.names.lights)
    for d in sorted(run.glob("test_lg0_rli_*")):
        light = match_light(d.name[len("test_lg0_rli_"):], imp.names.lights)
        if light is None or light not in wanted:
            continue
        imp.kind("relight", [d / "env6" / "render" / f"{j}.png" for j in range(n)], "srgb", light)
    return info


SPEC = ExternalMethod(
    name="irgs", title="IRGS", repo="github.com/piotrmwojcik/IRGS", commit="4aeea2518d12fe8e7403361c6dc325c9761ca196",
    upstream="github.com/fudan-zvg/IRGS@1461869c0da84f26aebd8bb6d1caaa8a7bd91326", trains_on="static",
    relight_names_light=True, commands=commands, import_outputs=import_outputs)
