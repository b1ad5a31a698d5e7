"""What the four external methods share: the paper's dataset layout, name mapping, image import, the adapter.

The authors of LumiMotion ran IRGS, R-3DGS and GI-GS (through their own forks) and LumiMotion on one
dataset layout, the one their loaders and evaluation scripts read. We call it the *paper layout*; every
fact below was read from those loaders (each method module names the file and commit)::

    OUT/<scene>/                              dynamic variant (LumiMotion trains on it)
      transforms_train.json, transforms_test.json
          {"camera_angle_x", "frames": [{"file_path": "r_NNNN", "transform_matrix", "time"}]}
          file_path is a BARE name (no split folder, no extension): the GT look-ups match the file
          name by prefix or substring in flat folders, which fails on "test/r_0000"
      <light>/r_NNNN.png                      FLAT per light: train and test views, RGBA, alpha = coverage
      albedo/r_NNNN0001.png                   FLAT GT albedo (sRGB), ONE file per view, named with a suffix
                                              after the stem (like the paper's Blender outputs r_NNNN<frame>):
                                              GI-GS's find_matching_file skips "r_NNNN.png" itself, IRGS and
                                              GI-GS take the first name starting with the stem, LumiMotion and
                                              R-3DGS the first containing it
      roughness/r_NNNN.png, roughness/r_NNNN0001.png   FLAT GT roughness (linear, as RGB): LumiMotion reads
                                              r_<4 digits>.png, IRGS the albedo file's name
      normal/r_NNNN.png                       world normals (n + 1) / 2 (no loader needs them; for viewing)
      <light>.hdr                             the env maps as rendered (32 x 16 unless a light names its size), named like the light folders
      lumibench_export.json                   our manifest: where each exported name comes from
    OUT/<scene>_statictimestepNNNN/           static variant (the baselines train on it); same layout.
                                              LumiMotion's *_static evaluation scripts find it with
                                              glob(f"{source_path}_statictimestep*") and read NNNN from it

Names: our train views ``train/r_i`` keep ``r_i``; our test views ``test/r_j`` become ``r_{n_train + j}``,
so that one flat folder holds both splits without a clash (the loaders sort frames by that number, so
exported test order = our test order). The importers map back with :class:`SceneNames`, computed from
our scene alone, so importing needs no state from the export.
"""
from __future__ import annotations

import json
import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from lumibench import layout
from lumibench.errors import UserError
from lumibench.io import atomic_write_json, read_image, write_png

from ..base import MethodAdapter, MethodNotRun, save

EXPORT_FORMAT = "lumibench-external-export"
MANIFEST = "lumibench_export.json"
GT_SUFFIX = "0001"  # albedo/<name>0001.png: see the module docstring
_STATIC_RE = re.compile(r"^(?P<base>.+)_statictimestep(?P<t>\d+)$")
RUNS_ENV = "LUMIBENCH_EXTERNAL_RUNS"


# ----------------------------------------------------------------------------------------------- names
@dataclass(frozen=True)
class SceneNames:
    """Our scene (both variants) and the names its views get in the paper layout."""

    scene: Path            # our dynamic scene dir
    static: Path           # our static sibling <scene>_statictimestepNNNN
    timestep: int
    n_train: int
    test_stems: tuple[str, ...]     # our test stems, in transforms_test.json order
    lights: tuple[str, ...]

    @property
    def name(self) -> str:
        return self.scene.name

    @property
    def static_name(self) -> str:
        return self.static.name

    def exported(self, split: str, index: int) -> str:
        return layout.frame_stem(index if split == "train" else self.n_train + index)

    @property
    def test_names(self) -> tuple[str, ...]:
        """Exported names of our test views, in our test order (= the loaders' sorted order)."""
        return tuple(self.exported("test", j) for j in range(len(self.test_stems)))

    def gt_shape(self) -> tuple[int, int]:
        """(H, W) of the test views (what a prediction must have)."""
        fp = layout.read_transforms(self.scene, "test").frames[0].file_path
        for light in self.lights:
            path = layout.lit_image_path(self.scene, light, fp)
            if path.is_file():
                return tuple(read_image(path).shape[:2])  # type: ignore[return-value]
        raise UserError(f"{self.scene}: no lit test image found for {fp}")


