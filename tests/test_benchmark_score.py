"""Scoring prediction folders: analytic PSNR of a noisy oracle, floors worse than GT, clear errors."""
from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lumibench.io import sha256_file

from baselines_adapters import get_adapter
from baselines_adapters.trivial import NoisyGT, expected_psnr
from benchmark.score import score
from lumibench.errors import UserError
from benchmark_fakes import make_fake_scene

SIGMA = 0.02
REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_fake_scene(tmp_path_factory.mktemp("bench_scene"), res=32, n_test=3, n_train=3)


@pytest.fixture(scope="module")
def scene_full_alpha(tmp_path_factory):
    return make_fake_scene(tmp_path_factory.mktemp("bench_scene_full"), res=32, n_test=3, n_train=3,
                           full_alpha=True, seed=3)


@pytest.fixture(scope="module")
def noisy_strict(scene, tmp_path_factory):
    pred = NoisyGT(SIGMA).run(scene, "city", ["sunrise"], 7, "ci", tmp_path_factory.mktemp("noisy") / "pred")
    return score(scene, pred, "city", "sunrise", protocol="strict")


def test_noisy_gt_strict_psnr_is_analytic(noisy_strict):
    # values stay in [0.2, 0.8] and sigma = 0.02: no clipping, so MSE = sigma^2 on the foreground
    want = expected_psnr(SIGMA)  # 33.98 dB
    m = noisy_strict["metrics"]
    assert m["nvs"]["psnr"] == pytest.approx(want, abs=0.3)
    assert m["relight"]["psnr"] == pytest.approx(want, abs=0.3)
    assert m["albedo"]["psnr"] == pytest.approx(want, abs=0.5)  # after a (near-identity) median alignment
    assert m["albedo"]["scale"] == pytest.approx([1, 1, 1], abs=0.02)
    assert m["roughness"]["mse"] == pytest.approx(SIGMA**2, rel=0.15)
    assert m["delta_psnr"]["db"] == pytest.approx(m["nvs"]["psnr"] - m["relight"]["psnr"])
    assert m["separation"]["iou"] == 1.0  # noise of 0.02 never crosses 0.5
    assert noisy_strict["metric_config"]["lpips_input_range"] == "[-1,1]"
    assert len(noisy_strict["metric_config"]["lpips_weights"]["sha256"]) == 64
    assert set(noisy_strict["per_image"]["relight"]) == {"r_0000", "r_0001", "r_0002"}
    assert noisy_strict["inputs"]["dataset_spec_hash"] == "fake-0-32"
    pred = Path(noisy_strict["inputs"]["pred_dir"])  # the predictions it scored, by their meta.json
    assert noisy_strict["inputs"]["pred_meta_sha256"] == sha256_file(pred / "meta.json")


def test_noisy_gt_lumimotion_psnr_per_channel_and_masked(scene_full_alpha, tmp_path):
    # full alpha: the masked full image is the whole image, and per-channel PSNRs all equal the analytic value
    pred = NoisyGT(SIGMA).run(scene_full_alpha, "city", ["sunrise"], 1, "ci", tmp_path / "pred")
    for kind in ("albedo", "nvs"):
        shutil.rmtree(tmp_path / "pred" / kind)  # score relight (and roughness) only: keeps the test short
    res = score(scene_full_alpha, pred, "city", "sunrise", protocol="lumimotion")
    assert res["metrics"]["relight"]["psnr"] == pytest.approx(expected_psnr(SIGMA), abs=0.3)
    assert res["metrics"]["albedo"] is None and res["metrics"]["delta_psnr"] is None
    assert res["metric_config"]["lpips_input_range"] == "[0,1]"


def test_lit_as_albedo_scores_worse_than_ground_truth(scene, noisy_strict, tmp_path):
    pred = get_adapter("lit_as_albedo").run(scene, "city", ["sunrise"], 0, "ci", tmp_path / "lit")
    lit = score(scene, pred, "city", "sunrise", protocol="strict")["metrics"]
    gt = noisy_strict["metrics"]
    assert lit["nvs"] is None
    assert lit["albedo"]["psnr"] < gt["albedo"]["psnr"] - 5
    assert lit["albedo"]["lpips"] > gt["albedo"]["lpips"]
    assert lit["relight"]["psnr"] < gt["relight"]["psnr"] - 5
    assert lit["roughness"]["mse"] > 5 * gt["roughness"]["mse"]


def _copy_pred(scene, tmp_path):
    return get_adapter("mean_albedo").run(scene, "city", ["sunrise"], 0, "ci", tmp_path / "pred")


def test_missing_prediction_file_is_named(scene, tmp_path):
    pred = _copy_pred(scene, tmp_path)
    (pred / "albedo" / "r_0001.png").unlink()
    with pytest.raises(UserError, match=r"albedo/r_0001"):
        score(scene, pred, "city", "sunrise")


