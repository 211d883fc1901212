"""Truth written beside every render: `<name>.png`, `<name>.json` (everything small) and `<name>.npz` (arrays).

A truth is a flat dict: numpy arrays at the top level go to the npz (corners, depth maps, object points); all
other values, nested dicts and lists included, go to the JSON. Files are written under temporary names and
renamed, so a folder never holds a half-written render.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dstereo.errors import DstereoError
from dstereo.io.atomic_files import replace_atomically
from dstereo.io.json_files import jsonable
from dstereo.models.camera import Camera
from dstereo.models.distortion import COEFF_NAMES, FISHEYE_SLOTS, PRESETS


def camera_truth(camera: Camera) -> dict:
    """JSON-ready intrinsics: fx, fy, cx, cy (px), distortion in OpenCV order, image size (width, height); a
    fisheye camera adds `model: fisheye` and its coefficients are cv2.fisheye's k1..k4 (then four zeros)."""
    fx, fy, cx, cy = (float(v) for v in np.asarray(camera.k))
    fish = camera.lens == "fisheye"
    return {
        "fx": fx, "fy": fy, "cx": cx, "cy": cy,
        "coeffs": [float(v) for v in np.asarray(camera.dist.coeffs)],
        "coeff_names": list(FISHEYE_SLOTS if fish else COEFF_NAMES),
        "image_size": [int(v) for v in camera.image_size],
    } | ({"model": "fisheye"} if fish else {})


def camera_from_truth(d: dict) -> Camera:
    free = PRESETS["fisheye"] if d.get("model") == "fisheye" else PRESETS["default"]
    return Camera.create(d["fx"], d["fy"], d["cx"], d["cy"], d["coeffs"], free, image_size=tuple(d["image_size"]))


def split_truth(truth: dict) -> tuple[dict, dict[str, np.ndarray]]:
    """(JSON part, array part) of a truth dict."""
    arrays = {k: v for k, v in truth.items() if isinstance(v, np.ndarray)}
    meta = {k: jsonable(v) for k, v in truth.items() if k not in arrays}
    meta["arrays"] = sorted(arrays)
    return meta, arrays


def write_render(folder, image: np.ndarray | None, truth: dict, name: str = "render") -> Path:
    """Write `<folder>/<name>.png` (8-bit, via cv2; skipped when `image` is None), `.json` and `.npz`."""
    import cv2

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    meta, arrays = split_truth(truth)
    if image is not None:
        if image.dtype != np.uint8:
            raise DstereoError(f"write_render {folder / name}.png: image dtype {image.dtype}; expected uint8")

        def write_png(p):
            if not cv2.imwrite(str(p), image):
                raise DstereoError(f"write_render: cv2 could not write {p}; check the folder is writable")

        replace_atomically(folder / f"{name}.png", write_png)
    replace_atomically(folder / f"{name}.json", lambda p: p.write_text(json.dumps(meta, indent=1)))

    def write_npz(p):
        with open(p, "wb") as f:
            np.savez_compressed(f, **arrays)

    replace_atomically(folder / f"{name}.npz", write_npz)
    return folder / name


def read_truth(folder, name: str = "render") -> dict:
    """The truth dict written by `write_render` (JSON values plus npz arrays)."""
    folder = Path(folder)
    meta_path = folder / f"{name}.json"
    if not meta_path.exists():
        raise DstereoError(f"read_truth: {meta_path} does not exist; render it first")
    truth = json.loads(meta_path.read_text())
    with np.load(folder / f"{name}.npz") as npz:
        truth.update({k: npz[k] for k in npz.files})
    truth.pop("arrays", None)
    return truth
