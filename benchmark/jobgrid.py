"""The job grid: dataset-rendering jobs, then (method, scene, train light, seed) jobs, local or on Ray.

A method job runs the adapter once (one predictions folder per method, scene, train light and seed,
shared by every configuration with that train light, so two jobs never write the same folder) and
scores each of its configurations under each protocol of the grid, from those same predictions, into
``RESULTS/runs/<method>/<scene>/<train>_to_<test>/seed<k>/`` ``results.json`` (``lumimotion``) and
``results_<protocol>.json`` (any other, e.g. ``results_strict.json``; benchmark.results.result_filename).
The grid resumes: a job whose result files all exist, validate, say "ok" and hold their own protocol is
not run again (failed ones are retried), and a job that runs scores only its missing (configuration,
protocol) results: a stored result is never recomputed. When the only results missing are of another
protocol than the stored ones, the predictions those were scored from are scored as they are (the
adapter does not run, even when its version has moved on since), so both protocols always describe the
same predictions and adding a protocol to a grid costs its scoring only. A job that fails is recorded as
a result with status "failed" and the cause in every protocol's file (the traceback goes to
``error.log`` beside them); the other jobs go on. Jobs are plain dicts handed to a top-level function,
so they pickle to worker processes and to Ray workers alike.
"""
from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from lumibench import layout
from lumibench.errors import UserError
from lumibench.io import atomic_write_text
from lumibench.progress import track

from .config import BenchmarkConfig, Configuration, known_scenes
from .results import DEFAULT_PROTOCOL, failed_result, is_finished, read_result, result_filename, write_result

EXECUTORS = ("local", "ray")


@dataclass(frozen=True)
class Paths:
    data: Path      # DATA (the generator's root; scenes at DATA/PROFILE/<scene>)
    runs: Path      # RUNS (predictions and checkpoints at RUNS/PROFILE/<method>/...)
    results: Path   # RESULTS (this profile's outputs at RESULTS/PROFILE/)
    profile: str

    @property
    def out(self) -> Path:
        return self.results / self.profile


def result_path(paths: Paths, method: str, scene: str, conf: Configuration, seed: int,
                protocol: str = DEFAULT_PROTOCOL) -> Path:
    return paths.out / "runs" / method / scene / conf.slug / f"seed{seed}" / result_filename(protocol)


def pred_dir(paths: Paths, method: str, scene: str, train_light: str, seed: int) -> Path:
    return paths.runs / paths.profile / method / scene / train_light / f"seed{seed}" / "predictions"


def extra_lights(config: BenchmarkConfig) -> list[str]:
    """The named lights of the grid's configurations that are not rendered by default (``default: false`` in
    configs/lights.yaml, e.g. city_sharp): a missing scene is rendered with them besides the default ones."""
    from generator.lights import load_lights

    named = load_lights()
    return [x for x in config.lights() if x in named and not named[x].default]


def render_jobs(config: BenchmarkConfig, paths: Paths) -> list[dict[str, Any]]:
    """One job per scene whose dataset is missing or unfinished (lumibench.layout.is_complete); the grid's
    light files and its named lights that are not rendered by default are rendered besides the default ones."""
    extra: dict[str, Any] = {"light_files": list(config.light_files)} if config.light_files else {}
    if extra_lights(config):
        extra["light_names"] = extra_lights(config)
    return [{"kind": "render", "scene": s, "profile": paths.profile, "data": str(paths.data), **extra}
            for s in config.scenes if not layout.is_complete(layout.scene_dir(paths.data, paths.profile, s))]


