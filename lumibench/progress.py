"""Progress bars with rate and ETA for long work (rich)."""
from __future__ import annotations

import sys
from typing import Iterable, Iterator, TypeVar

from rich.console import Console
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                           TimeRemainingColumn)

T = TypeVar("T")


def make_progress(disable: bool = False) -> Progress:
    """A rich Progress printing to stderr: description, bar, n/total, rate, elapsed, ETA."""
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("[cyan]{task.fields[rate]}"),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        console=Console(file=sys.stderr),
        disable=disable,
        transient=False,
    )


def track(items: Iterable[T], total: int | None = None, description: str = "working",
          unit: str = "it", disable: bool = False) -> Iterator[T]:
    """Iterate over ``items`` with a progress bar showing rate (unit/s) and ETA."""
    if total is None:
        try:
            total = len(items)  # type: ignore[arg-type]
        except TypeError:
            total = None
    with make_progress(disable) as prog:
        task = prog.add_task(description, total=total, rate="")
        for item in items:
            yield item
            speed = prog.tasks[0].speed
            prog.update(task, advance=1, rate=f"{speed:.2f} {unit}/s" if speed else "")
