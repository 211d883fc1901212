"""Stereo rectification in JAX: Bouguet's method as OpenCV's `stereoRectify`, plus Hartley's uncalibrated homographies.

Calibrated (`stereo_rectify`): both cameras are rotated by half the relative rotation, then by the rotation that
aligns the baseline with the image x axis (y for a vertical rig); the new focal length is the mean of the two
fy (fx for vertical rigs), the principal points centre the undistorted image corners, and `alpha` blends between
keeping only valid pixels (0) and keeping every source pixel (1); `alpha < 0` keeps OpenCV's default scale.
The two cameras may differ (intrinsics, distortion). OpenCV 5.0's algorithm is reproduced step by step,
including its 5-step fixed-point undistortion of the image border and the float32 rounding of the four
corner points, so R1, R2, P1, P2, Q and the valid ROIs agree with `cv2.stereoRectify` to machine precision.
`undistort="exact"` uses the Newton inverse of `dstereo.models.distortion` instead (the result then differs
from OpenCV wherever its 5 fixed-point steps have not converged: 1.3e-5 relative in P1 for the strong rational
lens of OpenCV's sample stereo set).

Uncalibrated (`rectify_uncalibrated`, numpy): Hartley's homographies, as OpenCV's `stereoRectifyUncalibrated`.
Conventions: x_right = R x_left + T (OpenCV), pixel (0, 0) is the centre of the top-left pixel.
"""

from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dstereo.errors import DstereoError
from dstereo.models.camera import Camera, project
from dstereo.models.distortion import undistort as undistort_newton
from dstereo.models.pose import rodrigues
from dstereo.models.rig import Rig

GRID = 9  # border sampling of OpenCV's getUndistortRectangles: a 9 x 9 grid of pixels


PINHOLE = "pinhole"  # rectified images are pinhole images: u = cx + f x / z (OpenCV's)
SPHERICAL = "spherical"  # epipolar-rectified spherical (`rectify_wide`): rows are planes through the baseline
PROJECTIONS = (PINHOLE, SPHERICAL)


class Rectification(eqx.Module):
    """Rectifying rotations R1, R2 (original -> rectified camera), projections P1, P2, disparity-to-depth Q.

    `roi1`, `roi2` are OpenCV's valid-pixel rectangles (x, y, w, h) in the rectified images of size `size`.
    `projection` says what a rectified pixel is: PINHOLE (P maps a point, Q maps a disparity to it exactly) or
    SPHERICAL (`dstereo.stereo.rectify_wide`: P holds px per radian and the pixel of the angles' zero, P2[0, 3]
    the baseline; Q is then only the paraxial equivalent, f B / d, and points come from
    `triangulate.reproject_spherical`). `why` says why this projection was chosen ("" when not chosen).
    """

    R1: Float[Array, "3 3"]
    R2: Float[Array, "3 3"]
    P1: Float[Array, "3 4"]
    P2: Float[Array, "3 4"]
    Q: Float[Array, "4 4"]
    roi1: Float[Array, "4"]
    roi2: Float[Array, "4"]
    size: tuple[int, int] = eqx.field(static=True)
    vertical: bool = eqx.field(static=True, default=False)
    projection: str = eqx.field(static=True, default=PINHOLE)
    why: str = eqx.field(static=True, default="")


def undistort_fixed_point(coeffs: Float[Array, "8"], xy_d: Float[Array, "2"], iterations: int = 5) -> Float[Array, "2"]:
    """OpenCV's `undistortPoints` inverse (fixed-point steps, 5 by default), one normalised point.

    Not an exact inverse for strong distortion; it exists to reproduce OpenCV's numbers.
    """
    k1, k2, p1, p2, k3, k4, k5, k6 = coeffs

    def step(carry, _):
        xy, stopped = carry
        x, y = xy[0], xy[1]
        r2 = x * x + y * y
        icdist = (1.0 + ((k6 * r2 + k5) * r2 + k4) * r2) / (1.0 + ((k3 * r2 + k2) * r2 + k1) * r2)
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        new = jnp.stack([(xy_d[0] - dx) * icdist, (xy_d[1] - dy) * icdist])
        bad = icdist < 0  # OpenCV gives up and returns the distorted point
        new = jnp.where(stopped, xy, jnp.where(bad, xy_d, new))
        return (new, stopped | bad), None

    (xy, _), _ = jax.lax.scan(step, (xy_d, jnp.array(False)), None, length=iterations)
    return xy


