"""mrcal's `.cameramodel` file: write the models mrcal shares with dstereo, and read them back.

The format (mrcal's doc/cameramodels.org) is the text of a Python dict, read with `ast.literal_eval`:
`lensmodel` ('LENSMODEL_...'), `intrinsics` [fx, fy, cx, cy, distortion...], `rt_cam_ref` (6: the reference
-> camera transform, Rodrigues r then t; mrcal < 2.5 calls it `extrinsics`, and both are written), `imagersize`
[width, height]. mrcal's OpenCV models take OpenCV's coefficient order, so dstereo's 8 slots map directly:
LENSMODEL_OPENCV4 = k1 k2 p1 p2, OPENCV5 adds k3, OPENCV8 adds k4 k5 k6; a camera with no free coefficient is
LENSMODEL_PINHOLE. Pixel coordinates are OpenCV's in both (pixel (0, 0) is the centre of the top-left pixel).

dstereo's fisheye model (Kannala-Brandt, cv2.fisheye) has no mrcal twin: mrcal's lens models are PINHOLE,
STEREOGRAPHIC, LONLAT, LATLON, OPENCV4/5/8/12, CAHVOR, CAHVORE and SPLINED_STEREOGRAPHIC (mrcal master,
mrcal-lensmodel-genericparams.h, read 2026-12), none of them Kannala-Brandt. No file is written for it:
`lensmodel_for` says why, and the report carries that sentence.

Numbers are written with repr (17 significant digits), so a file reads back bit for bit (mrcal writes 10).

A one-camera results folder's file also holds the optimization inputs of the solve that produced it
(`optimization_inputs`) and the valid-intrinsics region (`calib.valid_region`), so that mrcal's own tools
(projection uncertainty, residuals, re-solving) run on it; so does every rig_<camera>.cameramodel of `calibrate --cameras` (the joint solve, as mrcal writes a rig: the same inputs in each
file, that camera its intrinsics k). A `--left/--right` rig's left/right.cameramodel does not yet (its stereo.yml
holds a solve with the intrinsics held); each file's comment says which it holds.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from dstereo.errors import DstereoError

# mrcal lens model -> how many of dstereo's 8 OpenCV-order coefficient slots it holds
OPENCV_MODELS = {"LENSMODEL_PINHOLE": 0, "LENSMODEL_OPENCV4": 4, "LENSMODEL_OPENCV5": 5, "LENSMODEL_OPENCV8": 8}
NO_TWIN = ("the fisheye model (Kannala-Brandt, cv2.fisheye) has no mrcal twin (mrcal's models: PINHOLE, "
           "STEREOGRAPHIC, LONLAT, LATLON, OPENCV4/5/8/12, CAHVOR, CAHVORE, SPLINED_STEREOGRAPHIC): no "
           "camera.cameramodel written")
NO_MODEL_CONVERSION = ("--mrcal-convert: fewer than 20 grid pixels of the valid region lie where a pinhole model "
                       "holds rays: no nearest mrcal model written")
NO_SPLINED_TWIN = ("dstereo's splined lens has no mrcal twin: mrcal's LENSMODEL_SPLINED_STEREOGRAPHIC scales its "
                   "surface by the focal length, spans the grid by a field of view and lays its knots otherwise, so "
                   "the two models differ: no camera.cameramodel written")


@dataclass(frozen=True)
class CameraModelFile:
    """One camera as a .cameramodel holds it."""

    lensmodel: str
    intrinsics: np.ndarray  # (4,) fx, fy, cx, cy
    coeffs: np.ndarray  # (8,) OpenCV order, zeros beyond what the lens model holds
    image_size: tuple[int, int]  # (width, height)
    rt_cam_ref: np.ndarray  # (6,) reference -> camera: Rodrigues vector, translation

    @property
    def free(self) -> tuple[str, ...]:
        """dstereo's free coefficient names that this lens model holds (OpenCV order)."""
        from dstereo.models.distortion import COEFF_NAMES

        return COEFF_NAMES[:OPENCV_MODELS[self.lensmodel]]


def lensmodel_for(free: Sequence[str]) -> tuple[str | None, str]:
    """(mrcal lens model name or None, why): the smallest of mrcal's OpenCV models holding every free coefficient."""
    from dstereo.models.distortion import lens_model

    free = set(free)
    if lens_model(tuple(free)) == "fisheye":
        return None, NO_TWIN
    if lens_model(tuple(free)) == "splined":
        return None, NO_SPLINED_TWIN
    for name, n in OPENCV_MODELS.items():
        if free <= set(("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")[:n]):
            return name, f"{name}: the OpenCV model holding {', '.join(sorted(free)) or 'no distortion'}"
    raise AssertionError("unreachable: OPENCV8 holds every OpenCV coefficient")


