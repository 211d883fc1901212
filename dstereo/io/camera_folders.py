"""The `--cameras DIR` layout read into one observation array: DIR/<camera>/<frame image>, one subfolder per camera.

Cameras are the subfolders in sorted order (the first is the reference); frames are matched by file name across
them, a missing file or a rejected image meaning "not seen". Every detection is put in the canonical corner
order (`io.corner_order`), so a frame's corners mean the same board points in every camera.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dstereo.errors import DstereoError
from dstereo.io.corner_order import order_detection
from dstereo.io.corners import Detection, detect_folder, list_images


@dataclass
class CameraFolders:
    """cameras (K names), frames (F file names), obs (F, K, n, 2) px (NaN where not seen), visible (F, K),
    image_sizes (K (w, h)), object_points (n, 3), per-camera detections and the images renumbered."""

    cameras: list[str]
    frames: list[str]
    obs: np.ndarray
    visible: np.ndarray
    image_sizes: list[tuple[int, int]]
    object_points: np.ndarray
    detections: list[Detection]
    reversed: dict[str, list[str]]


def camera_subfolders(root: Path | str) -> list[Path]:
    root = Path(root)
    if not root.is_dir():
        raise DstereoError(f"cameras: {root} is not a folder; point it at a folder with one subfolder per camera")
    subs = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    if len(subs) < 2:
        raise DstereoError(f"cameras: {root} has {len(subs)} camera subfolder(s); a rig needs at least 2 "
                           "(DIR/<camera>/<frame>.png, frames matched by file name)")
    return subs


def read_camera_folders(root: Path | str, pattern: tuple[int, int], square: float, use_cache: bool = True,
                        suffix: str | None = None) -> CameraFolders:
    """Detect and order the corners of every camera subfolder of `root` (module docstring)."""
    subs = camera_subfolders(root)
    detections, reversed_names = [], {}
    for sub in subs:
        det, flipped = order_detection(detect_folder(sub, pattern, square, suffix=suffix, use_cache=use_cache))
        detections.append(det)
        reversed_names[sub.name] = flipped
    frames = sorted({p.name for sub in subs for p in list_images(sub, suffix)})
    n = pattern[0] * pattern[1]
    obs = np.full((len(frames), len(subs), n, 2), np.nan)
    visible = np.zeros((len(frames), len(subs)), bool)
    for k, det in enumerate(detections):
        for f, name in enumerate(frames):
            if name in det.corners:
                obs[f, k], visible[f, k] = det.corners[name], True
    return CameraFolders([s.name for s in subs], frames, obs, visible, [d.image_size for d in detections],
                         detections[0].object_points, detections, reversed_names)