def _undistort_pixels(k, coeffs, q, method: str):
    """Pixels (n, 2) -> undistorted normalised coordinates (n, 2), OpenCV's `(u - cx) * (1 / fx)` first."""
    xy_d = (q - k[2:4]) * (1.0 / k[0:2])
    inverse = undistort_fixed_point if method == "opencv" else undistort_newton
    return jax.vmap(lambda p: inverse(coeffs, p))(xy_d)


def _to_f32(x):
    return x.astype(jnp.float32).astype(x.dtype)


def _corner_centre(k, coeffs, r_k, fc, nx, ny, method):
    """Mean of the four undistorted image corners seen through r_k with focal fc (OpenCV rounds them to float32)."""
    corners = jnp.array([[0.0, 0.0], [nx - 1.0, 0.0], [0.0, ny - 1.0], [nx - 1.0, ny - 1.0]])
    xy = _to_f32(_undistort_pixels(k, coeffs, corners, method))
    p = jnp.concatenate([xy, jnp.ones((4, 1))], axis=1) @ r_k.T
    uv = _to_f32(fc * p[:, :2] / p[:, 2:3])
    return jnp.array([(nx - 1.0) / 2.0, (ny - 1.0) / 2.0]) - jnp.mean(uv, axis=0)


def _rectangles(k, coeffs, r_k, p_k, nx, ny, method):
    """Inner (all valid) and outer (all source pixels) rectangles (x, y, w, h) of the rectified 9 x 9 grid."""
    g = jnp.arange(GRID, dtype=float)
    gx, gy = jnp.meshgrid(g, g)  # rows: y
    q = jnp.stack([gx.ravel() * ((nx - 1) / (GRID - 1.0)), gy.ravel() * ((ny - 1) / (GRID - 1.0))], axis=1)
    xy = _undistort_pixels(k, coeffs, q, method)
    h = jnp.concatenate([xy, jnp.ones((xy.shape[0], 1))], axis=1) @ (p_k[:, :3] @ r_k).T
    w = 1.0 / h[:, 2]
    u = (h[:, 0] * w).reshape(GRID, GRID)
    v = (h[:, 1] * w).reshape(GRID, GRID)
    x0, y0, x1, y1 = u[:, 0].max(), v[0, :].max(), u[:, -1].min(), v[-1, :].min()
    inner = jnp.array([x0, y0, x1 - x0, y1 - y0])
    x0, y0, x1, y1 = u.min(), v.min(), u.max(), v.max()
    return inner, jnp.array([x0, y0, x1 - x0, y1 - y0])


def _scale_bounds(c0, c, rect, new_w, new_h):
    """Per-side ratios of OpenCV's free scaling: how much the rectangle must grow to reach each image edge."""
    return jnp.array([
        c[0] / (c0[0] - rect[0]),
        c[1] / (c0[1] - rect[1]),
        (new_w - 1 - c[0]) / (rect[0] + rect[2] - c0[0]),
        (new_h - 1 - c[1]) / (rect[1] + rect[3] - c0[1]),
    ])


def _roi(rect, c0, c, s, new_w, new_h):
    """OpenCV's valid ROI: ceil of the scaled inner corner, floor of its size, clipped to the image."""
    x = jnp.ceil((rect[0] - c0[0]) * s + c[0])
    y = jnp.ceil((rect[1] - c0[1]) * s + c[1])
    w = jnp.floor(rect[2] * s)
    h = jnp.floor(rect[3] * s)
    x0, y0 = jnp.maximum(x, 0), jnp.maximum(y, 0)
    x1, y1 = jnp.minimum(x + w, new_w), jnp.minimum(y + h, new_h)
    empty = (x1 <= x0) | (y1 <= y0)
    return jnp.where(empty, jnp.zeros(4), jnp.array([x0, y0, x1 - x0, y1 - y0]))


