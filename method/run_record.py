"""A run directory's record of itself: who it is (scene, light, seed), the configuration it trains with
(config.yaml), a lock held while a process trains in it, and JSON files merged atomically.

These are what make a run impossible to mix up silently: stage 2 or a resume on a run of another scene,
light or seed is refused naming both; a resume with settings that differ from the record is refused
naming the keys (the record is never rewritten by a resume); two trainings in one directory at once are
refused naming the other process.
"""
from __future__ import annotations

import fcntl
import hashlib
import json
import os
import socket
import time
from pathlib import Path

import yaml

from lumibench.errors import UserError
from lumibench.io import atomic_write_json, atomic_write_text
from method.config import load_method_config

IDENTITY_KEYS = ("scene_name", "light", "seed")
# configuration sections that define a stage's run (a resume or the next stage must agree with the record)
SECTIONS = {1: ("profile", "model", "data", "stage1"), 2: ("profile", "model", "data", "stage1", "stage2")}
# settings added after runs were recorded, with the behaviour every run before them had: a record without the
# key means this, whatever the profile says today, and a run at this value hashes as if the key did not exist
# (so results stored before it keep their settings hash; tests/test_training_loop.py holds one to it). Add
# every new key here.
PREDATING = {"model.mlp_precision": "fp32",  # session 19
             "stage1.p_motion_floor": 0.0,  # session 20
             "stage2.env_fit_colour": False,  # session 27
             "model.deform_nodes": 0,  # session 28
             "stage2.normal_filter": 0.0,  # session 38
             "model.motion_bases": 0,  # session 45
             "stage2.relight_indirect": False,  # session 48
             "stage1.depth_ratio": 0.0,  # session 58
             "stage2.env_fit_regions": 1}  # session 59
# settings that decide only how a trained run is shaded at test time (its predictions, relighting, the
# diagnostic), not what its stages train: a resume or the next stage does not compare them, and writing the
# predictions records the value they were written with (record_prediction_settings), so the run's settings
# hash tells predictions shaded one way from the other
TEST_TIME = ("stage2.normal_filter", "stage2.relight_indirect")
# stage-1 settings only the deformation network and the P split read (method/stage1.py: the split runs only
# when the scene is not static, the network's optimiser and the dynamic loss terms only when it has one): a
# static run neither compares nor hashes them, so a change to the split does not set its static runs apart
DYNAMIC_ONLY = ("stage1.p_from_motion", "stage1.p_from_motion_logit", "stage1.p_motion_relative",
                "stage1.p_motion_floor", "stage1.lr_mlp", "stage1.lr_mlp_final", "stage1.lr_p", "stage1.lambda_p",
                "stage1.lambda_dc", "stage1.lambda_dmu")
# settings only the motion bases read (method/model/motion_basis.py): a run without them (`model.motion_bases` 0)
# neither compares nor hashes them, so the runs recorded before they existed keep their hash
BASES_ONLY = ("model.motion_knots", "stage1.lr_basis_logit", "stage1.lr_basis_translation",
              "stage1.lr_basis_rotation", "stage1.basis_sharpness")
# settings only the P split reads (P = 1 for every Gaussian without it, method/model/scene.py): a run with
# `model.separation` false (the wo_P ablation) neither compares nor hashes them, so a change to the split does
# not set its wo_P runs apart either
SPLIT_ONLY = ("model.p_temperature", "model.p_init_logit", "stage1.p_from_motion", "stage1.p_from_motion_logit",
              "stage1.p_motion_relative", "stage1.p_motion_floor", "stage1.lr_p", "stage1.lambda_p")


def identity(scene_dir: Path, light: str, seed: int, device, static: bool, train_views: list[str] | None = None) -> dict:
    """Who the run is; ``train_views``: the stems of the training views it trains on, when not all of them
    (``data.train_frames`` < 1; recorded, not compared: the setting itself is compared)."""
    out = {"scene": str(Path(scene_dir).resolve()), "scene_name": Path(scene_dir).name, "light": light,
           "seed": int(seed), "device": str(device), "static": bool(static)}
    if train_views is not None:
        out["train_views"] = list(train_views)
    return out


def read_record(run_dir: Path) -> dict | None:
    """config.yaml of a run, or None when there is none (a run directory put together by hand)."""
    path = Path(run_dir) / "config.yaml"
    if not path.is_file():
        return None
    try:
        rec = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise UserError(f"{path}: malformed YAML ({exc.__class__.__name__}); it is the run's record: restore it "
                        f"or start a new run directory") from None
    return rec if isinstance(rec, dict) else None


