"""Run integrity, the user-facing weak cases of `python -m method relight` and scene/env-map loading: each
is one actionable line (exit code 2) or the right behaviour, never a traceback or silence."""
from __future__ import annotations

import json
import os
import shutil
import stat

import numpy as np
import pytest
import yaml

from tests.test_method_relight import TINY, tiny_run  # noqa: F401  (the module's tiny trained run)


def _cli(argv, capsys) -> tuple[int, list[str]]:
    from method.__main__ import main

    rc = main(argv)
    cap = capsys.readouterr()
    return rc, cap.err.strip().splitlines()


def _one_line_error(argv, capsys, *needles) -> str:
    rc, err = _cli(argv, capsys)
    assert rc == 2 and len(err) == 1, (argv, rc, err)
    for needle in needles:
        assert needle in err[0], (argv, needle, err[0])
    return err[0]


def _copy_run(run, dst):
    """A private copy of the tiny run (the shared one stays untouched)."""
    shutil.copytree(run, dst)
    return dst


# ------------------------------------------------------------------ 1. --frames / --dirs out of range

@pytest.mark.parametrize("extra,needles", [
    (["--views", "orbit", "--frames", "0"], ["--frames", ">= 1", "got 0"]),
    (["--views", "orbit", "--frames", "-3"], ["--frames", ">= 1", "got -3"]),
    (["--dirs", "0"], ["--dirs", ">= 1", "got 0"]),
    (["--dirs", "-5"], ["--dirs", ">= 1", "got -5"]),
])
def test_relight_rejects_frames_and_dirs_below_one(tiny_run, tmp_path, capsys, extra, needles):  # noqa: F811
    out = tmp_path / "out"
    _one_line_error(["relight", "--run", str(tiny_run), "--envmap", "city", "--out", str(out)] + extra,
                    capsys, *needles)
    assert not out.exists()  # refused before anything was written


# ------------------------------------------------------------------ 2. an output that cannot be written

def test_relight_out_that_is_an_existing_file(tiny_run, tmp_path, capsys):  # noqa: F811
    f = tmp_path / "taken.png"
    f.write_bytes(b"mine")
    _one_line_error(["relight", "--run", str(tiny_run), "--envmap", "city", "--out", str(f), "--dirs", "8"],
                    capsys, str(f), "existing file")
    assert f.read_bytes() == b"mine"


def test_relight_into_a_read_only_run_directory(tiny_run, tmp_path, capsys):  # noqa: F811
    run = _copy_run(tiny_run, tmp_path / "run")
    os.chmod(run, 0o555)
    try:
        if os.access(run, os.W_OK):  # root: chmod does not stop it; emulate with a folder under a regular file
            blocker = tmp_path / "blocker"
            blocker.write_text("a file, not a folder")
            out = blocker / "relight"
            argv = ["relight", "--run", str(run), "--envmap", "city", "--out", str(out), "--dirs", "8"]
            _one_line_error(argv, capsys, "cannot write", str(out))
        else:
            argv = ["relight", "--run", str(run), "--envmap", "city", "--dirs", "8"]
            _one_line_error(argv, capsys, "cannot write", str(run / "relight" / "city"))
    finally:
        os.chmod(run, stat.S_IRWXU | stat.S_IRGRP | stat.S_IXGRP | stat.S_IROTH | stat.S_IXOTH)


# ------------------------------------------------------------------ 3. an earlier relight's outputs

