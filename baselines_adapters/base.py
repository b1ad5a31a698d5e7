"""The adapter protocol: how the benchmark asks any method (ours, ablations, external) for predictions.

An adapter turns (scene, train light, seed, profile) into a predictions folder in the layout of
:mod:`benchmark.predictions`, finishing with ``meta.json``. Training, caching checkpoints under
``runs_dir`` and rendering are the adapter's business; scoring is not (the benchmark scores every
method the same way).
"""
from __future__ import annotations

import abc
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from lumibench.predictions import write_meta
from lumibench.io import atomic_path, write_png


class MethodAdapter(abc.ABC):
    """One scoreable method. Subclasses set ``name`` and ``version`` and implement :meth:`predict`."""

    name: str = ""
    version: str = "0"
    # False for methods whose output does not depend on the seed: the grid then runs only the first seed
    seed_dependent: bool = True

    def run(self, scene_dir: str | Path, train_light: str, test_lights: Sequence[str], seed: int,
            profile: str | None, out_dir: str | Path, runs_dir: str | Path | None = None) -> Path:
        """Write predictions for every test view and ``test_lights`` into ``out_dir``; return it.

        ``meta.json`` is written last, so a folder without it is an interrupted run.
        """
        out = Path(out_dir)
        (out / "meta.json").unlink(missing_ok=True)
        out.mkdir(parents=True, exist_ok=True)
        start, cpu_start = time.perf_counter(), time.process_time()
        extra = self.predict(Path(scene_dir), train_light, list(test_lights), int(seed), profile, out,
                             Path(runs_dir) if runs_dir is not None else None) or {}
        meta: dict[str, Any] = {
            "method": self.name, "version": self.version, "seed": int(seed), "profile": profile,
            "scene": Path(scene_dir).name, "train_light": train_light, "test_lights": list(test_lights),
            "device": "cpu", "timings": {"predict": time.perf_counter() - start},
            "cpu_timings": {"predict": time.process_time() - cpu_start},  # this process's threads only
        }
        meta.update(extra)
        if "timings" in extra and "cpu_timings" not in extra:  # its own stages, timed on the wall clock only
            del meta["cpu_timings"]
        write_meta(out, meta)
        return out

    @abc.abstractmethod
    def predict(self, scene_dir: Path, train_light: str, test_lights: list[str], seed: int,
                profile: str | None, out_dir: Path, runs_dir: Path | None) -> dict[str, Any] | None:
        """Write the prediction images; return extra meta (timings, model_size, device, ...)."""


def save(out_dir: Path, kind: str, stem: str, image: np.ndarray, light: str | None = None,
         fmt: str = "png") -> Path:
    """Write one prediction image where the predictions layout expects it (atomically)."""
    if kind in ("relight", "relight_scaled"):
        folder = out_dir / kind / str(light)
    elif kind == "p_map":
        folder = out_dir / "p_map" / "train"
    elif kind == "envmap":  # stem is the light's name
        folder = out_dir / "envmap"
    else:
        folder = out_dir / kind
    path = folder / f"{stem}.{fmt}"
    if fmt == "png":
        write_png(path, image)
    elif fmt == "npz":
        with atomic_path(path) as tmp:
            np.savez_compressed(tmp, image=np.asarray(image, dtype=np.float32))
    else:
        raise ValueError(f"unsupported prediction format {fmt!r}")
    return path


# --- external methods that have not been run (appended; the code above is unchanged) ---
from lumibench.errors import UserError  # noqa: E402

NOT_RUN_PREFIX = "not run: "


class MethodNotRun(UserError):
    """An external method (its code is not ours) has no outputs for this job yet.

    The message is one line, starts with :data:`NOT_RUN_PREFIX` and says what to run and where to put its
    output so that the adapter finds it. The benchmark shows such a job as "not run", not as a failure:
    detect it with ``isinstance(exc, MethodNotRun)``, or, from a stored result or a string that crossed a
    process boundary, with :func:`is_not_run_message`.
    """

    status = "not_run"

    def __init__(self, message: str):
        text = " ".join(str(message).split())  # one line, whatever the caller passed
        super().__init__(text if text.startswith(NOT_RUN_PREFIX) else NOT_RUN_PREFIX + text)


def is_not_run_message(text: object) -> bool:
    """True for the message of a :class:`MethodNotRun` (e.g. a failed result's ``error`` field)."""
    return isinstance(text, str) and text.startswith(NOT_RUN_PREFIX)
