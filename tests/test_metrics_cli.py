"""`python -m benchmark metrics A B [--json]`: values, JSON keys, and one-line errors with exit code 2."""
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmark.metrics import lpips, psnr, ssim
from lumibench.cli import build_main
from lumibench.io import read_image, write_png

ROOT = Path(__file__).resolve().parents[1]
main = build_main("python -m benchmark", "test", {"metrics": "benchmark.commands.metrics"})


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    d = tmp_path_factory.mktemp("metrics_cli")
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:48, 0:40] / 48
    a = np.stack([xx, 0.5 + 0.4 * np.sin(15 * yy), 0.3 + 0.2 * xx * yy], -1)
    b = np.clip(a + 0.05 * rng.standard_normal(a.shape), 0, 1)
    write_png(d / "a.png", a)
    rgba = np.concatenate([b, np.full(b.shape[:2] + (1,), 0.5)], -1)
    write_png(d / "b_rgba.png", rgba)  # alpha must be dropped
    np.savez(d / "b.npz", img=(np.round(b * 255) / 255).astype(np.float32))
    write_png(d / "small.png", a[:32])
    (d / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"truncated")
    return d


def test_json_keys_and_values(images, capsys):
    assert main(["metrics", str(images / "a.png"), str(images / "b_rgba.png"), "--json"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1
    res = json.loads(out[0])
    assert list(res) == ["psnr", "ssim", "lpips_vgg", "lpips_alex"]
    x = read_image(images / "a.png")[..., :3].astype(np.float64)
    y = read_image(images / "b_rgba.png")[..., :3].astype(np.float64)
    assert res["psnr"] == pytest.approx(psnr(x, y), abs=1e-9)
    assert res["ssim"] == pytest.approx(ssim(x, y), abs=1e-9)
    assert res["lpips_vgg"] == pytest.approx(lpips(x, y, net="vgg"), rel=1e-6)
    assert res["lpips_alex"] == pytest.approx(lpips(x, y, net="alex"), rel=1e-6)
    assert 20 < res["psnr"] < 35 and 0 < res["ssim"] < 1 and res["lpips_vgg"] > 0 and res["lpips_alex"] > 0


def test_png_and_npz_of_the_same_pixels_agree(images, capsys):
    main(["metrics", str(images / "a.png"), str(images / "b_rgba.png"), "--json"])
    png = json.loads(capsys.readouterr().out)
    main(["metrics", str(images / "a.png"), str(images / "b.npz"), "--json"])
    npz = json.loads(capsys.readouterr().out)
    for k in png:
        assert npz[k] == pytest.approx(png[k], rel=1e-5)


def test_identical_images(images, capsys):
    assert main(["metrics", str(images / "a.png"), str(images / "a.png"), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res == {"psnr": None, "ssim": 1.0, "lpips_vgg": 0.0, "lpips_alex": 0.0}


def test_human_output(images, capsys):
    assert main(["metrics", str(images / "a.png"), str(images / "b_rgba.png")]) == 0
    out = capsys.readouterr().out
    for label in ("PSNR", "SSIM", "LPIPS-VGG", "LPIPS-Alex"):
        assert label in out


@pytest.mark.parametrize("other, words", [("small.png", "sizes differ"), ("corrupt.png", "corrupt.png"),
                                          ("missing.png", "not found")])
def test_errors_are_one_line_exit_2(images, capsys, other, words):
    assert main(["metrics", str(images / "a.png"), str(images / other)]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and words in lines[0]


def test_real_entry_point(images):
    """The installed verb through `python -m benchmark`, in a subprocess: exit codes and stdout."""
    ok = subprocess.run([sys.executable, "-m", "benchmark", "metrics", str(images / "a.png"),
                         str(images / "b_rgba.png"), "--json"], cwd=ROOT, capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    assert set(json.loads(ok.stdout)) == {"psnr", "ssim", "lpips_vgg", "lpips_alex"}
    bad = subprocess.run([sys.executable, "-m", "benchmark", "metrics", str(images / "a.png"),
                          str(images / "corrupt.png")], cwd=ROOT, capture_output=True, text=True)
    assert bad.returncode == 2
    assert "Traceback" not in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
    assert math.isfinite(json.loads(ok.stdout)["psnr"])