def resolve_scene(path: str | Path) -> SceneNames:
    """Our scene from its dynamic dir or its static sibling; both variants must exist."""
    given = Path(path)
    if not (given / "transforms_train.json").is_file():
        raise UserError(f"{given} is not a rendered scene directory (no transforms_train.json; make dataset)")
    m = _STATIC_RE.match(given.name)
    if m:
        dyn = given.parent / m.group("base")
        if not (dyn / "transforms_train.json").is_file():
            raise UserError(f"static scene {given} has no dynamic sibling {dyn} (render both: make dataset)")
        static = given
    else:
        dyn = given
        found = sorted(p for p in dyn.parent.glob(f"{dyn.name}_statictimestep*") if _STATIC_RE.match(p.name))
        if len(found) != 1:
            what = "no" if not found else f"{len(found)}"
            raise UserError(f"{dyn}: found {what} static sibling {dyn.name}_statictimestepNNNN "
                            "(the external methods need exactly one; make dataset renders it)")
        static = found[0]
    timestep = int(_STATIC_RE.match(static.name).group("t"))  # type: ignore[union-attr]
    train, test = layout.read_transforms(dyn, "train"), layout.read_transforms(dyn, "test")
    lights = tuple(sorted(p.stem for p in dyn.glob("*.hdr") if (dyn / p.stem / "test").is_dir()))
    if not lights:
        raise UserError(f"{dyn}: no light has a rendered test split (<light>/test/ beside <light>.hdr)")
    return SceneNames(dyn.resolve(), static.resolve(), timestep, len(train.frames),
                      tuple(f.stem for f in test.frames), lights)


# ---------------------------------------------------------------------------------------------- export
def _copy(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dst)


def _write_rgb(src: Path, dst: Path) -> None:
    """Copy a PNG as RGB: grey images get three channels (IRGS's reader indexes [..., :1] of HxWxC)."""
    img = read_image(src)
    if img.shape[-1] == 1:
        write_png(dst, np.repeat(img, 3, axis=-1))
    elif img.shape[-1] == 2:  # grey + alpha
        write_png(dst, np.repeat(img[..., :1], 3, axis=-1))
    else:
        _copy(src, dst)


def _export_variant(src: Path, dst: Path, names: SceneNames) -> int:
    files = 0
    for split in layout.SPLITS:
        tr = layout.read_transforms(src, split)
        frames = []
        for i, f in enumerate(tr.frames):
            name = names.exported(split, i)
            frames.append({"file_path": name, "transform_matrix": f.c2w.tolist(), "time": f.time})
            for light in names.lights:
                lit = layout.lit_image_path(src, light, f.file_path)
                if lit.is_file():
                    _copy(lit, dst / light / f"{name}.png")
                    files += 1
            targets = {"albedo": [f"{name}{GT_SUFFIX}"], "roughness": [name, f"{name}{GT_SUFFIX}"], "normal": [name]}
            for kind, stems in targets.items():
                gt = layout.gt_path(src, kind, f.file_path)
                if gt.is_file():
                    for stem in stems:
                        (_write_rgb if kind == "roughness" else _copy)(gt, dst / kind / f"{stem}.png")
                        files += 1
                elif split == "test" and kind != "normal":
                    raise UserError(f"missing ground truth {gt} (the external evaluation scripts need it)")
        atomic_write_json(dst / f"transforms_{split}.json", {"camera_angle_x": tr.camera_angle_x, "frames": frames})
    for light in names.lights:
        hdr = layout.envmap_path(src, light)
        if not hdr.is_file():
            hdr = layout.envmap_path(names.scene, light)
        _copy(hdr, dst / f"{light}.hdr")
    return files


