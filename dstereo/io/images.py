"""Images in: one file to an 8-bit BGR array, with a message naming the file when it cannot be read."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dstereo.errors import DstereoError


def read_image(path: str | Path) -> np.ndarray:
    """8-bit BGR image (grey images are expanded to three channels)."""
    import cv2

    path = Path(path)
    if path.is_dir():
        raise DstereoError(f"image {path} is a folder, not an image file; give one image file of it")
    if not path.is_file():
        raise DstereoError(f"image {path} does not exist")
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise DstereoError(f"image {path} cannot be decoded; give a PNG, JPEG or TIFF file")
    return image

