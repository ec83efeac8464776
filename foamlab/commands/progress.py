"""What a long command is doing, on a terminal: stage, elapsed time and an estimate (rich).

Quiet (a no-op) when stderr is not a terminal or the command prints JSON, so pipes and
scripts get only their result. The callback has the shape fit_run and diagnose report in:
``(stage: str, fraction: float in 0..1)``.
"""

from __future__ import annotations

import contextlib
import sys
from typing import Callable, Iterator

Callback = Callable[[str, float], None]


@contextlib.contextmanager
def terminal_progress(title: str, quiet: bool = False) -> Iterator[Callback]:
    """A progress callback shown on stderr while the block runs (nothing if quiet or piped)."""
    if quiet or not sys.stderr.isatty():
        yield lambda stage, fraction: None
        return
    from rich.console import Console  # noqa: PLC0415 (keep `foamlab --help` fast)
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn  # noqa: PLC0415
    bar = Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.percentage:>3.0f} %"),
                   TimeElapsedColumn(), TextColumn("left"), TimeRemainingColumn(),
                   console=Console(stderr=True), transient=True,
                   # drawn on each report, not by rich's refresh thread: a process with one thread may
                   # fork the diagnosis's workers (analysis.parallel)
                   auto_refresh=False)
    with bar:
        task = bar.add_task(title, total=1.0)

        def report(stage: str, fraction: float) -> None:
            bar.update(task, completed=min(max(float(fraction), 0.0), 1.0), description=f"{title}: {stage}")
            bar.refresh()

        yield report
