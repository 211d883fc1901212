"""One file replaced atomically: written beside its target under a unique hidden name, then renamed over it, so a
reader never sees half a file and a failed write leaves the old one (and no temporary file) behind."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


def umask() -> int:
    """The process's umask, read without changing it where Linux shows it (/proc/self/status); elsewhere set and
    restored at once (os.umask is the only portable reader)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def follow_umask(path, folder: bool = False) -> None:
    """Give `path` the mode an ordinary open()/mkdir() would have: mkstemp and mkdtemp make 0600 files and 0700
    folders (private temporaries), which the rename would otherwise hand on to the results, whatever the umask."""
    try:
        os.chmod(path, (0o777 if folder else 0o666) & ~umask())
    except OSError:  # a file system without modes (vfat, some network mounts): the private mode is the safe one
        pass


def replace_atomically(path, write) -> Path:
    """Call `write(tmp)` on a temporary path in `path`'s folder, then rename it to `path`. The temporary name
    keeps `path`'s suffix, since cv2.FileStorage and numpy choose the format by it."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    try:
        write(Path(tmp))
        follow_umask(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
