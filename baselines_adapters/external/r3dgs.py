"""R-3DGS (Relightable 3D Gaussians, NJU-3DV) on a LumiBench scene: export, commands, import.

Convention read from the LumiMotion authors' fork that produced the paper's R-3DGS rows,
github.com/piotrmwojcik/Relightable3DGaussian @ f51ca15b3de68c25f478d9fbc4e877114127c92b, based on
github.com/NJU-3DV/Relightable3DGaussian @ a102f14c7e34b7bd5e421990e6f1593d39ebab83:

* ``scene/dataset_readers.py`` ``readCamerasFromTransforms`` (Blender branch): keys ``camera_angle_x``,
  ``frames[].file_path``, ``frames[].transform_matrix``; the image is
  ``<source>/<envmap_prefix>/<file_path>.png`` (``--envmap_prefix`` = the train light folder; upstream has
  no prefix: ``<source>/<file_path>.png``); ``image_name`` = the file stem.
* ``scale_albedo.py`` / ``eval_relighting_ours.py``: ground truth in FLAT ``<static>/albedo/`` and
  ``<static>/<test_light_folder>/`` (RGBA, alpha = mask), found by ``render_name in f`` over
  ``os.listdir``; env map ``<static>/<test_light_folder>.hdr``; relit images written to
  ``<model>/test_rli/env/pbr/<idx>.png`` (sRGB; idx = test camera order, ``Scene(shuffle=False)`` = file
  order) -- the test light's name is not in the path, so import one test light per run.
* ``eval_nvs.py``: ``<model>/test/ours_<iter>/{renders,base_color,roughness,pbr}/<image_name>.png``
  (renders = NVS under the train light, sRGB; base_color sRGB (the eval scripts linearise it);
  roughness linear, one channel).

Commands: the paper's ``script/run_all.sh`` (we drop ``--resolution 2``; our images are <= 400 px).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from lumibench.errors import UserError

from .common import ExternalMethod, Importer, latest_iteration_dir, one_test_light


def commands(c: dict[str, str]) -> list[str]:
    ck = f"{c['RUN']}/neilf/chkpnt40000.pth"
    return [
        "# github.com/piotrmwojcik/Relightable3DGaussian (the LumiMotion authors' fork of NJU-3DV's), CUDA GPU",
        f"python train.py --eval -s {c['STATIC']} -m {c['RUN']}/3dgs --envmap_prefix {c['TRAIN']} "
        "--lambda_normal_render_depth 0.01 --lambda_normal_smooth 0.01 --lambda_mask_entropy 0.1 "
        "--save_training_vis --lambda_depth_var 1e-2",
        f"python train.py --eval -s {c['STATIC']} -m {c['RUN']}/neilf --envmap_prefix {c['TRAIN']} "
        f"-c {c['RUN']}/3dgs/chkpnt30000.pth --save_training_vis --position_lr_init 0.000016 "
        "--position_lr_final 0.00000016 --normal_lr 0.001 --sh_lr 0.00025 --opacity_lr 0.005 --scaling_lr 0.0005 "
        "--rotation_lr 0.0001 --iterations 40000 --lambda_base_color_smooth 0 --lambda_roughness_smooth 0 "
        "--lambda_light_smooth 0 --lambda_light 0.01 -t neilf --sample_num 64 --save_training_vis_iteration 200 "
        "--lambda_env_smooth 0.01",
        f"python eval_nvs.py --eval -m {c['RUN']}/neilf -c {ck} -t neilf",
        f"python scale_albedo.py --eval -m {c['RUN']}/neilf -c {ck} -t neilf --static_source_path {c['STATIC']} "
        f"--test_light_folder {c['TEST']}",
        f"python eval_relighting_ours.py --eval -m {c['RUN']}/neilf -c {ck} --static_source_path {c['STATIC']} "
        f"--test_light_folder {c['TEST']} --sample_num 1024   # one test light per RUN dir",
    ]


def import_outputs(imp: Importer, run: Path, test_lights: list[str]) -> dict[str, Any]:
    if not (run / "test").is_dir() and not (run / "test_rli").is_dir() and (run / "neilf").is_dir():
        run = run / "neilf"  # the RUN dir of the commands above holds 3dgs/ and neilf/
    names = imp.names.test_names
    n = len(names)
    info: dict[str, Any] = {"model_dir": str(run)}
    ours = latest_iteration_dir(run / "test", must_have="renders")
    if ours is not None:
        imp.kind("nvs", [ours / "renders" / f"{x}.png" for x in names], "srgb")
        imp.kind("albedo", [ours / "base_color" / f"{x}.png" for x in names], "srgb")
        imp.kind("roughness", [ours / "roughness" / f"{x}.png" for x in names], "scalar")
    rli = run / "test_rli" / "env"
    if (rli / "pbr").is_dir():
        light = one_test_light(SPEC, test_lights)
        if light is None:
            raise UserError("R-3DGS writes test_rli/env/pbr/ without the light's name: pass --test-light <the "
                            "--test_light_folder given to eval_relighting_ours.py>")
        imp.kind("relight", [rli / "pbr" / f"{j}.png" for j in range(n)], "srgb", light)
        if ours is None:  # albedo of the relighting pass (scaled; we align again anyway)
            imp.kind("albedo", [rli / "base_color" / f"{j}.png" for j in range(n)], "srgb")
    return info


SPEC = ExternalMethod(
    name="r3dgs", title="R-3DGS", repo="github.com/piotrmwojcik/Relightable3DGaussian",
    commit="f51ca15b3de68c25f478d9fbc4e877114127c92b",
    upstream="github.com/NJU-3DV/Relightable3DGaussian@a102f14c7e34b7bd5e421990e6f1593d39ebab83",
    trains_on="static", relight_names_light=False, commands=commands, import_outputs=import_outputs)
