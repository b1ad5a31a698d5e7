"""Progress with rate and ETA for long work: a rich bar on a terminal, plain lines in a log.

A grid run as `make eval ... > grid.log 2>&1 &` (or under a batch scheduler) has no terminal, and rich draws
its bar there only once, when the work ends: nine hours of a `small` grid with an empty log. So where stderr is
not a terminal, :func:`make_progress` returns :class:`LineProgress`, which prints one line when a task starts,
then at most one line per ``LINE_INTERVAL_S`` as it advances, and always the line that completes it.
"""
from __future__ import annotations

import sys
import time
from typing import Any, Callable, Iterable, Iterator, TypeVar

from rich.console import Console
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                           TimeRemainingColumn)

T = TypeVar("T")

LINE_INTERVAL_S = 30.0  # a line per half minute: 10-20 for a `small` stage 1 (5-10 min), one per grid job


def make_progress(disable: bool = False) -> Progress | "LineProgress":
    """A progress display on stderr: description, bar, n/total, rate, elapsed, ETA (rich on a terminal, plain
    lines otherwise)."""
    console = Console(file=sys.stderr)
    if not disable and not console.is_terminal:
        return LineProgress()
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("[cyan]{task.fields[rate]}"),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        console=console,
        disable=disable,
        transient=False,
    )


def _hms(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


class _LineTask:
    def __init__(self, description: str, total: float | None, completed: float, fields: dict[str, Any]):
        self.description, self.total, self.completed, self.fields = description, total, completed, fields
        self.start_completed = completed
        self.t0 = time.monotonic()
        self.last_line = self.t0

    @property
    def speed(self) -> float | None:
        dt = time.monotonic() - self.t0
        done = self.completed - self.start_completed
        return done / dt if dt > 0 and done > 0 else None

    def line(self) -> str:
        elapsed = time.monotonic() - self.t0
        of = f"/{self.total:g}" if self.total is not None else ""
        parts = [f"{self.description}: {self.completed:g}{of}"]
        if self.fields.get("rate"):
            parts.append(str(self.fields["rate"]))
        parts.append(f"{_hms(elapsed)} elapsed")
        speed = self.speed
        if self.total is not None and speed:
            parts.append(f"ETA {_hms(max(self.total - self.completed, 0) / speed)}")
        return ", ".join(parts)


class LineProgress:
    """The part of rich's Progress that our loops use (add_task, update, tasks[i].speed, a context manager),
    printing plain lines to stderr: the start, then at most one per ``interval`` seconds, and the end."""

    def __init__(self, interval: float | None = None):
        self.interval = LINE_INTERVAL_S if interval is None else interval
        self.tasks: list[_LineTask] = []

    def __enter__(self) -> "LineProgress":
        return self

    def __exit__(self, *exc) -> None:
        return None

    def _print(self, task: _LineTask) -> None:
        print(task.line(), file=sys.stderr, flush=True)
        task.last_line = time.monotonic()

    def add_task(self, description: str, total: float | None = None, completed: float = 0, **fields: Any) -> int:
        task = _LineTask(description, total, completed, fields)
        self.tasks.append(task)
        self._print(task)
        return len(self.tasks) - 1

    def update(self, task_id: int, *, advance: float | None = None, completed: float | None = None,
               description: str | None = None, **fields: Any) -> None:
        task = self.tasks[task_id]
        if completed is not None:
            task.completed = completed
        if advance is not None:
            task.completed += advance
        if description is not None:
            task.description = description
        task.fields.update(fields)
        finished = task.total is not None and task.completed >= task.total
        if finished or time.monotonic() - task.last_line >= self.interval:
            self._print(task)


def track(items: Iterable[T], total: int | None = None, description: str = "working",
          unit: str = "it", disable: bool = False, label: Callable[[T], str] | None = None) -> Iterator[T]:
    """Iterate over ``items`` with a progress display showing rate (unit/s) and ETA; ``label(item)``, when
    given, names the item just finished beside the description (which grid job ended, and how)."""
    if total is None:
        try:
            total = len(items)  # type: ignore[arg-type]
        except TypeError:
            total = None
    with make_progress(disable) as prog:
        task = prog.add_task(description, total=total, rate="")
        t0 = time.monotonic()
        for n, item in enumerate(items, 1):
            yield item
            speed = n / max(time.monotonic() - t0, 1e-9)
            extra = {"description": f"{description} (last: {label(item)})"} if label is not None else {}
            prog.update(task, advance=1, rate=_rate(speed, unit), **extra)


def _rate(speed: float | None, unit: str) -> str:
    """'12.5 it/s', or for work slower than one a second (grid jobs, trainings) '312 s/job'."""
    if not speed:
        return ""
    return f"{speed:.2f} {unit}/s" if speed >= 1 else f"{1 / speed:.0f} s/{unit.rstrip('s') or unit}"
