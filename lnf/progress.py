"""A progress bar for long work outside a Lightning run (decoding, long rollouts, simulating a dataset)."""
from __future__ import annotations

import contextlib
from typing import Callable, Iterator


@contextlib.contextmanager
def progress_bar(enabled: bool, total: int, description: str, unit: str = "frames") -> Iterator[Callable[[int], None]]:
    """A rich progress bar over `total` `unit`s (``advance(k)``), or a no-op when not `enabled`."""
    if not enabled:
        yield lambda k: None
        return
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TextColumn(unit),
                  TimeElapsedColumn(), TextColumn("left"), TimeRemainingColumn()) as bar:
        task = bar.add_task(description, total=total)
        yield lambda k: bar.advance(task, k)
