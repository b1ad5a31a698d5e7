"""The training loop shared by both stages (method/train.py) and the run record (method/run_record.py):
stage-2 resume equal to an uninterrupted run, and runs that cannot be mixed up silently (another scene,
light or seed; two processes in one directory; a resume with other settings; bad iteration counts)."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from lumibench.errors import UserError

TINY = ["stage1.iterations=12", "stage1.init_points=300", "stage1.max_gaussians=0", "stage1.warmup=4",
        "stage1.densify_from=100", "stage1.eval_every=0", "stage1.checkpoint_every=6",
        "stage2.iterations=8", "stage2.checkpoint_every=4", "stage2.log_every=2", "stage2.dirs_train=8",
        "stage2.dirs_eval=8", "stage2.rays_per_iteration=512"]


def _cfg(extra=()):
    from method.config import load_method_config

    return load_method_config("ci", TINY + list(extra))


@pytest.fixture(scope="module")
def stage1_run(ci_dataset, tmp_path_factory):
    from method.train import train_stage1

    torch.set_num_threads(1)
    run = tmp_path_factory.mktemp("loop") / "run"
    train_stage1(ci_dataset, "city", run, _cfg(), seed=0, progress=False, write_outputs=False)
    return run


def _copy(src, dst):
    shutil.copytree(src, dst)
    (dst / ".lock").unlink(missing_ok=True)
    return dst


def test_stage2_resume_equals_an_uninterrupted_run(ci_dataset, stage1_run, tmp_path):
    """Killed after its iteration-4 checkpoint and resumed, stage 2 ends with the same tensors as a run that
    was not interrupted: the generator, the optimiser and the tracer grids (built from the opacities stage 2
    started with, not from those of the iteration a frame is first drawn at) all come back the same."""
    from method.checkpoints import checkpoint_paths, load_checkpoint
    from method.train import train_stage2

    torch.set_num_threads(1)
    full = _copy(stage1_run, tmp_path / "full")
    train_stage2(ci_dataset, "city", full, _cfg(), seed=0, progress=False)
    assert [i for i, _ in checkpoint_paths(full, 2)] == [4, 8]
    part = _copy(full, tmp_path / "part")
    (part / "checkpoints" / "stage2_000008.pt").unlink()
    (part / "metrics_stage2.json").unlink()
    train_stage2(ci_dataset, "city", part, _cfg(), seed=0, resume=True, progress=False)
    a = load_checkpoint(full / "checkpoints" / "stage2_000008.pt", "cpu")
    b = load_checkpoint(part / "checkpoints" / "stage2_000008.pt", "cpu")
    four = load_checkpoint(part / "checkpoints" / "stage2_000004.pt", "cpu")
    assert not torch.equal(four["materials"]["albedo_logit"], a["materials"]["albedo_logit"])  # it trained on
    for k in ("albedo_logit", "roughness_logit"):
        assert torch.equal(a["materials"][k], b["materials"][k]), k
    assert torch.equal(a["materials"]["env"]["log_radiance"], b["materials"]["env"]["log_radiance"])
    for k in ("colour_logit", "opacity_logit"):
        assert torch.equal(a["gaussians"][k], b["gaussians"][k]), k
    # the resumed log holds each iteration once, in order
    its = [json.loads(x)["iteration"] for x in (part / "log_stage2.jsonl").read_text().splitlines()]
    assert its == sorted(set(its)) and its[-1] == 8
    # the CPU seconds are the stage's over both sessions (the fit and iterations 1-4 came from the checkpoint)
    t = json.loads((part / "timings.json").read_text())["stage2"]
    assert four["cpu_seconds"] > 0 and t["cpu_seconds"] == pytest.approx(four["cpu_seconds"]
                                                                        + t["cpu_seconds_this_session"], abs=0.05)


def test_stage_cpu_seconds_of_runs_from_before_the_total_was_kept():
    from method.predictions import stage_cpu_seconds

    assert stage_cpu_seconds({"cpu_seconds": 5.0, "cpu_seconds_this_session": 1.0}) == 5.0
    one = {"iterations": 10, "breakdown_iterations": 10, "cpu_seconds_this_session": 7.0}
    assert stage_cpu_seconds(one) == 7.0
    assert stage_cpu_seconds({**one, "env_fit_seconds": 2.0}) == 9.0  # stage 2 counted its fit before the clock
    assert stage_cpu_seconds({**one, "breakdown_iterations": 6}) is None  # resumed: the first session is lost
    assert stage_cpu_seconds({"iterations": 10}) is None


def test_stage2_refuses_a_run_of_another_scene_light_or_seed(ci_dataset, stage1_run, tmp_path):
    from method.train import train_stage2

    run = _copy(stage1_run, tmp_path / "run")
    with pytest.raises(UserError, match=r"seed 0.*seed 5"):
        train_stage2(ci_dataset, "city", run, _cfg(), seed=5, progress=False)
    with pytest.raises(UserError, match=r"light city.*light sunrise"):
        train_stage2(ci_dataset, "sunrise", run, _cfg(), seed=0, progress=False)
    static = ci_dataset.parent / f"{ci_dataset.name}_statictimestep0000"
    with pytest.raises(UserError, match=f"scene_name {static.name}"):
        train_stage2(static, "city", run, _cfg(), seed=0, progress=False)
    assert not (run / "log_stage2.jsonl").exists()  # nothing was trained


def test_predictions_refuse_a_run_of_another_seed(ci_dataset, stage1_run, tmp_path):
    from method.predictions import write_predictions

    run = _copy(stage1_run, tmp_path / "run")
    with pytest.raises(UserError, match="seed 3"):
        write_predictions(run, ci_dataset, "city", _cfg(), seed=3, albedo_from_colour=True)


def test_resume_with_other_settings_is_refused_and_the_record_kept(ci_dataset, stage1_run, tmp_path):
    from method.train import train_stage1

    run = _copy(stage1_run, tmp_path / "run")
    before = (run / "config.yaml").read_text()
    with pytest.raises(UserError, match=r"stage1.iterations=12 \(this command: 20\)"):
        train_stage1(ci_dataset, "city", run, _cfg(["stage1.iterations=20"]), seed=0, resume=True, progress=False)
    assert (run / "config.yaml").read_text() == before
    # the same settings resume (here: a finished run, nothing left to train) and keep the record as it was
    train_stage1(ci_dataset, "city", run, _cfg(), seed=0, resume=True, progress=False, write_outputs=False)
    assert (run / "config.yaml").read_text() == before


def test_a_second_training_in_the_same_directory_is_refused(ci_dataset, stage1_run, tmp_path):
    """While one process holds the run's lock, another is refused naming it; the lock dies with its holder."""
    from method.run_record import RunLock
    from method.train import train_stage2

    run = _copy(stage1_run, tmp_path / "run")
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from pathlib import Path; from method.run_record import RunLock\n"
        f"with RunLock(Path({str(run)!r})):\n    print('held', flush=True); time.sleep(60)")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(UserError, match=f"in use by process {holder.pid}"):
            train_stage2(ci_dataset, "city", run, _cfg(), seed=0, progress=False)
    finally:
        holder.kill()
        holder.wait()
    with RunLock(run):  # released by the kernel when the holder died
        pass


