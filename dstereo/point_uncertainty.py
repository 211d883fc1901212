"""Uncertainty of every reconstructed 3D point: calibration covariance and disparity noise, first order.

The calibration parameter vector theta is whatever the calibration file's covariance names (`cov_names` of a
dstereo stereo.yml): a subset of the 30 rig parameters `PARAMETER_NAMES` = left fx fy cx cy k1..k6, right
likewise, RVx RVy RVz (axis-angle of R) and Tx Ty Tz; parameters outside it are held at their values.

The point as a function of theta (`point_from_pixels`). What a reconstruction fixes is the physical match: the
pixels q_left, q_right in the ORIGINAL images where the same surface point is seen; the calibration only
changes how they are turned into a point. The pipeline rectifies with its theta, takes the left pixel's row and
the disparity along that row, and reprojects through Q. Geometrically that is the intersection of the left
pixel's ray with the plane through the right camera centre that holds the right pixel's ray and the rectified
y axis (the points whose rectified right column equals the match's). At the estimated theta the two rays meet
exactly (they come from one rectified row), so that intersection is the reconstructed point for any choice of
the plane's in-plane axis: the axis' own dependence on theta (through the rectifying rotation) has no first-order
effect, and it is held at its value. With q fixed and theta = theta_true + delta, the pipeline's point moves by
J_theta delta to first order, so cov_calib = J_theta S_theta J_theta^T. The undistortion of q is one Newton step
from the known root (the ray of the rectified pixel): its value is exact at the linearisation point and its
derivative is the implicit-function one (-J_distort^-1 d residual / d theta).
`tests/test_point_uncertainty.py` checks J_theta against central differences of the actual pipeline (re-run
`stereo_rectify` with theta, rectify the two pixels, reproject through Q).

Disparity noise sigma_d (rectified px, along the row): the point moves along the left ray by dp/dd of the
Q reprojection; cov = J_theta S J_theta^T + sigma_d^2 (dp/dd)(dp/dd)^T, per point, in the original left frame.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dstereo.errors import DstereoError
from dstereo.models.camera import INTRINSIC_NAMES, project
from dstereo.models.distortion import COEFF_NAMES, distort
from dstereo.models.pose import rodrigues

RIG_NAMES: tuple[str, ...] = ("RVx", "RVy", "RVz", "Tx", "Ty", "Tz")
PARAMETER_NAMES: tuple[str, ...] = (tuple(f"left.{n}" for n in INTRINSIC_NAMES + COEFF_NAMES)
                                    + tuple(f"right.{n}" for n in INTRINSIC_NAMES + COEFF_NAMES) + RIG_NAMES)
NOT_INCLUDED = "calibration uncertainty not included (the calibration file has no covariance): disparity noise only"
DEFAULT_SIGMA_D = 0.25  # px, used only when the left-right check leaves too few pixels to estimate it
MAD_TO_STD = 1.4826  # std of a normal distribution / its median absolute deviation


class RectGeometry(NamedTuple):
    """The nominal rectification the disparity map lives on (as `dstereo.rectify.Rectification`)."""

    R1: Float[Array, "3 3"]
    R2: Float[Array, "3 3"]
    P1: Float[Array, "3 4"]
    P2: Float[Array, "3 4"]
    Q: Float[Array, "4 4"]


def parameter_vector(K1, D1, K2, D2, R, T) -> np.ndarray:
    """(30,) all rig parameters in `PARAMETER_NAMES` order (rvec = axis-angle of R)."""
    from scipy.spatial.transform import Rotation

    k = lambda K: [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]  # noqa: E731
    rvec = Rotation.from_matrix(np.asarray(R, float)).as_rotvec()
    return np.concatenate([k(K1), np.ravel(D1)[:8], k(K2), np.ravel(D2)[:8], rvec, np.ravel(T)]).astype(float)


def theta_index(names) -> tuple[int, ...]:
    """Positions of covariance names in `PARAMETER_NAMES`; a name that is not a rig parameter is an error."""
    unknown = [n for n in names if n not in PARAMETER_NAMES]
    if unknown:
        raise DstereoError(f"calibration covariance: unknown parameter name(s) {unknown}; names are left.fx.., "
                           "right.k1.., RVx..Tz; rewrite cov_names or drop cov from the file")
    return tuple(PARAMETER_NAMES.index(n) for n in names)


def _unpack(params):
    return params[0:4], params[4:12], params[12:16], params[16:24], params[24:27], params[27:30]


def newton_step(k, coeffs, q, x0):
    """One Newton step of distort(coeffs, x) = (q - c) / f from x0, the 2 x 2 system solved in closed form
    (jaxlib 0.10.2's CPU LAPACK call, vmapped over large chunks, deadlocked intermittently here)."""
    qn = (q - k[2:4]) / k[0:2]
    a = jax.jacfwd(distort, argnums=1)(coeffs, x0)
    r = distort(coeffs, x0) - qn
    det = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]  # 2 x 2 inverse written out: no LAPACK call per point
    return x0 - jnp.array([a[1, 1] * r[0] - a[0, 1] * r[1], a[0, 0] * r[1] - a[1, 0] * r[0]]) / det


