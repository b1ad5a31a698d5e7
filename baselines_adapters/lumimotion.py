"""In-project adapters: LumiMotion, its ablations, the static baseline, and budget variants.

Each trains (or reuses) a run under ``RUNS/PROFILE/<name>/<scene>/<train light>/seed<k>/`` with the
method's own training code and writes the benchmark predictions there (``.../predictions``, the folder
the job grid scores). A finished run is never retrained: stage 1, stage 2 and the predictions are each
skipped when their outputs exist, so scoring another test light or re-running `make eval` costs nothing.

* ``lumimotion``  stage 1 + stage 2 on the dynamic variant
* ``wo_stage2``   stage 1 only; the canonical colour is the albedo, roughness stays at its initial value,
                  relit with the same shading (paper's "w/o stage 2"); it takes the finished stage 1 of
                  ``lumimotion`` (same budget, scene, light, seed, settings) when there is one
* ``wo_dc``       no delta colour: moving shadows must be explained by geometry
* ``wo_P``        no static/dynamic separation: P = 1 for every Gaussian
* ``static``      the same pipeline without the deformation network, on ``<scene>_statictimestepNNNN``
                  (same cameras, one timestep): the IRGS-like baseline that isolates the paper's thesis
* ``<method>@<budget>``  the same at a fraction of the profile's iterations (``@0.25``; one stage's alone:
                  ``@s1x8``), a Gaussian cap
                  (``@cap10000``) and/or a share of the training frames, kept evenly over time
                  (``@frames0.25``: method/data.py even_subset, the run's ``data.train_frames``), joined with
                  ``+`` (``lumimotion@0.5+cap10000``, ``static@frames0.25+cap2000``)

The variants with a stage 2 also run the relight diagnostic (method/diagnose.py) for each test light the
grid scores: all test views, the run's ``stage2.dirs_eval`` directions capped at :data:`DIAGNOSE_MAX_DIRS`.
Its record, ``RUN/diagnose/<test light>/diagnose.json``, is reused when it has the current steps and all
test views, so a rescore computes nothing; the steps' PSNR and LPIPS go into meta.json under ``diagnose``
(one block per test light), and from there into each configuration's results.json.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import NamedTuple

from lumibench.errors import UserError

from .base import MethodAdapter

VARIANTS = {
    "lumimotion": {"overrides": [], "static": False, "stage2": True},
    "wo_stage2": {"overrides": [], "static": False, "stage2": False},
    "wo_dc": {"overrides": ["model.delta_colour=false"], "static": False, "stage2": True},
    # without the split there are no moving Gaussians to fit rigid bases to (small's model.motion_bases): the
    # network moves every Gaussian, as the paper's ablation has it
    "wo_P": {"overrides": ["model.separation=false", "model.motion_bases=0"], "static": False, "stage2": True},
    "static": {"overrides": [], "static": True, "stage2": True},
}
DIAGNOSE_MAX_DIRS = 128  # directions per pixel of the diagnostic: the run's dirs_eval, at most this
_BUDGET = re.compile(r"^(?:(?P<frac>\d*\.?\d+)|cap(?P<cap>\d+)|frames(?P<frames>[^+]*)"
                     r"|s(?P<stage>[12])x(?P<sfrac>\d*\.?\d+))$")
MAX_FRACTION = 8  # `make demo` runs stage 1 at 8x ci's iterations
_SHARE = re.compile(r"^\d*\.?\d+$")


class Budget(NamedTuple):
    """A budget variant's settings: ``fraction`` scales every iteration schedule point of both stages,
    ``stage1``/``stage2`` one stage's on top of it (``s1x8``: why, `make demo` learns its moving balls only
    at 8x ci's stage 1, while stage 2 at 8x scores the same as at 1x; BENCHMARKS.md, "make demo")."""

    fraction: float = 1.0
    cap: int = 0
    frames: float = 1.0
    stage1: float = 1.0
    stage2: float = 1.0

    def stage_fraction(self, stage: str) -> float:
        return self.fraction * (self.stage1 if stage == "stage1" else self.stage2)


