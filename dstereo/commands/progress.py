"""Progress reporting shared by the long-running commands (calibrate, recession)."""

from __future__ import annotations

import time

import typer

from dstereo.runtime.tasks import eta_text

PLAIN_EVERY_S = 30.0  # without a terminal, a long stage prints a line with its ETA at most this often


class Reporter:
    """progress(stage, done, total) callback with `note(text)`: a line printed above the bars."""

    def __init__(self, owner: "progress_bars"):
        self.owner = owner

    def __call__(self, stage: str, done: int, total: int) -> None:
        self.owner.update(stage, done, total)

    def note(self, text: str) -> None:
        self.owner.note(text)


class progress_bars:
    """Context manager giving a progress(stage, done, total) callback (a `Reporter`): rich bars with elapsed
    time and ETA on stderr, else plain lines (a long stage's ETA every PLAIN_EVERY_S). None when quiet."""

    def __init__(self, quiet: bool):
        self.quiet, self.bars, self.tasks = quiet, None, {}
        self.started: dict[str, tuple[float, float]] = {}  # stage -> (start time, last plain line)

    def __enter__(self):
        if self.quiet:
            return None
        try:
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, \
                TimeRemainingColumn
        except ImportError:
            return Reporter(self)
        console = Console(stderr=True)
        if not console.is_terminal:
            return Reporter(self)
        self.bars = Progress(TextColumn("{task.description:<16}"), BarColumn(), MofNCompleteColumn(),
                             TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(), console=console,
                             transient=False)
        self.bars.__enter__()
        return Reporter(self)

    def update(self, stage: str, done: int, total: int) -> None:
        if self.bars is not None:
            if stage not in self.tasks:
                self.tasks[stage] = self.bars.add_task(stage, total=total)
            self.bars.update(self.tasks[stage], completed=done, total=total)
            return
        now = time.perf_counter()
        start, last = self.started.setdefault(stage, (now, now))
        if done == total and total:
            typer.echo(f"{stage}: {done}/{total} done", err=True)
        elif now - last >= PLAIN_EVERY_S:
            self.started[stage] = (start, now)
            typer.echo(f"{stage}: {done}/{total} {eta_text(done, total, now - start)}".rstrip(), err=True)

    def note(self, text: str) -> None:
        if self.bars is not None:
            self.bars.console.print(f"dstereo: {text}", markup=False, highlight=False)
        else:
            typer.echo(f"dstereo: {text}", err=True)

    def __exit__(self, *exc):
        if self.bars is not None:
            self.bars.__exit__(*exc)
        return False
