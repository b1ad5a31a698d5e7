"""External methods (IRGS, R-3DGS, GI-GS, the authors' LumiMotion): export, import, "not run", published rows.

The exporters are read back by small re-implementations of each repository's loader and evaluation
look-ups (file names, keys; see baselines_adapters/external/*.py for the files and commits); the
importers read fixture folders laid out exactly as each repository's scripts write their outputs.
"""
from __future__ import annotations

import glob
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from baselines_adapters.base import MethodNotRun, is_not_run_message
from baselines_adapters.external import get_method
from baselines_adapters.external.common import export_paper_layout, resolve_scene
from baselines_adapters.registry import get_adapter
from benchmark.predictions import PredictionFolder, srgb_encode
from benchmark_fakes import make_fake_scene
from lumibench import layout
from lumibench.errors import UserError

ROOT = Path(__file__).resolve().parents[1]
LIGHTS = ("city", "sunrise")
N_TRAIN, N_TEST, RES = 3, 2, 8


@pytest.fixture
def scene(tmp_path) -> Path:
    data = tmp_path / "data" / "ci"
    make_fake_scene(data, "fake_statictimestep0001", lights=LIGHTS, n_train=N_TRAIN, n_test=N_TEST, res=RES)
    return make_fake_scene(data, "fake", lights=LIGHTS, n_train=N_TRAIN, n_test=N_TEST, res=RES)


@pytest.fixture
def exported(scene, tmp_path):
    names, dirs = export_paper_layout(scene, tmp_path / "export", "irgs")
    return names, dirs


def _png(path: Path) -> np.ndarray:
    return np.asarray(iio.imread(path))


def _ours(scene: Path, kind: str, split: str, j: int, light: str | None = None) -> np.ndarray:
    fp = layout.file_path(split, j)
    return _png(layout.lit_image_path(scene, light, fp) if light else layout.gt_path(scene, kind, fp))


# ------------------------------------------------------------------ the loaders' conventions, re-implemented
def lumimotion_reads(source: Path, train_light: str, test_light: str) -> dict:
    """joaxkal/LumiMotion scene/dataset_readers.py + the *_static evaluation scripts' look-ups."""
    cams = {}
    for split in ("train", "test"):
        contents = json.loads((source / f"transforms_{split}.json").read_text())
        frames = sorted(contents["frames"], key=lambda x: int(os.path.basename(x["file_path"]).split(".")[0].split("_")[-1]))
        assert isinstance(contents["camera_angle_x"], float)
        cams[split] = []
        for idx, fr in enumerate(frames):
            path = os.path.join(source, train_light, fr["file_path"] + ".png")
            assert not os.path.exists(os.path.join(os.path.dirname(os.path.dirname(path)), "rgba"))
            assert os.path.isfile(path), path
            assert np.asarray(fr["transform_matrix"]).shape == (4, 4)
            cams[split].append({"path": path, "time": fr["time"] if "time" in fr else idx / len(frames)})
    static = glob.glob(f"{source}_statictimestep*")[0]
    frame_static = re.search(r"timestep(\d+)", static).group(1)
    fid_static = [c for c in cams["test"] + cams["train"] if frame_static.zfill(4) in c["path"]][0]["time"]
    out = {"static": Path(static), "fid_static": fid_static, "test": []}
    for view in cams["test"]:
        render_name = os.path.basename(view["path"]).split(".")[0]
        albedo = [f for f in os.listdir(os.path.join(static, "albedo")) if render_name in f]
        lit = [f for f in os.listdir(os.path.join(static, test_light)) if render_name in f]
        assert len(albedo) == 1 and len(lit) == 1, (render_name, albedo, lit)  # [0] would pick arbitrarily
        rough = os.path.join(static, "roughness", f"r_{render_name[-4:]}.png")
        out["test"].append({"albedo": Path(static, "albedo", albedo[0]), "lit": Path(static, test_light, lit[0]),
                            "roughness": Path(rough), "dyn_albedo": [f for f in os.listdir(source / "albedo")
                                                                     if render_name in f]})
    assert (source / f"{test_light}.hdr").is_file()
    return out


def _find_matching_file(folder, prefix_file):  # the same rule in the IRGS and GI-GS forks
    prefix = os.path.splitext(prefix_file)[0]
    for f in sorted(os.listdir(folder)):
        if f.startswith(prefix) and f.endswith(".png") and f != prefix_file:
            return f
    return None


