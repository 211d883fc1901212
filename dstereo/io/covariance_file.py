"""calibration_covariance.npz: a camera's lens parameters and the covariance the tool reports for them.

Written into every camera's results folder beside camera.yml, for `dstereo diff` (and anyone who propagates the
calibration's uncertainty). Keys:

    names       (G,) str   the lens parameters: fx fy cx cy, then the free coefficients (a solved board sag is
                           the board's, not the camera's: marginalised, i.e. its rows and columns dropped)
    values      (G,)       their values in the solve the covariance belongs to
    cov         (G, G)     the covariance every +- of the results folder shows: with the views' effects where
                           fitted (`kind`), the marginal one (every board pose solved out)
    cov_jacobian (G, G)    sigma^2 (J'J)^-1's block alone, sigma^2 = SSE / (residuals - parameters) (a results
                           folder's; not written for a cross-validation half)
    kind        str        "per-view random effects" or "jacobian": which one `cov` is
    solve       str        which solve: "full set" (camera.yml holds the same unless --per-set's survivors or
                           --final mean differ; `dstereo diff` says so when the values differ), or a
                           cross-validation half
    views       int        the views that solve used
    lens_model  str        pinhole, fisheye or splined
    joint       (G + 6V, G + 6V)  the covariance of the lens parameters and the V board poses together (what the
                           pose-compensated map propagates; absent when the solve kept no per-view blocks)
    poses       (V, 6)     the board poses (rvec, tvec of T_cam_board, the calibration's unit)
    range, grid, image_size   the distance (calibration unit), grid (columns, rows) and image of the folder's
                           projection_uncertainty.npz: `dstereo diff`'s defaults
    field       (rows, columns) bool  the grid pixels within 1.5 grid steps of a corner the solve saw: where the maps claim
                           something (beyond, the lens model is extrapolated and the map is a lower bound);
                           `dstereo diff` takes its statistic inside both cameras' fields

A file without it (written before it existed, or by another program) still diffs, without a prediction.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dstereo.errors import DstereoError

NAME = "calibration_covariance.npz"


def write_calibration_covariance(folder: Path, cov, lens_model: str, range_: float, grid, image_size,
                                solve: str = "full set", field=None) -> dict:
    """Write `cov` (a `calib.finished.LensCovariance`) as NAME into `folder`, with the range, grid and image size
    of its projection-uncertainty map and its corners' `field` on that grid (None: not written); returns the summary
    entry."""
    joint = {} if cov.joint is None else {"joint": cov.joint, "poses": cov.poses}
    if field is not None:
        joint["field"] = np.asarray(field, bool)
    jacobian = {} if cov.jacobian is None else {"cov_jacobian": cov.jacobian}
    np.savez(Path(folder) / NAME, names=np.array(cov.names), values=cov.values, cov=cov.cov, **jacobian,
             kind=cov.kind, solve=solve, views=cov.views, lens_model=lens_model,
             range=float(range_), grid=np.asarray(grid, int), image_size=np.asarray(image_size, int), **joint)
    return {"file": NAME, "parameters": list(cov.names), "kind": cov.kind, "solve": solve, "views": cov.views,
            "joint_with_poses": cov.joint is not None}


def read_calibration_covariance(path: Path) -> dict:
    """{'names', 'values', 'cov', 'kind', 'solve', 'views', 'lens_model'} of a NAME file; a one-line error for a
    file that is not one."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            out = {k: data[k] for k in data.files}
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the user's to replace
        raise DstereoError(f"{path}: not a readable {NAME} ({type(exc).__name__}); write it again with dstereo "
                           "calibrate or remove it") from None
    missing = [k for k in ("names", "values", "cov") if k not in out]
    if missing:
        raise DstereoError(f"{path}: has no {', '.join(missing)}; write it again with dstereo calibrate")
    names = tuple(str(n) for n in np.atleast_1d(out["names"]))
    cov, values = np.asarray(out["cov"], float), np.asarray(out["values"], float).ravel()
    if cov.shape != (len(names),) * 2 or values.shape != (len(names),):
        raise DstereoError(f"{path}: cov {cov.shape} and values {values.shape} do not match {len(names)} names; "
                           "write it again with dstereo calibrate")
    if not np.all(np.isfinite(cov)):
        raise DstereoError(f"{path}: the covariance has non-finite entries (the solve left a parameter "
                           "undetermined); diff without it (remove the file) or calibrate again")
    joint, poses = out.get("joint"), out.get("poses")
    if joint is not None and (poses is None or np.shape(joint) != (len(names) + 6 * len(poses),) * 2
                              or not np.all(np.isfinite(joint))):
        raise DstereoError(f"{path}: joint {np.shape(joint)} does not match {len(names)} parameters and "
                           f"{0 if poses is None else len(poses)} poses, or is not finite; write it again with "
                           "dstereo calibrate")
    grid = out.get("grid")
    return {"names": names, "values": values, "cov": cov, "kind": str(out.get("kind", "")),
            "solve": str(out.get("solve", "")), "views": int(out["views"]) if "views" in out else None,
            "lens_model": str(out.get("lens_model", "")),
            "joint": None if joint is None else np.asarray(joint, float),
            "poses": None if poses is None else np.asarray(poses, float),
            "range": float(out["range"]) if "range" in out else None,
            "grid": None if grid is None else tuple(int(g) for g in np.ravel(grid)),
            "field": _field(out.get("field"), grid, path),
            "image_size": tuple(int(x) for x in np.ravel(out["image_size"])) if "image_size" in out else None}


def _field(field, grid, path: Path):
    """The written corners' field (rows, columns) bool, checked against the grid; None when not written."""
    if field is None:
        return None
    field = np.asarray(field)
    if grid is None or field.dtype != bool or field.shape != (int(np.ravel(grid)[1]), int(np.ravel(grid)[0])):
        raise DstereoError(f"{path}: field {field.shape} {field.dtype} does not match its grid; write it again with "
                           "dstereo calibrate")
    return field