def test_corrupt_prediction_file_is_named(scene, tmp_path):
    pred = _copy_pred(scene, tmp_path)
    bad = pred / "relight" / "sunrise" / "r_0002.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    with pytest.raises(UserError, match=r"r_0002\.png"):
        score(scene, pred, "city", "sunrise")


def test_wrong_size_unknown_light_and_missing_meta(scene, tmp_path):
    from lumibench.io import write_png

    pred = _copy_pred(scene, tmp_path)
    write_png(pred / "roughness" / "r_0000.png", np.zeros((8, 8)))
    with pytest.raises(UserError, match=r"roughness/r_0000\.png is 8x8 pixels"):
        score(scene, pred, "city", "sunrise")
    with pytest.raises(UserError, match=r"unknown test light 'moon'.*rendered: city, courtyard, sunrise, sunset"):
        score(scene, pred, "city", "moon")
    with pytest.raises(UserError, match=r"relight/sunset/: the method relit sunrise only"):
        score(scene, pred, "city", "sunset")
    (pred / "meta.json").unlink()
    with pytest.raises(UserError, match=r"meta\.json"):
        score(scene, pred, "city", "sunrise")


def test_score_cli_errors_are_one_line(scene, tmp_path):
    pred = _copy_pred(scene, tmp_path)
    (pred / "albedo" / "r_0000.png").unlink()
    cmd = [sys.executable, "-m", "benchmark", "score", "--data", str(scene), "--pred", str(pred),
           "--train-light", "city", "--test-light", "sunrise", "--out", str(tmp_path / "r.json")]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "albedo/r_0000" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "r.json").exists()


