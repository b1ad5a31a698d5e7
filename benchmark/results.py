"""Result files: one JSON per scored run and protocol, with a schema version, validated on every read.

A run (method, scene, configuration, seed) is scored once per protocol of its grid, from the same
predictions, into files side by side in its folder: ``results.json`` holds the ``lumimotion`` protocol
(the paper's conventions; every result published before both protocols were scored is one of these) and
``results_<protocol>.json`` any other (``results_strict.json``), see :func:`result_filename`.

A result is the only thing aggregation, tables, charts and the job grid's resume logic look at, so a
malformed file is refused with a message naming the file and the field rather than skewing a table.

    {"schema_version": 1, "status": "ok" | "failed", "error": null | "<cause>",
     "method", "adapter_version", "scene", "train_light", "test_light", "seed", "profile", "protocol",
     "metric_config": {"lpips_net", "lpips_input_range", "psnr_channels", "masking", "ssim",
                       "lpips_weights": {"file", "sha256", "package"}},
     "inputs": {"scene_dir", "pred_dir", "dataset_spec_hash", "dataset_json_sha256",
                "pred_meta_sha256" (the predictions' meta.json; absent in older results),
                "method_settings_sha256" (the settings the run was trained with, in-project methods; absent in
                older results)},
     "metrics": {"nvs": {psnr, ssim, lpips} | null, "albedo": {psnr, ssim, lpips, scale[3]} | null,
                 "roughness": {mse} | null, "relight": {psnr, ssim, lpips} | null,
                 "delta_psnr": {db, percent} | null, "separation": {iou, balanced_accuracy, dynamic_recall,
                 static_recall (the last two absent in older results)} | null,
                 "normal": {mae_deg} | null,
                 "nvs_moving": {foreground_psnr, moving_psnr, gap_db, moving_pixels} | null},
     "per_image": {"<task>": {"r_NNNN": {metric: value}}},
     "timings": {"<stage>": seconds} | null (wall clock),
     "cpu_timings": {"<stage>": CPU seconds, all threads} | null (absent in older results),
     "iterations_per_s", "peak_memory_bytes", "device",
     "model_size": {"gaussians", "parameters", "bytes"} | null, "created": ISO-8601 UTC,
     "diagnose" (optional, methods that run the relight diagnostic of method/diagnose.py):
         {"views": int, "dirs": int, "protocol": str, "steps": {"<step>": {"psnr", "lpips"}}}}
"""
from __future__ import annotations

import datetime as _dt
import math
from pathlib import Path
from typing import Any

from lumibench.errors import UserError
from lumibench.io import atomic_write_json, read_json

SCHEMA_VERSION = 1
STATUSES = ("ok", "failed")
TASK_METRICS = {
    "nvs": ("psnr", "ssim", "lpips"),
    "albedo": ("psnr", "ssim", "lpips"),
    "roughness": ("mse",),
    "relight": ("psnr", "ssim", "lpips"),
    "delta_psnr": ("db", "percent"),
    "separation": ("iou", "balanced_accuracy"),
    "normal": ("mae_deg",),
    "nvs_moving": ("foreground_psnr", "moving_psnr", "gap_db"),
}
_IDENTITY = (("method", str), ("adapter_version", str), ("scene", str), ("train_light", str),
             ("test_light", str), ("seed", int), ("protocol", str))


DEFAULT_PROTOCOL = "lumimotion"  # the protocol of the plain results.json name (and of an old grid without the key)


def result_filename(protocol: str = DEFAULT_PROTOCOL) -> str:
    """The file name of a run's result under ``protocol``: fixed per protocol, whatever a grid's order, so a
    folder never holds two protocols under one name and old published results.json files stay valid."""
    return "results.json" if protocol == DEFAULT_PROTOCOL else f"results_{protocol}.json"


def now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()


def failed_result(identity: dict[str, Any], cause: str) -> dict[str, Any]:
    """A result recording why a run failed: it is shown in tables and charts, never dropped."""
    res = {"schema_version": SCHEMA_VERSION, "status": "failed", "error": str(cause) or "unknown error"}
    res.update({key: identity.get(key) for key, _ in _IDENTITY})
    res["adapter_version"] = res["adapter_version"] or "unknown"
    res["profile"] = identity.get("profile")
    res["metrics"] = None
    res["created"] = now_iso()
    return res