def parse_budget(spec: str) -> Budget:
    """'0.25', 'cap10000', 'frames0.25', 's1x8' (one stage's iterations) or any of them joined with '+'
    ('0.5+cap10000+frames0.25') -> :class:`Budget`; one-line errors."""
    frac, cap, frames, per_stage = 1.0, 0, 1.0, {"1": 1.0, "2": 1.0}
    seen: set[str] = set()
    for part in spec.split("+"):
        m = _BUDGET.match(part.strip())
        if not m:
            raise UserError(f"unknown budget '{part}' in '{spec}': use a fraction of the iterations (0.25), one "
                            f"stage's fraction (s1x8, s2x0.5), a Gaussian cap (cap10000) and/or a share of the "
                            f"training frames (frames0.25), joined with '+'")
        kind = next(k for k in ("frac", "cap", "frames", "stage") if m.group(k) is not None)
        key = f"s{m.group('stage')}" if kind == "stage" else kind
        if key in seen:
            what = {"frac": "iteration fraction", "cap": "Gaussian cap", "frames": "share of frames",
                    "s1": "stage-1 fraction", "s2": "stage-2 fraction"}[key]
            raise UserError(f"budget '{spec}' gives the {what} twice")
        seen.add(key)
        if kind == "frac":
            frac = float(m.group("frac"))
        elif kind == "stage":
            per_stage[m.group("stage")] = float(m.group("sfrac"))
        elif kind == "cap":
            cap = int(m.group("cap"))
            if cap < 1:
                raise UserError(f"budget '{spec}': the Gaussian cap must be at least 1 (cap2000)")
        else:
            raw = m.group("frames")
            if not _SHARE.match(raw) or not 0 < float(raw) <= 1:
                raise UserError(f"budget 'frames{raw}' in '{spec}': the share of the training frames kept must be "
                                f"a number in (0, 1] (frames0.25 keeps every 4th frame)")
            frames = float(raw)
    budget = Budget(frac, cap, frames, per_stage["1"], per_stage["2"])
    for stage in ("stage1", "stage2"):
        f = budget.stage_fraction(stage)
        if not 0 < f <= MAX_FRACTION:
            raise UserError(f"budget '{spec}': {stage} runs at {f:g}x its iterations, which must be in "
                            f"(0, {MAX_FRACTION}]")
    return budget


class LumiMotionAdapter(MethodAdapter):
    # the grid reuses a predictions folder of this version, others are redone. 2: relight_scaled/ (method/
    # predictions.py VERSION); 3: meta.json carries the relight diagnostic (the same predictions as 2), so a
    # rescore of a version-2 folder predicts again (no training) and its results get the block; 4: the normal
    # map filtered before test-time shading where the profile asks (stage2.normal_filter; `small`), so stored
    # version-3 predictions are shaded again from their checkpoints (no training); 5: indirect light from the
    # Gaussians relit under the test light (stage2.relight_indirect), so version-4 predictions are shaded again
    version = "5"

    def __init__(self, name: str = "lumimotion", budget: str | None = None):
        base = name.split("@", 1)[0]
        if base not in VARIANTS:
            raise UserError(f"unknown LumiMotion variant '{base}' (known: {', '.join(VARIANTS)})")
        self.name = name if budget is None else f"{base}@{budget}"
        self.base = base
        self.variant = VARIANTS[base]
        self.budget = budget

    def overrides(self, profile: str) -> list[str]:
        from method.config import ITERATION_KEYS, load_method_config

        out = list(self.variant["overrides"])
        if self.budget:
            budget = parse_budget(self.budget)
            cap, frames = budget.cap, budget.frames
            cfg = load_method_config(profile)
            for stage, keys in ITERATION_KEYS.items():  # every schedule point scales with its stage's run
                frac = budget.stage_fraction(stage)     # (0 stays 0: a mechanism that is off)
                if frac != 1.0:
                    for key in keys:
                        if cfg[stage][key] > 0:
                            out.append(f"{stage}.{key}={max(1, round(cfg[stage][key] * frac))}")
            if cap:
                out.append(f"stage1.max_gaussians={cap}")
                out.append(f"stage1.init_points={min(cap, cfg['stage1']['init_points'])}")
            if frames != 1.0:
                out.append(f"data.train_frames={frames}")
        return out

    def scene_for(self, scene_dir: Path) -> Path:
        if not self.variant["static"]:
            return scene_dir
        from lumibench import layout

        if "_statictimestep" in scene_dir.name:
            return scene_dir
        found = sorted(scene_dir.parent.glob(f"{scene_dir.name}_statictimestep*"))
        found = [p for p in found if layout.is_complete(p) or not (p / "dataset.json").is_file()]
        if not found:
            raise UserError(f"no static variant beside {scene_dir} ({scene_dir.name}_statictimestepNNNN): "
                            f"render it with `make dataset`")
        return found[0]

    def predict(self, scene_dir, train_light, test_lights, seed, profile, out_dir, runs_dir):
        from method.config import load_method_config
        from method.data import available_lights
        from method.checkpoints import checkpoint_paths
        from method.predictions import write_predictions
        from method.train import share_stage1, train_stage1, train_stage2

        profile = profile or "ci"
        cfg = load_method_config(profile, self.overrides(profile))
        run_dir = Path(out_dir).parent if Path(out_dir).name == "predictions" else (
            Path(runs_dir or "runs") / self.name / Path(scene_dir).name / train_light / f"seed{seed}")
        train_scene = self.scene_for(Path(scene_dir))
        if not self.variant["stage2"] and not (run_dir / "metrics_stage1.json").is_file():
            # w/o stage 2 is LumiMotion's stage 1 itself: take the finished one of the same scene, light, seed
            # and settings when there is one, so the ablation compares the very same stage 1
            # (RUNS/PROFILE/<name>/<scene>/<light>/seed<k> -> RUNS/PROFILE/lumimotion[@budget]/<scene>/...)
            where = run_dir.resolve()
            sibling = where.parents[3] / "@".join(filter(None, ("lumimotion", self.budget))) / Path(*where.parts[-3:])
            share_stage1(sibling, run_dir, cfg, scene=train_scene.name, light=train_light, seed=seed)
        if not (run_dir / "metrics_stage1.json").is_file():
            train_stage1(train_scene, train_light, run_dir, cfg, seed=seed, static=self.variant["static"],
                         resume=bool(checkpoint_paths(run_dir, 1)), progress=False)
        if self.variant["stage2"] and not (run_dir / "metrics_stage2.json").is_file():
            train_stage2(train_scene, train_light, run_dir, cfg, seed=seed, resume=bool(checkpoint_paths(run_dir, 2)),
                         progress=False)
        lights = sorted(set(test_lights) | {x for x in available_lights(scene_dir) if x != train_light})
        pred = write_predictions(run_dir, Path(scene_dir), train_light, cfg, method=self.name, seed=seed,
                                 test_lights=lights, albedo_from_colour=not self.variant["stage2"],
                                 train_scene_dir=train_scene)
        import json

        meta = json.loads((pred / "meta.json").read_text())
        if Path(out_dir).resolve() != pred.resolve():  # the grid asked for another folder: copy the images
            import shutil

            shutil.copytree(pred, out_dir, dirs_exist_ok=True)
            (Path(out_dir) / "meta.json").unlink(missing_ok=True)
        keep = {k: meta[k] for k in ("timings", "cpu_timings", "device", "model_size", "relight_albedo_scale",
                                     "settings_sha256") if k in meta}
        keep["run_dir"] = str(run_dir)
        if self.variant["stage2"]:  # wo_stage2's albedo is the canonical colour: nothing to take apart
            keep["diagnose"] = {t: diagnose_block(run_dir, Path(scene_dir), t) for t in dict.fromkeys(test_lights)}
        return keep


