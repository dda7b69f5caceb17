"""One progress helper for the CLI: a rich progress bar behind a plain callback.

Library loops accept ``progress: Callable[[int, int], None] | None`` (done, total);
the CLI passes :func:`rich_progress` so the library never imports rich or typer.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

ProgressFn = Callable[[int, int], None]

__all__ = ["ProgressFn", "rich_progress"]


@contextlib.contextmanager
def rich_progress(description: str, enabled: bool = True) -> Iterator[ProgressFn]:
    """Yield a ``(done, total)`` callback that drives a rich bar with ETA."""
    if not enabled:
        yield lambda done, total: None
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn(), transient=False) as prog:
        task = prog.add_task(description, total=None)

        def cb(done: int, total: int) -> None:
            prog.update(task, completed=done, total=total)

        yield cb