def point_from_pixels(params, q_left, q_right, x_left0, x_right0, axis) -> Float[Array, "3"]:
    """The reconstructed point (left camera frame) of the original-image match (q_left, q_right) under the rig
    parameters `params` (30,): left ray meets the plane through the right camera centre spanned by the right
    ray and `axis` (the rectified y axis in the left frame). x_*0 are the pixels' undistorted normalised
    coordinates at the linearisation point (module docstring)."""
    k_l, c_l, k_r, c_r, rvec, t = _unpack(params)
    # One Newton step from the root at the linearisation point: exact value there, and its derivative with
    # respect to (k, coeffs) is the implicit-function one, -J_distort^-1 d residual / d params.
    x_l = newton_step(k_l, c_l, q_left, x_left0)
    x_r = newton_step(k_r, c_r, q_right, x_right0)
    rot = rodrigues(rvec)
    v_l = jnp.append(x_l, 1.0)
    v_r = rot.T @ jnp.append(x_r, 1.0)
    normal = jnp.cross(v_r, axis)
    return (normal @ (-rot.T @ t)) / (normal @ v_l) * v_l


def rays_of_rectified(uvd, rect: RectGeometry):
    """Undistorted normalised coordinates of the left pixel (u, v) and of its match (u - d, v) in the original
    cameras (d = u_left - u_right on the rectified pair)."""
    u, v, d = uvd[0], uvd[1], uvd[2]

    def ray(R, P, col):
        r = R.T @ jnp.array([(col - P[0, 2]) / P[0, 0], (v - P[1, 2]) / P[1, 1], 1.0])
        return r[:2] / r[2]

    return ray(rect.R1, rect.P1, u), ray(rect.R2, rect.P2, u - d)


def disparity_jacobian(uvd, rect: RectGeometry) -> Float[Array, "3"]:
    """d p / d d of the Q reprojection, in the original left frame."""
    hom = rect.Q @ jnp.array([uvd[0], uvd[1], uvd[2], 1.0])
    x = hom[:3] / hom[3]
    return rect.R1.T @ ((rect.Q[:3, 2] - x * rect.Q[3, 2]) / hom[3])


def point_covariance(params, index: tuple[int, ...], cov_theta, sigma_d, uvd, rect: RectGeometry):
    """(3x3 calibration part, 3x3 disparity part) of the covariance of one rectified pixel (u, v, d)'s point.

    params (30,) the rig at the linearisation point, `index` (static) the positions of theta in it, cov_theta
    its (G, G) covariance, sigma_d in rectified px. Pure JAX, one point: vmap it.
    """
    j_d = disparity_jacobian(uvd, rect)
    disp = sigma_d ** 2 * jnp.outer(j_d, j_d)
    if not index:
        return jnp.zeros((3, 3)), disp
    x_l0, x_r0 = rays_of_rectified(uvd, rect)
    k_l, c_l, k_r, c_r, _, _ = _unpack(params)
    q_l = project(k_l, c_l, jnp.append(x_l0, 1.0))
    q_r = project(k_r, c_r, jnp.append(x_r0, 1.0))
    axis = rect.R1.T @ jnp.array([0.0, 1.0, 0.0])
    idx = jnp.array(index)
    point = lambda theta: point_from_pixels(params.at[idx].set(theta), q_l, q_r, x_l0, x_r0, axis)  # noqa: E731
    j_theta = jax.jacfwd(point)(params[idx])
    return j_theta @ cov_theta @ j_theta.T, disp