def check_scene_lights(config: BenchmarkConfig, paths: Paths) -> None:
    """A rendered scene that lacks a light the grid names (rendered before the grid named it): one line
    saying how to get it, before any job runs (adding a light to a scene renders every frame again, so the
    grid does not do it to a finished dataset that other grids may be reading)."""
    for s in config.scenes:
        scene = layout.scene_dir(paths.data, paths.profile, s)
        if not layout.is_complete(scene):
            continue
        have = sorted(p.name for p in scene.iterdir() if (p / "train").is_dir() and p.name not in layout.GT_KINDS
                      and not p.name.startswith("."))  # as method.data.available_lights, without torch
        missing = [x for x in config.lights() if x not in have]
        if missing:
            raise UserError(f"{scene} was rendered without the light(s) {', '.join(missing)} that {config.source} "
                            f"names (it has {', '.join(have) or 'none'}): give the grid another --data root (a "
                            f"missing scene is rendered with every light it needs), or render this one again with "
                            f"them: make dataset PROFILE={paths.profile} SCENES={s} DATA={paths.data} "
                            f"LIGHTS=\"{' '.join(list(dict.fromkeys(have + missing)))}\" (every frame again)")


def method_jobs(config: BenchmarkConfig, paths: Paths) -> list[dict[str, Any]]:
    """Every (method, scene, train light, seed) job with the configurations it scores, and for each protocol
    of the grid the result file of each configuration (``job["results"][protocol]``, in ``tests`` order).

    A method whose adapter says it is not seed-dependent runs with the first seed only (its std over
    seeds would be zero by construction; the table's run count shows it).
    """
    from baselines_adapters.registry import get_adapter

    jobs = []
    trains = list(dict.fromkeys(c.train for c in config.configurations))
    for method in config.methods:
        seeds = config.seeds if get_adapter(method).seed_dependent else config.seeds[:1]
        for scene in config.scenes:
            for train in trains:
                confs = [c for c in config.configurations if c.train == train and c.runs(method)]
                if not confs:  # every configuration with this train light names its methods, not this one
                    continue
                for seed in seeds:
                    confs_s = [c for c in confs if c.runs_seed(seed)]
                    if not confs_s:
                        continue
                    jobs.append({
                        "kind": "method", "method": method, "scene": scene, "train": train,
                        "tests": [c.test for c in confs_s], "seed": seed, "profile": paths.profile,
                        "protocols": list(config.protocols), "lpips_net": config.lpips_net,
                        "scene_dir": str(layout.scene_dir(paths.data, paths.profile, scene)),
                        "pred_dir": str(pred_dir(paths, method, scene, train, seed)),
                        "runs_dir": str(paths.runs / paths.profile),
                        "results": {p: [str(result_path(paths, method, scene, c, seed, p)) for c in confs_s]
                                    for p in config.protocols},
                    })
    return jobs


def job_results(job: dict[str, Any]) -> Iterator[tuple[str, str, str]]:
    """(protocol, test light, result path) of every result file of a method job."""
    for protocol in job["protocols"]:
        for test, path in zip(job["tests"], job["results"][protocol]):
            yield protocol, test, path


def missing_results(job: dict[str, Any]) -> list[tuple[str, str, str]]:
    """The job's (protocol, test light, path) whose result is not finished under that protocol."""
    return [(p, t, path) for p, t, path in job_results(job) if not is_finished(path, p, job["lpips_net"])]


def job_finished(job: dict[str, Any]) -> bool:
    return not missing_results(job)


def job_label(job: dict[str, Any]) -> str:
    if job["kind"] == "render":
        return f"render {job['profile']}/{job['scene']}"
    return f"{job['method']} {job['scene']} {job['train']}->{','.join(job['tests'])} seed {job['seed']}"


def _identity(job: dict[str, Any], test: str, protocol: str, version: str = "unknown") -> dict[str, Any]:
    return {"method": job["method"], "adapter_version": version, "scene": job["scene"], "train_light": job["train"],
            "test_light": test, "seed": job["seed"], "protocol": protocol, "profile": job["profile"]}


def _cause(exc: BaseException) -> str:
    """One line: tables and the report list causes, the full traceback goes to error.log."""
    text = str(exc) if isinstance(exc, UserError) else f"{type(exc).__name__}: {exc}"
    lines = [l.strip() for l in text.splitlines() if l.strip()]
    return lines[0] if lines else type(exc).__name__


def record_failure(job: dict[str, Any], cause: str, tb: str | None = None, version: str = "unknown") -> None:
    """Write a failed result for every configuration and protocol of ``job`` whose result is not finished
    (a stored result is kept) and ``error.log`` beside it (the traceback, or the cause when there is none,
    e.g. a worker process that died)."""
    for protocol, test, path in missing_results(job):
        write_result(path, failed_result(_identity(job, test, protocol, version), cause))
        atomic_write_text(Path(path).with_name("error.log"), tb or f"{cause}\n")