def _half_rotations(rvec, T):
    """Half-rotations r_r (right half) and the rotated baseline t = r_r T (rvec: the rig's axis-angle)."""
    r_r = rodrigues(-0.5 * rvec)
    return r_r, r_r @ T


def rectifying_rotations(rvec, T, idx: int):
    """Bouguet's R1, R2 (original -> rectified camera) and the rectified baseline (R2 T)[idx]: half the relative
    rotation each, then the rotation that turns the baseline onto image axis `idx` (0: x, 1: y). Shared by every
    lens model's rectification (cv2.stereoRectify and cv2.fisheye.stereoRectify rotate alike)."""
    r_r, t = _half_rotations(rvec, T)
    c = t[idx]
    uu = jnp.zeros(3).at[idx].set(jnp.where(c > 0, 1.0, -1.0))
    ww = jnp.cross(t, uu)  # rotation axis x sin(angle) |t| that turns t onto the image axis
    nw2 = ww @ ww
    small = nw2 < 1e-24 * (c * c)  # baseline already aligned: angle / nw -> 1 / |c| (finite gradients)
    nw = jnp.sqrt(jnp.where(small, 1.0, nw2))
    w_r = rodrigues(ww * jnp.where(small, 1.0 / jnp.abs(c), jnp.arctan2(nw, jnp.abs(c)) / nw))
    R1 = w_r @ r_r.T
    R2 = w_r @ r_r
    return R1, R2, (R2 @ T)[idx]


@partial(jax.jit, static_argnames=("idx", "method"))
def _rectify(k1, c1, k2, c2, rvec, T, alpha, zero_disparity, sizes, *, idx, method):
    nx, ny, new_w, new_h = sizes  # traced: one compilation serves every image size
    R1, R2, t_idx = rectifying_rotations(rvec, T, idx)

    ratio = (new_w / nx if idx == 1 else new_h / ny) / 2.0
    fc = (k1[idx ^ 1] + k2[idx ^ 1]) * ratio
    cc = jnp.stack([
        _corner_centre(k1, c1, R1, fc, nx, ny, method),
        _corner_centre(k2, c2, R2, fc, nx, ny, method),
    ])
    other = 1 - idx  # the coordinate along which the images must share a principal point
    cc = jnp.where(zero_disparity, jnp.broadcast_to(cc.mean(axis=0), (2, 2)), cc.at[:, other].set(cc[:, other].mean()))

    def projection(cc_k, fc, tx):
        P = jnp.zeros((3, 4)).at[0, 0].set(fc).at[1, 1].set(fc).at[0:2, 2].set(cc_k).at[2, 2].set(1.0)
        return P.at[idx, 3].set(tx)

    P1 = projection(cc[0], fc, 0.0)
    P2 = projection(cc[1], fc, t_idx * fc)
    inner1, outer1 = _rectangles(k1, c1, R1, P1, nx, ny, method)
    inner2, outer2 = _rectangles(k2, c2, R2, P2, nx, ny, method)

    scale_new = jnp.array([new_w / nx, new_h / ny])
    cc_new = cc * scale_new
    a = jnp.minimum(alpha, 1.0)
    s0 = jnp.max(jnp.concatenate([
        _scale_bounds(cc[0], cc_new[0], inner1, new_w, new_h), _scale_bounds(cc[1], cc_new[1], inner2, new_w, new_h)
    ]))
    s1 = jnp.min(jnp.concatenate([
        _scale_bounds(cc[0], cc_new[0], outer1, new_w, new_h), _scale_bounds(cc[1], cc_new[1], outer2, new_w, new_h)
    ]))
    s = jnp.where(a >= 0, s0 * (1.0 - a) + s1 * a, 1.0)  # alpha < 0: OpenCV's default scale
    P1 = projection(cc_new[0], fc * s, 0.0)
    P2 = projection(cc_new[1], fc * s, t_idx * fc * s)
    Q = q_matrix(P1, P2, vertical=idx == 1)
    roi1 = _roi(inner1, cc[0], cc_new[0], s, new_w, new_h)
    roi2 = _roi(inner2, cc[1], cc_new[1], s, new_w, new_h)
    return R1, R2, P1, P2, Q, roi1, roi2


