"""Shared plumbing: YAML validation messages, atomic writes, image reading errors, profiles."""

import os
import numpy as np
import pytest

from lumibench.config import Node, load_yaml
from lumibench.errors import UserError, run_cli
from lumibench.io import atomic_path, atomic_write_json, read_image, read_json, write_png
from lumibench.profiles import available_profiles, load_profile


def test_malformed_yaml_names_file_and_line(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: 1\nb: [1, 2\nc: 3\n")
    with pytest.raises(UserError, match=r"bad\.yaml: malformed YAML at line \d+"):
        load_yaml(bad)


def test_node_messages_name_the_key():
    root = Node({"camera": {"radius": "far"}}, "scene.yaml")
    with pytest.raises(UserError, match=r"scene\.yaml: key 'camera\.radius' must be a number"):
        root.child("camera").get("radius", float)
    with pytest.raises(UserError, match=r"key 'camera\.fov' is required"):
        root.child("camera").get("fov", float)
    with pytest.raises(UserError, match=r"key 'camera\.radius' is not a known key"):
        root.child("camera").reject_unknown(["distance"])
    assert Node({"n": 3}, "x").get("n", float) == 3.0
    with pytest.raises(UserError, match="must be positive"):
        Node({"n": -1}, "x").get("n", int, check=lambda v: v > 0, check_msg="must be positive")
    with pytest.raises(UserError, match="got a boolean"):
        Node({"n": True}, "x").get("n", int)


def test_atomic_path_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.json"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed")
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []
    atomic_write_json(target, {"a": np.float32(1.5)})
    assert read_json(target) == {"a": 1.5}


def test_read_image_roundtrip_and_errors(tmp_path):
    img = np.random.default_rng(0).random((5, 7, 3)).astype(np.float32)
    write_png(tmp_path / "a.png", img)
    back = read_image(tmp_path / "a.png")
    assert back.shape == (5, 7, 3)
    assert np.abs(back - img).max() <= 0.5 / 255 + 1e-6
    np.savez(tmp_path / "b.npz", img)
    assert np.array_equal(read_image(tmp_path / "b.npz"), img)
    (tmp_path / "c.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(UserError, match=r"cannot read image .*c\.png"):
        read_image(tmp_path / "c.png")
    with pytest.raises(UserError, match=r"image not found: .*missing\.png"):
        read_image(tmp_path / "missing.png")


def test_profiles_load_and_unknown_profile():
    assert {"ci", "demo", "small", "full"} <= set(available_profiles())
    ci = load_profile("ci")
    assert ci.dataset.resolution <= 64 and ci.dataset.dynamic_frames <= 16
    assert ci.dataset.test_views <= 4 and ci.dataset.spp <= 8
    full = load_profile("full")
    assert full.dataset.frames_for("spheres") == 100 and full.dataset.frames_for("hook") == 150
    with pytest.raises(UserError, match="unknown profile 'huge'"):
        load_profile("huge")


def test_demo_profile_is_ci_with_the_spheres_frames_and_named_settings():
    """`make demo`'s profile: ci's images with small's 60 spheres frames (at ci's 16 the balls are not
    learned), and ci's method settings but for the keys BENCHMARKS.md measured for it (sessions 35, 42)."""
    from method.config import load_method_config

    ci, demo = load_profile("ci").dataset, load_profile("demo").dataset
    assert (demo.resolution, demo.test_views, demo.spp, demo.static_timestep) == \
        (ci.resolution, ci.test_views, ci.spp, ci.static_timestep)
    assert demo.frames_for("spheres") == load_profile("small").dataset.frames_for("spheres") == 60
    # stage 2 at half of ci's iterations: the same scores on three seeds, ~10 s of the demo (session 42)
    assert (load_profile("demo").method.stage1_iterations, load_profile("demo").method.stage2_iterations) == \
        (load_profile("ci").method.stage1_iterations, 100)

    def flat(d, prefix=""):
        out = {}
        for k, v in d.items():
            out.update(flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
        return out

    c, d = flat(load_method_config("ci")), flat(load_method_config("demo"))
    assert set(c) == set(d)
    changed = {k for k in c if c[k] != d[k]} - {"profile"}
    assert changed == {"model.time_freqs", "model.time_net_width", "model.time_net_out", "stage1.lambda_normal",
                       "stage1.p_from_motion", "stage1.p_motion_relative", "stage1.p_motion_floor",
                       "stage2.normal_offset", "stage2.env_quadrature", "stage2.iterations"}
    small = flat(load_method_config("small"))
    assert all(d[k] == small[k] for k in changed - {"stage2.iterations"})
    assert (c["stage2.iterations"], d["stage2.iterations"]) == (200, 100)


def test_run_cli_turns_user_error_into_exit_2(capsys):
    def main(argv):
        raise UserError("unknown light 'moon'")

    assert run_cli(main, []) == 2
    err = capsys.readouterr().err
    assert err.strip() == "error: unknown light 'moon'"


def test_parse_light_names_a_file_by_its_stem(tmp_path):
    from pathlib import Path

    from lumibench.layout import parse_light

    assert parse_light("city") == ("city", None)
    assert parse_light(tmp_path / "my_sky.hdr") == ("my_sky", tmp_path / "my_sky.hdr")
    assert parse_light("maps/Dusk.EXR") == ("Dusk", Path("maps/Dusk.EXR"))
    assert parse_light("~/sky.hdr") == ("sky", Path("~/sky.hdr").expanduser())
    with pytest.raises(UserError, match=r"light file /maps/sky\.png: unsupported format '\.png'"):
        parse_light("/maps/sky.png")
    with pytest.raises(UserError, match="rename the file"):
        parse_light("/maps/.hidden.hdr")


@pytest.mark.parametrize("entry", ["method", "benchmark"])
def test_entry_points_set_the_thread_environment_before_torch(entry):
    """`python -m method` / `python -m benchmark` set NUMBA_NUM_THREADS from OMP_NUM_THREADS, and
    OMP_WAIT_POLICY=PASSIVE where that is below the cores, before torch or Numba load (the grid's workers
    inherit them): with spinning waits, two one-thread grid workers on a 2-core box ran stage 1 ~7x slower,
    and Numba's idle pool thread took ~25 % of a one-thread worker's CPU. A process on every core keeps
    OpenMP's default wait (`make demo`'s stage 1 116 s -> 60 s). Values the user set are kept."""
    from lumibench.machine import usable_cores
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "NUMBA_NUM_THREADS", "OMP_NUM_THREADS")}
    code = (f"import os, sys; import {entry}.__main__; print(os.environ.get('OMP_WAIT_POLICY'), "
            "os.environ.get('NUMBA_NUM_THREADS'), 'torch' in sys.modules, 'numba' in sys.modules)")

    def run(**extra):
        out = subprocess.run([sys.executable, "-c", code], env={**env, **extra}, capture_output=True, text=True,
                             check=True)
        return out.stdout.split()

    below = "PASSIVE" if usable_cores() > 1 else "None"
    assert run() == ["None", "None", "False", "False"]
    assert run(OMP_NUM_THREADS="1") == [below, "1", "False", "False"]
    assert run(OMP_NUM_THREADS=str(usable_cores())) == ["None", str(usable_cores()), "False", "False"]
    assert run(OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="2", OMP_WAIT_POLICY="ACTIVE")[:2] == ["ACTIVE", "2"]


@pytest.mark.parametrize("entry", ["method", "benchmark"])
def test_entry_point_imported_after_numba_leaves_its_pool_alone(entry):
    """An entry point's ``main`` imported into a process whose Numba pool already runs (the test suite, a
    notebook) with OMP_NUM_THREADS=1 set: NUMBA_NUM_THREADS stays unset, so Numba's next compilation works
    (setting it then made every later compilation fail, as `OMP_NUM_THREADS=1 make test` did)."""
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS")}
    code = ("import os, numba, numpy as np\n"
            "@numba.njit(parallel=True)\ndef total(x):\n    s = 0.0\n"
            "    for i in numba.prange(x.size):\n        s += x[i]\n    return s\n"
            "total(np.ones(64))\n"  # the pool is launched here
            f"import {entry}.__main__\n"
            "@numba.njit\ndef one_more(x):\n    return x + 1\n"
            "print(one_more(1), os.environ.get('NUMBA_NUM_THREADS'))\n")
    out = subprocess.run([sys.executable, "-c", code], env={**env, "OMP_NUM_THREADS": "1"}, capture_output=True,
                         text=True)
    assert out.returncode == 0, out.stderr[-400:]
    assert out.stdout.split() == ["2", "None"]


def test_grid_workers_beside_each_other_wait_passively(monkeypatch):
    """Several local grid workers share the cores, so they start with OMP_WAIT_POLICY=PASSIVE (their idle
    OpenMP threads sleep); a single job runs in the calling process and leaves the environment alone; a
    policy the user set is kept."""
    from benchmark.jobgrid import _run_local

    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    assert [out for _, out in _run_local(os.getenv, ["OMP_WAIT_POLICY"], 1)] == [None]
    assert "OMP_WAIT_POLICY" not in os.environ
    outs = [out for _, out in _run_local(os.getenv, ["OMP_WAIT_POLICY"] * 2, 2)]
    assert outs == ["PASSIVE", "PASSIVE"]
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    assert [out for _, out in _run_local(os.getenv, ["OMP_WAIT_POLICY"] * 2, 2)] == ["ACTIVE", "ACTIVE"]