def check_identity(run_dir: Path, ident: dict, what: str) -> None:
    """Refuse ``what`` (e.g. "stage 2") when the run's record names another scene, light or seed."""
    rec = read_record(run_dir)
    have = (rec or {}).get("run")
    if not isinstance(have, dict):
        return
    diff = [k for k in IDENTITY_KEYS if k in have and str(have[k]) != str(ident[k])]
    if diff:
        def show(d):
            return ", ".join(f"{k} {d.get(k)}" for k in IDENTITY_KEYS)
        raise UserError(f"{what}: {run_dir} is a run of {show(have)}, but this command asks for {show(ident)} "
                        f"(pass the run's own --scene/--light/--seed, or another --run-dir)")


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, dict):
            out.update(_flat(v, key))
        else:
            out[key] = v
    return out


def _is_static(rec: dict) -> bool:
    """Whether a record is of the static pipeline's run (no deformation network)."""
    return isinstance(rec.get("run"), dict) and rec["run"].get("static") is True


def _ignored(rec: dict) -> set[str]:
    """The settings that decide nothing in the run ``rec`` records: the network's and the split's in a static
    run (its model section is left out whole), the split's in a run without the split, the motion bases' in
    a run without them."""
    model = rec.get("model")
    bases = set() if isinstance(model, dict) and model.get("motion_bases") else set(BASES_ONLY)
    if _is_static(rec):
        return set(DYNAMIC_ONLY) | bases
    if isinstance(model, dict) and model.get("separation") is False:
        return set(SPLIT_ONLY) | bases
    return bases


def check_settings(run_dir: Path, cfg: dict, stage: int, what: str) -> None:
    """Refuse ``what`` when a setting of the stage's sections differs from the run's record (keys that
    only one side knows are not compared: a record from an older version of the settings file)."""
    rec = read_record(run_dir)
    if not rec:
        return
    diffs = []
    static, ignored = _is_static(rec), _ignored(rec)
    for sec in SECTIONS[stage]:
        if sec not in rec or sec not in cfg or (static and sec == "model"):  # a static run has no network
            continue
        a = _flat(rec[sec], sec) if isinstance(rec[sec], dict) else {sec: rec[sec]}
        a = {**{k: v for k, v in PREDATING.items() if k.startswith(f"{sec}.")}, **a}
        b = _flat(cfg[sec], sec) if isinstance(cfg[sec], dict) else {sec: cfg[sec]}
        diffs += [f"{k}={a[k]!r} (this command: {b[k]!r})" for k in sorted(a.keys() & b.keys())
                  if a[k] != b[k] and k not in ignored and k not in TEST_TIME]
    if diffs:
        more = f" and {len(diffs) - 3} more" if len(diffs) > 3 else ""
        raise UserError(f"{what}: {run_dir} was trained with {'; '.join(diffs[:3])}{more}: pass the run's own "
                        f"profile and overrides, or start another --run-dir")


# bookkeeping keys: how often a run logs, evaluates or checkpoints does not change what it trains
BOOKKEEPING_KEYS = ("checkpoint_every", "log_every", "eval_every")


def recorded_settings(rec: dict, stage: int = 2) -> dict:
    """The settings of a run's record (or of a resolved configuration) that decide what its stages up to
    ``stage`` train, flat (``stage1.lr_opacity``), bookkeeping keys left out. A key added to the settings
    file after the run was recorded counts at its :data:`PREDATING` value, else at its profile's value (a
    new setting's default keeps the old behaviour), so adding one does not set old runs apart. A static run
    (``run.static``) has no deformation network and no P split: the model section and the stage-1 keys of
    :data:`DYNAMIC_ONLY` decide nothing there and are left out; a run without the split (``model.separation``
    false), the keys of :data:`SPLIT_ONLY`."""
    known: dict = {}
    try:
        known = load_method_config(str(rec.get("profile")), [])
    except (UserError, OSError):
        pass  # a profile this version does not know: the record alone
    flat = {}
    for sec in SECTIONS[stage]:
        if sec not in rec:
            continue
        if isinstance(rec[sec], dict):
            flat.update(_flat(known.get(sec) or {}, sec))
            flat.update({k: v for k, v in PREDATING.items() if k.startswith(f"{sec}.")})
            flat.update(_flat(rec[sec], sec))
        else:
            flat[sec] = rec[sec]
    static, ignored = _is_static(rec), _ignored(rec)
    return {k: v for k, v in flat.items()
            if k.rsplit(".", 1)[-1] not in BOOKKEEPING_KEYS
            and not (static and k.startswith("model.")) and k not in ignored}