def q_matrix(P1: Float[Array, "3 4"], P2: Float[Array, "3 4"], vertical: bool = False) -> Float[Array, "4 4"]:
    """OpenCV's disparity-to-depth matrix from rectified projections (P2[idx, 3] = Tx * f).

    [X Y Z W] = Q [u v d 1] gives the point in the rectified left camera frame; units those of T.
    """
    idx = 1 if vertical else 0
    f = P1[0, 0]
    cx1, cy1 = P1[0, 2], P1[1, 2]
    tx = P2[idx, 3] / P2[idx, idx]
    offset = (cx1 - P2[0, 2]) if idx == 0 else (cy1 - P2[1, 2])
    return jnp.array([
        [1.0, 0.0, 0.0, -cx1],
        [0.0, 1.0, 0.0, -cy1],
        [0.0, 0.0, 0.0, f],
        [0.0, 0.0, -1.0 / tx, offset / tx],
    ])


def stereo_rectify(
    left: Camera,
    right: Camera,
    rig: Rig,
    image_size: tuple[int, int],
    *,
    alpha: float = -1.0,
    zero_disparity: bool = True,
    new_size: tuple[int, int] | None = None,
    undistort: str = "opencv",
    vertical: bool | None = None,
) -> Rectification:
    """Bouguet rectification of a calibrated pair, as `cv2.stereoRectify` (whose Python default flag is
    CALIB_ZERO_DISPARITY, i.e. `zero_disparity=True`: both principal points equal).

    The two cameras' k = (fx, fy, cx, cy) px and 8 coefficients (OpenCV order) and the rig (x_right = R x_left
    + T; T in mm gives Q in mm); image_size = (width, height). `alpha` in [0, 1] is OpenCV's free scaling,
    negative for the default. `zero_disparity=False` keeps each image's own principal point along the baseline
    (smaller disparities for converging rigs). Differentiable in every array of the cameras and the rig; under
    a JAX transform of the rig give `vertical` (is the baseline closer to the image y axis?), which is
    otherwise read off the rig.
    """
    if undistort not in ("opencv", "exact"):
        raise DstereoError(f"undistort={undistort!r}: use 'opencv' (reproduce cv2) or 'exact' (Newton inverse)")
    for side, cam in (("left", left), ("right", right)):
        if cam.lens == "fisheye":  # its coefficients are cv2.fisheye's, not OpenCV's pinhole distortion
            raise DstereoError(f"stereo_rectify: the {side} camera is a fisheye; rectify the pair with "
                               "dstereo.stereo.rectify_fisheye.stereo_rectify_lenses (rectify_any for a calibration)")
    w, h = (int(v) for v in image_size)
    if w < 2 or h < 2:
        raise DstereoError(f"image_size {image_size}: need width and height of at least 2 pixels")
    new = (w, h) if new_size is None or new_size[0] * new_size[1] == 0 else (int(new_size[0]), int(new_size[1]))
    rvec = jnp.asarray(rig.rvec, dtype=float).reshape(3)
    T = jnp.asarray(rig.tvec, dtype=float).reshape(3)
    if vertical is None:
        if isinstance(rvec, jax.core.Tracer) or isinstance(T, jax.core.Tracer):
            raise DstereoError("stereo_rectify under a JAX transform of the rig: pass vertical=True/False")
        t = np.asarray(_half_rotations(rvec, T)[1])
        if not np.linalg.norm(t) > 0:
            raise DstereoError("stereo calibration: the baseline T is zero; check the extrinsics (T) of the calibration")
        vertical = bool(abs(t[0]) <= abs(t[1]))
    idx = 1 if vertical else 0
    arrays = [jnp.asarray(a, dtype=float) for a in (left.k, left.dist.coeffs, right.k, right.dist.coeffs)]
    out = _rectify(*arrays, rvec, T, jnp.asarray(alpha, dtype=float), jnp.asarray(bool(zero_disparity)),
                   jnp.array([w, h, *new], dtype=float), idx=idx, method=undistort)
    return Rectification(*out, size=new, vertical=idx == 1)