def render_log_path(out: Path, job: dict[str, Any]) -> Path:
    return Path(out) / "logs" / f"render_{job['scene']}.log"


def failure_log(job: dict[str, Any], outcome: dict[str, Any]) -> Path | None:
    """Where the cause of a failed job is written in full."""
    if job["kind"] == "render":
        return Path(outcome["log"]) if outcome.get("log") else None
    logs = [Path(p).with_name("error.log") for _, _, p in job_results(job)]
    return next((p for p in logs if p.is_file()), None)


def failure_summary(failed: list[tuple[dict, dict]], total: int, limit: int = 3) -> str:
    """One line: how many jobs failed, which, and where their logs are."""
    items = []
    for job, outcome in failed[:limit]:
        log = failure_log(job, outcome)
        items.append(f"{job_label(job)} (log: {log})" if log else job_label(job))
    more = f"; and {len(failed) - limit} more" if len(failed) > limit else ""
    return f"{len(failed)} of {total} jobs run failed: " + "; ".join(items) + more


def execute(job: dict[str, Any]) -> dict[str, Any]:
    """Run one job in the current process; never raises (the outcome says what happened)."""
    if job.get("threads"):
        try:
            import torch

            torch.set_num_threads(int(job["threads"]))
        except ImportError:  # pragma: no cover - torch is a dependency
            pass
    if job["kind"] == "render":
        return _execute_render(job)
    return _execute_method(job)


def _execute_render(job: dict[str, Any]) -> dict[str, Any]:
    try:
        from generator.pipeline import render_scene

        lights = {}
        if job.get("light_files") or job.get("light_names"):
            # the default lights, as `make dataset` renders, the grid's other named lights and its files
            from generator.pipeline import default_lights

            lights = {"lights": default_lights() + job.get("light_names", []) + job.get("light_files", [])}
        render_scene(job["scene"], job["profile"], job["data"], job.get("jobs", 1), **lights)
        scene = layout.scene_dir(job["data"], job["profile"], job["scene"])
        if not layout.is_complete(scene):
            raise RuntimeError(f"rendering finished but {scene}/dataset.json does not say complete")
        return {"status": "ok"}
    except Exception as exc:  # recorded, reported; the grid goes on
        return {"status": "failed", "error": _cause(exc), "traceback": traceback.format_exc()}


def _execute_method(job: dict[str, Any]) -> dict[str, Any]:
    """Run the adapter once when the predictions are not reusable, then score every missing (protocol,
    configuration) result from them; finished results are left as they are."""
    from baselines_adapters.registry import get_adapter

    from .predictions import PredictionFolder
    from .score import score

    version = "unknown"
    todo = missing_results(job)
    try:
        adapter = get_adapter(job["method"])
        version = adapter.version
        scene = Path(job["scene_dir"])
        if not layout.is_complete(scene):
            raise UserError(f"dataset {scene} is missing or incomplete (render it: make dataset)")
        pdir = Path(job["pred_dir"])
        if not _predictions_reusable(pdir, job, version, _stored_versions(job, todo)):
            adapter.run(scene, job["train"], job["tests"], job["seed"], job["profile"], pdir, job["runs_dir"])
        PredictionFolder(pdir).meta()
    except Exception as exc:
        record_failure(job, _cause(exc), traceback.format_exc(), version)
        return {"status": "failed", "error": _cause(exc)}
    failures = []
    for protocol, test, path in todo:
        try:
            res = score(scene, pdir, job["train"], test, protocol, job["lpips_net"], job["profile"],
                        scene_name=job["scene"])
            write_result(path, res)
        except Exception as exc:
            write_result(path, failed_result(_identity(job, test, protocol, version), _cause(exc)))
            atomic_write_text(Path(path).with_name("error.log"), traceback.format_exc())
            failures.append(_cause(exc))
    return {"status": "failed", "error": "; ".join(dict.fromkeys(failures))} if failures else {"status": "ok"}