def test_score_cli_writes_a_valid_result(scene, tmp_path):
    from benchmark.results import read_result

    pred = get_adapter("lit_as_albedo").run(scene, "city", ["sunrise"], 0, "ci", tmp_path / "pred")
    shutil.rmtree(pred / "albedo")  # relight and roughness only: keeps the subprocess short
    out = tmp_path / "res" / "results.json"
    proc = subprocess.run([sys.executable, "-m", "benchmark", "score", "--data", str(scene), "--pred", str(pred),
                           "--train-light", "city", "--test-light", "sunrise", "--protocol", "strict",
                           "--out", str(out)], capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    res = read_result(out)
    assert res["method"] == "lit_as_albedo" and res["protocol"] == "strict" and res["status"] == "ok"
    assert math.isfinite(res["metrics"]["relight"]["psnr"])
    assert json.loads(out.read_text())["schema_version"] == 1


def test_albedo_alignment_is_per_channel_in_linear_space(scene, tmp_path):
    """An albedo off by a per-channel factor in linear space scores as perfect after alignment."""
    from baselines_adapters.base import save
    from benchmark.predictions import write_meta
    from benchmark.score import read_gt
    from lumibench import layout

    factor = np.array([0.5, 0.8, 1.2], np.float32)
    pred = tmp_path / "scaled"
    for frame in layout.read_transforms(scene, "test").frames:
        save(pred, "albedo", frame.stem, read_gt(scene, "albedo", frame.file_path) * factor, fmt="npz")
    write_meta(pred, {"method": "scaled", "version": "1", "seed": 0})
    res = score(scene, pred, "city", "sunrise", protocol="strict")
    assert res["metrics"]["albedo"]["scale"] == pytest.approx(list(1 / factor), rel=1e-4)
    assert res["metrics"]["albedo"]["psnr"] > 60 and res["metrics"]["albedo"]["lpips"] < 1e-3
    assert res["metrics"]["relight"] is None and res["per_image"].keys() == {"albedo"}


# ---- bad input: one line, exit 2, never a silently missing score --------------------------------------


def _cli(*args, cwd=REPO):
    proc = subprocess.run([sys.executable, "-m", "benchmark", "score", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd)
    return proc


def _one_line_error(proc, *needles):
    assert proc.returncode == 2, (proc.returncode, proc.stdout[-500:], proc.stderr[-1500:])
    err = proc.stderr.strip()
    assert err.count("\n") == 0 and "Traceback" not in err, err
    for needle in needles:
        assert needle in err, (needle, err)
    return err


def test_unreadable_formats_are_refused_not_skipped(scene, tmp_path):
    """`benchmark metrics` reads JPEG; scoring does not (lossy): a folder of .jpg must not score as 'albedo: null'."""
    import imageio.v3 as iio

    pred = _copy_pred(scene, tmp_path)
    for p in sorted((pred / "albedo").glob("*.png")):
        iio.imwrite(p.with_suffix(".jpg"), iio.imread(p)[..., :3])
        p.unlink()
    with pytest.raises(UserError, match=r"albedo/ holds files the scorer does not read: r_0000\.jpg, r_0001\.jpg"):
        score(scene, pred, "city", "sunrise")
    # a stray .npy beside valid files, and files straight in relight/, are named too
    shutil.rmtree(pred / "albedo")
    np.save(pred / "roughness" / "r_0000.npy", np.zeros((32, 32), np.float32))
    with pytest.raises(UserError, match=r"roughness/ holds files the scorer does not read: r_0000\.npy"):
        score(scene, pred, "city", "sunrise")
    (pred / "roughness" / "r_0000.npy").unlink()
    shutil.copy(pred / "relight" / "sunrise" / "r_0000.png", pred / "relight" / "r_0000.png")
    with pytest.raises(UserError, match=r"relight/ holds files \(r_0000\.png\); it should hold a folder per test light"):
        score(scene, pred, "city", "sunrise")


def test_empty_kind_folder_and_letter_case_of_extensions(scene, tmp_path):
    pred = _copy_pred(scene, tmp_path)
    (pred / "nvs").mkdir()
    with pytest.raises(UserError, match=r"empty predictions folder .*nvs/"):
        score(scene, pred, "city", "sunrise")
    (pred / "nvs").rmdir()
    (pred / "relight" / "sunset").mkdir()
    with pytest.raises(UserError, match=r"empty predictions folder .*relight/sunset/"):
        score(scene, pred, "city", "sunrise")
    (pred / "relight" / "sunset").rmdir()
    # r_0001.PNG beside r_0001.png: two files for one view
    shutil.copy(pred / "albedo" / "r_0001.png", pred / "albedo" / "r_0001.PNG")
    with pytest.raises(UserError, match=r"ambiguous predictions: .*r_0001\.PNG, .*r_0001\.png"):
        score(scene, pred, "city", "sunrise")
    # alone, an upper-case extension is read like the lower-case one (same numbers)
    shutil.rmtree(pred / "relight")  # albedo and roughness only: keeps the test short
    (pred / "albedo" / "r_0001.png").unlink()
    upper = score(scene, pred, "city", "sunrise")
    (pred / "albedo" / "r_0001.PNG").rename(pred / "albedo" / "r_0001.png")
    lower = score(scene, pred, "city", "sunrise")
    assert upper["metrics"]["albedo"] == lower["metrics"]["albedo"]


def test_meta_contradicting_the_command_line(scene, tmp_path):
    import json as _json

    pred = _copy_pred(scene, tmp_path)
    meta_path = pred / "meta.json"
    meta = _json.loads(meta_path.read_text())
    assert meta["scene"] == scene.name and meta["train_light"] == "city"
    proc = _cli("--data", scene, "--pred", pred, "--train-light", "sunset", "--test-light", "sunrise",
                "--out", tmp_path / "r.json")
    _one_line_error(proc, "trained under light 'city', not 'sunset'", "meta.json")
    meta_path.write_text(_json.dumps(dict(meta, scene="hook")))
    with pytest.raises(UserError, match=r"predictions are for scene 'hook', not 'fake'"):
        score(scene, pred, "city", "sunrise")
    assert not (tmp_path / "r.json").exists()


def test_incomplete_dataset_and_data_that_is_not_a_scene(scene, tmp_path):
    pred = _copy_pred(scene, tmp_path)
    args = ["--pred", pred, "--train-light", "city", "--test-light", "sunrise", "--out", tmp_path / "r.json"]
    # the profile folder (DATA/PROFILE) instead of the scene: named, with the scene to pick
    _one_line_error(_cli("--data", scene.parent, *args), "is not a rendered scene",
                    f"the scenes inside it are {scene.name}")
    _one_line_error(_cli("--data", tmp_path, *args), "is not a rendered scene", "DATA/PROFILE/<scene>")
    assert "light" not in _cli("--data", tmp_path, *args).stderr
    # an unfinished dataset (no "complete": true)
    import json as _json

    unfinished = tmp_path / "unfinished"
    shutil.copytree(scene, unfinished)
    meta = _json.loads((unfinished / "dataset.json").read_text())
    (unfinished / "dataset.json").write_text(_json.dumps(dict(meta, complete=False)))
    with pytest.raises(UserError, match=r"is not complete .*\"complete\": true"):
        score(unfinished, pred, "city", "sunrise")
    (unfinished / "dataset.json").unlink()
    _one_line_error(_cli("--data", unfinished, *args), "is not complete")


def test_unwritable_out_is_one_line_before_scoring(scene, tmp_path):
    pred = _copy_pred(scene, tmp_path)
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    args = ["--data", scene, "--pred", pred, "--train-light", "city", "--test-light", "sunrise"]
    _one_line_error(_cli(*args, "--out", blocker / "r.json"), "cannot write the result file", "a_file/r.json")
    _one_line_error(_cli(*args, "--out", tmp_path), "is a directory")