def rectify_calibration(calib, image_size: tuple[int, int] | None = None, **options) -> Rectification:
    """`stereo_rectify` of a `StereoCalibration` (its cameras and rig), at its own image size unless given."""
    size = image_size if image_size is not None else calib.image_size
    if size is None:
        raise DstereoError(f"stereo calibration {calib.source or ''}: no image size; give image_size")
    return stereo_rectify(*calib.cameras(), calib.rig, size, **options)


def rectified_from_projections(P1, P2, size: tuple[int, int]) -> Rectification:
    """A pair that is already rectified (e.g. Middlebury): identity rotations, the given projections."""
    P1 = jnp.asarray(P1, dtype=float)
    P2 = jnp.asarray(P2, dtype=float)
    full = jnp.array([0.0, 0.0, size[0], size[1]])
    vertical = bool(abs(float(P2[1, 3])) > abs(float(P2[0, 3])))
    return Rectification(jnp.eye(3), jnp.eye(3), P1, P2, q_matrix(P1, P2, vertical), full, full, tuple(size), vertical)


@partial(jax.jit, static_argnames=("size",))
def rectify_map(
    k: Float[Array, "4"], coeffs: Float[Array, "8"], R: Float[Array, "3 3"], P: Float[Array, "3 4"], size: tuple[int, int]
) -> tuple[Float[Array, "h w"], Float[Array, "h w"]]:
    """Source pixel of every rectified pixel (as `cv2.initUndistortRectifyMap`): maps (h, w) for `cv2.remap`."""
    w, h = size
    inv = jnp.linalg.inv(P[:, :3] @ R)
    u, v = jnp.meshgrid(jnp.arange(w, dtype=float), jnp.arange(h, dtype=float))
    rays = jnp.stack([u, v, jnp.ones_like(u)], axis=-1) @ inv.T
    q = jax.vmap(jax.vmap(lambda p: project(k, coeffs, p)))(rays)
    return q[..., 0], q[..., 1]


# --- uncalibrated (Hartley 1999), numpy ---------------------------------------------------------------------