def test_run_dir_that_is_a_file_or_unwritable(ci_dataset, tmp_path):
    from method.train import train_stage1

    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(UserError, match="is a file"):
        train_stage1(ci_dataset, "city", f, _cfg(), progress=False)
    with pytest.raises(UserError, match="cannot write into the run directory"):
        train_stage1(ci_dataset, "city", f / "run", _cfg(), progress=False)


@pytest.mark.parametrize("key", ["stage1.iterations", "stage2.iterations"])
def test_negative_iterations_are_refused(key):
    from method.config import load_method_config

    with pytest.raises(UserError, match=f"'{key}' must be >= 0"):
        load_method_config("ci", [f"{key}=-5"])
    zero = load_method_config("ci", [f"{key}=0"])  # 0: the profile's number
    assert zero[key.split(".")[0]]["iterations"] > 0


def test_static_flag_on_a_dynamic_scene_names_the_static_variant(ci_dataset, tmp_path, capsys):
    from method.__main__ import main

    rc = main(["train", "--scene", str(ci_dataset), "--static", "--run-dir", str(tmp_path / "r"), "--no-progress"])
    assert rc != 0
    err = capsys.readouterr().err
    assert f"{ci_dataset.name}_statictimestep0000" in err and "Traceback" not in err


def test_budget_variants_scale_every_schedule_point():
    """Every setting that is a point in a stage's schedule is in ITERATION_KEYS, and an @0.5 variant halves
    each (nonzero) one of them."""
    from baselines_adapters.lumimotion import LumiMotionAdapter
    from method.config import ITERATION_KEYS, load_method_config, parse_overrides

    cfg = load_method_config("small")
    for stage in ("stage1", "stage2"):
        named = {k for k in cfg[stage] if k in ("iterations", "warmup") or k.endswith(("_from", "_until"))}
        assert named == set(ITERATION_KEYS[stage]), stage
    half = parse_overrides(LumiMotionAdapter("lumimotion", "0.5").overrides("small"))
    for stage, keys in ITERATION_KEYS.items():
        for key in keys:
            if cfg[stage][key] > 0:
                assert half[stage][key] == max(1, round(cfg[stage][key] * 0.5)), (stage, key)