def _stored_versions(job: dict[str, Any], todo: list[tuple[str, str, str]]) -> set[str] | None:
    """The adapter version shared by the finished results of every configuration the job still has to score
    under some protocol, when each such configuration has one (only other protocols are missing): the
    version of the predictions those results were scored from. None otherwise."""
    versions: set[str] = set()
    for test in dict.fromkeys(t for _, t, _ in todo):
        found = set()
        for protocol, t, path in job_results(job):
            if t == test and is_finished(path, protocol, job["lpips_net"]):
                found.add(read_result(path)["adapter_version"])
        if len(found) != 1:
            return None
        versions |= found
    return versions if len(versions) == 1 else None


def _predictions_reusable(pdir: Path, job: dict[str, Any], version: str, stored: set[str] | None = None) -> bool:
    """The predictions folder holds this method's, seed's and test lights' predictions at the adapter's
    version, or at the version the job's stored results were scored from (``stored``: another protocol is
    scored from the same predictions, never from remade ones)."""
    import json

    meta = pdir / "meta.json"
    if not meta.is_file():
        return False
    try:
        m = json.loads(meta.read_text())
    except json.JSONDecodeError:
        return False
    return (m.get("method") == job["method"] and (m.get("version") == version or m.get("version") in (stored or ()))
            and m.get("seed") == job["seed"] and set(job["tests"]) <= set(m.get("test_lights") or job["tests"]))


# --------------------------------------------------------------------------------------------- executors

def _run_local(fn: Callable, jobs: list[dict], workers: int) -> Iterator[tuple[dict, dict]]:
    if workers <= 1 or len(jobs) <= 1:
        for job in jobs:
            yield job, fn(job)
        return
    # several workers share the cores: their idle OpenMP threads sleep rather than spin (lumibench/threads.py);
    # the spawned workers read it from the environment they inherit
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    ctx = multiprocessing.get_context("spawn")  # torch and fork do not mix
    with cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
        futures = {pool.submit(fn, job): job for job in jobs}
        for fut in cf.as_completed(futures):
            job = futures[fut]
            try:
                yield job, fut.result()
            except Exception as exc:  # a worker died (e.g. out of memory): record it, carry on
                yield job, {"status": "failed", "error": f"worker process failed: {_cause(exc)}", "lost": True}


def _ray_address_problem(address: str) -> str | None:
    """Why RAY_ADDRESS cannot name a reachable Ray cluster (a one-line message), or None when it may:
    ray.init retries an unreachable head for minutes, so a host:port refusing a TCP connection is refused
    here first."""
    import importlib.util
    import socket

    if address in ("auto", "local"):
        return None
    rest = address
    if address.startswith("ray://"):
        if importlib.util.find_spec("grpc") is None:
            return (f"RAY_ADDRESS={address} goes through the Ray client, which needs pip install 'ray[client]' "
                    f"(or run on a node of the cluster with RAY_ADDRESS=<head>:6379)")
        rest = address[len("ray://"):]
    host, sep, port = rest.rstrip("/").rpartition(":")
    if not sep or not port.isdigit() or "/" in rest.rstrip("/"):
        return None  # not host:port: let Ray say what it makes of it
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=5).close()
    except OSError as exc:
        return (f"cannot reach the Ray cluster at RAY_ADDRESS={address} ({type(exc).__name__}: "
                f"{exc.strerror or exc}): start it (ray start --head --port=6379 on the head) or point RAY_ADDRESS "
                f"at its head's host:port (unset: a local Ray instance)")
    return None


def _ray_token_hint(address: str | None) -> str:
    """The likely cause when a cluster refuses a driver that does not send Ray's auth token: Ray (2.60 here)
    enables token authentication on a cluster started where ~/.ray/auth_token exists, and a driver sends
    the token only with RAY_AUTH_MODE=token."""
    if not address or os.environ.get("RAY_AUTH_MODE", "").lower() == "token":
        return ""
    return ("; if its nodes use token authentication (Ray's default where ~/.ray/auth_token exists), set "
            "RAY_AUTH_MODE=token here, with the cluster's token in ~/.ray/auth_token or RAY_AUTH_TOKEN")