def irgs_reads(static: Path, data_subdir: str, map_name: str) -> list[dict]:
    """piotrmwojcik/IRGS readCamerasFromTransforms ($DATA_SUBDIR), eval_material_syn4, eval_relighting_syn4."""
    assert "TensoIR" not in str(static) and "Synthetic4Relight" not in str(static)
    for split in ("train", "test"):
        for fr in json.loads((static / f"transforms_{split}.json").read_text())["frames"]:
            fp = fr["file_path"] if ".png" in fr["file_path"] else fr["file_path"] + ".png"
            assert (static / data_subdir / os.path.basename(fp)).is_file()
    out = []
    for fr in json.loads((static / "transforms_test.json").read_text())["frames"]:
        match = _find_matching_file(static / "albedo", fr["file_path"])
        assert match is not None, fr["file_path"]
        rough = imageio_read(static / "roughness" / match)
        assert rough.ndim == 3, "IRGS indexes roughness[..., :1]: it must have channels"
        out.append({"albedo": static / "albedo" / match, "roughness": static / "roughness" / match,
                    "lit": static / map_name / (fr["file_path"].split("/")[-1] + ".png")})
    assert (static / f"{map_name}.hdr").is_file()
    return out


def imageio_read(path):
    return np.asarray(iio.imread(path))


def r3dgs_reads(static: Path, envmap_prefix: str, test_light: str) -> list[dict]:
    """piotrmwojcik/Relightable3DGaussian readCamerasFromTransforms(envmap_prefix), eval_relighting_ours."""
    out = []
    for split in ("train", "test"):
        for fr in json.loads((static / f"transforms_{split}.json").read_text())["frames"]:
            image_path = static / envmap_prefix / (fr["file_path"] + ".png")
            assert image_path.is_file()
            if split == "test":
                render_name = image_path.stem
                lit = [f for f in os.listdir(static / test_light) if render_name in f]
                alb = [f for f in os.listdir(static / "albedo") if render_name in f]
                assert len(lit) == 1 and len(alb) == 1
                out.append({"name": render_name, "albedo": static / "albedo" / alb[0], "lit": static / test_light / lit[0]})
    assert (static / f"{test_light}.hdr").is_file()
    return out


def gigs_reads(static: Path, data_subdir: str) -> list[dict]:
    """piotrmwojcik/GI-GS readCamerasFromTransforms ($DATA_SUBDIR) and render.py eval_brdf look-ups."""
    out = []
    for fr in json.loads((static / "transforms_test.json").read_text())["frames"]:
        cam_name = os.path.join(static, fr["file_path"] + ".png")
        assert (static / data_subdir / os.path.basename(cam_name)).is_file()
        albedo_path = fr["file_path"].replace("rgba", "albedo") + ".png"
        match = _find_matching_file(static / "albedo", albedo_path)
        assert match is not None, f"GI-GS finds no albedo for {albedo_path} (it skips {albedo_path} itself)"
        mask = imageio_read(static / data_subdir / albedo_path)
        assert mask.shape[-1] == 4
        out.append({"name": Path(cam_name).stem, "albedo": static / "albedo" / match})
    return out


# --------------------------------------------------------------------------------------------- exporters
def test_export_read_by_lumimotion_loader(exported, scene):
    names, dirs = exported
    got = lumimotion_reads(dirs["dynamic"], "city", "sunrise")
    assert got["static"] == dirs["static"]
    assert got["fid_static"] == pytest.approx(layout.read_transforms(scene, "train").frames[1].time)
    for j, view in enumerate(got["test"]):
        assert np.array_equal(_png(view["albedo"]), _ours(scene, "albedo", "test", j))
        assert np.array_equal(_png(view["lit"]), _ours(scene, None, "test", j, "sunrise"))
        assert np.array_equal(_png(view["roughness"])[..., 0], _ours(scene, "roughness", "test", j))
        assert len(view["dyn_albedo"]) == 1
    assert names.test_names == ("r_0003", "r_0004") and names.test_stems == ("r_0000", "r_0001")


def test_export_read_by_irgs_r3dgs_gigs_loaders(exported, scene):
    _, dirs = exported
    static = dirs["static"]
    for j, v in enumerate(irgs_reads(static, "city", "sunrise")):
        assert np.array_equal(_png(v["albedo"]), _ours(scene, "albedo", "test", j))
        assert np.array_equal(_png(v["roughness"])[..., 0], _ours(scene, "roughness", "test", j))
        assert np.array_equal(_png(v["lit"]), _ours(scene, None, "test", j, "sunrise"))
    r3 = r3dgs_reads(static, "city", "sunrise")
    assert [v["name"] for v in r3] == ["r_0003", "r_0004"]
    for j, v in enumerate(gigs_reads(static, "city")):
        assert np.array_equal(_png(v["albedo"]), _ours(scene, "albedo", "test", j))


