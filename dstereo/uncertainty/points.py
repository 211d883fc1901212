"""Uncertainty of every point of a disparity map (`point_covariances`, with a per-pixel disparity noise map
from `dstereo.stereo.disparity_noise`), the calibration covariance a stereo file carries (`calibration_covariance`),
and the disparity noise of a left-right check (`disparity_noise_from_lr`: a lower bound, no longer used by the
pipeline, kept as a diagnostic). The per-point model and why it is right: `dstereo.uncertainty.point_jacobians`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from dstereo.errors import DstereoError
from dstereo.uncertainty.point_jacobians import (  # re-exported: the public names of the propagation
    PARAMETER_NAMES,
    RIG_NAMES,
    RectGeometry,
    disparity_jacobian,
    newton_step,
    parameter_vector,
    point_covariance,
    point_from_pixels,
    rays_of_rectified,
    spherical_disparity_jacobian,
    theta_index,
)

__all__ = ["PARAMETER_NAMES", "RIG_NAMES", "RectGeometry", "PointUncertainty", "calibration_covariance",
           "disparity_jacobian", "disparity_noise_from_lr", "newton_step", "parameter_vector", "point_covariance",
           "point_covariances", "disparity_covariances", "point_from_pixels", "rays_of_rectified", "rect_geometry",
           "spherical_disparity_jacobian", "theta_index"]

NOT_INCLUDED = "calibration uncertainty not included (the calibration file has no covariance): disparity noise only"
MAD_TO_STD = 1.4826  # std of a normal distribution / its median absolute deviation


@functools.lru_cache(maxsize=None)
def _chunk_fn(index: tuple[int, ...]):
    one = lambda p, c, s, uvd, rect: point_covariance(p, index, c, s, uvd, rect)  # noqa: E731
    return jax.jit(jax.vmap(one, in_axes=(None, None, 0, 0, None)))  # sigma_d per point


# --- the dense map ------------------------------------------------------------------------------------------


@dataclass
class PointUncertainty:
    """Per-pixel standard deviations (mm) of the points of a disparity map, NaN where there is no point."""

    sigma_xyz: np.ndarray  # (h, w, 3) per-axis std, original left camera frame
    sigma_z_calibration: np.ndarray  # (h, w) the calibration's share of the depth std
    sigma_z_disparity: np.ndarray  # (h, w) the disparity noise's share
    sigma_d: float  # median of sigma_d_map over the points
    sigma_d_source: str
    calibration_included: bool
    note: str
    cov: np.ndarray | None = None  # (h, w, 3, 3) with full=True
    extras: dict = field(default_factory=dict)
    sigma_d_map: np.ndarray | None = None  # (h, w) disparity noise px per pixel

    @property
    def sigma_z(self) -> np.ndarray:
        return self.sigma_xyz[..., 2]

    def summary(self) -> dict:
        """Median / 95th percentile of sigma_z, sigma_d and its source, the split at the median point."""
        z = self.sigma_z
        ok = np.isfinite(z)
        out = {"sigma_d_px": self.sigma_d, "sigma_d_source": self.sigma_d_source,
               "calibration_included": self.calibration_included, "note": self.note, "points": int(ok.sum())}
        if ok.any():
            median = float(np.median(z[ok]))
            i = np.flatnonzero(ok.ravel())[np.argmin(np.abs(z[ok] - median))]
            cal, dis = self.sigma_z_calibration.ravel()[i], self.sigma_z_disparity.ravel()[i]
            out |= {"sigma_z_mm": {"median": median, "p95": float(np.percentile(z[ok], 95)),
                                   "max": float(z[ok].max())},
                    "sigma_xyz_median_mm": [float(np.median(self.sigma_xyz[..., a][ok])) for a in range(3)],
                    "median_point": {"pixel": [int(i % z.shape[1]), int(i // z.shape[1])],
                                     "sigma_z_mm": float(z.ravel()[i]), "calibration_mm": float(cal),
                                     "disparity_mm": float(dis),
                                     "calibration_variance_share": float(cal ** 2 / max(cal ** 2 + dis ** 2, 1e-300))}}
        return out | self.extras


def calibration_covariance(calib) -> tuple[tuple[str, ...], np.ndarray, str] | None:
    """(names, covariance, structure note) from a `StereoCalibration`'s extras, or None when it has none."""
    cov, names = calib.extras.get("cov"), calib.extras.get("cov_names")
    if cov is None or names is None:
        return None
    names = tuple(names)
    cov = np.asarray(cov, float)
    if cov.shape != (len(names), len(names)) or not np.all(np.isfinite(cov)):
        raise DstereoError(f"{calib.source}: cov is {cov.shape} (finite: {np.all(np.isfinite(cov))}) but cov_names "
                           f"lists {len(names)} parameters; rewrite the file or drop cov and cov_names")
    return names, cov, str(calib.extras.get("cov_structure", ""))


