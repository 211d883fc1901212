"""Stereo calibration files at the OpenCV edge (a rig's pairs are matched by name in `jobs/rig_sources.py`).

- `write_stereo_yml`: OpenCV FileStorage YAML with the keys of OpenCV's stereo_calib sample (M1 D1 M2 D2 R T)
  plus E, F and `imageSize` [w, h] (`imageSize2` when the right camera's differs), readable by
  `dstereo.io.calib_files.read_stereo_calibration`. A rig with a fisheye camera adds `distortion_model1` and
  `distortion_model2` (pinhole or fisheye); a fisheye camera's D is then cv2.fisheye's 1x4 (k1 k2 k3 k4).
- `write_json`: JSON of any nest of dicts, lists, arrays and scalars.
Every file is written under a temporary name and renamed, so none is ever left half-written.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dstereo.errors import DstereoError
from dstereo.io.atomic_files import replace_atomically as _replace_atomically


def write_stereo_yml(path, K1, D1, K2, D2, R, T, E, F, image_size: tuple[int, int],
                     image_size_right: tuple[int, int] | None = None, rms: float | None = None, *,
                     cov: np.ndarray | None = None, cov_names: tuple[str, ...] | None = None,
                     cov_structure: str | None = None, models: tuple[str, str] = ("pinhole", "pinhole"),
                     unit: str = "mm") -> Path:
    """OpenCV YAML with M1 D1 M2 D2 R T E F imageSize (+ imageSize2, rms) and `unit`, the length unit of T (and of
    the board depths appended after): readers convert from it (`calib_files.read_opencv_stereo`). The default, mm,
    is a `StereoCalibration`'s unit; a calibration's writer passes its board unit. D as 1x8 rows in OpenCV's order.

    With `cov`: the calibration covariance as `cov` (G x G matrix), `cov_names` (one string, comma separated:
    left.fx .. left.<free coefficients>, right.*, RVx RVy RVz Tx Ty Tz; RV is the axis-angle vector of R) and
    `cov_structure` (how it was obtained), read back into `StereoCalibration.extras` by `read_stereo_calibration`.
    """
    import cv2

    from dstereo.config.units import check_unit
    from dstereo.io.calib_files import LENS_MODELS

    unit = check_unit(unit, f"{path}: unit {unit!r}")
    if any(m not in LENS_MODELS for m in models):
        raise DstereoError(f"{path}: lens models {models}; each is one of {list(LENS_MODELS)}")
    D1, D2 = (np.asarray(d, float).ravel()[:4] if m == "fisheye" else d for d, m in zip((D1, D2), models))
    if cov is not None:
        cov = np.asarray(cov, dtype=float)
        if cov_names is None or cov.shape != (len(cov_names), len(cov_names)):
            raise DstereoError(f"{path}: covariance {cov.shape} needs one name per row ({cov_names})")

    def write(tmp: Path) -> None:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        if not fs.isOpened():
            raise DstereoError(f"{path}: cannot be written; check that the folder exists and is writable")
        try:
            for key, value, shape in (("M1", K1, (3, 3)), ("D1", D1, (1, -1)), ("M2", K2, (3, 3)), ("D2", D2, (1, -1)),
                                      ("R", R, (3, 3)), ("T", T, (3, 1)), ("E", E, (3, 3)), ("F", F, (3, 3))):
                fs.write(key, np.asarray(value, dtype=float).reshape(shape))
            fs.write("unit", unit)
            if "fisheye" in models:  # without the fields a reader takes both cameras as OpenCV's pinhole model
                fs.write("distortion_model1", models[0])
                fs.write("distortion_model2", models[1])
            fs.write("imageSize", np.array(image_size, dtype=np.int32).reshape(1, 2))
            if image_size_right is not None and tuple(image_size_right) != tuple(image_size):
                fs.write("imageSize2", np.array(image_size_right, dtype=np.int32).reshape(1, 2))
            if rms is not None:
                fs.write("rms", float(rms))
            if cov is not None:
                fs.write("cov_names", ",".join(cov_names))
                fs.write("cov", cov)
                fs.write("cov_structure", cov_structure or "")
        finally:
            fs.release()

    return _replace_atomically(Path(path), write)


def board_depth_range(solution, object_points: np.ndarray) -> dict:
    """Nearest and farthest board corner depth (left camera z, the calibration's unit) over the solution's
    board poses: `reconstruct` uses it as a search-range prior when a pair has too few sparse matches."""
    from dstereo.models.pose import rotation_matrix

    obj = np.asarray(object_points, float).reshape(-1, 3)
    z = np.concatenate([obj @ rotation_matrix(p[:3])[2] + p[5] for p in np.asarray(solution.poses)])
    return {"board_depth_min": float(z.min()), "board_depth_max": float(z.max())}


def corner_angle_range(solution, object_points: np.ndarray) -> dict:
    """{'corner_angle_max1', 'corner_angle_max2'}: the widest angle (degrees) off each camera's optical axis of the
    board corners at the solution's poses (x_right = R x_left + T): where each lens model was measured, written to
    stereo.yml so that `reconstruct` takes a fisheye's field no farther."""
    from dstereo.models.pose import rotation_matrix

    obj = np.asarray(object_points, float).reshape(-1, 3)
    left = np.concatenate([obj @ np.asarray(rotation_matrix(p[:3])).T + p[3:6] for p in np.asarray(solution.poses)])
    right = left @ np.asarray(solution.R, float).T + np.asarray(solution.T, float).reshape(3)
    def widest(p):
        return float(np.degrees(np.arccos(np.clip(p[:, 2] / np.linalg.norm(p, axis=1), -1.0, 1.0))).max())

    return {"corner_angle_max1": widest(left), "corner_angle_max2": widest(right)}


def append_board_depths(path: Path, depths: dict) -> None:
    """Add `board_depth_range`'s two scalars to a written stereo.yml (top-level OpenCV YAML nodes, optional:
    readers that do not know them ignore them)."""
    with Path(path).open("a") as fh:
        fh.writelines(f"{key}: {value!r}\n" for key, value in depths.items())


def write_json(path, data: dict) -> Path:
    """Any nest of dicts, lists, numpy arrays and scalars as indented JSON (non-finite numbers as null)."""
    from dstereo.io.json_files import json_text

    text = json_text(data, indent=1)
    return _replace_atomically(Path(path), lambda tmp: tmp.write_text(text))
