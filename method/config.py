"""LumiMotion configuration: `configs/method/lumimotion.yaml` defaults + a profile section + overrides.

Every key that a profile or a ``key=value`` override sets must exist in ``defaults`` and keep its type
(an int may stand for a float); anything else is a one-line error naming the key, so a typo never
silently trains with the default.
"""
from __future__ import annotations

import copy
import re
from pathlib import Path
from typing import Any, Iterable

import yaml

from lumibench.config import load_yaml
from lumibench.errors import UserError
from lumibench.profiles import CONFIG_DIR, load_profile
from method.model.deform import PRECISIONS

METHOD_CONFIG = CONFIG_DIR / "method" / "lumimotion.yaml"

# the settings that are points in a stage's schedule (an iteration count or an iteration number): a
# budget variant (baselines_adapters/lumimotion.py, "@0.5") scales every one of them with the iterations,
# so a shorter run keeps the same shape; periods (checkpoint_every, densify_every, ...) are not scaled
ITERATION_KEYS = {
    "stage1": ("iterations", "warmup", "normal_from", "distortion_from", "densify_from", "densify_until",
               "c2f_until", "time_window_until"),
    "stage2": ("iterations",),
}


def _check_value(key: str, default: Any, value: Any, source: str) -> Any:
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise UserError(f"{source}: key '{key}' must be true or false, got {value!r}")
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise UserError(f"{source}: key '{key}' must be a number, got {value!r}")
        return float(value)
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise UserError(f"{source}: key '{key}' must be an integer, got {value!r}")
        return value
    if isinstance(default, list):
        if not isinstance(value, list) or len(value) != len(default):
            raise UserError(f"{source}: key '{key}' must be a list of {len(default)} values, got {value!r}")
        return [_check_value(f"{key}[{i}]", d, v, source) for i, (d, v) in enumerate(zip(default, value))]
    if isinstance(default, str):
        if not isinstance(value, str):
            raise UserError(f"{source}: key '{key}' must be a string, got {value!r}")
        return value
    raise UserError(f"{source}: key '{key}' has an unsupported default {default!r}")


def _merge(base: dict, over: Any, source: str, prefix: str = "") -> None:
    if not isinstance(over, dict):
        raise UserError(f"{source}: '{prefix or '<top level>'}' must be a mapping")
    for key, value in over.items():
        path = f"{prefix}.{key}" if prefix else str(key)
        if key not in base:
            known = ", ".join(sorted(base))
            raise UserError(f"{source}: unknown key '{path}' (known at this level: {known})")
        if isinstance(base[key], dict):
            _merge(base[key], value, source, path)
        else:
            base[key] = _check_value(path, base[key], value, source)


_NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)[eE][+-]?\d+")


def parse_overrides(items: Iterable[str]) -> dict:
    """``["stage1.iterations=500", "model.mlp_width=64"]`` -> nested dict (values parsed as YAML)."""
    out: dict = {}
    for item in items:
        if "=" not in item:
            raise UserError(f"override '{item}' must look like key=value (e.g. stage1.iterations=500)")
        key, raw = item.split("=", 1)
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError:
            raise UserError(f"override '{item}': cannot parse the value {raw!r}") from None
        if isinstance(value, str) and _NUMBER.fullmatch(value.strip()):
            value = float(value)  # YAML 1.1 reads 3e-3 (no dot) as a string; a user means the number
        node = out
        parts = key.strip().split(".")
        if not all(parts):
            raise UserError(f"override '{item}': empty key part")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise UserError(f"override '{item}' conflicts with another override of '{part}'")
        node[parts[-1]] = value
    return out


def load_method_config(profile: str, overrides: Iterable[str] = (), path: str | Path = METHOD_CONFIG) -> dict:
    """The resolved configuration for ``profile`` as a plain nested dict (written to config.yaml)."""
    raw = load_yaml(path)
    source = str(path)
    if not isinstance(raw, dict) or "defaults" not in raw:
        raise UserError(f"{source}: must have a 'defaults' mapping")
    unknown = set(raw) - {"defaults", "profiles"}
    if unknown:
        raise UserError(f"{source}: unknown top-level key '{sorted(unknown)[0]}' (known: defaults, profiles)")
    cfg = copy.deepcopy(raw["defaults"])
    prof = load_profile(profile)
    sections = raw.get("profiles") or {}
    if profile in sections and sections[profile]:
        _merge(cfg, sections[profile], f"{source} (profiles.{profile})")
    _merge(cfg, parse_overrides(overrides), "command line")
    for st in ("stage1", "stage2"):
        if cfg[st]["iterations"] < 0:
            raise UserError(f"key '{st}.iterations' must be >= 0 (0: the profile's {st}_iterations), "
                            f"got {cfg[st]['iterations']}")
    if cfg["stage1"]["iterations"] == 0:
        cfg["stage1"]["iterations"] = prof.method.stage1_iterations
    if cfg["stage2"]["iterations"] == 0:
        cfg["stage2"]["iterations"] = prof.method.stage2_iterations
    _validate(cfg)
    cfg["profile"] = profile
    return cfg


