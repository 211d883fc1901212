"""One camera's `camera.yml` (OpenCV FileStorage, as `dstereo calibrate` writes it): K, D, image size, lens model.

The layout is OpenCV's (`camera_matrix`, `distortion_coefficients`, `image_width`, `image_height`). A fisheye
camera carries `distortion_model: fisheye` and D is cv2.fisheye's (k1, k2, k3, k4); without the field D is
OpenCV's pinhole distortion vector (4, 5, 8, 12 or 14 entries).

A splined camera (`dstereo.models.splined`) carries `distortion_model: splined`, no distortion vector (no OpenCV
function takes this lens), and its own section:

    splined:
      base: stereographic          # the base projection the surfaces correct
      grid_nx, grid_ny: 10, 8      # control knots across x and y
      domain: 1.25                 # the grid spans a in [-domain, domain]^2, a = (fx u_x / cx, fy u_y / cy)
      knots_x, knots_y: (ny, nx)   # the two correction surfaces' control values, px (row = y)
      valid_spans: (ny-3, nx-3)    # 1 where a grid span held >= valid_min_corners corners: the valid region
      valid_min_corners: 4

read back exactly (`read_camera_file`: coeffs are the knots, knots_x then knots_y, row-major).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dstereo.errors import DstereoError

from dstereo.io.calib_files import LENS_MODELS  # noqa: F401  (the lens models a file may name)
CAMERA_LENS_MODELS = LENS_MODELS + ("splined",)  # one camera's file may also hold a splined lens


@dataclass(frozen=True)
class CameraFile:
    """K (3, 3) px; coeffs (8,) in the lens model's slots (`distortion.coeff_slots`: fisheye D in [:4])."""

    K: np.ndarray
    coeffs: np.ndarray
    model: str
    image_size: tuple[int, int] | None
    source: str = ""
    valid: np.ndarray | None = None  # a splined camera's valid spans (NY - 3, NX - 3) bool
    free: tuple[str, ...] = ()  # a splined camera's knot names (its model), else empty
    # the board's length unit of the calibration (K and D are in px: nothing here to convert); None: the file
    # names none (OpenCV's own files, dstereo's before the unit was written)
    unit: str | None = None

    @property
    def D(self) -> np.ndarray:
        """The distortion vector as OpenCV's functions for this model take it (cv2.fisheye: 4 entries)."""
        if self.model == "splined":
            raise DstereoError(f"{self.source}: a splined camera has no OpenCV distortion vector; use a camera "
                               "calibrated with a pinhole or fisheye model here")
        return self.coeffs[:4] if self.model == "fisheye" else self.coeffs


def write_splined_section(fs, knots: np.ndarray, free: tuple[str, ...], valid: np.ndarray) -> None:
    """The `splined` section (module docstring) into an open cv2.FileStorage."""
    import cv2

    from dstereo.models import splined

    nx, ny = splined.grid_of(tuple(free))
    knots = np.asarray(knots, np.float64).reshape(2, ny, nx)
    fs.startWriteStruct("splined", cv2.FileNode_MAP)
    fs.write("base", "stereographic")
    fs.write("grid_nx", nx)
    fs.write("grid_ny", ny)
    fs.write("domain", float(splined.DOMAIN))
    fs.write("knots_x", knots[0])
    fs.write("knots_y", knots[1])
    fs.write("valid_spans", np.asarray(valid, np.uint8))
    fs.write("valid_min_corners", int(splined.VALID_MIN_CORNERS))
    fs.endWriteStruct()


def _read_splined_section(path: Path) -> tuple[np.ndarray, tuple[str, ...], np.ndarray]:
    """(knots (2 NX NY,), knot names, valid spans) of a camera file's `splined` section."""
    import cv2

    from dstereo.models import splined

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        node = fs.getNode("splined")
        if node.empty() or not node.isMap():
            raise DstereoError(f"{path}: distortion_model splined needs its `splined` section (grid, knots); "
                               "write the file with dstereo calibrate --model splined")
        get = lambda key: node.getNode(key)  # noqa: E731
        base, domain = get("base").string(), get("domain").real()
        nx, ny = int(get("grid_nx").real()), int(get("grid_ny").real())
        kx, ky, valid = get("knots_x").mat(), get("knots_y").mat(), get("valid_spans").mat()
    finally:
        fs.release()
    if base != "stereographic" or domain != splined.DOMAIN:
        raise DstereoError(f"{path}: splined base {base!r}, domain {domain}: this dstereo reads base stereographic "
                           f"with domain {splined.DOMAIN}")
    shapes = [None if m is None else m.shape for m in (kx, ky, valid)]
    if nx < 4 or ny < 4 or shapes != [(ny, nx), (ny, nx), (ny - 3, nx - 3)]:
        raise DstereoError(f"{path}: splined section: knots_x, knots_y must be {ny} x {nx} and valid_spans "
                           f"{ny - 3} x {nx - 3} (grid_ny x grid_nx, NX, NY >= 4), got {shapes}")
    knots = np.concatenate([np.asarray(kx, float).ravel(), np.asarray(ky, float).ravel()])
    return knots, splined.knot_names(nx, ny), np.asarray(valid) > 0


def read_camera_file(path: str | Path) -> CameraFile:
    from dstereo.io.calib_files import _check_matrix, _coeffs8, _read_storage

    path = Path(path)
    if not path.is_file():
        raise DstereoError(f"camera file {path} does not exist")
    data = _read_storage(path)
    if data.get("camera_matrix") is None:
        raise DstereoError(f"{path}: no camera_matrix; expected a camera.yml as `dstereo calibrate` writes it")
    model = str(data.get("distortion_model") or "pinhole").strip().lower()
    if model not in CAMERA_LENS_MODELS:
        raise DstereoError(f"{path}: distortion_model {model!r} is not one of {list(CAMERA_LENS_MODELS)}")
    w, h = data.get("image_width"), data.get("image_height")
    size = (int(w), int(h)) if w is not None and h is not None else None
    k = _check_matrix(data["camera_matrix"], f"{path}: camera_matrix")
    from dstereo.config.units import UNITS

    # recorded, not converted (no length here): a `unit` of another meaning in someone's file is left out
    unit = str(data.get("unit", "")).strip().lower() or None
    unit = unit if unit in UNITS else None
    if model == "splined":
        knots, free, valid = _read_splined_section(path)
        return CameraFile(k, knots, model, size, str(path), valid, free, unit)
    d = data.get("distortion_coefficients")
    d = np.zeros(0) if d is None else np.asarray(d, float).ravel()
    if model == "fisheye":
        if d.size != 4:
            raise DstereoError(f"{path}: a fisheye camera needs 4 distortion coefficients (cv2.fisheye's k1..k4), "
                               f"got {d.size}")
        coeffs = np.concatenate([d, np.zeros(4)])
    else:
        coeffs = _coeffs8(d, f"{path}: distortion_coefficients")
    return CameraFile(k, coeffs, model, size, str(path), unit=unit)