def export_paper_layout(scene: str | Path, out: str | Path, method: str) -> tuple[SceneNames, dict[str, Path]]:
    """Write both variants of our scene under ``out`` in the paper layout; return the names and the dirs."""
    names = resolve_scene(scene)
    out = Path(out)
    dirs = {"dynamic": out / names.name, "static": out / names.static_name}
    for d in dirs.values():
        if d.exists() and any(d.iterdir()) and not (d / MANIFEST).is_file():
            raise UserError(f"{d} exists and was not written by this exporter; choose another --out")
    manifest: dict[str, Any] = {
        "format": EXPORT_FORMAT, "version": 1, "method": method,
        "source_scene": str(names.scene), "source_static_scene": str(names.static),
        "static_timestep": names.timestep, "lights": list(names.lights),
        "names": {**{names.exported("train", i): ["train", layout.frame_stem(i)] for i in range(names.n_train)},
                  **{n: ["test", s] for n, s in zip(names.test_names, names.test_stems)}},
    }
    for variant, src in (("dynamic", names.scene), ("static", names.static)):
        (dirs[variant] / MANIFEST).unlink(missing_ok=True)
        _export_variant(src, dirs[variant], names)
        atomic_write_json(dirs[variant] / MANIFEST, {**manifest, "variant": variant})  # last: marks it complete
    return names, dirs


# ---------------------------------------------------------------------------------------------- import
def _source_path_from_cfg(run_dir: Path) -> Path | None:
    """3DGS-family code writes the training arguments to <model>/cfg_args as a Namespace(...) repr."""
    for d in (run_dir, *list(run_dir.parents)[:2]):
        cfg = d / "cfg_args"
        if cfg.is_file():
            m = re.search(r"source_path=['\"]([^'\"]+)['\"]", cfg.read_text(errors="replace"))
            if m:
                return Path(m.group(1))
    return None


def scene_for_import(from_dir: Path, data: str | Path | None = None, export: str | Path | None = None) -> SceneNames:
    """Our scene for an import: --data, else the manifest of --export, else cfg_args' source_path."""
    if data:
        return resolve_scene(data)
    candidates = [Path(export)] if export else []
    src = _source_path_from_cfg(from_dir)
    if src is not None:
        candidates.append(src)
    for c in candidates:
        for m in (c / MANIFEST, c.parent / MANIFEST):
            if m.is_file():
                try:
                    meta = json.loads(m.read_text())
                    return resolve_scene(meta["source_scene"])
                except (json.JSONDecodeError, KeyError) as exc:
                    raise UserError(f"{m}: corrupt export manifest ({exc})") from None
    raise UserError(f"cannot tell which LumiBench scene {from_dir} belongs to: pass --data <scene dir> "
                    "(or --export <the folder written by 'export'>)")


