"""Many frames as independent tasks: run here, on a local Dask cluster or on a cluster (`runner`), each
finished frame kept on disk at once so a stop loses nothing and `--resume` continues (`store`)."""

from dstereo.frames.runner import FrameRunner, TaskDone
from dstereo.frames.store import PartialStore, fingerprint, partial_folder

__all__ = ["FrameRunner", "PartialStore", "TaskDone", "fingerprint", "partial_folder"]
