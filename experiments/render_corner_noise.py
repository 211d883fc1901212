"""How far OpenCV's detected corners lie from the true ones on the ring rig's renders (`synth.multiview`): the
renderer's realistic corner noise, the figure `experiments/rig_acceptance.py --noise` takes (issue 29).

    python -m experiments.render_corner_noise [PATTERN ...]      # default 9x6 13x10 (20 mm squares)

Renders `multiview_set(3, 10, seed=5)` of each board, detects every image with `io.corners.detect_folder` (no
cache) and prints the per-coordinate RMS, mean and largest error of the detected corners against the truth (a view
whose detection runs from the opposite board corner is compared in that order).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np


def measure(pattern: tuple[int, int], folder: Path) -> str:
    from dstereo.io.corners import detect_folder
    from dstereo.synth import multiview_set, write_multiview_set
    from dstereo.synth.board import Board

    mset = multiview_set(3, 10, seed=5, board=Board(pattern, 20.0, 20.0))
    root = write_multiview_set(folder, mset, force=True)
    truth, errors = mset.truth["corners"], []
    for k, name in enumerate(mset.rig.names):
        det = detect_folder(root / name, pattern, 20.0, use_cache=False)
        for f, frame in enumerate(mset.frame_names):
            q = det.corners.get(frame + ".png")
            if q is not None and np.isfinite(truth[f, k]).all():
                errors.append(min((q - truth[f, k], q[::-1] - truth[f, k]), key=lambda d: np.abs(d).max()))
    e = np.concatenate(errors)
    return (f"board {pattern[0]}x{pattern[1]}: {len(errors)} views, per-coordinate RMS {np.sqrt(np.mean(e ** 2)):.4f} "
            f"px, mean ({e[:, 0].mean():+.4f}, {e[:, 1].mean():+.4f}) px, largest {np.abs(e).max():.3f} px")


if __name__ == "__main__":
    patterns = [tuple(int(v) for v in a.split("x")) for a in sys.argv[1:]] or [(9, 6), (13, 10)]
    with tempfile.TemporaryDirectory() as tmp:
        for p in patterns:
            print(measure(p, Path(tmp) / f"{p[0]}x{p[1]}"), flush=True)
