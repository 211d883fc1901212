"""One frame of a recession sequence (`dstereo.io.sequence_files.discover` finds them on disk)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Frame:
    """One stereo pair of the sequence: its key (the name without the side word), files and time (s)."""

    key: str
    left: Path
    right: Path
    time_s: float