def test_export_cli_prints_commands_and_refuses_foreign_dirs(scene, tmp_path, capsys):
    from baselines_adapters.__main__ import main

    assert main(["export", "lumimotion_official", "--data", str(scene), "--out", str(tmp_path / "e"),
                 "--train-light", "city", "--test-light", "sunrise"]) == 0
    text = capsys.readouterr().out
    assert "scripts.train_stage1" in text and "--train_light_folder city" in text and "--test-light sunrise" in text
    (tmp_path / "f" / "fake").mkdir(parents=True)
    (tmp_path / "f" / "fake" / "mine.txt").write_text("x")
    assert main(["export", "irgs", "--data", str(scene), "--out", str(tmp_path / "f")]) == 2
    assert "not written by this exporter" in capsys.readouterr().err


def test_export_needs_the_static_variant(tmp_path):
    s = make_fake_scene(tmp_path, "lonely", lights=LIGHTS, n_train=2, n_test=1, res=RES)
    with pytest.raises(UserError, match="statictimestep"):
        resolve_scene(s)


# ----------------------------------------------------------------------------- fixtures of method outputs
def _val(j: int, k: int = 0) -> float:
    return round(0.2 + 0.15 * j + 0.05 * k, 2)


def _write(path: Path, value: float, channels: int = 3, size: int = RES) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.full((size, size, channels), round(value * 255), np.uint8)
    iio.imwrite(path, img[..., 0] if channels == 1 else img)


def make_irgs_outputs(run: Path, size: int = RES) -> None:
    ours = run / "test" / "ours_20000"
    for j in range(N_TEST):  # render.py: <idx:05d>.png in transforms_test.json order
        for sub, k in (("render", 0), ("base_color_linear", 1), ("base_color", 2), ("roughness", 3), ("rend_normal", 4)):
            _write(ours / sub / f"{j:05d}.png", _val(j, k), size=size)
        # eval_relighting_syn4.py of the fork, run with MAP_NAME=sunrise -e light, renders at 400x400
        _write(run / "test_lg0_rli_sunrise_light" / "env6" / "render" / f"{j}.png", _val(j, 5), size=2 * size)
    _write(run / "test" / "ours_7000" / "render" / "00000.png", 0.9)  # an older iteration: ignored


def make_r3dgs_outputs(run: Path) -> None:
    ours = run / "neilf" / "test" / "ours_40000"
    for j, name in enumerate(("r_0003", "r_0004")):  # eval_nvs.py: <image_name>.png
        _write(ours / "renders" / f"{name}.png", _val(j, 0))
        _write(ours / "base_color" / f"{name}.png", _val(j, 2))
        _write(ours / "roughness" / f"{name}.png", _val(j, 3), channels=1)
        _write(run / "neilf" / "test_rli" / "env" / "pbr" / f"{j}.png", _val(j, 5))  # eval_relighting_ours.py


def make_gigs_outputs(run: Path) -> None:
    pbr = run / "test" / "ours_None" / "pbr"
    for j, name in enumerate(("r_0003", "r_0004")):  # render.py --pbr, relight.py --hdri .../sunrise.hdr
        _write(pbr / f"{name}.png", _val(j, 0))
        _write(pbr / f"{name}_albedo.png", _val(j, 1))
        _write(pbr / f"{name}_roughness.png", _val(j, 3), channels=1)
        _write(pbr / f"{name}_diffuse.png", 0.99)
        _write(run / "test" / "ours_None" / "relight" / f"{name}_sunrise.png", _val(j, 5))


def make_lumimotion_outputs(run: Path) -> None:
    for j in range(N_TEST):  # the *_static evaluation scripts: <prefix><idx>.png, idx = sorted test order
        _write(run / "eval_material_static" / "ours_55000" / f"albedo_train_static{j}.png", _val(j, 1))
        _write(run / "eval_material_static" / "ours_55000" / f"roughness_train_static{j}.png", _val(j, 3), channels=1)
        _write(run / "eval_nvs_static" / "ours_55000" / f"render{j}.png", _val(j, 0))
        _write(run / "eval_relight_static" / "ours_55000" / f"render{j}.png", _val(j, 5))


MAKERS = {"irgs": make_irgs_outputs, "r3dgs": make_r3dgs_outputs, "gigs": make_gigs_outputs,
          "lumimotion_official": make_lumimotion_outputs}
ALBEDO_K = {"irgs": 1, "r3dgs": 2, "gigs": 1, "lumimotion_official": 1}   # which fixture value is the albedo
ALBEDO_LINEAR = {"irgs": True, "r3dgs": False, "gigs": True, "lumimotion_official": True}


