"""Finished frames kept on disk as they complete, so a stop (Ctrl-C, a crash, a lost node) loses nothing.

Layout, beside the results folder OUT:

    OUT.partial/inputs.json          the fingerprint of the run (calibration bytes, frame files, settings)
    OUT.partial/frames/<n>.npz       one finished frame's arrays
    OUT.partial/frames/<n>.json      its other values; written last, so a frame counts only once both exist

Every file is written under a temporary name and renamed (atomic on one file system): a frame is there whole
or not at all. `--resume` reuses the frames only when the fingerprint is the same; the folder is removed once
the results folder is in place.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np

from dstereo.errors import DstereoError
from dstereo.io.atomic_files import replace_atomically
from dstereo.io.json_files import json_default  # numpy/Path -> JSON, exact for float64


def partial_folder(out: str | Path) -> Path:
    out = Path(out)
    return out.with_name(out.name + ".partial")


def fingerprint(files_hashed, files_stat, settings) -> str:
    """sha256 over the bytes of `files_hashed` (the calibration: small, and an edit must count), the name, size
    and modification time of `files_stat` (the frames: too many to read twice) and the text of `settings`."""
    h = hashlib.sha256()
    for path in files_hashed:
        if path is not None:
            h.update(str(Path(path).name).encode())
            h.update(Path(path).read_bytes())
    for path in files_stat:
        st = Path(path).stat()
        h.update(f"{Path(path).absolute()}|{st.st_size}|{st.st_mtime_ns}\n".encode())
    h.update(repr(settings).encode())
    return h.hexdigest()


class PartialStore:
    """OUT.partial (module docstring). `open` refuses a folder left by another run unless `resume` (same
    fingerprint) or `force` (start afresh)."""

    def __init__(self, out: str | Path, key: str):
        self.folder, self.key = partial_folder(out), key
        self.frames = self.folder / "frames"

    def open(self, resume: bool, force: bool) -> "PartialStore":
        inputs = self.folder / "inputs.json"
        if self.folder.exists() and not resume:
            if not force:
                raise DstereoError(f"{self.folder} holds the finished frames of an earlier run; pass `resume` to "
                                   "continue it, or `force` to start afresh (its frames are deleted)")
            shutil.rmtree(self.folder)
        if self.folder.exists():
            try:
                found = json.loads(inputs.read_text())["fingerprint"]
            except (OSError, ValueError, KeyError):
                found = None
            if found != self.key:
                raise DstereoError(f"`resume`: {self.folder} was made from other inputs or settings (calibration, "
                                   "frame files or options differ); rerun with the same ones, or pass `force` "
                                   "without `resume` to start afresh")
        self.frames.mkdir(parents=True, exist_ok=True)
        if not inputs.exists():
            replace_atomically(inputs, lambda p: p.write_text(json.dumps({"fingerprint": self.key}) + "\n"))
        return self

    def save(self, name: str, arrays: dict, meta: dict) -> None:
        def write_npz(path: Path):
            with path.open("wb") as fh:
                np.savez(fh, **arrays)

        replace_atomically(self.frames / f"{name}.npz", write_npz)
        replace_atomically(self.frames / f"{name}.json", lambda p: p.write_text(json.dumps(meta, default=json_default)))

    def load(self, name: str) -> tuple[dict, dict] | None:
        """(arrays, meta) of a stored frame, or None when it is not (wholly) there."""
        meta_path, npz_path = self.frames / f"{name}.json", self.frames / f"{name}.npz"
        if not (meta_path.exists() and npz_path.exists()):
            return None
        try:
            meta = json.loads(meta_path.read_text())
            with np.load(npz_path, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
        except (OSError, ValueError) as exc:
            raise DstereoError(f"`resume`: {npz_path} cannot be read ({exc}); delete it (and its .json) to "
                               "recompute that frame") from exc
        return arrays, meta

    def count(self) -> int:
        return len(list(self.frames.glob("*.json"))) if self.frames.exists() else 0

    def remove(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)