def _epilines(points: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Lines F [x y 1] (n, 3) scaled so a^2 + b^2 = 1 (OpenCV's computeCorrespondEpilines)."""
    lines = np.concatenate([points, np.ones((len(points), 1))], axis=1) @ F.T
    n = np.hypot(lines[:, 0], lines[:, 1])
    return lines / np.where(n > 0, n, 1.0)[:, None]


def _apply_h(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    p = np.concatenate([points, np.ones((len(points), 1))], axis=1) @ H.T
    return p[:, :2] / p[:, 2:3]


def rectify_uncalibrated(
    points1: np.ndarray, points2: np.ndarray, F: np.ndarray, image_size: tuple[int, int], threshold: float = 5.0
) -> tuple[np.ndarray, np.ndarray]:
    """Rectifying homographies (H1, H2) from matches and F (x2^T F x1 = 0), as `cv2.stereoRectifyUncalibrated`.

    H2 sends the right epipole to infinity along x (centred on the image middle); H1 is the matching
    homography that minimises the horizontal disparity of the matches. Pairs farther than `threshold` px from
    their epipolar lines are ignored (<= 0 keeps all).
    """
    m1 = np.asarray(points1, dtype=float).reshape(-1, 2)
    m2 = np.asarray(points2, dtype=float).reshape(-1, 2)
    if len(m1) != len(m2) or len(m1) == 0:
        raise DstereoError(f"rectify_uncalibrated: {len(m1)} and {len(m2)} points; give the same non-zero number")
    U, W, Vt = np.linalg.svd(np.asarray(F, dtype=float))
    F = U @ np.diag([W[0], W[1], 0.0]) @ Vt
    cx = float(np.floor((image_size[0] - 1) * 0.5 + 0.5))
    cy = float(np.floor((image_size[1] - 1) * 0.5 + 0.5))
    if threshold > 0:
        d1 = np.abs(np.sum(np.c_[m1, np.ones(len(m1))] * _epilines(m2, F.T), axis=1))
        d2 = np.abs(np.sum(np.c_[m2, np.ones(len(m2))] * _epilines(m1, F), axis=1))
        keep = (d1 <= threshold) & (d2 <= threshold)
        if not keep.any():
            raise DstereoError(
                f"rectify_uncalibrated: no match lies within {threshold} px of its epipolar line; "
                "check F or raise the threshold"
            )
        m1, m2 = m1[keep], m2[keep]
    e2 = U[:, 2] * (-1.0 if U[2, 2] < 0 else 1.0)
    T = np.array([[1.0, 0.0, -cx], [0.0, 1.0, -cy], [0.0, 0.0, 1.0]])
    e = T @ e2
    mirror = e[0] < 0
    d = max(np.hypot(e[0], e[1]), np.finfo(float).eps)
    Rz = np.array([[e[0] / d, e[1] / d, 0.0], [-e[1] / d, e[0] / d, 0.0], [0.0, 0.0, 1.0]])
    e = Rz @ e
    invf = 0.0 if abs(e[2]) < 1e-6 * abs(e[0]) else -e[2] / e[0]
    K = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [invf, 0.0, 1.0]])
    iT = np.array([[1.0, 0.0, cx], [0.0, 1.0, cy], [0.0, 0.0, 1.0]])
    H2 = iT @ K @ Rz @ T
    e2x = np.array([[0.0, -e2[2], e2[1]], [e2[2], 0.0, -e2[0]], [-e2[1], e2[0], 0.0]])
    H0 = H2 @ (e2x @ F + np.outer(e2, np.ones(3)))
    a = np.c_[_apply_h(H0, m1), np.ones(len(m1))]
    x, *_ = np.linalg.lstsq(a, _apply_h(H2, m2)[:, 0], rcond=None)
    H1 = np.array([x, [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) @ H0
    if mirror:
        M = np.array([[-1.0, 0.0, 2 * cx], [0.0, -1.0, 2 * cy], [0.0, 0.0, 1.0]])
        H1, H2 = M @ H1, M @ H2
    return H1, H2


def focal_px(
    focal_mm: float, image_width: int, *, pixel_size_mm: float | None = None, crop_factor: float | None = None
) -> float:
    """Focal length in px from the lens focal length and either the pixel pitch or the crop factor (36 mm frame)."""
    if (pixel_size_mm is None) == (crop_factor is None):
        raise DstereoError("focal length: give exactly one of the pixel size (mm) or the crop factor")
    if focal_mm <= 0:
        raise DstereoError(f"focal length {focal_mm} mm: must be positive")
    if pixel_size_mm is not None:
        if pixel_size_mm <= 0:
            raise DstereoError(f"pixel size {pixel_size_mm} mm: must be positive")
        return focal_mm / pixel_size_mm
    if crop_factor <= 0:
        raise DstereoError(f"crop factor {crop_factor}: must be positive")
    return focal_mm * image_width * crop_factor / 36.0


def q_uncalibrated(image_size: tuple[int, int], f_px: float, baseline: float = 1.0) -> Float[Array, "4 4"]:
    """Q for a homography-rectified pair (thesis 4.2.2.4): principal point at the image centre, focal f_px, the
    right camera `baseline` along +x (1 gives a reconstruction of unknown scale)."""
    cx, cy = (image_size[0] - 1) / 2.0, (image_size[1] - 1) / 2.0
    P1 = jnp.array([[f_px, 0.0, cx, 0.0], [0.0, f_px, cy, 0.0], [0.0, 0.0, 1.0, 0.0]])
    return q_matrix(P1, P1.at[0, 3].set(-baseline * f_px))