def test_cli_stage2_with_resume_starts_stage2_and_refuses_other_settings(ci_dataset, stage1_run, tmp_path, capsys):
    """`train --stage 2 --resume` on a run whose stage 1 is done starts stage 2; the same with a stage-1
    setting other than the run's is one line naming it, not a traceback."""
    from method.__main__ import main

    run = _copy(stage1_run, tmp_path / "run")
    base = ["train", "--scene", str(ci_dataset), "--run-dir", str(run), "--no-progress", "--stage", "2", "--resume"]
    assert main(base + TINY + ["stage1.lr_p=0.5"]) != 0
    err = capsys.readouterr().err
    assert "stage1.lr_p" in err and "Traceback" not in err
    assert main(base + TINY) == 0
    assert (run / "metrics_stage2.json").is_file() and (run / "predictions" / "meta.json").is_file()


def test_settings_hash_follows_the_training_settings_only(tmp_path):
    """Equal for runs of one setting on another scene, seed or machine, or with other bookkeeping periods;
    different when a trained setting differs; None without a record."""
    from method.config import load_method_config
    from method.run_record import identity, settings_hash, write_record

    cfg = load_method_config("ci", [])
    runs = {}
    for name, overrides, ident in (
            ("base", [], ("a", "city", 0, "cpu")),
            ("other_run", ["stage1.checkpoint_every=7", "stage1.log_every=3"], ("b", "sunrise", 2, "cuda")),
            ("other_setting", ["stage1.lambda_normal=0.5"], ("a", "city", 0, "cpu"))):
        c = load_method_config("ci", overrides)
        write_record(tmp_path / name, c, identity(tmp_path / ident[0], ident[1], ident[2], ident[3], False))
        runs[name] = settings_hash(tmp_path / name)
    assert runs["base"] == runs["other_run"] and len(runs["base"]) == 64
    assert runs["other_setting"] != runs["base"]
    # a record from before a setting existed (the key absent) equals one with the profile's value of it,
    # and not one with another value
    import yaml

    for name, value in (("older", None), ("other_value", 0.5)):
        rec = yaml.safe_load((tmp_path / "base" / "config.yaml").read_text())
        if value is None:
            del rec["data"]["train_frames"]
        else:
            rec["data"]["train_frames"] = value
        (tmp_path / name).mkdir()
        (tmp_path / name / "config.yaml").write_text(yaml.safe_dump(rec))
    assert settings_hash(tmp_path / "older") == runs["base"] != settings_hash(tmp_path / "other_value")
    assert settings_hash(tmp_path / "none") is None
    assert cfg["stage1"]["lambda_normal"] != 0.5


def test_a_record_from_before_mlp_precision_means_fp32_whatever_the_profile_says_now(tmp_path):
    """Runs recorded before mlp_precision existed were fp32: their hash stays the fp32 one whatever a profile
    says later, a resume in bf16 is refused naming the key, and a static run's hash ignores the model section
    (it has no network)."""
    import yaml

    from method.config import load_method_config
    from method.run_record import check_settings, identity, settings_hash, write_record

    small = load_method_config("small", ["model.mlp_precision=bf16"])
    for static in (False, True):
        for name, prec in (("fp32", "fp32"), ("bf16", "bf16"), ("older", None)):
            run = tmp_path / f"{name}_{static}"
            c = load_method_config("small", [f"model.mlp_precision={prec or 'fp32'}"])
            write_record(run, c, identity(tmp_path / "s", "city", 0, "cpu", static))
            if prec is None:
                rec = yaml.safe_load((run / "config.yaml").read_text())
                del rec["model"]["mlp_precision"]
                (run / "config.yaml").write_text(yaml.safe_dump(rec, sort_keys=False))
        h = {n: settings_hash(tmp_path / f"{n}_{static}") for n in ("fp32", "bf16", "older")}
        assert h["older"] == h["fp32"]
        assert (h["bf16"] == h["fp32"]) == static  # the precision of a network a static run does not have
    with pytest.raises(UserError, match=r"model.mlp_precision='fp32' \(this command: 'bf16'\)"):
        check_settings(tmp_path / "older_False", small, 1, "resuming stage 1")
    check_settings(tmp_path / "older_True", small, 1, "resuming stage 1")  # static: no network, nothing differs


