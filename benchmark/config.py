"""Benchmark grids (`configs/benchmark/<profile>.yaml`): scenes, train -> test configurations, methods, seeds.

Every key is validated with lumibench.config.Node, so a typo or a wrong type is reported with the file
and the key, before any job starts.

``protocols: [lumimotion, strict]`` scores every run under each protocol from the same predictions (one
result file per protocol, one table per protocol); the first is the grid's primary protocol (its charts
and image grids). ``protocol: <name>`` (older grids) means ``protocols: [<name>]``; without either key a
grid scores ``lumimotion`` only.

A configuration may name the methods that run under it (``{train: city_sharp, test: sunrise, methods:
[lumimotion, static]}``; each one of the grid's ``methods``); without ``methods`` every method of the grid
does. A stress sweep so runs each stress once instead of the whole cross product (configs/benchmark/
small_stress.yaml). A configuration may also name its seeds (a subset of the grid's ``seeds``), and the same
train -> test pair may appear twice when each names its methods and no method is in both: the published
grid runs its main methods with three seeds and the ablations with one under the same pair
(configs/benchmark/small.yaml).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from lumibench.config import Node, load_yaml
from lumibench.errors import UserError
from lumibench.layout import parse_light
from lumibench.profiles import CONFIG_DIR, available_profiles

from .protocol import PROTOCOLS
from .results import DEFAULT_PROTOCOL

LPIPS_NETS = ("vgg", "alex")


@dataclass(frozen=True)
class Configuration:
    train: str
    test: str
    methods: tuple[str, ...] = ()  # the methods that run under it; () = every method of the grid
    seeds: tuple[int, ...] = ()    # the seeds it runs; () = every seed of the grid

    def runs(self, method: str) -> bool:
        return not self.methods or method in self.methods

    def runs_seed(self, seed: int) -> bool:
        return not self.seeds or seed in self.seeds

    @property
    def label(self) -> str:
        return f"{self.train}->{self.test}"

    @property
    def slug(self) -> str:
        return f"{self.train}_to_{self.test}"


@dataclass(frozen=True)
class BenchmarkConfig:
    source: str
    profile: str
    protocols: tuple[str, ...]  # every protocol each run is scored under; the first is the primary one
    lpips_net: str
    scenes: tuple[str, ...]
    configurations: tuple[Configuration, ...]
    methods: tuple[str, ...]
    seeds: tuple[int, ...]
    light_files: tuple[str, ...] = ()  # the .hdr/.exr files the configurations name (by stem), for rendering

    @property
    def protocol(self) -> str:
        """The primary protocol (the first listed): charts and image grids use its results."""
        return self.protocols[0]

    def with_protocols(self, protocols: list[str] | None) -> "BenchmarkConfig":
        if not protocols:
            return self
        _check_protocols(protocols, "--protocols")
        return replace(self, protocols=tuple(protocols))

    def with_methods(self, methods: list[str] | None) -> "BenchmarkConfig":
        if not methods:
            return self
        _check_methods(methods, "--methods")
        return replace(self, methods=tuple(methods))

    def lights(self) -> list[str]:
        """Every light the configurations name (train and test), in order of appearance."""
        return list(dict.fromkeys(name for c in self.configurations for name in (c.train, c.test)))


def config_path(profile: str) -> Path:
    return CONFIG_DIR / "benchmark" / f"{profile}.yaml"


def load_benchmark_config(profile_or_path: str | Path) -> BenchmarkConfig:
    """Load a grid by profile name (configs/benchmark/<name>.yaml) or by path."""
    path = Path(profile_or_path)
    if path.suffix not in (".yaml", ".yml"):
        path = config_path(str(profile_or_path))
        if not path.is_file():
            known = sorted(p.stem for p in (CONFIG_DIR / "benchmark").glob("*.yaml"))
            raise UserError(f"no benchmark grid for profile '{profile_or_path}' (known: {', '.join(known)})")
    root = Node(load_yaml(path), str(path))
    root.reject_unknown(["profile", "protocols", "protocol", "lpips_net", "scenes", "configurations", "methods",
                         "seeds"])
    profile = root.get("profile", str, choices=available_profiles())
    protocols = _protocols(root)
    lpips_net = root.get("lpips_net", str, "vgg", choices=LPIPS_NETS)
    scenes = _strings(root, "scenes")
    # scene names are checked by the job grid: a rendered scene needs no spec in configs/scenes/
    known_lights = _known_lights()
    configurations, light_files, conf_seeds_nodes = [], {}, []
    methods = _strings(root, "methods")
    _check_methods(methods, f"{path}: key 'methods'")
    for node in root.children("configurations"):
        node.reject_unknown(["train", "test", "methods", "seeds"])
        names = []
        for key in ("train", "test"):
            light = node.get(key, str)
            hint = f"known: {', '.join(known_lights)}; or give a path to an .hdr or .exr file, named by its stem"
            try:
                name, file = parse_light(light)  # a file is named by its stem, never by its path
            except UserError as exc:
                raise node.error(key, f"{exc} ({hint})") from None
            if file is None and known_lights and name not in known_lights:
                raise node.error(key, f"names an unknown light '{light}' ({hint})")
            if file is not None and Path(light_files.setdefault(name, light)).expanduser() != file:
                raise node.error(key, f"light files {light_files[name]} and {light} would share the name '{name}'; "
                                      "rename one")
            names.append(name)
        train, test = names
        if train == test:
            raise node.error("test", f"must differ from the train light ('{train}')")
        only: tuple[str, ...] = ()
        if node.data.get("methods") is not None:
            only = tuple(_strings(node, "methods"))
            stray = [m for m in only if m not in methods]
            if stray:
                raise node.error("methods", f"names '{stray[0]}', which is not one of the grid's methods "
                                            f"({', '.join(methods)})")
        conf_seeds: tuple[int, ...] = ()
        if node.data.get("seeds") is not None:
            conf_seeds = tuple(node.get("seeds", list))
            if not conf_seeds or not all(isinstance(x, int) and not isinstance(x, bool) and x >= 0 for x in conf_seeds):
                raise node.error("seeds", f"must be a non-empty list of non-negative integers, got {list(conf_seeds)!r}")
            conf_seeds_nodes.append((node, conf_seeds))
        conf = Configuration(train, test, only, conf_seeds)
        for c in configurations:
            if (c.train, c.test) == (train, test) and (not c.methods or not only or set(c.methods) & set(only)):
                raise node.error("test", f"repeats the configuration {conf.label} (the same pair may appear twice "
                                         f"only when each names its methods and none is in both)")
        configurations.append(conf)
    if not configurations:
        raise root.error("configurations", "must list at least one {train, test} pair")
    idle = [m for m in methods if not any(c.runs(m) for c in configurations)]
    if idle:
        raise root.error("methods", f"lists '{idle[0]}', which no configuration runs (each configuration with "
                                    f"'methods' names the ones it runs)")
    seeds = root.get("seeds", list, [0])
    if not seeds or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in seeds):
        raise root.error("seeds", f"must be a non-empty list of non-negative integers, got {seeds!r}")
    for node, conf_seeds in conf_seeds_nodes:
        stray = [x for x in conf_seeds if x not in seeds]
        if stray:
            raise node.error("seeds", f"names seed {stray[0]}, which is not one of the grid's seeds ({seeds})")
    return BenchmarkConfig(str(path), profile, protocols, lpips_net, tuple(scenes), tuple(configurations),
                           tuple(methods), tuple(seeds), tuple(light_files.values()))


def known_scenes() -> list[str]:
    return sorted(p.stem for p in (CONFIG_DIR / "scenes").glob("*.yaml"))


def _strings(root: Node, key: str) -> list[str]:
    values = root.get(key, list)
    if not values or not all(isinstance(v, str) and v for v in values):
        raise root.error(key, f"must be a non-empty list of names, got {values!r}")
    if len(set(values)) != len(values):
        raise root.error(key, f"lists a name twice: {values!r}")
    return list(values)


def _protocols(root: Node) -> tuple[str, ...]:
    """``protocols: [a, b]``, or ``protocol: a`` (older grids), or the default; never both keys."""
    has_list = root.data.get("protocols") is not None
    if has_list and root.data.get("protocol") is not None:
        raise root.error("protocol", "cannot be given with 'protocols': list every protocol under 'protocols' "
                                     "(the first is the primary one)")
    if not has_list:
        return (root.get("protocol", str, DEFAULT_PROTOCOL, choices=list(PROTOCOLS)),)
    values = root.get("protocols", list)
    known = ", ".join(PROTOCOLS)
    if not values or not all(isinstance(v, str) for v in values):
        raise root.error("protocols", f"must be a non-empty list of protocol names ({known}), got {values!r}")
    bad = [v for v in values if v not in PROTOCOLS]
    if bad:
        raise root.error("protocols", f"names an unknown protocol '{bad[0]}' (known: {known})")
    if len(set(values)) != len(values):
        raise root.error("protocols", f"lists a protocol twice: {values!r}")
    return tuple(values)


def _check_protocols(protocols: list[str], where: str) -> None:
    bad = [p for p in protocols if p not in PROTOCOLS]
    if bad:
        raise UserError(f"{where}: unknown protocol '{bad[0]}' (known: {', '.join(PROTOCOLS)})")
    if len(set(protocols)) != len(protocols):
        raise UserError(f"{where}: lists a protocol twice: {' '.join(protocols)}")


def _check_methods(methods: list[str], where: str) -> None:
    from baselines_adapters.registry import available, is_known

    for m in methods:
        if not is_known(m):  # a registered method, or an in-project one at a budget ("lumimotion@0.25")
            raise UserError(f"{where}: unknown method '{m}' (known: {', '.join(available())})")


def _known_lights() -> list[str]:
    path = CONFIG_DIR / "lights.yaml"
    if not path.is_file():
        return []
    data = load_yaml(path)
    lights = data.get("lights") if isinstance(data, dict) else None
    return sorted(lights) if isinstance(lights, dict) else []
