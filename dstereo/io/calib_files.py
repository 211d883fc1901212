"""Calibration and disparity files: OpenCV stereo YAML/XML, Middlebury `calib.txt`, PFM.

`read_stereo_calibration(path)` accepts
- one OpenCV FileStorage file (YAML or XML) holding M1 D1 M2 D2 R T (also K1/K2, cameraMatrix1/2,
  distCoeffs1/2), with the image size if present (`imageSize`/`image_size` [w, h], or `width`/`height`);
- either file of an `intrinsics.yml` + `extrinsics.yml` pair (OpenCV's stereo_calib sample): the other is
  read from the same folder;
- a Middlebury `calib.txt` (an already rectified pair).
Distortion vectors are padded to OpenCV's 8 rational coefficients; thin-prism and tilt terms must be zero.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from dstereo.errors import DstereoError
from dstereo.models.stereo_calibration import StereoCalibration  # noqa: F401  (the type the readers return)

ALIASES = {
    "K1": ("M1", "K1", "cameraMatrix1", "camera_matrix_1", "cameraMatrixL"),
    "D1": ("D1", "distCoeffs1", "dist_coeffs_1", "distCoeffsL"),
    "K2": ("M2", "K2", "cameraMatrix2", "camera_matrix_2", "cameraMatrixR"),
    "D2": ("D2", "distCoeffs2", "dist_coeffs_2", "distCoeffsR"),
    "R": ("R",),
    "T": ("T",),
}
LENS_MODELS = ("pinhole", "fisheye")  # a file's `distortion_model` values (none: pinhole)
# Keys of a one-camera file (dstereo calibrate's camera.yml, OpenCV's calibration samples).
MONO_KEYS = ("camera_matrix", "cameraMatrix", "distortion_coefficients", "distCoeffs")


def _coeffs8(d: np.ndarray | None, where: str) -> np.ndarray:
    d = np.zeros(8) if d is None else np.asarray(d, dtype=float).ravel()
    if d.size not in (0, 4, 5, 8, 12, 14):
        raise DstereoError(f"{where}: {d.size} distortion coefficients; OpenCV uses 4, 5, 8, 12 or 14")
    if not np.all(np.isfinite(d)):
        raise DstereoError(f"{where}: non-finite distortion coefficients {d.tolist()}; fix the file")
    if d.size > 8 and np.any(d[8:] != 0):
        raise DstereoError(
            f"{where}: thin-prism/tilt coefficients (s1..s4, tauX, tauY) are not supported; recalibrate without them"
        )
    out = np.zeros(8)
    out[: min(d.size, 8)] = d[:8]
    return out


def _shape(a: np.ndarray) -> str:
    return "x".join(map(str, np.shape(a))) or "a scalar"


def _check_matrix(K: np.ndarray, where: str) -> np.ndarray:
    K = np.asarray(K, dtype=float)
    if K.shape != (3, 3):
        raise DstereoError(f"{where}: camera matrix must be 3x3, got {_shape(K)}; fix the file")
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise DstereoError(f"{where}: camera matrix must be 3x3 with positive focal lengths, got {K.tolist()}")
    if K[0, 1] != 0:
        raise DstereoError(f"{where}: camera matrix has skew {K[0, 1]}; dstereo's camera model has none")
    return K


def _read_storage(path: Path) -> dict:
    import cv2

    if path.stat().st_size == 0:
        raise DstereoError(f"{path}: the file is empty; give a stereo calibration (stereo.yml from dstereo calibrate "
                           "--left/--right, OpenCV YAML with M1 D1 M2 D2 R T, or calib.txt)")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # OpenCV raises SystemError wrapping cv2.error on a parse failure
        cause = exc.__cause__ if isinstance(exc, SystemError) and exc.__cause__ is not None else exc
        detail = " ".join(str(cause).split()).rsplit("error: ", 1)[-1]
        raise DstereoError(f"{path}: not a readable OpenCV YAML/XML file ({detail}); fix or regenerate it") from None
    if not fs.isOpened():
        raise DstereoError(f"{path}: cannot be read as an OpenCV YAML/XML file")
    out = {"__file__": str(path)}
    try:
        root = fs.root()
        for key in root.keys():
            node = fs.getNode(key)
            if node.isMap() and not node.empty():
                if node.getNode("dt").empty():  # a section, not a matrix (a splined camera's): its reader reads it
                    continue
                value = node.mat()
                out[key] = value if value is not None else None
            elif node.isSeq():
                out[key] = np.array([node.at(i).real() for i in range(node.size())])
            elif node.isReal() or node.isInt():
                out[key] = node.real()
            elif node.isString():
                out[key] = node.string()
    finally:
        fs.release()
    return out


def _pick(data: dict, name: str):
    for alias in ALIASES[name]:
        if alias in data and data[alias] is not None:
            try:
                return np.asarray(data[alias], dtype=float)
            except (TypeError, ValueError):
                raise DstereoError(f"{data.get('__file__', 'calibration file')}: {alias} = {data[alias]!r} is not a "
                                   "matrix of numbers; fix the file") from None
    return None


def _image_size(data: dict) -> tuple[int, int] | None:
    try:
        return _image_size_or_none(data)
    except (TypeError, ValueError):
        raise DstereoError(f"{data.get('__file__', 'calibration file')}: the image size (imageSize or width/height) "
                           "is not a pair of whole numbers; fix or remove it") from None


def _image_size_or_none(data: dict) -> tuple[int, int] | None:
    for key in ("imageSize", "image_size", "image_width"):
        if key in data and data[key] is not None:
            v = np.asarray(data[key]).ravel()
            if v.size >= 2:
                return int(v[0]), int(v[1])
    if "width" in data and "height" in data:
        return int(data["width"]), int(data["height"])
    return None


def read_opencv_stereo(path: str | Path, unscaled: bool = False) -> StereoCalibration:
    """OpenCV stereo calibration file (or an intrinsics/extrinsics pair, given either of them), lengths in mm
    (`_unit_scale`). `unscaled`: a file in board squares is read as it is (for `refine`, which sets the scale)."""
    path = Path(path)
    if not path.is_file():
        raise DstereoError(f"calibration file {path} does not exist")
    data = _read_storage(path)
    partner = {"intrinsics": "extrinsics", "extrinsics": "intrinsics"}.get(path.stem)
    if partner and (_pick(data, "K1") is None or _pick(data, "R") is None):
        other = path.with_name(partner + path.suffix)
        if other.is_file():
            data = {**_read_storage(other), **data}
    missing = [n for n in ("K1", "K2", "R", "T") if _pick(data, n) is None]
    if missing and any(k in data for k in MONO_KEYS):
        raise DstereoError(
            f"{path}: this is a one-camera file (camera_matrix, distortion_coefficients); a stereo calibration is "
            "needed: dstereo calibrate --left LEFT_DIR --right RIGHT_DIR --pattern COLSxROWS --out DIR writes "
            "DIR/stereo.yml")
    if missing:
        raise DstereoError(
            f"{path}: missing {missing}; a stereo calibration needs M1 D1 M2 D2 R T "
            "(or intrinsics.yml + extrinsics.yml side by side)"
        )
    R, T = _pick(data, "R"), _pick(data, "T")
    if R.size not in (3, 9):
        raise DstereoError(f"{path}: R has {R.size} values ({_shape(R)}); give a 3x3 rotation matrix or a "
                           "3-element rotation vector")
    if T.size != 3:
        raise DstereoError(f"{path}: T has {T.size} values ({_shape(T)}); T is the 3-element translation from "
                           "the left to the right camera (x_right = R x_left + T)")
    for name, value in (("R", R), ("T", T)):
        if not np.all(np.isfinite(value)):
            raise DstereoError(f"{path}: {name} holds non-finite values {value.ravel().tolist()}; fix the file")
    if R.size == 3:
        import cv2

        R = cv2.Rodrigues(R.reshape(3, 1))[0]
    R = R.reshape(3, 3)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise DstereoError(f"{path}: R is not a rotation matrix (R R^T != I); check the file")
    models = _lens_models(data, path)
    mm, unit_note = _unit_scale(data, path, unscaled)
    return StereoCalibration(
        extras=_in_mm(_covariance_extras(data, path) | _board_depth_extras(data), mm) | _corner_angle_extras(data),
        unit_note=unit_note,
        K1=_check_matrix(_pick(data, "K1"), f"{path}: M1"),
        D1=_lens_coeffs(_pick(data, "D1"), models[0], f"{path}: D1"),
        K2=_check_matrix(_pick(data, "K2"), f"{path}: M2"),
        D2=_lens_coeffs(_pick(data, "D2"), models[1], f"{path}: D2"),
        models=models,
        R=R,
        T=T.reshape(3) * mm,
        image_size=_image_size(data),
        source=str(path),
    )


def _unit_scale(data: dict, path: Path, unscaled: bool = False) -> tuple[float, str]:
    """(mm per unit of the file's lengths, the note saying so): a StereoCalibration is in mm, so a file in cm
    (dstereo calibrate --unit cm) has its T and board depths converted here, once for every reader (reconstruct,
    refine, recession). A file without `unit` (OpenCV's own, dstereo's before the unit was written) is read in mm
    as before, and the note says it was assumed; a file in board squares has no scale and is refused."""
    from dstereo.config.units import SQUARES, check_unit, mm_per

    if data.get("unit") is None:
        return 1.0, f"{path.name} names no unit: its lengths are taken as mm"
    unit = check_unit(data["unit"], f"{path}: unit {data['unit']!r}")
    if unit == SQUARES and unscaled:
        return 1.0, f"{path.name} is in board squares: no scale until a reference sets it"
    mm = mm_per(unit, str(path))
    return mm, f"{path.name} is in {unit}: converted to mm (x {mm:g})" if unit != "mm" else f"{path.name} is in mm"


def _in_mm(extras: dict, mm: float) -> dict:
    """The file's lengths among `extras` in mm: board depths, and the covariance's rows and columns of T (Tx Ty Tz)."""
    if mm == 1.0:
        return extras
    out = dict(extras)
    for key in ("board_depth_min", "board_depth_max"):
        if key in out:
            out[key] = out[key] * mm
    if "cov" in out:
        scale = np.array([mm if n in ("Tx", "Ty", "Tz") else 1.0 for n in out["cov_names"]])
        out["cov"] = out["cov"] * np.outer(scale, scale)
    return out


def _lens_models(data: dict, path: Path) -> tuple[str, str]:
    """Each camera's lens model: `distortion_model1` / `distortion_model2` (dstereo's stereo.yml), else one
    `distortion_model` for both, else pinhole (OpenCV's own files)."""
    both = data.get("distortion_model") or "pinhole"
    models = []
    for key in ("distortion_model1", "distortion_model2"):
        value = data.get(key) or both
        model = str(value).strip().lower() if isinstance(value, str) else value
        if model not in LENS_MODELS:
            raise DstereoError(f"{path}: {key if key in data else 'distortion_model'} {value!r} is not one of "
                               f"{list(LENS_MODELS)}; fix the file")
        models.append(model)
    return models[0], models[1]


def _lens_coeffs(d: np.ndarray | None, model: str, where: str) -> np.ndarray:
    """D padded to 8 slots: OpenCV's vector (`_coeffs8`), or cv2.fisheye's 4 coefficients in the first four."""
    if model != "fisheye":
        return _coeffs8(d, where)
    d = np.zeros(0) if d is None else np.asarray(d, float).ravel()
    if d.size != 4 or not np.all(np.isfinite(d)):
        raise DstereoError(f"{where}: a fisheye camera needs 4 finite distortion coefficients (cv2.fisheye's k1..k4), "
                           f"got {d.tolist()}; fix the file")
    return np.concatenate([d, np.zeros(4)])


def _covariance_extras(data: dict, path: Path) -> dict:
    """{'cov', 'cov_names', 'cov_structure'} when the file carries a calibration covariance (dstereo's stereo.yml),
    else {} (OpenCV's own files): the point uncertainties then cover disparity noise only."""
    cov, names = data.get("cov"), data.get("cov_names")
    if cov is None and names is None:
        return {}
    if cov is None or not isinstance(names, str):
        raise DstereoError(f"{path}: has {'cov' if cov is not None else 'cov_names'} without "
                           f"{'cov_names' if cov is not None else 'cov'}; give both or remove both")
    names = tuple(n.strip() for n in names.split(",") if n.strip())
    cov = np.asarray(cov, dtype=float)
    if cov.shape != (len(names), len(names)):
        raise DstereoError(f"{path}: cov is {cov.shape[0]}x{cov.shape[1] if cov.ndim > 1 else 1} but cov_names lists "
                           f"{len(names)} parameters; rewrite the file or remove cov and cov_names")
    return {"cov": cov, "cov_names": names, "cov_structure": str(data.get("cov_structure", ""))}


def _board_depth_extras(data: dict) -> dict:
    """{'board_depth_min', 'board_depth_max'} (the calibration boards' depth range, dstereo's stereo.yml) when
    both are there as numbers, else {}."""
    values = {k: data.get(k) for k in ("board_depth_min", "board_depth_max")}
    return {k: float(v) for k, v in values.items()} if all(isinstance(v, float) for v in values.values()) else {}


def _corner_angle_extras(data: dict) -> dict:
    """{'corner_angle_max1', 'corner_angle_max2'} (degrees: the widest angle off each camera's axis its calibration
    corners reached, dstereo's stereo.yml) where they are numbers; reconstruct's fisheye field stops there."""
    return {k: float(data[k]) for k in ("corner_angle_max1", "corner_angle_max2") if isinstance(data.get(k), float)}


# Official calib.txt files round cx0, cx1 and doffs to 3 decimals each: cx1 - cx0 may differ from doffs by up to
# 1.5e-3 px (measured: 47.562 vs doffs 47.561). 0.01 px accepts that and still refuses a wrong doffs.
DOFFS_TOLERANCE_PX = 0.01

_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


def read_middlebury_calib(path: str | Path) -> StereoCalibration:
    """Middlebury 2014 `calib.txt` (tolerant of spaces around '=', '[' and ';'): an already rectified pair.

    Depth Z = baseline f / (d + doffs); the extras hold every scalar of the file (doffs, ndisp, vmin, ...).
    """
    path = Path(path)
    if not path.is_file():
        raise DstereoError(f"Middlebury calibration {path} does not exist")
    values: dict[str, object] = {}
    for line in path.read_text().splitlines():
        if "=" not in line:
            continue
        key, _, value = line.partition("=")
        key = key.strip()
        numbers = [float(x) for x in re.findall(_NUMBER, value)]
        if "[" in value:
            if len(numbers) != 9:
                raise DstereoError(f"{path}: {key} should be a 3x3 matrix '[fx 0 cx; 0 fy cy; 0 0 1]'")
            values[key] = np.array(numbers).reshape(3, 3)
        elif len(numbers) == 1:
            values[key] = numbers[0]
    missing = [k for k in ("cam0", "cam1", "baseline") if k not in values]
    if missing:
        raise DstereoError(f"{path}: missing {missing} (a Middlebury calib.txt has cam0, cam1, doffs, baseline)")
    K1 = _check_matrix(values["cam0"], f"{path}: cam0")
    K2 = _check_matrix(values["cam1"], f"{path}: cam1")
    baseline = values["baseline"]
    # Z = baseline f / (d + doffs): a negative baseline puts every point behind the cameras (exit 0 and depths
    # 1.2-2.9x wrong, once), zero puts them all at infinity (an empty cloud)
    if isinstance(baseline, np.ndarray) or not (np.isfinite(baseline) and baseline > 0):
        raise DstereoError(f"{path}: baseline = {baseline}: the distance between the camera centres must be a "
                           "positive number (mm); fix the file's 'baseline=' line")
    doffs = float(values.get("doffs", K2[0, 2] - K1[0, 2]))
    if abs(doffs - (K2[0, 2] - K1[0, 2])) > DOFFS_TOLERANCE_PX:
        raise DstereoError(f"{path}: doffs {doffs} differs from cx1 - cx0 = {K2[0, 2] - K1[0, 2]:.6g} by more than "
                           f"the files' rounding ({DOFFS_TOLERANCE_PX} px); fix doffs or cam1's cx")
    K2 = K2.copy()
    K2[0, 2] = K1[0, 2] + doffs  # the files round cx; depth is defined through doffs
    size = (int(values["width"]), int(values["height"])) if "width" in values and "height" in values else None
    extras = {k: v for k, v in values.items() if not isinstance(v, np.ndarray)}
    return StereoCalibration(
        K1=K1, D1=np.zeros(8), K2=K2, D2=np.zeros(8), R=np.eye(3), T=np.array([-float(values["baseline"]), 0.0, 0.0]),
        image_size=size, rectified=True, source=str(path), extras=extras,
        unit_note=f"{path.name}: Middlebury's baseline is in mm",
    )


def read_stereo_calibration(path: str | Path, unscaled: bool = False) -> StereoCalibration:
    """Any supported stereo calibration file (see the module docstring), by content; lengths in mm (`unscaled`:
    see `read_opencv_stereo`)."""
    path = Path(path)
    if not path.is_file():
        raise DstereoError(f"calibration file {path} does not exist; give `calib` a stereo.yml, OpenCV YAML or calib.txt")
    head = path.read_text(errors="replace")[:4000]
    if re.search(r"^\s*cam0\s*=", head, flags=re.MULTILINE):
        return read_middlebury_calib(path)
    return read_opencv_stereo(path, unscaled)


def calibration_unit_note(path: str | Path) -> str | None:
    """`StereoCalibration.unit_note` of the calibration file at `path` (its unit: converted to mm, or mm assumed),
    for a results summary that holds only the file's name; None when it cannot be read there now."""
    try:
        return read_stereo_calibration(path).unit_note if Path(path).is_file() else None
    except (DstereoError, OSError):
        return None


def write_opencv_stereo(path: str | Path, calib: StereoCalibration, **extra: np.ndarray) -> None:
    """Write M1 D1 M2 D2 R T (+ imageSize, + any extra matrices such as R1 P1 Q) as OpenCV YAML; a rig with a
    fisheye camera adds distortion_model1/2, and a fisheye camera's D is cv2.fisheye's 4 coefficients."""
    import cv2

    D1, D2 = (np.asarray(d, float).ravel()[:4] if m == "fisheye" else d for d, m in zip((calib.D1, calib.D2),
                                                                                           calib.models))
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        for key, value in (("M1", calib.K1), ("D1", D1), ("M2", calib.K2), ("D2", D2),
                           ("R", calib.R), ("T", calib.T.reshape(3, 1)), *extra.items()):
            fs.write(key, np.asarray(value, dtype=float))
        fs.write("unit", "mm")  # a StereoCalibration is in mm (its readers convert to it)
        if "fisheye" in calib.models:
            fs.write("distortion_model1", calib.models[0])
            fs.write("distortion_model2", calib.models[1])
        if calib.image_size is not None:
            fs.write("imageSize", np.array(calib.image_size, dtype=np.int32).reshape(1, 2))
    finally:
        fs.release()


# --- PFM ---------------------------------------------------------------------------------------------------


def read_pfm(path: str | Path) -> np.ndarray:
    """Portable float map -> float32 array (h, w) or (h, w, 3), top row first (PFM stores bottom-up)."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            kind = f.readline().strip()
            if kind not in (b"Pf", b"PF"):
                raise DstereoError(f"{path}: not a PFM file (header {kind[:8]!r}, expected 'Pf' or 'PF')")
            dims = f.readline().split()
            while not dims:
                dims = f.readline().split()
            width, height = int(dims[0]), int(dims[1])
            scale = float(f.readline().strip())
            data = np.frombuffer(f.read(), dtype="<f4" if scale < 0 else ">f4")
    except FileNotFoundError:
        raise DstereoError(f"PFM file {path} does not exist") from None
    except DstereoError:
        raise
    except (ValueError, IndexError):
        raise DstereoError(f"{path}: malformed PFM header") from None
    channels = 3 if kind == b"PF" else 1
    if data.size != width * height * channels:
        raise DstereoError(f"{path}: {data.size} values for a {width}x{height}x{channels} PFM; the file is truncated")
    shape = (height, width, 3) if channels == 3 else (height, width)
    return np.flipud(data.reshape(shape)).astype(np.float32)


def write_pfm(path: str | Path, image: np.ndarray) -> None:
    """float array (h, w) or (h, w, 3), top row first -> little-endian PFM."""
    image = np.asarray(image, dtype="<f4")
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        raise DstereoError(f"PFM {path}: need an (h, w) or (h, w, 3) array, got shape {image.shape}")
    kind = b"PF" if image.ndim == 3 else b"Pf"
    with Path(path).open("wb") as f:
        f.write(kind + b"\n" + f"{image.shape[1]} {image.shape[0]}\n-1.0\n".encode())
        f.write(np.ascontiguousarray(np.flipud(image)).tobytes())
