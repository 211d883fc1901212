"""Write whole synthetic data sets to a folder (thesis layout: images_left/, images_right/), truth beside each image;
a multi-camera set in the `--cameras` layout (one subfolder per camera, truth at the top).

A set is written into a temporary sibling folder and renamed into place at the end, so an interrupted write
never leaves a half-written folder; an existing folder is replaced only with `force=True`.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

from dstereo.errors import DstereoError
from dstereo.synth.multiview import MultiviewSet
from dstereo.synth.scenes import CalibrationSet, StereoRender
from dstereo.synth.truth import write_render

INDEX_KEYS = ("frame", "time_s", "recession_stagnation_mm")


def _write_folder(folder, force: bool, fill) -> Path:
    folder = Path(folder)
    if folder.exists() and not force:
        raise DstereoError(f"{folder} already exists; choose another folder or pass force=True to replace it")
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        fill(tmp)
        if folder.exists():
            shutil.rmtree(folder)
        tmp.rename(folder)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    return folder


def write_calibration_set(folder, cset: CalibrationSet, force: bool = False) -> Path:
    """`images_left/left_NN.png` (+ .json/.npz truth), `images_right/right_NN.*` for a rig, and `truth.*`."""

    def fill(tmp: Path):
        sides = [("left", cset.left, cset.views_left)]
        if cset.right is not None:
            sides.append(("right", cset.right, cset.views_right))
        for side, images, views in sides:
            for i, (image, truth) in enumerate(zip(images, views)):
                write_render(tmp / f"images_{side}", image, truth, name=f"{side}_{i:02d}")
        write_render(tmp, None, cset.truth, name="truth")

    return _write_folder(folder, force, fill)


def write_stereo_renders(folder, renders: list[StereoRender], force: bool = False) -> Path:
    """`images_left/left_NNN.*` and `images_right/right_NNN.*` for each pair (a sample pair or a sequence), and
    `index.json` listing the pairs with their timestamps and stagnation-point recession where they have them."""

    def fill(tmp: Path):
        index = []
        for i, pair in enumerate(renders):
            write_render(tmp / "images_left", pair.left, pair.truth_left, name=f"left_{i:03d}")
            write_render(tmp / "images_right", pair.right, pair.truth_right, name=f"right_{i:03d}")
            entry = {k: pair.truth_left[k] for k in INDEX_KEYS if k in pair.truth_left}
            index.append({"left": f"images_left/left_{i:03d}.png", "right": f"images_right/right_{i:03d}.png"} | entry)
        (tmp / "index.json").write_text(json.dumps(index, indent=1))

    return _write_folder(folder, force, fill)


def write_recession_sequence(folder, renders: list[StereoRender], force: bool = False) -> Path:
    """A recession sequence as `dstereo recession` reads it: `images_left/left_NNN.png`, `images_right/right_NNN.png`
    (truth beside each), `timestamps.csv` (`name,time_s`, name = the left image's file name) and `index.json`."""

    def fill(tmp: Path):
        lines = ["name,time_s"]
        index = []
        for i, pair in enumerate(renders):
            write_render(tmp / "images_left", pair.left, pair.truth_left, name=f"left_{i:03d}")
            write_render(tmp / "images_right", pair.right, pair.truth_right, name=f"right_{i:03d}")
            if "time_s" not in pair.truth_left:
                raise DstereoError(f"render {i} has no time_s in its truth; render it with recession_sequence")
            lines.append(f"left_{i:03d}.png,{pair.truth_left['time_s']!r}")
            entry = {k: pair.truth_left[k] for k in INDEX_KEYS if k in pair.truth_left}
            index.append({"left": f"images_left/left_{i:03d}.png", "right": f"images_right/right_{i:03d}.png"} | entry)
        (tmp / "timestamps.csv").write_text("\n".join(lines) + "\n")
        (tmp / "index.json").write_text(json.dumps(index, indent=1))

    return _write_folder(folder, force, fill)


def write_multiview_set(folder, mset: MultiviewSet, force: bool = False) -> Path:
    """`<camera>/<frame>.png` for every frame a camera sees (no file where it does not: the `--cameras` layout)
    and `truth.json` / `truth.npz` at the top, so the camera folders hold images only."""
    import cv2

    def fill(tmp: Path):
        for name, row in zip(mset.rig.names, mset.images):
            (tmp / name).mkdir()
            for frame, image in zip(mset.frame_names, row):
                if image is not None and not cv2.imwrite(str(tmp / name / f"{frame}.png"), image):
                    raise DstereoError(f"write_multiview_set: cv2 could not write {tmp / name / frame}.png")
        write_render(tmp, None, mset.truth, name="truth")

    return _write_folder(folder, force, fill)
