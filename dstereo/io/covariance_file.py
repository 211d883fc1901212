"""calibration_covariance.npz: a camera's lens parameters and the covariance the tool reports for them.

Written into every camera's results folder beside camera.yml, for `dstereo diff` (and anyone who propagates the
calibration's uncertainty). Keys:

    names       (G,) str   the lens parameters: fx fy cx cy, then the free coefficients (a solved board sag is
                           the board's, not the camera's: marginalised, i.e. its rows and columns dropped)
    values      (G,)       their values in the solve the covariance belongs to
    cov         (G, G)     the covariance every +- of the results folder shows: with the views' effects where
                           fitted (`kind`), the marginal one (every board pose solved out)
    cov_jacobian (G, G)    sigma^2 (J'J)^-1's block alone, sigma^2 = SSE / (residuals - parameters)
    kind        str        "per-view random effects" or "jacobian": which one `cov` is
    solve       str        which solve: "full set" (camera.yml holds the same unless --per-set's survivors or
                           --final mean differ; `dstereo diff` says so when the values differ)
    views       int        the views that solve used
    lens_model  str        pinhole, fisheye or splined

A file without it (written before it existed, or by another program) still diffs, without a prediction.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dstereo.errors import DstereoError

NAME = "calibration_covariance.npz"


def write_calibration_covariance(folder: Path, cov, lens_model: str) -> dict:
    """Write `cov` (a `calib.finished.LensCovariance`) as NAME into `folder`; returns the summary entry."""
    np.savez(Path(folder) / NAME, names=np.array(cov.names), values=cov.values, cov=cov.cov,
             cov_jacobian=cov.jacobian, kind=cov.kind, solve="full set", views=cov.views, lens_model=lens_model)
    return {"file": NAME, "parameters": list(cov.names), "kind": cov.kind, "solve": "full set", "views": cov.views}


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
    return {"names": names, "values": values, "cov": cov, "kind": str(out.get("kind", "")),
            "solve": str(out.get("solve", "")), "views": int(out["views"]) if "views" in out else None,
            "lens_model": str(out.get("lens_model", ""))}