def test_relight_into_an_earlier_output_folder_replaces_its_outputs_only(tiny_run, tmp_path, capsys):  # noqa: F811
    from method.__main__ import main

    out = tmp_path / "out"
    base = ["relight", "--run", str(tiny_run), "--envmap", "city", "--out", str(out), "--dirs", "8"]
    assert main(base) == 0  # the test views r_0000..r_0003
    # the user's own files in the folder, and subfolders, are not the relight's to remove
    (out / "notes.txt").write_text("keep")
    (out / "relit" / "keep.txt").write_text("keep")
    (out / "albedo" / "mine").mkdir()
    (out / "albedo" / "mine" / "r_0000.png").write_bytes(b"keep")
    assert main(base + ["--views", "orbit", "--frames", "3"]) == 0
    assert main(base + ["--views", "orbit", "--frames", "2"]) == 0
    capsys.readouterr()
    for kind in ("albedo", "roughness", "normal", "relit"):
        pngs = sorted(p.name for p in (out / kind).glob("*.png"))
        assert pngs == ["orbit_000.png", "orbit_001.png"], (kind, pngs)
    assert sorted(p.name for p in (out / "albedo").glob("*.npz")) == ["orbit_000.npz", "orbit_001.npz"]
    assert (out / "relit_orbit.gif").is_file() and (out / "envmap_estimated.hdr").is_file()
    assert (out / "notes.txt").read_text() == "keep" and (out / "relit" / "keep.txt").read_text() == "keep"
    assert (out / "albedo" / "mine" / "r_0000.png").read_bytes() == b"keep"
    # back to the test views: the orbit's frames and its GIF go
    assert main(base) == 0
    assert sorted(p.stem for p in (out / "relit").glob("*.png")) == ["r_0000", "r_0001", "r_0002", "r_0003"]
    assert not (out / "relit_orbit.gif").exists()


# ------------------------------------------------------------------ 4. --device

def test_relight_device_is_checked_before_the_checkpoint(tiny_run, tmp_path, capsys, monkeypatch):  # noqa: F811
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    base = ["relight", "--run", str(tiny_run), "--envmap", "city", "--out", str(tmp_path / "out"), "--device"]
    for dev in ("cuda", "cuda:1"):
        _one_line_error(base + [dev], capsys,
                        f"--device {dev} asked for, but this torch has no CUDA device (use --device cpu)")
    _one_line_error(base + ["gpu"], capsys, "--device 'gpu'", "use cpu, cuda")
    _one_line_error(base + ["cuda:x"], capsys, "--device 'cuda:x'")


# ------------------------------------------------------------------ 5. cameras and times in transforms_*.json

def _nan_matrix(f):
    f["transform_matrix"][0][3] = float("nan")


def _inf_matrix(f):
    f["transform_matrix"][2][1] = float("inf")


def _short_matrix(f):
    f["transform_matrix"] = f["transform_matrix"][:3]


@pytest.mark.parametrize("change,problem", [
    (_nan_matrix, "NaN or infinite"),
    (_inf_matrix, "NaN or infinite"),
    (_short_matrix, "shape (3, 4)"),
    (lambda f: f.update(time=1.5), "time 1.5 is outside [0, 1]"),
    (lambda f: f.update(time=-0.25), "time -0.25 is outside [0, 1]"),
    (lambda f: f.update(time=float("nan")), "time nan is outside [0, 1]"),
    (lambda f: f.pop("time"), "has no time"),
    (lambda f: f.update(time="soon"), "time 'soon' is not a number"),
    (lambda f: f.update(time=None), "time None is not a number"),
])
def test_load_scene_refuses_bad_cameras_and_times(ci_dataset, tmp_path, change, problem):
    from lumibench.errors import UserError
    from method.data import load_scene

    scene = tmp_path / ci_dataset.name
    shutil.copytree(ci_dataset, scene)
    for split in ("train", "test"):
        path = scene / f"transforms_{split}.json"
        good = path.read_text()
        raw = json.loads(good)
        frame = raw["frames"][1]
        change(frame)
        path.write_text(json.dumps(raw))  # NaN / Infinity as JSON's usual extension, as Python writes it
        with pytest.raises(UserError) as exc:
            load_scene(scene, "city")
        msg = str(exc.value)
        assert str(path) in msg and frame["file_path"] in msg and problem in msg and "\n" not in msg, msg
        path.write_text(good)
    load_scene(scene, "city")  # the untouched files load


