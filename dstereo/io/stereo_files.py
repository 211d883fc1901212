"""Stereo pairs and stereo calibration files at the OpenCV edge.

- `detect_pairs`: board corners in both cameras' images, pairs matched by name order; a pair where either
  image lacks the full board is listed in `dropped` with the reason, never dropped silently.
- `write_stereo_yml`: OpenCV FileStorage YAML with the keys of OpenCV's stereo_calib sample (M1 D1 M2 D2 R T)
  plus E, F and `imageSize` [w, h] (`imageSize2` when the right camera's differs), readable by
  `dstereo.io.calib_files.read_stereo_calibration`.
- `write_stereo_json`, `write_stereo_corners` (`left/<file>`, `right/<file>`, `object_points`).
Every file is written under a temporary name and renamed, so none is ever left half-written.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
import numpy as np

from dstereo.errors import DstereoError
from dstereo.io.corners import Detection, detect_folder, list_images

@dataclass(frozen=True)
class DroppedPair:
    left: str
    right: str
    reason: str


@dataclass
class StereoDetection:
    """Corners of both cameras and the stereo pairs (left name, right name) that show the board in both."""

    left: Detection
    right: Detection
    pairs: list[tuple[str, str]]
    dropped: list[DroppedPair] = field(default_factory=list)

    @property
    def object_points(self) -> np.ndarray:
        return self.left.object_points

    def observations(self) -> tuple[np.ndarray, np.ndarray]:
        """(V, n, 2) left and right corners of the pairs, in pair order."""
        return (np.stack([self.left.corners[a] for a, _ in self.pairs]),
                np.stack([self.right.corners[b] for _, b in self.pairs]))


def image_files(source: str | Path | list, suffix: str | None = None) -> list[Path]:
    """A folder's images (sorted by name), or an explicit sequence of image paths kept in its order."""
    if isinstance(source, (str, Path)):
        return list_images(Path(source), suffix)
    files = [Path(p) for p in source]
    missing = [str(p) for p in files if not p.is_file()]
    if missing:
        raise DstereoError(f"images: {missing[:3]} do not exist; check the image list")
    if not files:
        raise DstereoError("images: the image list is empty")
    return files


def _where(source, files: list[Path]) -> str:
    return str(source) if isinstance(source, (str, Path)) else f"the list starting {files[0]}"


def detect_pairs(left, right, pattern: tuple[int, int], square: float, suffix: str | None = None,
                 use_cache: bool = True, progress=None) -> StereoDetection:
    """Detect the board in `left` and `right` (folders or image lists) and pair the images by name order."""
    files_l, files_r = image_files(left, suffix), image_files(right, suffix)
    if len(files_l) != len(files_r):
        raise DstereoError(
            f"stereo images: {len(files_l)} left images in {_where(left, files_l)} but {len(files_r)} right images "
            f"in {_where(right, files_r)}; pairs are matched by name order, so give both cameras the same number"
        )
    det_l = detect_folder(files_l[0].parent, pattern, square, files=files_l, use_cache=use_cache, progress=progress)
    det_r = detect_folder(files_r[0].parent, pattern, square, files=files_r, use_cache=use_cache, progress=progress)
    pairs, dropped = match_pairs(det_l, det_r, [p.name for p in files_l], [p.name for p in files_r])
    if not pairs:
        raise DstereoError(
            f"stereo images: no pair shows the full {pattern[0]}x{pattern[1]} board in both cameras (left boards "
            f"in {sorted(det_l.corners) or 'none'}, right boards in {sorted(det_r.corners) or 'none'}); check that "
            "the left and right images are taken at the same moments and sort in the same order"
        )
    return StereoDetection(det_l, det_r, pairs, dropped)


def match_pairs(det_left: Detection, det_right: Detection, names_left: list[str],
                names_right: list[str]) -> tuple[list[tuple[str, str]], list[DroppedPair]]:
    """Pair the i-th left with the i-th right image; pairs missing the board on either side are dropped."""
    pairs, dropped = [], []
    for a, b in zip(names_left, names_right):
        reasons = [f"{side} {name}: {det.rejected.get(name, 'no board')}"
                   for side, name, det in (("left", a, det_left), ("right", b, det_right)) if name not in det.corners]
        if reasons:
            dropped.append(DroppedPair(a, b, "; ".join(reasons)))
        else:
            pairs.append((a, b))
    return pairs, dropped


# --- writers ---------------------------------------------------------------------------------------------------


def _replace_atomically(path: Path, write) -> Path:
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def write_stereo_yml(path, K1, D1, K2, D2, R, T, E, F, image_size: tuple[int, int],
                     image_size_right: tuple[int, int] | None = None, rms: float | None = None) -> Path:
    """OpenCV YAML with M1 D1 M2 D2 R T E F imageSize (+ imageSize2, rms). D as 1x8 rows in OpenCV's order."""
    import cv2

    def write(tmp: Path) -> None:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        if not fs.isOpened():
            raise DstereoError(f"{path}: cannot be written; check that the folder exists and is writable")
        try:
            for key, value, shape in (("M1", K1, (3, 3)), ("D1", D1, (1, -1)), ("M2", K2, (3, 3)), ("D2", D2, (1, -1)),
                                      ("R", R, (3, 3)), ("T", T, (3, 1)), ("E", E, (3, 3)), ("F", F, (3, 3))):
                fs.write(key, np.asarray(value, dtype=float).reshape(shape))
            fs.write("imageSize", np.array(image_size, dtype=np.int32).reshape(1, 2))
            if image_size_right is not None and tuple(image_size_right) != tuple(image_size):
                fs.write("imageSize2", np.array(image_size_right, dtype=np.int32).reshape(1, 2))
            if rms is not None:
                fs.write("rms", float(rms))
        finally:
            fs.release()

    return _replace_atomically(Path(path), write)


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None  # JSON has no NaN/inf
    return value


def write_json(path, data: dict) -> Path:
    """Any nest of dicts, lists, numpy arrays and scalars as indented JSON (non-finite numbers as null)."""
    text = json.dumps(_jsonable(data), indent=1)
    return _replace_atomically(Path(path), lambda tmp: tmp.write_text(text))


def write_stereo_corners(path, detection: StereoDetection) -> Path:
    """corners.npz: `left/<file>`, `right/<file>` (n, 2) px of the stereo pairs, and `object_points` (n, 3)."""
    arrays = {"object_points": detection.object_points}
    for a, b in detection.pairs:
        arrays[f"left/{a}"] = detection.left.corners[a]
        arrays[f"right/{b}"] = detection.right.corners[b]

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)

    return _replace_atomically(Path(path), write)