def settings_hash(run_dir: Path) -> str | None:
    """sha256 of the settings a run was trained with (:func:`recorded_settings` of both stages as canonical
    JSON): the same for every run of one setting, whatever its scene, light, seed or machine, so a table can
    tell when its rows mix settings. None with no record."""
    rec = read_record(run_dir)
    if not rec:
        return None
    # a setting at the value runs had before it existed is left out, so their hashes (stored in results)
    # stay what they were
    kept = {k: v for k, v in recorded_settings(rec, 2).items() if not (k in PREDATING and v == PREDATING[k])}
    return hashlib.sha256(json.dumps(kept, sort_keys=True).encode()).hexdigest()


def write_record(run_dir: Path, cfg: dict, ident: dict) -> None:
    atomic_write_text(Path(run_dir) / "config.yaml", yaml.safe_dump({**cfg, "run": ident}, sort_keys=False))


def record_stage2(run_dir: Path, cfg: dict) -> None:
    """Put the stage-2 settings into config.yaml when stage 2 starts (stage 1's sections stay as trained)."""
    rec = read_record(run_dir)
    if rec is None:
        return
    rec["stage2"] = dict(cfg["stage2"])
    atomic_write_text(Path(run_dir) / "config.yaml", yaml.safe_dump(rec, sort_keys=False))


def record_prediction_settings(run_dir: Path, cfg: dict) -> None:
    """Put the :data:`TEST_TIME` settings of ``cfg`` that the run's predictions are being written with into
    config.yaml (the training sections stay as trained), so its settings hash says how they were shaded."""
    rec = read_record(run_dir)
    if rec is None:
        return
    changed = False
    for key in TEST_TIME:
        sec, name = key.split(".", 1)
        if sec not in cfg or name not in cfg[sec]:
            continue
        part = rec.setdefault(sec, {})
        if not isinstance(part, dict):
            continue
        if part.get(name) != cfg[sec][name]:  # also when the record predates the key
            part[name] = cfg[sec][name]
            changed = True
    if changed:
        atomic_write_text(Path(run_dir) / "config.yaml", yaml.safe_dump(rec, sort_keys=False))


class RunLock:
    """An exclusive lock on a run directory for as long as a process trains in it (``RUN/.lock``, flock: the
    kernel drops it when the process dies, so a killed run never leaves a stale lock)."""

    def __init__(self, run_dir: Path):
        self.path = Path(run_dir) / ".lock"
        self.fd: int | None = None

    def __enter__(self) -> "RunLock":
        run_dir = self.path.parent
        if run_dir.exists() and not run_dir.is_dir():
            raise UserError(f"run directory {run_dir} is a file: choose a directory (--run-dir) or remove the file")
        try:
            run_dir.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise UserError(f"cannot write into the run directory {run_dir} ({exc.strerror}): choose a writable "
                            f"--runs or --run-dir") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                who = os.read(fd, 512).decode(errors="replace").strip() or "another process"
            finally:
                os.close(fd)
            raise UserError(f"{self.path.parent} is in use by {who}: wait for it to finish (or stop it), "
                            f"or train into another --run-dir") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"process {os.getpid()} on {socket.gethostname()} since "
                     f"{time.strftime('%Y-%m-%d %H:%M:%S')}\n".encode())
        self.fd = fd
        return self

    def __exit__(self, *exc) -> None:
        if self.fd is not None:
            os.ftruncate(self.fd, 0)
            fcntl.flock(self.fd, fcntl.LOCK_UN)
            os.close(self.fd)
            self.fd = None


def merge_json(path: Path, new: dict) -> None:
    """Update a JSON object file with ``new``'s keys (atomically; an unreadable file starts empty)."""
    old = {}
    if path.is_file():
        try:
            old = json.loads(path.read_text())
        except json.JSONDecodeError:
            old = {}
    old.update(new)
    atomic_write_json(path, old)


def truncate_log(path: Path, iteration: int) -> None:
    """Drop the log lines after ``iteration`` (a resumed run trains them again and writes them anew)."""
    if not path.is_file():
        return
    keep = []
    for line in path.read_text().splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue  # a line cut short by the kill
        if int(rec.get("iteration", 0)) <= iteration:
            keep.append(line)
    atomic_write_text(path, "".join(x + "\n" for x in keep))