def _fail(source: str, field: str, msg: str) -> UserError:
    return UserError(f"{source}: field '{field}' {msg}")


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def validate(obj: Any, source: str = "<result>") -> dict[str, Any]:
    """Return ``obj`` if it is a well-formed result; otherwise raise a UserError naming the field."""
    if not isinstance(obj, dict):
        raise UserError(f"{source}: a result file must hold a JSON object")
    if obj.get("schema_version") != SCHEMA_VERSION:
        raise _fail(source, "schema_version", f"must be {SCHEMA_VERSION}, got {obj.get('schema_version')!r}")
    status = obj.get("status")
    if status not in STATUSES:
        raise _fail(source, "status", f"must be one of {', '.join(STATUSES)}, got {status!r}")
    for key, typ in _IDENTITY:
        value = obj.get(key)
        if not isinstance(value, typ) or isinstance(value, bool):
            raise _fail(source, key, f"must be a {typ.__name__}, got {value!r}")
    if obj.get("profile") is not None and not isinstance(obj["profile"], str):
        raise _fail(source, "profile", "must be a string or null")
    if status == "failed":
        if not isinstance(obj.get("error"), str) or not obj["error"]:
            raise _fail(source, "error", "must state the cause of a failed run")
        return obj
    metrics = obj.get("metrics")
    if not isinstance(metrics, dict):
        raise _fail(source, "metrics", "must be an object in a result with status 'ok'")
    for task, value in metrics.items():
        if task not in TASK_METRICS:
            raise _fail(source, f"metrics.{task}", f"is not a known task (known: {', '.join(TASK_METRICS)})")
        if value is None:
            continue
        if not isinstance(value, dict):
            raise _fail(source, f"metrics.{task}", "must be an object or null")
        for name in TASK_METRICS[task]:
            if not _number(value.get(name)):
                raise _fail(source, f"metrics.{task}.{name}", f"must be a finite number, got {value.get(name)!r}")
    albedo = metrics.get("albedo")
    if albedo is not None:
        scale = albedo.get("scale")
        if not (isinstance(scale, list) and len(scale) == 3 and all(_number(s) for s in scale)):
            raise _fail(source, "metrics.albedo.scale", f"must be a list of 3 numbers, got {scale!r}")
    if not any(metrics.get(t) is not None for t in ("albedo", "relight", "nvs", "roughness")):
        raise _fail(source, "metrics", "has no scored task (nvs, albedo, roughness or relight)")
    mc = obj.get("metric_config")
    if not isinstance(mc, dict):
        raise _fail(source, "metric_config", "must be an object")
    weights = mc.get("lpips_weights")
    if not isinstance(weights, dict) or not isinstance(weights.get("sha256"), str):
        raise _fail(source, "metric_config.lpips_weights.sha256", "must record the LPIPS weights' sha256")
    if not isinstance(obj.get("per_image"), dict):
        raise _fail(source, "per_image", "must be an object of per-view values")
    for key in ("timings", "cpu_timings", "model_size"):
        value = obj.get(key)
        if value is not None and not (isinstance(value, dict) and all(_number(v) for v in value.values())):
            raise _fail(source, key, "must be null or an object of numbers")
    if obj.get("diagnose") is not None:
        _validate_diagnose(obj["diagnose"], source)
    return obj


def _validate_diagnose(diag: Any, source: str) -> None:
    """The optional relight-diagnostic block: per step a finite PSNR and LPIPS, and the views/dirs used."""
    if not isinstance(diag, dict):
        raise _fail(source, "diagnose", "must be null or an object")
    for key in ("views", "dirs"):
        if not isinstance(diag.get(key), int) or isinstance(diag.get(key), bool) or diag[key] < 1:
            raise _fail(source, f"diagnose.{key}", f"must be a positive integer, got {diag.get(key)!r}")
    steps = diag.get("steps")
    if not isinstance(steps, dict) or "ours" not in steps:
        raise _fail(source, "diagnose.steps", "must be an object of steps that includes 'ours'")
    for name, step in steps.items():
        for metric in ("psnr", "lpips"):
            if not isinstance(step, dict) or not _number(step.get(metric)):
                got = step.get(metric) if isinstance(step, dict) else step
                raise _fail(source, f"diagnose.steps.{name}.{metric}", f"must be a finite number, got {got!r}")


def write_result(path: str | Path, result: dict[str, Any]) -> None:
    """Validate, then write atomically: a result file on disk is always a valid one."""
    validate(result, str(path))
    atomic_write_json(path, result)


def read_result(path: str | Path) -> dict[str, Any]:
    return validate(read_json(path), str(path))


def is_finished(path: str | Path, protocol: str | None = None, lpips_net: str | None = None) -> bool:
    """A job is finished when its result file exists, validates and says 'ok' (failed ones are retried).

    With ``protocol`` / ``lpips_net`` given, a result scored otherwise is not finished (it is re-scored).
    """
    path = Path(path)
    if not path.is_file():
        return False
    try:
        res = read_result(path)
    except UserError:
        return False
    if res["status"] != "ok" or (protocol is not None and res["protocol"] != protocol):
        return False
    return lpips_net is None or res["metric_config"].get("lpips_net") == lpips_net
