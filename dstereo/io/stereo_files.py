"""Stereo pairs and stereo calibration files at the OpenCV edge.

- `detect_pairs`: board corners in both cameras' images, pairs matched by name (`io.pairing`: left05 with
  right05); a pair where either image lacks the full board is listed in `dropped` with the reason, never dropped
  silently, and images without a partner are listed in `warnings`.
- `write_stereo_yml`: OpenCV FileStorage YAML with the keys of OpenCV's stereo_calib sample (M1 D1 M2 D2 R T)
  plus E, F and `imageSize` [w, h] (`imageSize2` when the right camera's differs), readable by
  `dstereo.io.calib_files.read_stereo_calibration`. A rig with a fisheye camera adds `distortion_model1` and
  `distortion_model2` (pinhole or fisheye); a fisheye camera's D is then cv2.fisheye's 1x4 (k1 k2 k3 k4).
- `write_stereo_json`, `write_stereo_corners` (`left/<file>`, `right/<file>`, `object_points`).
Every file is written under a temporary name and renamed, so none is ever left half-written.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
import numpy as np

from dstereo.errors import DstereoError
from dstereo.io.corners import Detection, detect_folder, list_images
from dstereo.io.pairing import check_enough_pairs, pair_by_name
from dstereo.models.board import Board


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
    warnings: list[str] = field(default_factory=list)  # images left out for want of a partner named like them
    # (n, 3) the board the rig was solved on when it is not flat (the board's sag, `stereo_pipeline.rig_board_sag`)
    solved_board: np.ndarray | None = None

    @property
    def board(self) -> Board:
        return self.left.board  # both cameras were detected on the one board

    @property
    def object_points(self) -> np.ndarray:
        """The board's corners the rig was solved on: sagged when solved so (corners.npz's `object_points_solved`)."""
        return self.board.object_points() if self.solved_board is None else self.solved_board

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
    """Detect the board in `left` and `right` (folders or image lists), the images paired by name
    (`io.pairing`): images without a partner are left out with a warning; too few pairs are refused before any
    detection."""
    files_l, files_r = image_files(left, suffix), image_files(right, suffix)
    named = pair_by_name(files_l, files_r)
    check_enough_pairs(named, _where(left, files_l), _where(right, files_r))
    same = [a for a, b in named.pairs if a.resolve() == b.resolve()]
    if same:
        raise DstereoError(f"stereo images: {same[0]} is given as both the left and the right image"
                           + (f" ({len(same) - 1} more)" if len(same) > 1 else "")
                           + "; give each camera's own images (`left` and `right` point at different files)")
    files_l, files_r = [a for a, _ in named.pairs], [b for _, b in named.pairs]
    det_l = detect_folder(files_l[0].parent, pattern, square, files=files_l, use_cache=use_cache, progress=progress)
    det_r = detect_folder(files_r[0].parent, pattern, square, files=files_r, use_cache=use_cache, progress=progress)
    pairs, dropped = match_pairs(det_l, det_r, [p.name for p in files_l], [p.name for p in files_r])
    if not pairs:
        raise DstereoError(
            f"stereo images: no pair shows the full {pattern[0]}x{pattern[1]} board in both cameras (left boards "
            f"in {sorted(det_l.corners) or 'none'}, right boards in {sorted(det_r.corners) or 'none'}); check that "
            "the left and right images are taken at the same moments and named alike"
        )
    warnings = [named.warning()] if named.warning() else []
    warnings += _align_right_order(det_l, det_r, pairs, pattern)
    return StereoDetection(det_l, det_r, pairs, dropped, warnings)


def _align_right_order(det_l: Detection, det_r: Detection, pairs: list[tuple[str, str]],
                       pattern: tuple[int, int]) -> list[str]:
    """Renumber a right image's corners that OpenCV numbered from another corner of the board than the left's
    (`calib.view_checks.align_order`); otherwise the pair's corners would not correspond. Returns the warning."""
    from dstereo.calib.view_checks import align_order

    turned = []
    for a, b in pairs:
        aligned, turn = align_order(det_l.corners[a], det_r.corners[b], pattern)
        if turn:
            det_r.corners[b] = aligned
            turned.append(f"{a} / {b} ({turn} deg)")
    if not turned:
        return []
    return [f"{len(turned)} stereo pair(s) had their right corners numbered from another corner of the board than the "
            f"left ({', '.join(turned[:6])}{' ...' if len(turned) > 6 else ''}); renumbered to match the left, as the "
            f"{pattern[0]}x{pattern[1]} grid's symmetry allows"]


def match_pairs(det_left: Detection, det_right: Detection, names_left: list[str],
                names_right: list[str]) -> tuple[list[tuple[str, str]], list[DroppedPair]]:
    """Pair left and right images by name (`io.pairing`); pairs missing the board on either side are dropped with
    the reason, and so is an image without a partner."""
    named = pair_by_name([Path(n) for n in names_left], [Path(n) for n in names_right])
    pairs, dropped = [], []
    for a, b in ((str(a), str(b)) for a, b in named.pairs):
        reasons = [f"{side} {name}: {det.rejected.get(name, 'no board')}"
                   for side, name, det in (("left", a, det_left), ("right", b, det_right)) if name not in det.corners]
        if reasons:
            dropped.append(DroppedPair(a, b, "; ".join(reasons)))
        else:
            pairs.append((a, b))
    dropped += [DroppedPair(str(a), "", "no right image named like it") for a in named.left_alone]
    dropped += [DroppedPair("", str(b), "no left image named like it") for b in named.right_alone]
    return pairs, dropped


# --- writers ---------------------------------------------------------------------------------------------------


from dstereo.io.atomic_files import replace_atomically as _replace_atomically  # noqa: E402


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


def write_stereo_corners(path, detection: StereoDetection) -> Path:
    """corners.npz: `left/<file>`, `right/<file>` (n, 2) px of the stereo pairs, `object_points` (n, 3) the nominal
    flat board and, when the rig was solved on a sagged one, `object_points_solved` (as one camera's corners.npz)."""
    arrays = {"object_points": detection.board.object_points()}
    if detection.solved_board is not None:
        arrays["object_points_solved"] = detection.solved_board
    for a, b in detection.pairs:
        arrays[f"left/{a}"] = detection.left.corners[a]
        arrays[f"right/{b}"] = detection.right.corners[b]

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)

    return _replace_atomically(Path(path), write)