def _import(method: str, run: Path, scene: Path, out: Path, *extra: str) -> int:
    from baselines_adapters.__main__ import main

    return main(["import", method, "--from", str(run), "--data", str(scene), "--out", str(out),
                 "--train-light", "city", *extra])


@pytest.mark.parametrize("method", list(MAKERS))
def test_importer_reads_the_repository_outputs(method, scene, tmp_path):
    run, out = tmp_path / "run", tmp_path / "pred"
    MAKERS[method](run)
    extra = ["--test-light", "sunrise"] if method in ("r3dgs", "lumimotion_official") else []
    assert _import(method, run, scene, out, *extra) == 0
    pred = PredictionFolder(out)
    meta = pred.meta()
    assert meta["method"] == method and meta["test_lights"] == ["sunrise"]
    for j, stem in enumerate(("r_0000", "r_0001")):  # our test stems, not the exported names
        q = lambda v: round(v * 255) / 255  # noqa: E731 - 8-bit fixture values
        albedo = pred.read("albedo", stem, (RES, RES))
        raw = q(_val(j, ALBEDO_K[method]))
        expect = float(srgb_encode(np.float32(raw))) if ALBEDO_LINEAR[method] else raw
        assert albedo[0, 0] == pytest.approx([expect] * 3, abs=2e-3), (method, "albedo", j)
        assert pred.read("roughness", stem, (RES, RES))[0, 0, 0] == pytest.approx(q(_val(j, 3)), abs=2e-3)
        assert pred.read("nvs", stem, (RES, RES))[0, 0] == pytest.approx([q(_val(j, 0))] * 3, abs=2e-3)
        relit = pred.read("relight", stem, (RES, RES), light="sunrise")  # resized where the script changed size
        assert relit[3, 3] == pytest.approx([q(_val(j, 5))] * 3, abs=2e-3)
    assert not (out / "relight" / "city").exists()


def test_importer_refuses_incomplete_outputs_and_finds_the_scene_from_cfg_args(scene, tmp_path):
    run = tmp_path / "run"
    make_irgs_outputs(run)
    (run / "test" / "ours_20000" / "base_color_linear" / "00001.png").unlink()
    with pytest.raises(UserError, match="incomplete albedo.*00001.png"):
        from baselines_adapters.external.common import Importer, import_run

        import_run(get_method("irgs"), Importer(resolve_scene(scene), tmp_path / "p"), run, [])
    run2 = tmp_path / "run2"
    make_gigs_outputs(run2)
    _, dirs = export_paper_layout(scene, tmp_path / "export", "gigs")
    (run2 / "cfg_args").write_text(f"Namespace(eval=True, source_path='{dirs['static']}', white_background=False)")
    from baselines_adapters.__main__ import main

    assert main(["import", "gigs", "--from", str(run2), "--out", str(tmp_path / "p2")]) == 0
    assert PredictionFolder(tmp_path / "p2").has("relight", "sunrise")


def test_imported_predictions_score_with_no_glue(tmp_path, monkeypatch):
    """The registry adapter finds a run under runs/<profile>/external/... and the benchmark scores it."""
    from benchmark.score import score

    monkeypatch.delenv("LUMIBENCH_EXTERNAL_RUNS", raising=False)
    data = tmp_path / "data" / "ci"
    make_fake_scene(data, "fake_statictimestep0001", lights=LIGHTS, n_train=N_TRAIN, n_test=N_TEST, res=16)
    scene = make_fake_scene(data, "fake", lights=LIGHTS, n_train=N_TRAIN, n_test=N_TEST, res=16)
    runs = tmp_path / "runs" / "ci"
    make_irgs_outputs(runs / "external" / "irgs" / "fake" / "city", size=16)
    pdir = get_adapter("irgs").run(scene, "city", ["sunrise"], 0, "ci", tmp_path / "pred", runs)
    res = score(scene, pdir, "city", "sunrise", "lumimotion", "vgg", "ci")
    assert res["status"] == "ok"
    assert res["metrics"]["albedo"]["psnr"] > 0 and res["metrics"]["relight"]["psnr"] > 0
    assert res["metrics"]["roughness"]["mse"] >= 0