def ray_connect(workers: int = 1) -> None:
    """Connect to the cluster at RAY_ADDRESS, or start a local Ray instance with ``workers`` CPUs when it is
    unset; nothing when Ray is initialised already (e.g. by the caller). One-line UserError otherwise."""
    import logging

    try:
        import ray
    except ImportError:
        raise UserError("--executor ray needs ray: pip install 'ray[default]' (or use --executor local)") from None
    if ray.is_initialized():
        return
    address = os.environ.get("RAY_ADDRESS") or None
    where = f"the Ray cluster at RAY_ADDRESS={address}" if address else "a local Ray instance"
    problem = _ray_address_problem(address) if address else None
    if problem:
        raise UserError(problem)
    try:
        # the workers wait passively, as `python -m benchmark` makes the local ones (benchmark/__main__.py)
        ray.init(address=address, ignore_reinit_error=True, include_dashboard=False, log_to_driver=False,
                 logging_level=logging.WARNING, num_cpus=None if address else max(workers, 1),
                 runtime_env={"env_vars": {"OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}})
    except Exception as exc:
        cause = " ".join(str(exc).split())[:300]
        raise UserError(f"cannot connect to {where}: {type(exc).__name__}: {cause}{_ray_token_hint(address)}") from None
    if ray.cluster_resources().get("CPU", 0) < 1:
        print(f"warning: {where} has no CPUs yet; the jobs (1 CPU each) wait until a node with CPUs joins "
              f"(ray start --address=<head>:<port> --num-cpus=N)", flush=True)


def _ray_task(fn: Callable, job: dict[str, Any], cwd: str) -> dict[str, Any]:
    """One job on a Ray worker. It runs from the driver's working directory, so that relative paths (DATA,
    RUNS, RESULTS, as `make eval` passes them) name the same files as on the driver: every node needs the
    repository and the data, runs and results folders at the driver's paths. The outcome says where it ran."""
    import socket

    import ray

    where = {"node": ray.get_runtime_context().get_node_id(), "host": socket.gethostname(), "pid": os.getpid()}
    try:
        os.chdir(cwd)
    except OSError as exc:
        return {"status": "failed", "lost": True, **where,
                "error": f"Ray node {where['host']} cannot enter the driver's directory {cwd} ({exc.strerror}): every "
                         f"node needs the repository and the data, runs and results folders at the driver's paths"}
    return {**fn(job), **where}


def _run_ray(fn: Callable, jobs: list[dict], workers: int) -> Iterator[tuple[dict, dict]]:
    ray_connect(workers)
    import ray

    remote = ray.remote(num_cpus=1, max_retries=0)(_ray_task)
    cwd = os.getcwd()
    pending = {remote.remote(fn, job, cwd): job for job in jobs}
    while pending:
        done, _ = ray.wait(list(pending), num_returns=1)
        for ref in done:
            job = pending.pop(ref)
            try:
                yield job, ray.get(ref)
            except Exception as exc:
                yield job, {"status": "failed", "error": f"ray task failed: {_cause(exc)}", "lost": True}


def placement_summary(outcomes: list[tuple[dict, dict]]) -> str | None:
    """One line: how many jobs ran on which Ray node (node id prefix, host), or None when none says."""
    counts: dict[tuple[str, str], int] = {}
    for _, outcome in outcomes:
        if outcome.get("node"):
            key = (outcome["node"][:8], outcome.get("host", "?"))
            counts[key] = counts.get(key, 0) + 1
    if not counts:
        return None
    nodes = ", ".join(f"node {n} on {h}: {c}" for (n, h), c in sorted(counts.items()))
    return f"ray: {sum(counts.values())} jobs on {len(counts)} node{'s' if len(counts) > 1 else ''} ({nodes})"


def run_jobs(jobs: list[dict], executor: str = "local", workers: int = 1, description: str = "jobs",
             quiet: bool = False) -> list[tuple[dict, dict]]:
    """Run ``jobs`` with a progress bar; return (job, outcome) pairs. Lost workers are recorded as failures."""
    if executor not in EXECUTORS:
        raise UserError(f"unknown executor '{executor}' (known: {', '.join(EXECUTORS)})")
    if not jobs:
        return []
    threads = 1 if workers > 1 or executor == "ray" else None  # a Ray task holds one CPU
    jobs = [dict(job, threads=threads) for job in jobs]
    if executor == "ray":
        ray_connect(workers)  # before the progress bar: a refused address is one line, not a stalled bar
    runner = _run_local if executor == "local" else _run_ray
    outcomes = []
    for job, outcome in track(runner(execute, jobs, workers), total=len(jobs), description=description, unit="jobs",
                              disable=quiet, label=lambda done: f"{job_label(done[0])} {done[1]['status']}"):
        if outcome.get("lost") and job["kind"] == "method":
            record_failure(job, outcome["error"])
        outcomes.append((job, outcome))
    summary = placement_summary(outcomes) if executor == "ray" and not quiet else None
    if summary:
        print(summary, flush=True)
    return outcomes


@dataclass
class GridReport:
    rendered: list[tuple[dict, dict]]
    executed: list[tuple[dict, dict]]
    skipped: list[dict]

    @property
    def failed(self) -> list[tuple[dict, dict]]:
        return [(j, o) for j, o in self.rendered + self.executed if o["status"] != "ok"]


def run_grid(config: BenchmarkConfig, paths: Paths, executor: str = "local", workers: int = 1,
             render: bool = True, quiet: bool = False) -> GridReport:
    """Render missing scenes, then run every unfinished method job; return what was done."""
    rjobs = render_jobs(config, paths)
    specs = known_scenes()
    unknown = [j["scene"] for j in rjobs if j["scene"] not in specs]
    if unknown:
        raise UserError(f"{config.source}: scene(s) {', '.join(unknown)} neither rendered under "
                        f"{paths.data}/{paths.profile} nor specified in configs/scenes/ (known: {', '.join(specs)})")
    if rjobs and not render:
        missing = ", ".join(j["scene"] for j in rjobs)
        raise UserError(f"scenes not rendered under {paths.data}/{paths.profile}: {missing} (make dataset, "
                        f"or drop --no-render)")
    if len(rjobs) == 1 and executor == "local":  # one scene: let the generator use every worker itself
        rjobs, workers_r = [dict(rjobs[0], jobs=workers)], 1
    else:
        workers_r = workers
    check_scene_lights(config, paths)
    rendered = run_jobs(rjobs, executor, workers_r, "rendering scenes", quiet)
    for job, outcome in rendered:
        if outcome["status"] != "ok":
            log = render_log_path(paths.out, job)
            atomic_write_text(log, outcome.get("traceback") or f"{outcome.get('error')}\n")
            outcome["log"] = str(log)
            print(f"warning: {job_label(job)} failed: {outcome['error']} (log: {log})", flush=True)
    mjobs = method_jobs(config, paths)
    todo = [j for j in mjobs if not job_finished(j)]
    skipped = [j for j in mjobs if j not in todo]
    executed = run_jobs(todo, executor, workers, "method jobs", quiet)
    return GridReport(rendered, executed, skipped)


def iter_results(jobs: Iterable[dict]) -> Iterator[Path]:
    """Every result file of ``jobs``, all protocols."""
    for job in jobs:
        for _, _, p in job_results(job):
            yield Path(p)


def stored_results(out: Path) -> list[Path]:
    """Every result file stored under ``out``/runs (any method, scene, configuration, seed, protocol), sorted.

    Why the tables are built from these and not from the grid that just ran: results/<profile>/ is the
    profile's published record, filled over several grids and sessions (one seed today, another light
    tomorrow). Building the tables from the last grid's jobs alone would overwrite the published tables
    with a subset of them. A stored result a user no longer wants is removed by deleting its file."""
    from .protocol import PROTOCOLS
    from .results import result_filename

    names = {result_filename(p) for p in PROTOCOLS}
    root = Path(out) / "runs"
    return sorted(p for p in root.rglob("results*.json") if p.name in names and p.is_file()) if root.is_dir() else []