def rect_geometry(matrices: dict) -> RectGeometry:
    return RectGeometry(*(jnp.asarray(matrices[k], float) for k in ("R1", "R2", "P1", "P2", "Q")))


def point_covariances(calib, result_or_disparity, sigma_d, full: bool = False, *, matrices: dict | None = None,
                      sigma_d_source: str = "given", chunk: int = 8192) -> PointUncertainty:
    """Covariance of every point of a disparity map from the calibration covariance (if the file has one) and
    disparity noise `sigma_d` (rectified px): one value, or an (h, w) map (`dstereo.stereo.disparity_noise`).

    `result_or_disparity`: a `reconstruction.PairResult` (its disparity, points' validity and rectification) or
    an (h, w) disparity on the rectified grid of `matrices` (R1 R2 P1 P2 Q, required with a bare disparity).
    Points are processed in fixed-size vmapped chunks, so memory
    stays bounded and one compilation serves any image size. `full` keeps the (h, w, 3, 3) covariances.
    """
    if hasattr(result_or_disparity, "disparity"):
        disparity = np.asarray(result_or_disparity.disparity, float)
        valid = np.isfinite(disparity) & np.all(np.isfinite(result_or_disparity.points), axis=2)
        matrices = result_or_disparity.matrices if matrices is None else matrices
    else:
        disparity = np.asarray(result_or_disparity, float)
        valid = np.isfinite(disparity)
    if matrices is None:  # the rectification is the caller's (stereo/ ranks above this room): it must be given
        raise DstereoError("point_covariances: a bare disparity map needs the rectification it was computed on "
                           "(matrices= R1 R2 P1 P2 Q, e.g. from dstereo.stereo.rectify.rectify_calibration)")
    sigma_map = np.broadcast_to(np.asarray(sigma_d, float), disparity.shape)
    valid &= np.isfinite(sigma_map)
    if np.any(sigma_map[valid] < 0) or (np.ndim(sigma_d) == 0 and not np.isfinite(sigma_d)):
        raise DstereoError(f"disparity noise sigma_d={sigma_d if np.ndim(sigma_d) == 0 else 'map'} px: give a "
                           "finite value >= 0 (or 'auto')")
    found = calibration_covariance(calib)
    params = jnp.asarray(parameter_vector(calib))
    names, cov, structure = found if found is not None else ((), np.zeros((0, 0)), "")
    index = theta_index(names)
    rect = rect_geometry(matrices)
    v, u = np.nonzero(valid)
    uvd = np.stack([u, v, disparity[v, u]], axis=1).astype(float)
    sig = sigma_map[v, u].astype(float)
    n = len(uvd)
    fn = _chunk_fn(index)
    cal_parts, dis_parts = [], []
    for start in range(0, n, chunk):
        block, sb = uvd[start:start + chunk], sig[start:start + chunk]
        pad = chunk - len(block)
        if pad:
            block = np.concatenate([block, np.repeat(block[-1:], pad, axis=0)])
            sb = np.concatenate([sb, np.repeat(sb[-1:], pad)])
        c, d = fn(params, jnp.asarray(cov), jnp.asarray(sb), jnp.asarray(block), rect)
        cal_parts.append(np.asarray(c)[:chunk - pad])
        dis_parts.append(np.asarray(d)[:chunk - pad])
    cal = np.concatenate(cal_parts) if n else np.zeros((0, 3, 3))
    dis = np.concatenate(dis_parts) if n else np.zeros((0, 3, 3))
    total = cal + dis
    h, w = disparity.shape
    sigma = np.full((h, w, 3), np.nan)
    sigma[v, u] = np.sqrt(np.maximum(np.diagonal(total, axis1=1, axis2=2), 0.0))
    sz_cal, sz_dis = np.full((h, w), np.nan), np.full((h, w), np.nan)
    sz_cal[v, u] = np.sqrt(np.maximum(cal[:, 2, 2], 0.0))
    sz_dis[v, u] = np.sqrt(np.maximum(dis[:, 2, 2], 0.0))
    full_cov = None
    if full:
        full_cov = np.full((h, w, 3, 3), np.nan)
        full_cov[v, u] = total
    note = (f"calibration covariance of {len(names)} parameters ({structure or 'structure not stated'}) and "
            f"disparity noise, first order" if found is not None else NOT_INCLUDED)
    median_d = float(np.median(sig)) if n else float("nan")
    smap = np.full((h, w), np.nan)
    smap[v, u] = sig
    return PointUncertainty(sigma, sz_cal, sz_dis, median_d, sigma_d_source, found is not None, note, full_cov,
                            {"calibration_parameters": list(names), "covariance_structure": structure}, smap)