# mrcal has no per-coefficient mask: its solve frees every coefficient of the lens model (or none), so a dstereo
# solve with some of them held at 0 (free = k1 only, in OPENCV4) is not the solve mrcal would re-run.
EXACT_FREE_SETS = {"LENSMODEL_PINHOLE": (), "LENSMODEL_OPENCV4": ("k1", "k2", "p1", "p2"),
                   "LENSMODEL_OPENCV5": ("k1", "k2", "p1", "p2", "k3"),
                   "LENSMODEL_OPENCV8": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")}


@dataclass(frozen=True)
class BoardSolve:
    """A board solve of K cameras over F frames as mrcal's optimization inputs hold it: the solve that produced the
    files. One camera: K = 1, every frame seen, no extrinsics."""

    free: tuple[str, ...]  # dstereo's free coefficients, the same for every camera (mrcal has one lens model)
    intrinsics: np.ndarray  # (K, 4) fx, fy, cx, cy of the solve
    coeffs8: np.ndarray  # (K, 8) OpenCV order
    image_sizes: tuple[tuple[int, int], ...]  # (K,) (width, height)
    extrinsics: np.ndarray  # (K - 1, 6) camera k >= 1 from the reference (camera 0): x_k = R x_ref + t, (rvec, t)
    poses: np.ndarray  # (F, 6) board -> reference camera (Rodrigues, translation), OpenCV's rvec, tvec
    observations: np.ndarray  # (F, K, n, 2) px, n = cols * rows in OpenCV's order (column fastest)
    visible: np.ndarray  # (F, K) bool: camera k saw frame f
    inliers: np.ndarray | None  # (F, K, n) the corners the solve used (None: every corner seen)
    pattern: tuple[int, int]  # (cols, rows) inner corners
    square: float
    sag: np.ndarray | None  # (2,) the board's sag solved (dstereo's sag is mrcal's calobject_warp), None: flat

    @classmethod
    def one_camera(cls, free, intrinsics, coeffs8, image_size, poses, observations, inliers, pattern, square, sag):
        """A one-camera solve: poses (V, 6), observations (V, n, 2), inliers (V, n) or None."""
        obs = np.asarray(observations, float)[:, None]
        return cls(tuple(free), np.asarray(intrinsics, float)[None], np.asarray(coeffs8, float)[None],
                   (tuple(image_size),), np.zeros((0, 6)), np.asarray(poses, float), obs,
                   np.ones(obs.shape[:2], bool), None if inliers is None else np.asarray(inliers, bool)[:, None],
                   tuple(pattern), float(square), sag)


def optimization_inputs(solve: BoardSolve) -> tuple[dict | None, str]:
    """(mrcal's optimization_inputs of `solve`, what was done or why not). The layout of mrcal's
    `mrcal.optimize()` arguments (mrcal 2.2's documentation): camera 0 is the reference, so frames_rt_toref are
    the board -> camera 0 poses and extrinsics_rt_fromref those of the other cameras; one board observation per
    (frame, camera) seen, in frame then camera order (mrcal wants them monotonic), each (rows, cols, 3) = x, y,
    weight, weight -1 marking a corner the solve rejected (mrcal's outlier mark); the board a grid of the square's
    spacing with point [i, j] = (j, i, 0) * square, the corner order of `Board.object_points`, and its warp the
    sag (both z = a (1 - u^2) + b (1 - v^2), u, v in [-1, 1] over the outer corners). Regularization off:
    dstereo's solve has none, so mrcal's optimum is dstereo's. do_optimize_extrinsics is on even with no
    extrinsics to optimize: mrcal 2.2's projection_uncertainty refuses a solve with it off."""
    lensmodel, _ = lensmodel_for(solve.free)
    if lensmodel is None or tuple(solve.free) != EXACT_FREE_SETS[lensmodel]:
        return None, ("no optimization inputs: mrcal frees every coefficient of a lens model, and this solve held "
                      f"some of {lensmodel}'s at 0 (free: {', '.join(solve.free) or 'none'})")
    cols, rows = solve.pattern
    obs = np.asarray(solve.observations, float)
    frames, cams = np.nonzero(np.asarray(solve.visible, bool))  # row-major: frame, then camera
    weight = (np.ones(obs.shape[:3]) if solve.inliers is None else np.where(solve.inliers, 1.0, -1.0))[frames, cams]
    board = np.concatenate([obs[frames, cams], weight[..., None]], axis=-1).reshape(len(frames), rows, cols, 3)
    n = OPENCV_MODELS[lensmodel]
    intr = np.concatenate([np.asarray(solve.intrinsics, float), np.asarray(solve.coeffs8, float)[:, :n]], axis=1)
    sag = None if solve.sag is None else np.asarray(solve.sag, float)
    inputs = {
        "intrinsics": intr, "extrinsics_rt_fromref": np.asarray(solve.extrinsics, float).reshape(-1, 6),
        "frames_rt_toref": np.asarray(solve.poses, float).reshape(-1, 6), "points": None,
        "observations_board": board,
        "indices_frame_camintrinsics_camextrinsics": np.column_stack([frames, cams, cams - 1]).astype(np.int32),
        "observations_point": None, "indices_point_camintrinsics_camextrinsics": None,
        "lensmodel": lensmodel, "imagersizes": np.array(solve.image_sizes, np.int32).reshape(-1, 2),
        "calobject_warp": sag, "do_optimize_intrinsics_core": True,
        "do_optimize_intrinsics_distortions": n > 0, "do_optimize_extrinsics": True, "do_optimize_frames": True,
        "do_optimize_calobject_warp": sag is not None, "calibration_object_spacing": float(solve.square),
        "do_apply_outlier_rejection": False, "do_apply_regularization": False}
    what = f"{len(solve.image_sizes)} cameras, " if len(solve.image_sizes) > 1 else ""
    return inputs, (f"with the optimization inputs of the solve ({what}{obs.shape[0]} frames, "
                    f"{int((weight > 0).sum())} corners, {int((weight < 0).sum())} rejected)")


def serialized_inputs(inputs: dict) -> bytes:
    """mrcal's on-file form of optimization inputs: an .npz (None stored as '') compressed, then base-85 text
    (mrcal's cameramodel.py documents it so; written here from that description)."""
    import base64
    import io

    data = io.BytesIO()
    np.savez_compressed(data, **{k: ("" if v is None else v) for k, v in inputs.items()})
    return base64.b85encode(data.getvalue())


def cameramodel_text(lensmodel: str, intrinsics, coeffs8, image_size, rt_cam_ref=np.zeros(6), note: str = "",
                     inputs: dict | None = None, region=None, icam: int = 0) -> str:
    """The .cameramodel text of one camera (k (4,), coeffs (8,) OpenCV order, (width, height)); `inputs`: the
    optimization inputs of the solve that produced it (`optimization_inputs`), this camera its intrinsics `icam`;
    `region`: the valid-intrinsics region (N, 2) px, a closed polygon (`calib.valid_region`)."""
    if lensmodel not in OPENCV_MODELS:
        raise DstereoError(f"cameramodel: lens model {lensmodel!r} is not one dstereo writes; use one of "
                           f"{list(OPENCV_MODELS)}")
    coeffs8 = np.asarray(coeffs8, float)
    n = OPENCV_MODELS[lensmodel]
    if np.any(coeffs8[n:] != 0):
        raise DstereoError(f"cameramodel: {lensmodel} holds {n} coefficients, but coefficients beyond them are "
                           "non-zero; choose a larger lens model")
    nums = lambda a: "[" + ", ".join(repr(float(x)) for x in a) + "]"  # noqa: E731
    rt = np.asarray(rt_cam_ref, float)
    lines = [f"# {line}" for line in note.splitlines()] + [
        "{", f"    'lensmodel': '{lensmodel}',", "",
        "    # intrinsics are fx,fy,cx,cy,distortion0,distortion1,.... (OpenCV's order)",
        f"    'intrinsics': {nums(np.concatenate([np.asarray(intrinsics, float), coeffs8[:n]]))},", "",
        f"    'rt_cam_ref': {nums(rt)},", f"    'extrinsics': {nums(rt)},  # for mrcal < 2.5", "",
        f"    'imagersize': [{int(image_size[0])}, {int(image_size[1])}],"]
    if region is not None:
        lines += ["", "    # where the model can be used: invertible and reached by the corners (dstereo's mask)",
                  "    'valid_intrinsics_region': [" + ", ".join(f"[{float(x)!r}, {float(y)!r}]" for x, y in
                                                                  np.asarray(region, float)) + "],"]
    if inputs is not None:
        lines += ["", "    # the solve that produced this camera, in mrcal's layout (mrcal.cameramodel.optimization_inputs())",
                  f"    'icam_intrinsics': {int(icam)},", f"    'optimization_inputs': {serialized_inputs(inputs)!r},"]
    return "\n".join(lines + ["}", ""])


def write_cameramodel(path: Path, free: Sequence[str], intrinsics, coeffs8, image_size,
                      rt_cam_ref=np.zeros(6), note: str = "", solve: BoardSolve | None = None,
                      no_solve_why: str = "", region=None, icam: int = 0) -> str:
    """Write `path` for a camera of free set `free`; returns what was done (the fisheye: nothing, and why).
    `solve`: the solve that produced these values, written as mrcal's optimization inputs where mrcal can re-run
    it (`optimization_inputs`); else `no_solve_why` (or the reason found) goes into the file's comment. `region`:
    the valid-intrinsics region (N, 2) px; `icam`: this camera's index in `solve`."""
    lensmodel, why = lensmodel_for(free)
    if lensmodel is None:
        return why
    inputs, inputs_why = (None, no_solve_why or "no optimization inputs") if solve is None else \
        optimization_inputs(solve)
    note = note + ("\n" if note else "") + inputs_why
    Path(path).write_text(cameramodel_text(lensmodel, intrinsics, coeffs8, image_size, rt_cam_ref, note, inputs,
                                           region, icam))
    return f"{Path(path).name}: {why} (mrcal's .cameramodel), {inputs_why}"


def read_cameramodel(path: Path) -> CameraModelFile:
    """Read a .cameramodel of one of mrcal's OpenCV models (or PINHOLE); a clear error for anything else."""
    path = Path(path)
    try:
        data = ast.literal_eval(path.read_text())
    except (OSError, ValueError, SyntaxError, MemoryError, RecursionError) as exc:
        raise DstereoError(f"{path}: not a readable mrcal .cameramodel (a Python dict literal): "
                           f"{type(exc).__name__}") from None
    if not isinstance(data, dict):
        raise DstereoError(f"{path}: a .cameramodel holds a dict {{'lensmodel': ..., 'intrinsics': ...}}")
    missing = [k for k in ("lensmodel", "intrinsics", "imagersize") if k not in data]
    if missing:
        raise DstereoError(f"{path}: .cameramodel lacks {', '.join(missing)}")
    model = str(data["lensmodel"])
    if model not in OPENCV_MODELS:
        raise DstereoError(f"{path}: lens model {model} has no dstereo twin; dstereo reads "
                           f"{', '.join(OPENCV_MODELS)}")
    n = OPENCV_MODELS[model]
    values = _numbers(data["intrinsics"], 4 + n, f"{path}: intrinsics of {model}")
    size = _numbers(data["imagersize"], 2, f"{path}: imagersize")
    rt = _numbers(data.get("rt_cam_ref", data.get("extrinsics", [0.0] * 6)), 6, f"{path}: rt_cam_ref")
    if not (np.all(size > 0) and np.all(size == np.round(size))):
        raise DstereoError(f"{path}: imagersize {size.tolist()} must be two positive whole numbers")
    coeffs = np.zeros(8)
    coeffs[:n] = values[4:]
    return CameraModelFile(model, values[:4], coeffs, (int(size[0]), int(size[1])), rt)


def _numbers(value, n: int, where: str) -> np.ndarray:
    try:
        out = np.asarray(value, dtype=float).ravel()
    except (TypeError, ValueError):
        raise DstereoError(f"{where}: not a list of numbers") from None
    if len(out) != n or not np.all(np.isfinite(out)):
        raise DstereoError(f"{where}: expected {n} finite numbers, got {len(out)}")
    return out


def write_rig_cameramodels(folder: Path, cameras, R, T) -> list[str]:
    """left.cameramodel and right.cameramodel of a stereo rig, the left camera as mrcal's reference: the left has
    rt_cam_ref = 0, the right rt_cam_ref = (Rodrigues(R), T), OpenCV's stereo R, T (x_right = R x_left + T is
    mrcal's reference -> camera transform). `cameras`: ((K 3x3, coeffs (8,), free, (width, height)) left, right).
    Returns what was done per camera (a fisheye camera: nothing, and why)."""
    import cv2

    rt_right = np.concatenate([cv2.Rodrigues(np.asarray(R, float))[0].ravel(), np.asarray(T, float).ravel()])
    return write_cameramodels_of_rig(folder, cameras, ("left", "right"), (np.zeros(6), rt_right))


def write_cameramodels_of_rig(folder: Path, cameras, names, rts, solve: BoardSolve | None = None,
                              no_solve_why: str = "") -> list[str]:
    """<name>.cameramodel for each camera of a rig of any size, camera names[0] mrcal's reference: camera k's
    rt_cam_ref = rts[k] (rvec, T of x_cam_k = R_k x_ref + T_k; zeros for the reference). `cameras` as in
    `write_rig_cameramodels`. `solve`: the rig's solve, the same optimization inputs in every file (camera k its
    intrinsics k), as mrcal writes a rig. Returns what was done per camera."""
    done = []
    for icam, (name, (k, coeffs, free, size), rt) in enumerate(zip(names, cameras, rts)):
        k = np.asarray(k, float)
        done.append(write_cameramodel(Path(folder) / f"{name}.cameramodel", free, k[[0, 1, 0, 1], [0, 1, 2, 2]],
                                      coeffs, size, np.asarray(rt, float),
                                      note=f"written by dstereo calibrate: the rig's camera {name} (reference: "
                                      f"camera {names[0]})", solve=solve, no_solve_why=no_solve_why, icam=icam))
    return done
