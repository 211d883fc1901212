"""The nearest mrcal model to a lens mrcal has no twin for (dstereo's fisheye, its splined lens): `--mrcal-convert`.

mrcal's OpenCV8 model (pinhole + k1..k6, p1, p2, OpenCV's order) fitted by least squares to the lens's own
projection of the rays of the grid pixels in its valid region (`calib.valid_region`: invertible and reached by the
corners) and of the detected corners themselves, where a pinhole model can hold them (in front of the camera,
under MAX_ANGLE_DEG off the axis). The corners matter: they reach past the outer grid nodes to the region's edge,
where the fit is worst (fisheye640: 0.0108 px at a corner against 0.0003 px at the nodes). What it is worth is
said beside it: the fit's RMS and largest error in px over those points, and the share of the valid region's grid
pixels it covers. It is a conversion of the camera, not a solve: no optimization inputs go with it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# a pinhole model maps a ray at angle t to r ~ f tan(t): beyond ~80 deg one pixel holds a degree and more, where no
# polynomial ratio of OpenCV8 follows a fisheye; the share of the region beyond is reported, not fitted
MAX_ANGLE_DEG = 80.0


@dataclass(frozen=True)
class Conversion:
    intrinsics: np.ndarray  # (4,) fx, fy, cx, cy
    coeffs8: np.ndarray  # (8,) OpenCV order
    rms_px: float  # fit error over the pixels fitted
    max_px: float
    covered: float  # share of the valid region's grid pixels fitted (the rest: too far off the axis)
    pixels: int
    corners: int

    def text(self) -> str:
        return (f"nearest mrcal model LENSMODEL_OPENCV8 fitted to the lens over {self.pixels} grid pixels of its "
                f"valid region ({100 * self.covered:.0f} % of them; the rest lie over {MAX_ANGLE_DEG:g} deg off the "
                f"axis) and {self.corners} detected corners: RMS {self.rms_px:.3g} px, largest {self.max_px:.3g} "
                "px: a conversion, not the solve")


def nearest_opencv8(k4, coeffs, model: str, u: np.ndarray, v: np.ndarray, valid: np.ndarray,
                    corners: np.ndarray | None = None) -> Conversion | None:
    """Fit OPENCV8 to lens (`k4`, `coeffs`, `model`: 'fisheye' or 'splined:NXxNY') over the grid pixels (u, v)
    where `valid` (gh, gw) and the detected `corners` (m, 2) px; None when under 20 grid pixels can be fitted."""
    import jax
    import jax.numpy as jnp
    from scipy.optimize import least_squares

    from dstereo.models.camera import project
    from dstereo.uncertainty.projection import pixel_ray

    uu, vv = np.meshgrid(u, v)
    nodes = np.stack([uu[valid], vv[valid]], axis=1)
    extra = np.zeros((0, 2)) if corners is None else np.asarray(corners, float).reshape(-1, 2)
    extra = extra[np.all(np.isfinite(extra), axis=1)]
    q = np.concatenate([nodes, extra])
    if len(nodes) == 0:
        return None
    k4, coeffs = jnp.asarray(k4, float), jnp.asarray(coeffs, float)
    rays, ok = jax.vmap(lambda p: pixel_ray(k4, coeffs, p, model))(jnp.asarray(q))
    rays, ok = np.asarray(rays), np.asarray(ok)
    with np.errstate(invalid="ignore"):
        fit = ok & (rays[:, 2] > np.cos(np.radians(MAX_ANGLE_DEG)))
    if fit[:len(nodes)].sum() < 20:
        return None
    covered, n_nodes, n_corners = float(fit[:len(nodes)].mean()), int(fit[:len(nodes)].sum()), int(fit[len(nodes):].sum())
    q, rays = q[fit], rays[fit]

    def residuals(x):
        return (jax.vmap(lambda p: project(x[:4], x[4:], p))(jnp.asarray(rays)) - q).ravel()

    fun = jax.jit(residuals)
    jac = jax.jit(jax.jacfwd(residuals))
    x0 = np.concatenate([np.asarray(k4), np.zeros(8)])
    out = least_squares(lambda x: np.asarray(fun(x)), x0, jac=lambda x: np.asarray(jac(x)), method="lm",
                        xtol=1e-12, ftol=1e-12)
    err = np.linalg.norm(out.fun.reshape(-1, 2), axis=1)
    return Conversion(out.x[:4], out.x[4:], float(np.sqrt(np.mean(err ** 2))), float(err.max()), covered, n_nodes,
                      n_corners)