@functools.lru_cache(maxsize=None)
def _chunk_fn(index: tuple[int, ...]):
    one = lambda p, c, s, uvd, rect: point_covariance(p, index, c, s, uvd, rect)  # noqa: E731
    return jax.jit(jax.vmap(one, in_axes=(None, None, None, 0, None)))


# --- the dense map ------------------------------------------------------------------------------------------


@dataclass
class PointUncertainty:
    """Per-pixel standard deviations (mm) of the points of a disparity map, NaN where there is no point."""

    sigma_xyz: np.ndarray  # (h, w, 3) per-axis std, original left camera frame
    sigma_z_calibration: np.ndarray  # (h, w) the calibration's share of the depth std
    sigma_z_disparity: np.ndarray  # (h, w) the disparity noise's share
    sigma_d: float
    sigma_d_source: str
    calibration_included: bool
    note: str
    cov: np.ndarray | None = None  # (h, w, 3, 3) with full=True
    extras: dict = field(default_factory=dict)

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


def point_covariances(calib, result_or_disparity, sigma_d: float, full: bool = False, *, matrices: dict | None = None,
                      sigma_d_source: str = "given", chunk: int = 8192) -> PointUncertainty:
    """Covariance of every point of a disparity map from the calibration covariance (if the file has one) and
    disparity noise `sigma_d` (rectified px).

    `result_or_disparity`: a `reconstruction.PairResult` (its disparity, points' validity and rectification) or
    an (h, w) disparity on the rectified grid of `matrices` (R1 R2 P1 P2 Q; default: `stereo_rectify` of the
    calibration with the reconstruction's defaults). Points are processed in fixed-size vmapped chunks, so memory
    stays bounded and one compilation serves any image size. `full` keeps the (h, w, 3, 3) covariances.
    """
    if hasattr(result_or_disparity, "disparity"):
        disparity = np.asarray(result_or_disparity.disparity, float)
        valid = np.isfinite(disparity) & np.all(np.isfinite(result_or_disparity.points), axis=2)
        matrices = result_or_disparity.matrices if matrices is None else matrices
    else:
        disparity = np.asarray(result_or_disparity, float)
        valid = np.isfinite(disparity)
    if matrices is None:
        from dstereo.rectify import stereo_rectify

        r = stereo_rectify(calib.k1, calib.D1, calib.k2, calib.D2, (disparity.shape[1], disparity.shape[0]), calib.R,
                           calib.T, zero_disparity=False)
        matrices = {k: getattr(r, k) for k in ("R1", "R2", "P1", "P2", "Q")}
    if not np.isfinite(sigma_d) or sigma_d < 0:
        raise DstereoError(f"disparity noise sigma_d={sigma_d} px: give a finite value >= 0 (or 'auto')")
    found = calibration_covariance(calib)
    params = jnp.asarray(parameter_vector(calib.K1, calib.D1, calib.K2, calib.D2, calib.R, calib.T))
    names, cov, structure = found if found is not None else ((), np.zeros((0, 0)), "")
    index = theta_index(names)
    rect = rect_geometry(matrices)
    v, u = np.nonzero(valid)
    uvd = np.stack([u, v, disparity[v, u]], axis=1).astype(float)
    n = len(uvd)
    fn = _chunk_fn(index)
    cal_parts, dis_parts = [], []
    for start in range(0, n, chunk):
        block = uvd[start:start + chunk]
        pad = chunk - len(block)
        block = np.concatenate([block, np.repeat(block[-1:], pad, axis=0)]) if pad else block
        c, d = fn(params, jnp.asarray(cov), float(sigma_d), jnp.asarray(block), rect)
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
    return PointUncertainty(sigma, sz_cal, sz_dis, float(sigma_d), sigma_d_source, found is not None, note, full_cov,
                            {"calibration_parameters": list(names), "covariance_structure": structure})


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
