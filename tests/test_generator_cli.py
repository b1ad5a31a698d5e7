"""`python -m generator dataset|demo|bench`: bad input gives one stderr line and exit code 2."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from lumibench import layout
from lumibench.io import read_image

REPO = Path(__file__).resolve().parent.parent


def _run(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "generator", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


def _user_error(proc: subprocess.CompletedProcess, *needles: str) -> None:
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-1500:])
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    assert "Traceback" not in proc.stderr
    for n in needles:
        assert n in lines[0], (n, lines[0])


def _no_scene_written(data: Path) -> None:
    assert not any(p.name == "dataset.json" for p in data.rglob("*")) if data.exists() else True


@pytest.mark.parametrize("args, needles", [
    (["--scenes", "no_such_scene"], ["unknown scene 'no_such_scene'", "spheres"]),
    (["--scenes", "spheres", "--lights", "no_such_light"], ["unknown light 'no_such_light'", "city"]),
    (["--scenes", "spheres", "--lights", "/nonexistent/map.hdr"], ["not found", "/nonexistent/map.hdr"]),
    (["--profile", "nope", "--scenes", "spheres"], ["unknown profile 'nope'"]),
    (["--scenes", "spheres", "--jobs", "0"], ["--jobs"]),
])
def test_bad_dataset_arguments(tmp_path, args, needles):
    data = tmp_path / "data"
    _user_error(_run("dataset", "--data", str(data), *args), *needles)
    _no_scene_written(data)


def test_malformed_scene_yaml_names_the_key(tmp_path):
    bad = tmp_path / "broken.yaml"
    src = (REPO / "configs" / "scenes" / "spheres.yaml").read_text()
    bad.write_text(src.replace("roughness: 0.15", "roughness: shiny"))
    proc = _run("dataset", "--data", str(tmp_path / "data"), "--scenes", str(bad))
    _user_error(proc, str(bad), "roughness")
    syntax = tmp_path / "syntax.yaml"
    syntax.write_text("seed: [1, 2\nobjects: {\n")
    _user_error(_run("dataset", "--data", str(tmp_path / "data"), "--scenes", str(syntax)), "malformed YAML")
    _no_scene_written(tmp_path / "data")


def test_corrupt_hdr_file(tmp_path):
    bad = tmp_path / "garbage.hdr"
    bad.write_bytes(b"this is not a radiance file")
    _user_error(_run("dataset", "--data", str(tmp_path / "data"), "--scenes", "spheres", "--lights", str(bad)),
                "garbage.hdr")
    _no_scene_written(tmp_path / "data")


def test_unwritable_data_directory(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    _user_error(_run("dataset", "--data", str(blocker / "data"), "--scenes", "spheres"), "not writable", "--data")


def test_bench_unwritable_output(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    _user_error(_run("bench", "--out", str(blocker / "sub" / "generator.json")), "cannot create")


@pytest.mark.slow
def test_demo_on_rendered_dataset_writes_contact_sheet(ci_dataset):
    """`demo` on DATA that already holds the ci scene resumes (nothing to render) and writes the sheet."""
    data = ci_dataset.parent.parent
    proc = _run("demo", "--data", str(data), "--no-progress", timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    sheet = data / "ci" / f"contact_sheet_{ci_dataset.name}.png"
    assert str(sheet) in proc.stdout
    img = read_image(sheet)
    assert img.shape[0] > 300 and img.shape[1] > 800 and img[..., :3].std() > 0.05
    assert layout.is_complete(ci_dataset)