def _reusable_record(path: Path, views: int, normal_filter: float = 0.0,
                     relight_indirect: bool = False) -> dict | None:
    """The stored diagnostic record at ``path`` when it has the current steps, all ``views`` test views and
    the run's test-time normal filter and relit indirect light (a record from before a setting: off)."""
    import json

    from method.diagnose import STEPS

    try:
        rec = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    steps = rec.get("steps") if isinstance(rec, dict) else None
    if not isinstance(steps, dict) or set(steps) != {name for name, _ in STEPS} or rec.get("views") != views:
        return None
    if float(rec.get("normal_filter", 0.0)) != float(normal_filter):
        return None
    if bool(rec.get("relight_indirect", False)) != bool(relight_indirect):
        return None
    return rec


def diagnose_block(run_dir: Path, scene_dir: Path, test_light: str) -> dict:
    """The relight diagnostic of ``run_dir`` under ``test_light`` on ``scene_dir``'s test views, as kept in
    the results: {views, dirs, protocol, steps: {name: {psnr, lpips}}}; computed once per (run, test light)."""
    from lumibench import layout
    from method import diagnose as dg
    from method.relight import read_run_config
    from method.shading.deferred import normal_filter_sigma, relight_indirect

    views = len(layout.read_transforms(scene_dir, "test").frames)
    s2 = read_run_config(run_dir)["stage2"]
    rec = _reusable_record(Path(run_dir) / "diagnose" / test_light / "diagnose.json", views, normal_filter_sigma(s2),
                           relight_indirect(s2))
    if rec is None:
        dirs = min(int(s2["dirs_eval"]), DIAGNOSE_MAX_DIRS)
        # the scene the benchmark scores on (the static variant trained on its static twin)
        rec = dg.diagnose(run_dir, test_light, dirs=dirs, data=scene_dir, progress=False)
    return {"views": int(rec["views"]), "dirs": int(rec["dirs"]), "protocol": str(rec.get("protocol", "lumimotion")),
            "steps": {name: {"psnr": float(s["psnr"]), "lpips": float(s["lpips"])}
                      for name, s in rec["steps"].items()}}




def lumimotion_factory():
    return LumiMotionAdapter("lumimotion")


def wo_stage2_factory():
    return LumiMotionAdapter("wo_stage2")


def wo_dc_factory():
    return LumiMotionAdapter("wo_dc")


def wo_P_factory():  # noqa: N802 (the method's name)
    return LumiMotionAdapter("wo_P")


def static_factory():
    return LumiMotionAdapter("static")