# ----------------------------------------------------------------------------------------------- not run
@pytest.mark.parametrize("method", list(MAKERS))
def test_not_run_adapter_says_what_to_run_in_one_line(method, scene, tmp_path, monkeypatch):
    monkeypatch.delenv("LUMIBENCH_EXTERNAL_RUNS", raising=False)
    adapter = get_adapter(method)
    assert adapter.seed_dependent is False
    with pytest.raises(MethodNotRun) as err:
        adapter.run(scene, "city", ["sunrise"], 0, "ci", tmp_path / "pred", tmp_path / "runs" / "ci")
    msg = str(err.value)
    assert "\n" not in msg and is_not_run_message(msg) and isinstance(err.value, UserError)
    assert f"python -m baselines_adapters export {method}" in msg
    assert str(tmp_path / "runs" / "ci" / "external" / method / "fake" / "city") in msg
    assert "python -m baselines_adapters import" in msg
    assert not (tmp_path / "pred" / "meta.json").exists()


def test_not_run_cli_exits_2_with_one_line(scene, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "baselines_adapters", "import", "irgs", "--from",
                           str(tmp_path / "never_run"), "--data", str(scene), "--out", str(tmp_path / "p")],
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: not run: ") and "export irgs" in lines[0]


# ------------------------------------------------------------------------------------ published numbers
def test_published_rows_are_the_papers_numbers():
    from baselines_adapters.published import LABEL, published_rows, rows

    all_rows = rows()
    assert len(all_rows) == 18  # 3 configurations x 5 methods + 3 ablations
    by = {(r.configuration, r.method): r for r in all_rows}
    lm = by[("chapel_day->golden_bay", "lumimotion")]
    assert lm.metrics["albedo.psnr"] == (30.838, 1.798) and lm.metrics["relight.lpips"] == (0.041, 0.007)
    assert lm.metrics["roughness.mse"] == (0.011, 0.002) and lm.metrics["delta_psnr.percent"][0] == -3.3
    nos = by[("golden_bay->dam_wall", "irgs_nosmooth")]
    assert nos.metrics["roughness.mse"] == (0.021, 0.008) and np.isnan(nos.metrics["albedo.psnr"][1])
    gi = by[("dam_wall->small_harbour_sunset", "gigs")]
    assert gi.metrics["relight.psnr"] == (18.434, 1.681) and any("18.431" in n for n in gi.notes)
    assert by[("golden_bay->dam_wall", "wo_P")].metrics["albedo.psnr"][0] == 26.768
    assert all(r.label == LABEL for r in all_rows)
    mapped = published_rows({"city->sunrise": "golden_bay->dam_wall"})
    assert {r.configuration for r in mapped} == {"city->sunrise"} and len(mapped) == 5
    assert all("[Golden Bay → Dam Wall]" in r.display for r in mapped)
    with pytest.raises(UserError, match="no published results"):
        published_rows(["city->sunrise"])


def test_published_rows_render_labelled_and_outside_our_means():
    import csv
    import io

    from benchmark import tables
    from benchmark.aggregate import aggregate, check_consistent, published_reference
    from benchmark_fakes import fake_result

    rs = [fake_result("ours", "a", albedo_psnr=20.0), fake_result("ours", "b", albedo_psnr=22.0),
          fake_result("lit_as_albedo", "a", albedo_psnr=10.0)]
    nr = fake_result("irgs", "a", status="failed")
    nr["error"] = str(MethodNotRun("IRGS (irgs) has no outputs for a: run ..."))
    rs.append(nr)
    groups, meta = aggregate(rs), check_consistent(rs)
    ref = published_reference({"city->sunrise": "golden_bay->dam_wall"}) + published_reference(["chapel_day->golden_bay"])
    md = tables.markdown(groups, meta, reference=ref)
    label = "published, on the paper's dataset"
    line = next(l for l in md.splitlines() if l.startswith("| *LumiMotion [Golden Bay → Dam Wall]"))
    assert label in line and "27.93 ± 1.93" in line and "**" not in line and line.endswith("| reference |")
    ours = next(l for l in md.splitlines() if l.startswith("| ours |"))
    assert "**21.00 ± 1.00**" in ours  # our mean and bold unchanged by a better published albedo
    assert f"### chapel_day → golden_bay ({label})" in md and label in md.split("**")[1]
    irgs = next(l for l in md.splitlines() if l.startswith("| irgs |"))
    assert irgs.endswith("| not run |") and "### Not run" in md and "### Failed runs" not in md
    tex = tables.latex(groups, meta, reference=ref)
    assert r"\textit{IRGS† (no roughness smoothness) [Golden Bay $\rightarrow$ Dam Wall] (published, on the paper's dataset)}" in tex
    rows_csv = list(csv.DictReader(io.StringIO(tables.csv_text(groups, meta, reference=ref))))
    pub = [r for r in rows_csv if r["reference"] == label]
    assert len(pub) == 10 and all(r["protocol"] == "" for r in pub)
    assert tables.markdown(groups, meta) == tables.markdown(groups, meta, reference=())  # opt-in
