"""Progress reporting shared by the long-running commands (calibrate, recession)."""

from __future__ import annotations

import typer


class progress_bars:
    """Context manager giving a progress(stage, done, total) callback: rich bars on stderr, else plain lines."""

    def __init__(self, quiet: bool):
        self.quiet, self.bars, self.tasks, self.plain = quiet, None, {}, None

    def __enter__(self):
        if self.quiet:
            return None
        try:
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
        except ImportError:
            return self._plain
        console = Console(stderr=True)
        if not console.is_terminal:
            return self._plain
        self.bars = Progress(TextColumn("{task.description:<16}"), BarColumn(), MofNCompleteColumn(),
                             TimeElapsedColumn(), console=console, transient=False)
        self.bars.__enter__()
        return self._rich

    def _rich(self, stage: str, done: int, total: int) -> None:
        if stage not in self.tasks:
            self.tasks[stage] = self.bars.add_task(stage, total=total)
        self.bars.update(self.tasks[stage], completed=done, total=total)

    def _plain(self, stage: str, done: int, total: int) -> None:
        if done == total and total:
            typer.echo(f"{stage}: {done}/{total} done", err=True)

    def __exit__(self, *exc):
        if self.bars is not None:
            self.bars.__exit__(*exc)
        return False
