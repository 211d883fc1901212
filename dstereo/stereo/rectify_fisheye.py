"""Rectification of a stereo pair with a fisheye camera (either or both), as cv2.fisheye.stereoRectify and
cv2.fisheye.initUndistortRectifyMap: each camera's rays through its own lens model, to one rectified pinhole pair
(or, for a field wider than a pinhole image holds, to the spherical pair of `rectify_wide`).

Rotations: Bouguet's (`rectify.rectifying_rotations`, the same R1, R2 as cv2.fisheye.stereoRectify).
Focal length and principal points, per camera, cv2.fisheye.estimateNewCameraMatrixForUndistortRectify's rule:
the four edge midpoints of the image, (w/2, 0), (w, h/2), (w/2, h), (0, h/2) (OpenCV's, integer halves), become
rays through the camera's lens (fisheye: the Kannala-Brandt inverse `models.fisheye.unproject`, convergence
checked; pinhole: the Newton inverse of its distortion), are turned into the rectified frame and projected with a
unit pinhole. Each gives the focal length that puts it on its image edge, about their mean; `balance` in [0, 1]
blends the largest of the four (0: the field reaches only the nearest edge midpoint, the most pixels per degree)
and the smallest (1: all four edge midpoints inside); `fov_scale` > 0 divides it (a wider field). The pair takes
the smaller of the two cameras' focal lengths (the wider field of the two) and principal points as
cv2.fisheye.stereoRectify (zero_disparity: both at their mean; else each its own column, the rows' mean).

The field is the one the lenses see (`field_rays`): a fisheye edge midpoint without a ray of its own (past the
angle where its polynomial folds back, `fold_angle`; the real rig of issue 30: f 227 px on 960 px) is replaced by
the ray where its field ends on the way to it, at the fold or, when the calibration recorded it
(`corner_reach`), where its corners reached; a pinhole lens whose distortion cannot be inverted there is refused.
Where every edge midpoint has its own ray, the rule is cv2's, unchanged.

Which rectification (`choose_projection`): where every field ray of both cameras lies within MAX_HALF_FIELD_DEG of
the rectified axis, the pinhole one above; where any lies beyond, the spherical one of `rectify_wide` (rows:
planes through the baseline, columns: the angle within them), whose disparity is an angle difference and whose
points come from the two ray angles; `projection` forces either. The `Rectification` says which and why.

Forced to a pinhole, a field wider than that is clamped: an edge midpoint whose ray lies more than
MAX_HALF_FIELD_DEG from the rectified axis is pulled in to that angle (its azimuth kept), which only changes the
result for lenses wider than that (OpenCV's numbers are then far outside the image: its rule is undefined there).
With balance 0 the image lies inside the midpoints, so it keeps at most 2 x MAX_HALF_FIELD_DEG across; with
balance 1 it reaches past them along the less constraining axis (still under 180 degrees, a pinhole's edges being
finite). `field_of_view` says what the rectified images keep: for the rig of `synth.fisheye_rig` (128 deg across
its 640 px) 110 x 94 deg at balance 0, 129 x 115 deg at balance 1 (measured by the since-removed
experiments/fisheye_rig.py).
Maps (`lens_map`): NaN where a rectified pixel's ray has no source pixel (behind a pinhole camera, or past the angle
where the fisheye polynomial folds back), never a number.
Conventions: x_right = R x_left + T (OpenCV), pixel (0, 0) is the centre of the top-left pixel.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dstereo.errors import DstereoError
from dstereo.models import fisheye
from dstereo.models.camera import Camera, project
from dstereo.models.distortion import undistort
from dstereo.models.pose import rotation_matrix
from dstereo.models.rig import Rig
from dstereo.stereo import rectify_wide as wide
from dstereo.stereo.rectify import (PINHOLE, PROJECTIONS, SPHERICAL, Rectification, _half_rotations, q_matrix,
                                    rectifying_rotations)

# At 75 degrees off axis a pinhole image is stretched 1 / cos^2 = 15x radially against its centre: a wider field
# would spend most of the rectified image on the rim of the lens.
MAX_HALF_FIELD_DEG = 75.0
# The optical axes of a rectifiable pair: beyond 90 degrees apart the two views share no rectified pinhole field.
MAX_AXES_DEG = 90.0
FOLD_SAMPLES = 4096  # theta grid on [0, pi) on which the fisheye polynomial's first fold is searched
ROI_GRID = 33  # rectified pixels sampled per side for the valid rectangles


def fold_angle(d: Float[Array, "4"]) -> Float[Array, ""]:
    """First theta in (0, pi) where d theta_d / d theta <= 0 (pi when it never does): past it the fisheye model
    maps two rays to one pixel, so no ray beyond it is imaged."""
    t = jnp.linspace(0.0, jnp.pi, FOLD_SAMPLES, endpoint=False)
    t2 = t * t
    slope = 1.0 + t2 * (3.0 * d[0] + t2 * (5.0 * d[1] + t2 * (7.0 * d[2] + t2 * 9.0 * d[3])))
    bad = slope <= 0
    return jnp.where(bad.any(), t[jnp.argmax(bad)], jnp.pi)


def lens_rays(k, coeffs, lens: str, q: Float[Array, "n 2"]):
    """Pixels -> unit rays (n, 3) in the camera frame through the lens model, and whether each was found."""
    if lens == "fisheye":
        return jax.vmap(fisheye.unproject, in_axes=(None, None, 0))(k, coeffs[:4], q)
    xy = jax.vmap(lambda p: undistort(coeffs, (p - k[2:4]) / k[0:2]))(q)
    ray = jnp.concatenate([xy, jnp.ones((q.shape[0], 1))], axis=1)
    back = jax.vmap(lambda r: project(k, coeffs, r))(ray)
    ok = jnp.all(jnp.abs(back - q) <= 1e-6, axis=1)  # the Newton inverse reproduces the pixel
    return ray / jnp.linalg.norm(ray, axis=1, keepdims=True), ok


def ray_limit(d: Float[Array, "4"]) -> Float[Array, ""]:
    """The widest angle off the axis (rad) at which a fisheye has rays: two fold-search steps inside `fold_angle`
    (whose grid point lies at or past the fold)."""
    return fold_angle(d) - 2.0 * jnp.pi / FOLD_SAMPLES


def field_rays(k, coeffs, lens: str, q: Float[Array, "n 2"], limit, edge=None):
    """Rays (n, 3) of the field at pixels q, whether each is the pixel's own ray, and whether each has one.

    A pixel with a ray below `limit` (`ray_limit`) keeps it; a fisheye pixel without (beyond the image circle the
    polynomial folds back) is replaced by the ray at `edge` (default `limit`; the corners' reach when smaller) in
    its azimuth, where the field ends on the way to it. A pinhole lens has no such edge: its pixel stays without
    a ray."""
    rays, ok = lens_rays(k, coeffs, lens, q)
    if lens != "fisheye":
        return rays, ok, ok
    edge = limit if edge is None else edge
    own = ok & (jnp.arccos(jnp.clip(rays[:, 2], -1.0, 1.0)) <= limit)
    xy = (q - k[2:4]) / k[0:2]
    n = jnp.hypot(xy[:, 0], xy[:, 1])
    cs = jnp.where((n > 0)[:, None], xy / jnp.where(n > 0, n, 1.0)[:, None], jnp.array([1.0, 0.0]))
    ray_edge = jnp.concatenate([jnp.sin(edge) * cs, jnp.full((q.shape[0], 1), jnp.cos(edge))], axis=1)
    return jnp.where(own[:, None], rays, ray_edge), own, jnp.ones_like(own)


def edge_midpoints(size: tuple[int, int]) -> Float[Array, "4 2"]:
    """OpenCV's four edge midpoints (integer halves) of a (w, h) image."""
    w, h = size
    return jnp.array([[w // 2, 0], [w, h // 2], [w // 2, h], [0, h // 2]], dtype=float)


def _clamped_plane_points(rays, R, max_half_angle):
    """Rays turned by R, pulled in to `max_half_angle` from the rectified axis, as points (x, y) on z = 1."""
    p = rays @ R.T
    rho = jnp.hypot(p[:, 0], p[:, 1])
    angle = jnp.arctan2(rho, p[:, 2])
    angle = jnp.minimum(angle, max_half_angle)
    cs = p[:, :2] / jnp.where(rho > 0, rho, 1.0)[:, None]
    return cs * jnp.tan(angle)[:, None]


def new_camera_matrix(k, coeffs, lens: str, size: tuple[int, int], R, balance, fov_scale,
                      new_size: tuple[int, int], max_half_angle, limit=jnp.pi, edge=None):
    """(f (2,), c (2,)) of one camera's rectified pinhole, cv2.fisheye.estimateNewCameraMatrixForUndistortRectify's
    rule (module docstring) through the camera's own lens, a fisheye's edge midpoints without a ray replaced by
    the edge of its field (`field_rays`, below `limit`); and whether all four then had a ray."""
    w, h = size
    rays, _, ok = field_rays(k, coeffs, lens, edge_midpoints(size), limit, edge)
    pts = _clamped_plane_points(jnp.where(ok[:, None], rays, jnp.array([0.0, 0.0, 1.0])), R, max_half_angle)
    aspect = k[0] / k[1]
    cn = jnp.mean(pts, axis=0) * jnp.array([1.0, aspect])
    pts = pts * jnp.array([1.0, aspect])
    lo, hi = jnp.min(pts, axis=0), jnp.max(pts, axis=0)
    fs = jnp.array([w * 0.5 / (cn[0] - lo[0]), w * 0.5 / (hi[0] - cn[0]),
                    h * 0.5 * aspect / (cn[1] - lo[1]), h * 0.5 * aspect / (hi[1] - cn[1])])
    b = jnp.clip(balance, 0.0, 1.0)
    f = b * jnp.min(fs) + (1.0 - b) * jnp.max(fs)
    f = f * jnp.where(fov_scale > 0, 1.0 / fov_scale, 1.0)
    c = -cn * f + jnp.array([w, h * aspect]) * 0.5
    f2 = jnp.array([f, f / aspect])
    c = c / jnp.array([1.0, aspect])
    scale = jnp.array([new_size[0] / w, new_size[1] / h])
    return f2 * scale, c * scale, jnp.all(ok)


@partial(jax.jit, static_argnames=("lenses", "size", "new_size", "idx"))
def _rectify_lenses(k1, c1, k2, c2, rvec, T, balance, fov_scale, zero_disparity, max_half_angle, limits, *, lenses,
                    size, new_size, idx):
    R1, R2, t_idx = rectifying_rotations(rvec, T, idx)
    f1, cc1, ok1 = new_camera_matrix(k1, c1, lenses[0], size, R1, balance, fov_scale, new_size, max_half_angle,
                                     limits[0, 0], limits[0, 1])
    f2, cc2, ok2 = new_camera_matrix(k2, c2, lenses[1], size, R2, balance, fov_scale, new_size, max_half_angle,
                                     limits[1, 0], limits[1, 1])
    fc = jnp.minimum(f1[1], f2[1])  # cv2.fisheye: the smaller vertical focal length serves both
    cc = jnp.stack([cc1, cc2])
    other = 1 - idx
    cc = jnp.where(zero_disparity, jnp.broadcast_to(cc.mean(axis=0), (2, 2)), cc.at[:, other].set(cc[:, other].mean()))

    def projection(cc_k, tx):
        P = jnp.zeros((3, 4)).at[0, 0].set(fc).at[1, 1].set(fc).at[0:2, 2].set(cc_k).at[2, 2].set(1.0)
        return P.at[idx, 3].set(tx)

    P1, P2 = projection(cc[0], 0.0), projection(cc[1], t_idx * fc)
    return R1, R2, P1, P2, q_matrix(P1, P2, vertical=idx == 1), jnp.array([ok1, ok2])


def _axes_angle_deg(rvec) -> float:
    """Angle between the two cameras' optical axes (degrees)."""
    r = np.asarray(rotation_matrix(jnp.asarray(rvec)))
    return float(np.degrees(np.arccos(np.clip(r[2, 2], -1.0, 1.0))))


def _limits(cameras, reach) -> list[tuple[float, float]]:
    """Each camera's (ray limit, field edge), rad: `ray_limit` and its minimum with the corners' reach (a pinhole
    lens: pi, its Newton inverse decides)."""
    out = []
    for cam, r in zip(cameras, reach):
        limit = float(ray_limit(jnp.asarray(cam.dist.coeffs[:4], float))) if cam.lens == "fisheye" else float(np.pi)
        out.append((limit, limit if r is None else min(limit, float(r))))
    return out


def choose_projection(cameras, R_pair, size, limits, projection: str, where: str) -> tuple[str, str]:
    """(PINHOLE or SPHERICAL, why): a pinhole rectification where every edge midpoint's field ray (`field_rays`) of
    both cameras lies within MAX_HALF_FIELD_DEG of its rectified axis, the spherical one where any lies beyond
    (`projection` "auto"); "pinhole" or "spherical" forces it."""
    if projection not in ("auto", *PROJECTIONS):
        raise DstereoError(f"{where}: rectification {projection!r}: use auto, pinhole or spherical")
    widest, notes = [], []
    for side, cam, R, (limit, edge) in zip(("left", "right"), cameras, R_pair, limits):
        k, coeffs = jnp.asarray(cam.k, float), jnp.asarray(cam.dist.coeffs, float)
        rays, own, ok = (np.asarray(a) for a in field_rays(k, coeffs, cam.lens, edge_midpoints(size),
                                                           jnp.asarray(limit), jnp.asarray(edge)))
        if not ok.all():
            raise DstereoError(f"{where}: the {side} lens model has no ray for an image edge midpoint (its distortion "
                               "is not invertible there); check or recalibrate its distortion")
        widest.append(float(np.degrees(np.arccos(np.clip(rays @ np.asarray(R)[2], -1.0, 1.0))).max()))
        if not own.all():
            notes.append(f"the {side} lens has no ray at {int((~own).sum())} of its image edge midpoints: its field "
                         f"taken to where it ends, {np.degrees(edge):.0f} deg off its axis"
                         + (" (the corners' reach)" if edge < limit else " (its polynomial's fold)"))
    side = "left" if widest[0] >= widest[1] else "right"
    field = f"the field reaches {max(widest):.0f} deg off the rectified axis ({side} camera)"
    fits = max(widest) <= MAX_HALF_FIELD_DEG
    if projection == "auto":
        kind = PINHOLE if fits else SPHERICAL
        why = (f"{field}, within {MAX_HALF_FIELD_DEG:g} deg: a pinhole rectification" if fits else
               f"{field}, more than a pinhole image holds ({MAX_HALF_FIELD_DEG:g} deg): a spherical rectification "
               "(rows: planes through the baseline, columns: the angle within them)")
    else:
        kind, why = projection, f"{field}; {projection} rectification as asked"
    return kind, "; ".join([why, *notes])


def stereo_rectify_lenses(left: Camera, right: Camera, rig: Rig, image_size: tuple[int, int], *,
                          balance: float = 0.0, fov_scale: float = 1.0, zero_disparity: bool = True,
                          new_size: tuple[int, int] | None = None, where: str = "stereo calibration",
                          projection: str = "auto", reach=(None, None)) -> Rectification:
    """Rectify a pair of any two lens models (pinhole + distortion or fisheye, `Camera.lens`) to one rectified
    pair (module docstring; cv2.fisheye.stereoRectify for a horizontal fisheye pair whose edge midpoints have
    rays within MAX_HALF_FIELD_DEG). Rig: x_right = R x_left + T. `projection`: "auto" (`choose_projection`),
    "pinhole" or "spherical" (`rectify_wide`). `reach`: per camera, the widest angle (rad) off its axis that the
    calibration's corners reached, or None; a fisheye's field is not taken past it where its edge midpoints have
    no ray of their own, nor, in a spherical rectification, anywhere. A spherical rectification shares one
    principal point (zero disparity at infinity) whatever `zero_disparity`, and has no use for `fov_scale`.

    Raises DstereoError (naming `where`) for a pair whose optical axes are more than 90 degrees apart, an edge
    midpoint a pinhole lens cannot invert, or a rectified field that sees neither image."""
    w, h = (int(v) for v in image_size)
    if w < 2 or h < 2:
        raise DstereoError(f"image_size {image_size}: need width and height of at least 2 pixels")
    new = (w, h) if new_size is None or new_size[0] * new_size[1] == 0 else (int(new_size[0]), int(new_size[1]))
    rvec = np.asarray(rig.rvec, float).reshape(3)
    T = np.asarray(rig.tvec, float).reshape(3)
    if not np.linalg.norm(T) > 0:
        raise DstereoError(f"{where}: the baseline T is zero; check the extrinsics (T) of the calibration")
    apart = _axes_angle_deg(rvec)
    if apart > MAX_AXES_DEG:
        raise DstereoError(f"{where}: the cameras' optical axes are {apart:.1f} deg apart (more than "
                           f"{MAX_AXES_DEG:g}); no rectified pinhole pair sees both views; check R, or pair other "
                           "cameras")
    if not (np.isfinite(balance) and np.isfinite(fov_scale)):
        raise DstereoError(f"{where}: balance {balance} / fov_scale {fov_scale} must be finite numbers")
    t = np.asarray(_half_rotations(jnp.asarray(rvec), jnp.asarray(T))[1])
    idx = 1 if abs(t[0]) <= abs(t[1]) else 0
    cameras = (left, right)
    limits = _limits(cameras, reach)
    R1, R2, t_idx = rectifying_rotations(jnp.asarray(rvec), jnp.asarray(T), idx)
    kind, why = choose_projection(cameras, (R1, R2), (w, h), limits, projection, where)
    if kind == SPHERICAL:
        return _spherical(cameras, (R1, R2), float(t_idx), limits, balance, (w, h), new, idx, where, why)
    lenses = (left.lens, right.lens)
    R1, R2, P1, P2, Q, _ = _rectify_lenses(  # every edge midpoint has a ray: `choose_projection` refused the rest
        jnp.asarray(left.k, float), jnp.asarray(left.dist.coeffs, float), jnp.asarray(right.k, float),
        jnp.asarray(right.dist.coeffs, float), jnp.asarray(rvec), jnp.asarray(T), jnp.asarray(float(balance)),
        jnp.asarray(float(fov_scale)), jnp.asarray(bool(zero_disparity)), jnp.asarray(np.radians(MAX_HALF_FIELD_DEG)),
        jnp.asarray(limits), lenses=lenses, size=(w, h), new_size=new, idx=idx)
    if not np.isfinite(np.asarray(P1)).all() or not float(P1[0, 0]) > 0:
        raise DstereoError(f"{where}: the rectified focal length is {float(P1[0, 0])!r}; the rectified field would be "
                           "empty; check the calibration (R, T and the lens coefficients)")
    rois = _rois(cameras, (R1, R2), (P1, P2), new, (w, h), PINHOLE, where)
    return Rectification(R1, R2, P1, P2, Q, jnp.asarray(rois[0]), jnp.asarray(rois[1]), size=new, vertical=idx == 1,
                         projection=PINHOLE, why=why)


def _rois(cameras, R_pair, P_pair, new, size, projection, where):
    rois = []
    for side, cam, R, P in zip(("left", "right"), cameras, R_pair, P_pair):
        rois.append(_valid_rectangle(cam, R, P, new, size, projection))
        if rois[-1][2] <= 0 or rois[-1][3] <= 0:
            raise DstereoError(f"{where}: the rectified field would be empty: no rectified pixel of the {side} camera "
                               "sees its image; check R, T and the lens coefficients")
    return rois


@partial(jax.jit, static_argnames=("lens", "size"))
def _grid_rays(k, coeffs, limit, *, lens, size):
    w, h = size
    u, v = jnp.meshgrid(jnp.linspace(0.0, w - 1.0, wide.FIELD_GRID), jnp.linspace(0.0, h - 1.0, wide.FIELD_GRID))
    rays, ok = lens_rays(k, coeffs, lens, jnp.stack([u.ravel(), v.ravel()], axis=1))
    return rays, ok & (jnp.arccos(jnp.clip(rays[:, 2], -1.0, 1.0)) <= limit)


def _spherical(cameras, R_pair, tx, limits, balance, size, new, idx, where, why) -> Rectification:
    """The spherical rectification (`rectify_wide`) of a horizontal pair."""
    if idx == 1:
        raise DstereoError(f"{where}: the baseline is vertical and the field too wide for a pinhole rectification; "
                           "rotate both images (and the calibration) by 90 degrees")
    boxes = []
    for side, cam, R, (_, edge) in zip(("left", "right"), cameras, R_pair, limits):
        rays, ok = _grid_rays(jnp.asarray(cam.k, float), jnp.asarray(cam.dist.coeffs, float), jnp.asarray(edge),
                              lens=cam.lens, size=size)
        box = wide.seen_box(np.asarray(rays), np.asarray(ok), np.asarray(R))
        if box is None:
            raise DstereoError(f"{where}: no pixel of the {side} camera has a ray in front of the rig; check R, T "
                               "and the lens coefficients")
        boxes.append(box)
    box = wide.pair_box(*boxes, balance)
    wide.check_box(box, where)
    P1, P2 = (jnp.asarray(P) for P in wide.spherical_projections(box, new, tx))
    Q = q_matrix(P1, P2)
    rois = _rois(cameras, R_pair, (P1, P2), new, size, SPHERICAL, where)
    return Rectification(R_pair[0], R_pair[1], P1, P2, Q, jnp.asarray(rois[0]), jnp.asarray(rois[1]), size=new,
                         vertical=False, projection=SPHERICAL, why=why)


@partial(jax.jit, static_argnames=("lens", "size", "projection"))
def lens_map(k, coeffs, R, P, lens: str, size: tuple[int, int], projection: str = PINHOLE):
    """Source pixel of every rectified pixel through the lens model (cv2.fisheye.initUndistortRectifyMap for a
    fisheye; cv2.initUndistortRectifyMap for a pinhole; a SPHERICAL rectification's pixels are angles,
    `rectify_wide`): maps (h, w) for `cv2.remap`, NaN where the ray has no source (behind a pinhole camera; past a
    fisheye's fold angle)."""
    w, h = size
    u, v = jnp.meshgrid(jnp.arange(w, dtype=float), jnp.arange(h, dtype=float))
    if projection == SPHERICAL:
        rays = wide.rectified_rays(P, u, v) @ R  # rectified -> camera frame: R^T r
    else:
        inv = jnp.linalg.inv(P[:, :3] @ R)
        rays = jnp.stack([u, v, jnp.ones_like(u)], axis=-1) @ inv.T
    if lens == "fisheye":
        d = coeffs[:4]
        rho = jnp.hypot(rays[..., 0], rays[..., 1])
        theta = jnp.arctan2(rho, rays[..., 2])  # valid beyond 90 degrees
        t2 = theta * theta
        theta_d = theta * (1.0 + t2 * (d[0] + t2 * (d[1] + t2 * (d[2] + t2 * d[3]))))
        scale = theta_d / jnp.where(rho > 0, rho, 1.0)  # on the axis x = y = 0: any finite scale will do
        q = jnp.stack([k[0] * rays[..., 0] * scale + k[2], k[1] * rays[..., 1] * scale + k[3]], axis=-1)
        valid = theta < fold_angle(d)
    else:
        q = jax.vmap(jax.vmap(lambda p: project(k, coeffs, p)))(rays)
        valid = rays[..., 2] > 0
    q = jnp.where(valid[..., None], q, jnp.nan)
    return q[..., 0], q[..., 1]


def _valid_rectangle(camera: Camera, R, P, new_size, size, projection: str = PINHOLE) -> np.ndarray:
    """(x, y, w, h): bounding box of the rectified pixels whose source lies in the image, sampled on a ROI_GRID x
    ROI_GRID grid (so to a grid step, 1/32 of the image); zeros when no sample does."""
    nw, nh = new_size
    grid = (ROI_GRID, ROI_GRID)
    scale_p = jnp.diag(jnp.array([(ROI_GRID - 1) / (nw - 1), (ROI_GRID - 1) / (nh - 1), 1.0])) @ P
    mx, my = (np.asarray(m) for m in lens_map(jnp.asarray(camera.k), jnp.asarray(camera.dist.coeffs), R, scale_p,
                                               camera.lens, grid, projection))
    w, h = size
    inside = np.isfinite(mx) & np.isfinite(my) & (mx >= 0) & (my >= 0) & (mx <= w - 1) & (my <= h - 1)
    if not inside.any():
        return np.zeros(4)
    rows, cols = np.nonzero(inside)
    x0, x1 = cols.min() * (nw - 1) / (ROI_GRID - 1), cols.max() * (nw - 1) / (ROI_GRID - 1)
    y0, y1 = rows.min() * (nh - 1) / (ROI_GRID - 1), rows.max() * (nh - 1) / (ROI_GRID - 1)
    return np.array([x0, y0, x1 - x0 + 1, y1 - y0 + 1])


def field_of_view(rect: Rectification) -> dict[str, float]:
    """Horizontal and vertical field of view (degrees) of the rectified left image, from its pixel edges."""
    P, (w, h) = np.asarray(rect.P1), rect.size
    if rect.projection == SPHERICAL:
        return wide.field_of_view(P, rect.size)
    f, cx, cy = P[0, 0], P[0, 2], P[1, 2]
    span = lambda lo, hi: float(np.degrees(np.arctan(hi / f) - np.arctan(lo / f)))  # noqa: E731
    return {"horizontal_deg": span(-0.5 - cx, w - 0.5 - cx), "vertical_deg": span(-0.5 - cy, h - 0.5 - cy)}


# --- any pair: the calibrated path's entry ------------------------------------------------------------------------


def has_fisheye(calib) -> bool:
    return "fisheye" in tuple(getattr(calib, "models", ("pinhole", "pinhole")))


def corner_reach(calib) -> tuple[float | None, float | None]:
    """Each camera's widest corner angle off its axis (rad) that the calibration recorded (`corner_angle_max1`,
    `corner_angle_max2` in degrees, dstereo's stereo.yml), None where it did not."""
    return tuple(np.radians(v) if isinstance(v := calib.extras.get(f"corner_angle_max{i}"), float) else None
                 for i in (1, 2))


def rectify_any(calib, image_size: tuple[int, int] | None = None, *, alpha: float = -1.0,
                zero_disparity: bool = True, undistort: str = "opencv", new_size=None,
                projection: str = "auto") -> Rectification:
    """A `StereoCalibration` rectified by its lens models: a pinhole pair by `rectify.rectify_calibration`
    (Bouguet, cv2.stereoRectify, unchanged) unless `projection` is "spherical"; a pair with a fisheye by
    `stereo_rectify_lenses` (`projection`: auto, pinhole or spherical), `alpha` in [0, 1] as its balance (alpha < 0,
    the default: balance 0, cv2.fisheye's default), the field not past the corners' reach (`corner_reach`)."""
    from dstereo.stereo.rectify import rectify_calibration

    if not has_fisheye(calib) and projection != SPHERICAL:
        return rectify_calibration(calib, image_size, alpha=alpha, zero_disparity=zero_disparity,
                                   undistort=undistort, new_size=new_size)
    size = image_size if image_size is not None else calib.image_size
    if size is None:
        raise DstereoError(f"stereo calibration {calib.source or ''}: no image size; give image_size")
    balance = float(alpha) if alpha >= 0 else 0.0
    return stereo_rectify_lenses(*calib.cameras(), calib.rig, size, balance=balance, zero_disparity=zero_disparity,
                                 new_size=new_size, where=f"stereo calibration {calib.source or ''}".strip(),
                                 projection=projection, reach=corner_reach(calib))


def rectification_maps(calib, rect: Rectification) -> list[tuple[np.ndarray, np.ndarray]]:
    """Both cameras' maps (float64, (h, w)) of `rect`; a pinhole pair's pinhole rectification maps are
    `rectify.rectify_map`'s (unchanged)."""
    from dstereo.stereo.rectify import rectify_map

    out = []
    for cam, R, P in zip(calib.cameras(), (rect.R1, rect.R2), (rect.P1, rect.P2)):
        if has_fisheye(calib) or rect.projection != PINHOLE:
            maps = lens_map(cam.k, cam.dist.coeffs, R, P, cam.lens, rect.size, rect.projection)
        else:
            maps = rectify_map(cam.k, cam.dist.coeffs, R, P, rect.size)
        out.append(tuple(np.asarray(m, np.float64) for m in maps))
    return out