def test_native_bf16_is_read_from_the_cpu_flags(tmp_path):
    from method.devices import cpu_has_native_bf16

    for flags, want in (("fpu avx512f avx512_bf16 sse", True), ("fpu amx_bf16 amx_tile", True),
                        ("fpu avx2 avx512f avx512bw", False)):
        (tmp_path / "cpuinfo").write_text(f"processor\t: 0\nflags\t\t: {flags}\n")
        assert cpu_has_native_bf16(str(tmp_path / "cpuinfo")) is want
    assert cpu_has_native_bf16(str(tmp_path / "absent")) is None


def test_a_published_records_hash_stays_what_its_results_store(tmp_path):
    """The record of a published `small` run (results/small: LumiMotion, spheres, city, seed 0, session 18)
    hashes to the value its results store. A setting added since must keep it: list the key in
    run_record.PREDATING with the behaviour runs had before it existed, or every stored result reads as
    another setting than the runs trained after it."""
    from method.run_record import settings_hash

    shutil.copyfile(Path(__file__).parent / "fixtures" / "record_small_lumimotion_s18.yaml", tmp_path / "config.yaml")
    assert settings_hash(tmp_path) == "658e03fc9adca8b67c3596c91a6be671d5800540fc59a90511010c67e3b16c65"


def test_a_static_run_neither_hashes_nor_compares_the_p_split_settings(tmp_path):
    """The static pipeline has no network and no P split: a static run recorded before the P floor existed
    hashes like one recorded with it and resumes under it, while a dynamic run is set apart and refused."""
    import yaml

    from method.config import load_method_config
    from method.run_record import DYNAMIC_ONLY, check_settings, identity, settings_hash, write_record

    now = load_method_config("small", [])
    assert now["stage1"]["p_motion_floor"] > 0 and now["stage1"]["lr_mlp"] != 8.0e-4
    for static in (False, True):
        for name, edit in (("now", None), ("older", "p_motion_floor"), ("other_lr", "lr_mlp")):
            run = tmp_path / f"{name}_{static}"
            write_record(run, now, identity(tmp_path / "s", "city", 0, "cpu", static))
            if edit:
                rec = yaml.safe_load((run / "config.yaml").read_text())
                if edit == "p_motion_floor":
                    del rec["stage1"]["p_motion_floor"]  # recorded before the floor: 0 (run_record.PREDATING)
                else:
                    rec["stage1"]["lr_mlp"] = 8.0e-4
                (run / "config.yaml").write_text(yaml.safe_dump(rec, sort_keys=False))
        h = {n: settings_hash(tmp_path / f"{n}_{static}") for n in ("now", "older", "other_lr")}
        assert (h["older"] == h["now"] == h["other_lr"]) == static
        if static:
            check_settings(tmp_path / "older_True", now, 1, "resuming stage 1")
            check_settings(tmp_path / "other_lr_True", now, 2, "stage 2")
        else:
            with pytest.raises(UserError, match=r"stage1.p_motion_floor=0.0 \(this command: 0.1\)"):
                check_settings(tmp_path / "older_False", now, 1, "resuming stage 1")
            with pytest.raises(UserError, match=r"stage1.lr_mlp"):
                check_settings(tmp_path / "other_lr_False", now, 2, "stage 2")
    # a setting the static pipeline reads is still compared
    run = tmp_path / "opacity_True"
    write_record(run, load_method_config("small", ["stage1.lr_opacity=0.5"]), identity(tmp_path / "s", "city", 0, "cpu", True))
    assert settings_hash(run) != settings_hash(tmp_path / "now_True")
    assert "stage1.lr_opacity" not in DYNAMIC_ONLY