# ------------------------------------------------------------------ 6. env maps: 2:1, finite, some light

def _write_exr(path, img):
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"RGB": np.ascontiguousarray(img, dtype=np.float32)}) as f:
        f.write(str(path))


@pytest.mark.parametrize("name,img,problem", [
    ("square.hdr", np.full((16, 16, 3), 0.5, np.float32), "16 x 16"),
    ("wide.hdr", np.full((8, 32, 3), 0.5, np.float32), "32 x 8"),
    ("black.hdr", np.zeros((16, 32, 3), np.float32), "no positive radiance"),
    ("negative.exr", np.full((16, 32, 3), -1.0, np.float32), "no positive radiance"),
    ("nan.exr", np.where(np.arange(16)[:, None, None] == 3, np.nan, 0.5) * np.ones((16, 32, 3), np.float32),
     "NaN or infinite"),
])
def test_envmap_must_be_two_to_one_finite_and_lit(tmp_path, name, img, problem):
    from generator.envmap import write_hdr
    from lumibench.errors import UserError
    from method.shading.envmap import load_envmap

    path = tmp_path / name
    if name.endswith(".hdr"):
        write_hdr(path, img)
    else:
        _write_exr(path, img)
    for kw in ({}, {"height": None, "width": None}):
        with pytest.raises(UserError, match="environment map") as exc:
            load_envmap(path, **kw)
        assert str(path) in str(exc.value) and problem in str(exc.value), str(exc.value)
    if name.endswith(".hdr"):  # the same map as a scene's <light>.hdr, found by the light's name
        scene = tmp_path / "scene"
        scene.mkdir()
        shutil.copy(path, scene / "dusk.hdr")
        with pytest.raises(UserError) as exc:
            load_envmap("dusk", scene)
        assert str(scene / "dusk.hdr") in str(exc.value) and problem in str(exc.value), str(exc.value)


def test_relight_with_a_square_envmap_is_one_line(tiny_run, tmp_path, capsys):  # noqa: F811
    from generator.envmap import write_hdr

    path = tmp_path / "square.hdr"
    write_hdr(path, np.full((8, 8, 3), 1.0, np.float32))
    _one_line_error(["relight", "--run", str(tiny_run), "--envmap", str(path), "--out", str(tmp_path / "o"),
                     "--dirs", "8"], capsys, str(path), "twice as wide as high")
    assert not (tmp_path / "o").exists()  # refused before the output folder was made


# ------------------------------------------------------------------ 7. a moved dataset: --data

def test_relight_after_the_dataset_moved(ci_dataset, tiny_run, tmp_path, capsys):  # noqa: F811
    from method.__main__ import main

    run = _copy_run(tiny_run, tmp_path / "run")
    cfg_path = run / "config.yaml"
    cfg = yaml.safe_load(cfg_path.read_text())
    assert cfg["profile"] == "ci" and cfg["run"]["scene_name"] == ci_dataset.name
    gone = tmp_path / "old_place" / "ci" / ci_dataset.name
    cfg["run"]["scene"] = str(gone)
    cfg_path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    # the moved dataset: a copy under another data root
    root = tmp_path / "new_place"
    shutil.copytree(ci_dataset, root / "ci" / ci_dataset.name)
    base = ["relight", "--run", str(run), "--envmap", "city", "--views", "orbit", "--frames", "1", "--dirs", "8"]
    _one_line_error(base, capsys, str(gone), "--data")
    _one_line_error(base + ["--data", str(tmp_path / "elsewhere")], capsys, "--data", str(tmp_path / "elsewhere"),
                    str(tmp_path / "elsewhere" / "ci" / ci_dataset.name))
    for data in (root, root / "ci" / ci_dataset.name):  # a data root, or the scene directory itself
        out = tmp_path / f"out_{data.name}"
        assert main(base + ["--data", str(data), "--out", str(out)]) == 0, capsys.readouterr().err
        assert (out / "relit" / "orbit_000.png").is_file()