def resize(img: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Bilinear resize of an H x W x C float image to ``shape`` (the external eval scripts change sizes)."""
    if img.shape[:2] == tuple(shape):
        return img
    from PIL import Image

    h, w = shape
    chans = [np.asarray(Image.fromarray(np.ascontiguousarray(img[..., c], dtype=np.float32), mode="F")
                        .resize((w, h), Image.BILINEAR), dtype=np.float32) for c in range(img.shape[-1])]
    return np.stack(chans, axis=-1)


# how each external output is encoded: "srgb" RGB for display, "linear" RGB, "scalar" linear one channel,
# "normal" (n + 1) / 2
ENCODINGS = ("srgb", "linear", "scalar", "normal")


@dataclass
class Importer:
    """Writes one predictions folder from a method's files, checking completeness per kind."""

    names: SceneNames
    out: Path

    def __post_init__(self):
        self.shape = self.names.gt_shape()
        self.written: dict[str, int] = {}

    def put(self, kind: str, stem: str, src: Path, encoding: str, light: str | None = None) -> None:
        img = resize(read_image(src), self.shape)
        if encoding == "srgb":
            save(self.out, kind, stem, np.clip(img[..., :3], 0.0, 1.0), light)
        elif encoding == "linear":
            save(self.out, kind, stem, img[..., :3], light, fmt="npz")
        elif encoding == "scalar":
            save(self.out, kind, stem, img[..., :1], light, fmt="npz")
        elif encoding == "normal":
            save(self.out, kind, stem, np.clip(img[..., :3], 0.0, 1.0), light)
        else:  # pragma: no cover - programming error
            raise ValueError(encoding)
        key = f"{kind}/{light}" if light else kind
        self.written[key] = self.written.get(key, 0) + 1

    def kind(self, kind: str, paths: Sequence[Path], encoding: str, light: str | None = None,
             required: bool = False) -> bool:
        """Import one kind: ``paths[j]`` is the file for our j-th test view. All or none must exist."""
        present = [p.is_file() for p in paths]
        if not any(present):
            if required:
                raise UserError(f"no {kind} outputs found (expected e.g. {paths[0]})")
            return False
        if not all(present):
            missing = next(p for p, ok in zip(paths, present) if not ok)
            raise UserError(f"incomplete {kind} outputs: {missing} is missing "
                            f"({sum(present)} of {len(paths)} test views found)")
        for stem, p in zip(self.names.test_stems, paths):
            self.put(kind, stem, p, encoding, light)
        return True


def latest_iteration_dir(parent: Path, prefix: str = "ours_", must_have: str | None = None) -> Path | None:
    """``parent/ours_<iter>`` with the highest numeric iteration (``ours_None`` last), holding ``must_have``."""
    dirs = [d for d in parent.glob(f"{prefix}*") if d.is_dir() and (must_have is None or (d / must_have).exists())]
    if not dirs:
        return None

    def key(d: Path) -> tuple[int, int]:
        tail = d.name[len(prefix):]
        return (1, int(tail)) if tail.isdigit() else (0, 0)

    return max(dirs, key=key)


def match_light(tail: str, lights: Iterable[str]) -> str | None:
    """The light a folder/file suffix names: ``tail`` equals it or continues with "_" (longest wins)."""
    for light in sorted(lights, key=len, reverse=True):
        if tail == light or tail.startswith(light + "_"):
            return light
    return None


# --------------------------------------------------------------------------------------------- methods
@dataclass(frozen=True)
class ExternalMethod:
    """One external method: where its conventions come from, how to run it, how to import its outputs."""

    name: str                # registry name
    title: str
    repo: str                # the repository whose loaders and scripts the convention was read from
    commit: str
    upstream: str            # the original repository (and commit) the fork is based on
    trains_on: str           # "static" or "dynamic" variant of the export
    relight_names_light: bool  # its relit outputs carry the test light's name (else --test-light is needed)
    commands: Callable[[dict[str, str]], list[str]]
    import_outputs: Callable[..., dict[str, Any]]  # (importer, run dir, test lights, **options)
    version: str = "1"

    def command_lines(self, names: SceneNames | None, dirs: dict[str, Path] | None, train: str | None,
                      test: str | None, run: str | None = None) -> list[str]:
        ctx = {"DYNAMIC": str(dirs["dynamic"]) if dirs else "EXPORT/<scene>",
               "STATIC": str(dirs["static"]) if dirs else "EXPORT/<scene>_statictimestepNNNN",
               "TRAIN": train or "<train light>", "TEST": test or "<test light>",
               "RUN": run or default_run_hint(self.name, names, train, test if not self.relight_names_light else None)}
        return self.commands(ctx)


def default_run_hint(method: str, names: SceneNames | None, train: str | None, test: str | None) -> str:
    """Where the grid's adapter looks for a run: runs/<profile>/external/<method>/<scene>/<train>[_to_<test>]."""
    profile = names.scene.parent.name if names else "<profile>"
    scene = names.name if names else "<scene>"
    leaf = (train or "<train light>") + (f"_to_{test}" if test else "")
    return f"runs/{profile}/external/{method}/{scene}/{leaf}"


def external_root(runs_dir: Path | None) -> Path | None:
    env = os.environ.get(RUNS_ENV)
    if env:
        return Path(env)
    return Path(runs_dir) / "external" if runs_dir is not None else None


class ExternalAdapter(MethodAdapter):
    """Scores an external method from its outputs; never trains it (its code is not ours and needs CUDA).

    Looks for the method's output (model) dir at ``ROOT/<method>/<scene>/<train>_to_<test>`` (one per test
    light) or ``ROOT/<method>/<scene>/<train>`` (one for all), with ROOT = ``$LUMIBENCH_EXTERNAL_RUNS`` or
    ``<runs_dir>/external`` (the grid passes ``runs/<profile>``). Nothing there: :class:`MethodNotRun`.
    """

    seed_dependent = False

    def __init__(self, spec: ExternalMethod):
        self.spec = spec
        self.name = spec.name
        self.version = spec.version

    def run_dirs(self, scene_dir: Path, train_light: str, test_lights: list[str],
                 runs_dir: Path | None) -> dict[str, Path]:
        root = external_root(runs_dir)
        if root is None:
            return {}
        base = root / self.name / Path(scene_dir).name
        found = {}
        for test in test_lights:
            for cand in (base / f"{train_light}_to_{test}", base / train_light):
                if cand.is_dir() and any(cand.iterdir()):
                    found[test] = cand
                    break
        return found

    def not_run(self, scene_dir: Path, train_light: str, test_lights: list[str], runs_dir: Path | None,
                missing: list[str]) -> MethodNotRun:
        root = external_root(runs_dir)
        names = None
        try:
            names = resolve_scene(scene_dir)
        except UserError:
            pass
        test = missing[0] if missing else (test_lights[0] if test_lights else None)
        leaf = f"{train_light}_to_{test}" if test and not self.spec.relight_names_light else train_light
        where = (root / self.name / Path(scene_dir).name / leaf) if root is not None else \
            Path(default_run_hint(self.name, names, train_light, None)).parent / leaf
        return MethodNotRun(
            f"{self.spec.title} ({self.name}) has no outputs for {Path(scene_dir).name} {train_light}->"
            f"{','.join(missing or test_lights)}: run 'python -m baselines_adapters export {self.name} "
            f"--data {scene_dir} --out EXPORT --train-light {train_light} --test-light {test}', train and "
            f"evaluate it as printed (README 'External methods') with its model dir at {where} "
            f"(or ${RUNS_ENV}/{self.name}/...), or import by hand: python -m baselines_adapters import "
            f"{self.name} --from {where} --data {scene_dir}"
            + ("" if self.spec.relight_names_light else f" --test-light {test}") + " --out PRED")

    def predict(self, scene_dir, train_light, test_lights, seed, profile, out_dir, runs_dir):
        dirs = self.run_dirs(scene_dir, train_light, test_lights, runs_dir)
        missing = [t for t in test_lights if t not in dirs]
        if missing:
            raise self.not_run(scene_dir, train_light, test_lights, runs_dir, missing)
        names = resolve_scene(scene_dir)
        extra: dict[str, Any] = {"device": "external", "external": {}}
        for test, run_dir in dirs.items():  # materials and NVS: the last dir wins (same training)
            extra["external"][test] = import_run(self.spec, Importer(names, Path(out_dir)), run_dir, [test])
        return extra


def import_run(spec: ExternalMethod, imp: Importer, run_dir: Path, test_lights: list[str],
               **options: Any) -> dict[str, Any]:
    """Import one model dir; ``test_lights``: the lights its relit outputs are under (empty: all it names)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise MethodNotRun(f"{spec.title} ({spec.name}) output dir {run_dir} does not exist: export the scene "
                           f"with 'python -m baselines_adapters export {spec.name} --data <scene> --out EXPORT', "
                           f"run the printed commands with their model dir at {run_dir}, then import again")
    for light in test_lights:
        if light not in imp.names.lights:
            raise UserError(f"unknown test light '{light}' for {imp.names.scene} "
                            f"(rendered: {', '.join(imp.names.lights)})")
    before = dict(imp.written)
    info = spec.import_outputs(imp, run_dir, test_lights, **options) or {}
    if imp.written == before:
        raise MethodNotRun(f"no {spec.title} ({spec.name}) outputs under {run_dir}: run its render and evaluation "
                           f"commands (printed by 'python -m baselines_adapters export {spec.name} ...', README "
                           f"'External methods') with that model dir, then import again")
    relit = sorted(k.split("/", 1)[1] for k in imp.written if k.startswith("relight/"))
    return {"source": str(run_dir), "repo": f"{spec.repo}@{spec.commit}", "kinds": dict(imp.written),
            "relit_lights": relit, **info}


def one_test_light(spec: ExternalMethod, test_lights: list[str]) -> str | None:
    """Methods whose relit files do not name the light need exactly one (given on the command line)."""
    if len(test_lights) > 1:
        raise UserError(f"{spec.title} writes its relit images without the light's name: import one test "
                        f"light per output dir (got {', '.join(test_lights)})")
    return test_lights[0] if test_lights else None