def test_a_run_without_the_split_neither_hashes_nor_compares_the_split_settings(tmp_path):
    """wo_P (``model.separation`` false: P = 1 for every Gaussian) reads none of the split's settings: its
    record with another P logit or L_P weight hashes like today's and takes stage 2 under today's, while a run
    with the split is set apart and refused; a setting wo_P does read is still compared."""
    import yaml

    from method.config import load_method_config
    from method.run_record import SPLIT_ONLY, check_settings, identity, settings_hash, write_record

    for separation in (True, False):
        # without the split, small's motion bases go too (wo_P's overrides: nothing to fit them to)
        now = load_method_config("small", [f"model.separation={str(separation).lower()}"]
                                 + ([] if separation else ["model.motion_bases=0"]))
        for name, edit in (("now", None), ("logit", ("stage1", "p_from_motion_logit", 9.0)),
                           ("lp", ("stage1", "lambda_p", 0.5)), ("temp", ("model", "p_temperature", 2.0))):
            run = tmp_path / f"{name}_{separation}"
            write_record(run, now, identity(tmp_path / "s", "city", 0, "cpu", False))
            if edit:
                rec = yaml.safe_load((run / "config.yaml").read_text())
                assert rec[edit[0]][edit[1]] != edit[2]
                rec[edit[0]][edit[1]] = edit[2]
                (run / "config.yaml").write_text(yaml.safe_dump(rec, sort_keys=False))
        h = {n: settings_hash(tmp_path / f"{n}_{separation}") for n in ("now", "logit", "lp", "temp")}
        assert (h["now"] == h["logit"] == h["lp"] == h["temp"]) == (not separation)
        for name, key in (("logit", "stage1.p_from_motion_logit"), ("lp", "stage1.lambda_p"),
                          ("temp", "model.p_temperature")):
            if separation:
                with pytest.raises(UserError, match=key):
                    check_settings(tmp_path / f"{name}_True", now, 2, "stage 2")
            else:
                check_settings(tmp_path / f"{name}_False", now, 2, "stage 2")
    wo_p = load_method_config("small", ["model.separation=false", "model.motion_bases=0"])
    run = tmp_path / "opacity_False"
    write_record(run, load_method_config("small", ["model.separation=false", "model.motion_bases=0", "stage1.lr_opacity=0.5"]),
                 identity(tmp_path / "s", "city", 0, "cpu", False))
    assert settings_hash(run) != settings_hash(tmp_path / "now_False")
    with pytest.raises(UserError, match="stage1.lr_opacity"):
        check_settings(run, wo_p, 1, "resuming stage 1")
    assert "stage1.lr_opacity" not in SPLIT_ONLY


def test_step_bench_replays_the_trainings_own_steps(stage1_run):
    """method.step_bench runs the loop's step from a checkpoint with the run's recorded settings, data and
    generator state: its last step's loss is the training's logged loss at that iteration, bit for bit."""
    from method.step_bench import bench_steps

    logged = {r["iteration"]: r["loss"] for r in map(json.loads, (stage1_run / "log_stage1.jsonl").read_text().splitlines())
              if "loss" in r}
    res = bench_steps(stage1_run, iteration=6, steps=6, warm=0)
    assert res["iteration"] == 6 and set(res["parts_ms"]) >= {"deform", "rasterize", "loss", "backward", "step"}
    assert res["last_loss"] == logged[12]
    assert not (stage1_run / "failure.json").exists()


def test_step_bench_names_what_is_missing(stage1_run, capsys):
    from method.step_bench import main

    assert main([str(stage1_run), "--iteration", "5"]) == 2
    assert "no stage-1 checkpoint at iteration 5 (there are: 6, 12)" in capsys.readouterr().err
    assert main([str(stage1_run), "--iteration", "6", "--steps", "20"]) == 2
    assert "pass the run's 12" in capsys.readouterr().err


def test_nan_guard_names_the_first_non_finite_value_and_passes_large_finite_ones(tmp_path):
    """One stacked test for all values, the search only on failure: the first non-finite one is named (in
    the order given, as the one-by-one guard did), values whose float32 sums overflow but that are all
    finite pass, and +inf in one value with -inf in another is caught (their sums cancel to NaN)."""
    from method.train import TrainingDiverged, finite_or_raise

    big = torch.full((4,), 3e38)  # finite; its float32 sum is inf
    finite_or_raise(tmp_path, 1, 7, [("a", torch.tensor(1.0)), ("big", big), ("c", torch.zeros(3))])
    finite_or_raise(tmp_path, 1, 7, [])
    assert not (tmp_path / "failure.json").exists()
    cases = [([("a", torch.tensor(1.0)), ("b", torch.tensor([1.0, float("nan")])), ("c", torch.tensor(float("inf")))], "b"),
             ([("a", torch.tensor([float("inf")])), ("b", torch.tensor([-float("inf")]))], "a"),
             ([("a", torch.ones(2)), ("b", big), ("c", torch.tensor([-float("inf"), 0.0]))], "c")]
    for checks, name in cases:
        with pytest.raises(TrainingDiverged, match=f"non-finite {name} at iteration 7"):
            finite_or_raise(tmp_path, 1, 7, checks)
        assert json.loads((tmp_path / "failure.json").read_text())["term"] == name
