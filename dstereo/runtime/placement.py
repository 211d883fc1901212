"""Where a command's blocks of independent work run, set around the command from outside (as the server and the
compile cache are): in this process (the default), or on a Dask cluster (`tasks.FrameRunner`: a local one of N
processes, or a running one at an address), and where finished blocks are kept so that a stopped run resumes.

`dstereo calibrate --workers N / --scheduler ADDRESS / --resume` sets it (commands/calibrate_placement.py); the
subset runner (calib/subset_runs.py) reads it. The job between them is unchanged: what it computes does not depend
on where.
"""

from __future__ import annotations

import contextlib
import contextvars
from dataclasses import dataclass
from typing import Callable


@dataclass(frozen=True)
class Placement:
    """`runner`: a `tasks.FrameRunner` (None, or one that is not parallel: here, one block after another).
    `store`: key -> an opened store of finished blocks (`io.partial_store.PartialStore`: save(name, arrays, meta),
    load(name)), the key naming the run's inputs (a store made from other inputs is refused, not reused); None:
    nothing kept."""

    runner: object | None = None
    store: Callable[[str], object] | None = None

    @property
    def parallel(self) -> bool:
        return self.runner is not None and bool(getattr(self.runner, "parallel", False))


_current: contextvars.ContextVar[Placement] = contextvars.ContextVar("dstereo_placement", default=Placement())


def current() -> Placement:
    return _current.get()


@contextlib.contextmanager
def placed(placement: Placement):
    """Run the enclosed work with `placement` (this thread and the contexts copied from it)."""
    token = _current.set(placement)
    try:
        yield placement
    finally:
        _current.reset(token)
