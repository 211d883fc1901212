"""One file replaced atomically: written beside its target under a unique hidden name, then renamed over it, so a
reader never sees half a file and a failed write leaves the old one (and no temporary file) behind."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


def replace_atomically(path, write) -> Path:
    """Call `write(tmp)` on a temporary path in `path`'s folder, then rename it to `path`. The temporary name
    keeps `path`'s suffix, since cv2.FileStorage and numpy choose the format by it."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    try:
        write(Path(tmp))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
