"""YAML loading and validation whose messages name the file and the offending key."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Iterable

import yaml

from .errors import UserError

_MISSING = object()


def load_yaml(path: str | Path) -> Any:
    """Parse a YAML file; a missing file or a syntax error becomes a one-line UserError."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"config file not found: {path}")
    try:
        with open(path, "r", encoding="utf-8") as fh:
            return yaml.safe_load(fh)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise UserError(f"{path}: malformed YAML{where}: {problem}") from None


class Node:
    """A view of one mapping inside a YAML document that remembers where it is (file and key path)."""

    def __init__(self, data: Any, source: str, path: str = ""):
        self.source = source
        self.path = path
        if not isinstance(data, dict):
            raise UserError(f"{source}: '{path or '<top level>'}' must be a mapping, got {type(data).__name__}")
        self.data = data

    def where(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def error(self, key: str, msg: str) -> UserError:
        return UserError(f"{self.source}: key '{self.where(key)}' {msg}")

    def get(
        self,
        key: str,
        types: type | tuple[type, ...],
        default: Any = _MISSING,
        *,
        choices: Iterable[Any] | None = None,
        check: Callable[[Any], bool] | None = None,
        check_msg: str = "is out of range",
    ) -> Any:
        """Return ``data[key]`` checked for type, membership and a predicate; name the key on failure."""
        if key not in self.data or self.data[key] is None:
            if default is _MISSING:
                raise self.error(key, "is required")
            return default
        value = self.data[key]
        if types is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if isinstance(types, tuple) and float in types and isinstance(value, int) and not isinstance(value, bool):
            value = float(value) if int not in types else value
        if isinstance(value, bool) and bool not in (types if isinstance(types, tuple) else (types,)):
            raise self.error(key, f"must be {_type_name(types)}, got a boolean")
        if not isinstance(value, types):
            raise self.error(key, f"must be {_type_name(types)}, got {type(value).__name__} {value!r}")
        if choices is not None:
            choices = list(choices)
            if value not in choices:
                raise self.error(key, f"must be one of {', '.join(map(str, choices))}; got {value!r}")
        if check is not None and not check(value):
            raise self.error(key, f"{check_msg} (got {value!r})")
        return value

    def child(self, key: str, default: Any = _MISSING) -> "Node":
        if key not in self.data and default is not _MISSING:
            return Node(default, self.source, self.where(key))
        return Node(self.get(key, dict), self.source, self.where(key))

    def children(self, key: str) -> list["Node"]:
        items = self.get(key, list)
        return [Node(item, self.source, f"{self.where(key)}[{i}]") for i, item in enumerate(items)]

    def reject_unknown(self, allowed: Iterable[str]) -> None:
        """Unknown keys are almost always typos: refuse them rather than ignore them."""
        allowed = set(allowed)
        for key in self.data:
            if key not in allowed:
                raise self.error(str(key), f"is not a known key (known: {', '.join(sorted(allowed))})")


def _type_name(types: type | tuple[type, ...]) -> str:
    if isinstance(types, tuple):
        return " or ".join(t.__name__ for t in types)
    return {dict: "a mapping", list: "a list", str: "a string", float: "a number", int: "an integer"}.get(
        types, types.__name__
    )
