"""GI-GS (Global Illumination Gaussian Splatting) on a LumiBench scene: export, commands, import.

Convention read from the LumiMotion authors' fork that produced the paper's GI-GS rows,
github.com/piotrmwojcik/GI-GS @ ee1d32f6e56b9b7330c3787029bf29f3877c7fbf, based on
github.com/stopaimme/GI-GS-official-implementation @ 9e75c82674726178e955dd3e6c4aca165cba9b31:

* ``scene/dataset_readers.py`` ``readCamerasFromTransforms`` (Blender branch): keys ``camera_angle_x``,
  ``frames[].file_path``, ``frames[].transform_matrix``; the image is
  ``<source>/$DATA_SUBDIR/<basename(file_path)>.png`` (RGBA); ``image_name`` = the file stem; test cameras
  are never shuffled.
* ``render.py`` (``--brdf_eval``): GT albedo from FLAT ``<source>/albedo/`` by ``find_matching_file``: the
  first name that starts with ``file_path`` and is NOT ``<file_path>.png`` itself (so the export names it
  ``<name>0001.png``, like the paper's Blender outputs), the mask from ``<source>/$DATA_SUBDIR/<file_path>.png``'s alpha; predictions read from
  ``<model>/test/ours_<iter>/pbr/<file_path>_albedo.png`` (LINEAR, compared with linearised GT).
  With ``--pbr`` it writes ``pbr/<name>.png`` (NVS under the train light, sRGB), ``pbr/<name>_albedo.png``
  (linear), ``pbr/<name>_roughness.png`` (linear); ``<iter>`` is ``None`` when loading ``--checkpoint``.
* ``relight.py``: env map ``--hdri``; writes ``<model>/test/ours_<iter>/relight/<name>_<light>.png`` with
  ``<light>`` = the hdri file name without extension (sRGB, multiplied by the GT mask).

Commands: the paper's ``train_all.bash``, ``eval_albedo.bash``, ``relight_all.bash`` (``--resolution 2``
dropped: our images are <= 400 px).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from .common import ExternalMethod, Importer, latest_iteration_dir, match_light


def commands(c: dict[str, str]) -> list[str]:
    ck = f"{c['RUN']}/chkpnt35000.pth"
    return [
        "# github.com/piotrmwojcik/GI-GS (the LumiMotion authors' fork of the official GI-GS), CUDA GPU",
        f"export DATA_SUBDIR={c['TRAIN']}",
        f"python train.py -m {c['RUN']} -s {c['STATIC']} --iterations 35000 --eval --gamma --radius 0.8 "
        "--bias 0.01 --thick 0.05 --delta 0.0625 --step 16 --start 64 --indirect",
        f"python render.py -m {c['RUN']} -s {c['STATIC']} --checkpoint {ck} --eval --skip_train --pbr --gamma "
        "--indirect --brdf_eval",
        f"python relight.py -m {c['RUN']} -s {c['STATIC']} --checkpoint {ck} --hdri {c['STATIC']}/{c['TEST']}.hdr "
        "--eval --gamma   # once per test light",
    ]


def import_outputs(imp: Importer, run: Path, test_lights: list[str]) -> dict[str, Any]:
    names = imp.names.test_names
    info: dict[str, Any] = {}
    ours = latest_iteration_dir(run / "test", must_have="pbr")
    if ours is not None:
        pbr = ours / "pbr"
        info["pbr_dir"] = str(pbr)
        imp.kind("nvs", [pbr / f"{x}.png" for x in names], "srgb")
        imp.kind("albedo", [pbr / f"{x}_albedo.png" for x in names], "linear")
        imp.kind("roughness", [pbr / f"{x}_roughness.png" for x in names], "scalar")
    rel = latest_iteration_dir(run / "test", must_have="relight")
    if rel is not None:
        wanted = test_lights or list(imp.names.lights)
        found = set()
        prefix = names[0] + "_"
        for f in (rel / "relight").glob(f"{prefix}*.png"):
            light = match_light(f.stem[len(prefix):], imp.names.lights)
            if light is not None and f.stem[len(prefix):] == light and light in wanted:
                found.add(light)
        for light in sorted(found):
            imp.kind("relight", [rel / "relight" / f"{x}_{light}.png" for x in names], "srgb", light)
    return info


SPEC = ExternalMethod(
    name="gigs", title="GI-GS", repo="github.com/piotrmwojcik/GI-GS", commit="ee1d32f6e56b9b7330c3787029bf29f3877c7fbf",
    upstream="github.com/stopaimme/GI-GS-official-implementation@9e75c82674726178e955dd3e6c4aca165cba9b31",
    trains_on="static", relight_names_light=True, commands=commands, import_outputs=import_outputs)