@functools.lru_cache(maxsize=None)
def _disparity_jacobians(projection: str):
    one = spherical_disparity_jacobian if projection == "spherical" else disparity_jacobian
    return jax.jit(jax.vmap(one, in_axes=(0, None)))


def disparity_covariances(result, sigma_d, note: str, full: bool = False,
                          sigma_d_source: str = "given") -> PointUncertainty:
    """The disparity noise's part alone of every point's covariance, sigma_d^2 (dp/dd)(dp/dd)^T: for a rectification
    the calibration covariance is not propagated through (a fisheye lens's; `note` says why). dp/dd through Q for a
    pinhole rectification (`disparity_jacobian`), through the two ray angles for a spherical one
    (`spherical_disparity_jacobian`; `result.matrices['projection']`)."""
    disparity = np.asarray(result.disparity, float)
    sigma_map = np.broadcast_to(np.asarray(sigma_d, float), disparity.shape)
    valid = np.isfinite(disparity) & np.all(np.isfinite(result.points), axis=2) & np.isfinite(sigma_map)
    v, u = np.nonzero(valid)
    uvd = np.stack([u, v, disparity[v, u]], axis=1).astype(float)
    sig = sigma_map[v, u].astype(float)
    projection = str(result.matrices.get("projection", "pinhole"))
    jac = np.asarray(_disparity_jacobians(projection)(jnp.asarray(uvd), rect_geometry(result.matrices))) if len(uvd) \
        else np.zeros((0, 3))
    dis = sig[:, None, None] ** 2 * jac[:, :, None] * jac[:, None, :]
    h, w = disparity.shape
    sigma, sz_dis, smap = np.full((h, w, 3), np.nan), np.full((h, w), np.nan), np.full((h, w), np.nan)
    sigma[v, u] = np.sqrt(np.maximum(np.diagonal(dis, axis1=1, axis2=2), 0.0))
    sz_dis[v, u] = sigma[v, u, 2]
    smap[v, u] = sig
    sz_cal = np.where(np.isfinite(sz_dis), 0.0, np.nan)
    full_cov = None
    if full:
        full_cov = np.full((h, w, 3, 3), np.nan)
        full_cov[v, u] = dis
    median_d = float(np.median(sig)) if len(sig) else float("nan")
    return PointUncertainty(sigma, sz_cal, sz_dis, median_d, sigma_d_source, False, note, full_cov,
                            {"calibration_parameters": [], "covariance_structure": ""}, smap)


# --- disparity noise from the left-right check ----------------------------------------------------------------


def disparity_noise_from_lr(disp_left: np.ndarray, disp_right: np.ndarray, min_pixels: int = 200):
    """(sigma_d px, pixels used) from a left-right consistency check, or (None, pixels) with too few pixels.

    At a pixel u with left disparity d_L(u), the right map at u_R = round(u - d_L) measures the same surface
    point: d_L = d + e_L, d_R = d + e_R. With independent errors of equal std sigma_d, the difference
    d_L - d_R has std sqrt(2) sigma_d, so sigma_d = std(d_L - d_R) / sqrt(2). The std is taken robustly: the
    differences farther than 3 robust stds (1.4826 x the median absolute deviation, at least 1/2 px) from their
    median are wrong matches and left out, and the rest's RMS about the median is used (SGBM's 1/16 px steps
    make the MAD alone zero when most differences are exactly 0). The rounding of u_R adds at most the
    disparity's change over half a pixel, negligible on smooth surfaces.
    Limitation: errors the two matchings share (both see the same image patches: pixel locking, texture bias)
    cancel in d_L - d_R, so this is a lower bound of the disparity error; set sigma_d when it is known.
    """
    h, w = disp_left.shape
    u = np.broadcast_to(np.arange(w), (h, w))
    ur = np.rint(u - np.nan_to_num(disp_left, nan=-1e9)).astype(np.int64)
    inside = np.isfinite(disp_left) & (ur >= 0) & (ur < w)
    rows, cols = np.nonzero(inside)
    diff = disp_left[rows, cols].astype(float) - disp_right[rows, ur[rows, cols]]
    diff = diff[np.isfinite(diff)]
    if len(diff) < min_pixels:
        return None, int(len(diff))
    centred = diff - np.median(diff)
    cutoff = max(3.0 * MAD_TO_STD * np.median(np.abs(centred)), 0.5)
    inliers = centred[np.abs(centred) <= cutoff]
    return float(np.sqrt(np.mean(inliers ** 2)) / np.sqrt(2.0)), int(len(inliers))