def _validate(cfg: dict) -> None:
    m, s = cfg["model"], cfg["stage1"]
    for key in ("mlp_depth", "mlp_width", "time_net_width", "time_net_out"):
        if m[key] < 1:
            raise UserError(f"key 'model.{key}' must be >= 1 (got {m[key]})")
    if not 0 <= m["mlp_skip"] < m["mlp_depth"]:
        raise UserError(f"key 'model.mlp_skip' must be in [0, mlp_depth) (got {m['mlp_skip']})")
    if m["mlp_precision"] not in PRECISIONS:
        raise UserError(f"key 'model.mlp_precision' must be one of {', '.join(PRECISIONS)} "
                        f"(got {m['mlp_precision']!r})")
    if not isinstance(m["deform_nodes"], int) or isinstance(m["deform_nodes"], bool) or m["deform_nodes"] < 0:
        raise UserError(f"key 'model.deform_nodes' must be an integer >= 0 (0: the network at every Gaussian; "
                        f"got {m['deform_nodes']!r})")
    if m["motion_bases"] < 0:
        raise UserError(f"key 'model.motion_bases' must be >= 0 (0: the network alone; got {m['motion_bases']})")
    if m["motion_bases"] and not (s["p_from_motion"] and m["separation"]):
        raise UserError("key 'model.motion_bases' needs stage1.p_from_motion: true and model.separation: true "
                        "(the bases are fitted to the moving Gaussians at the P split)")
    if m["motion_bases"] and m["motion_knots"] < 2:
        raise UserError(f"key 'model.motion_knots' must be >= 2 (got {m['motion_knots']})")
    if m["p_temperature"] <= 0:
        raise UserError(f"key 'model.p_temperature' must be positive (got {m['p_temperature']})")
    if s["init_points"] < 1:
        raise UserError(f"key 'stage1.init_points' must be >= 1 (got {s['init_points']})")
    if s["init_scale"] <= 0:
        raise UserError(f"key 'stage1.init_scale' must be positive (got {s['init_scale']})")
    if not 0 < s["init_opacity"] < 1:
        raise UserError(f"key 'stage1.init_opacity' must be in (0, 1) (got {s['init_opacity']})")
    if s["max_gaussians"] and s["max_gaussians"] < s["init_points"]:
        raise UserError(f"key 'stage1.max_gaussians' ({s['max_gaussians']}) is below stage1.init_points "
                        f"({s['init_points']})")
    if not 0 <= s["depth_ratio"] <= 1:
        raise UserError(f"key 'stage1.depth_ratio' must be in [0, 1] (0: expected depth, 1: median; got {s['depth_ratio']})")
    if not 0 <= s["lambda_dssim"] <= 1:
        raise UserError(f"key 'stage1.lambda_dssim' must be in [0, 1] (got {s['lambda_dssim']})")
    if not 0 < s["time_window_start"] <= 1:
        raise UserError(f"key 'stage1.time_window_start' must be in (0, 1] (got {s['time_window_start']})")
    if not 0 <= s["time_window_front"] <= 1:
        raise UserError(f"key 'stage1.time_window_front' must be in [0, 1] (got {s['time_window_front']})")
    if s["time_window_until"] < 0:
        raise UserError(f"key 'stage1.time_window_until' must be >= 0 (got {s['time_window_until']})")
    for key in ("checkpoint_every", "densify_every", "log_every"):
        if s[key] < 1:
            raise UserError(f"key 'stage1.{key}' must be >= 1 (got {s[key]})")
    for key in ("checkpoint_every", "log_every", "env_fit_regions"):
        if cfg["stage2"][key] < 1:
            raise UserError(f"key 'stage2.{key}' must be >= 1 (got {cfg['stage2'][key]})")
    for key in ("opacity_reset_every", "eval_every"):
        if s[key] < 0:
            raise UserError(f"key 'stage1.{key}' must be >= 0 (0: never; got {s[key]})")
    if not 0 < cfg["data"]["train_frames"] <= 1:
        raise UserError(f"key 'data.train_frames' must be in (0, 1] (the share of the training frames kept; "
                        f"got {cfg['data']['train_frames']})")
    if any(not 0 <= c <= 1 for c in cfg["data"]["background"]):
        raise UserError(f"key 'data.background' must be three values in [0, 1] (got {cfg['data']['background']})")
