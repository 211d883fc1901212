"""Sub-pixel refinement of an SGBM disparity map: exact cubic-spline rectification, then window-wise
Lucas-Kanade along the rectified rows (`ReconstructionConfig.refine`, `dstereo reconstruct --refine`, used by
`dstereo recession` and the demo).

Why: SGBM's sub-pixel disparity is pixel-locked. On the rendered cork sample 30 % of the face's disparities
have a fractional part within 1/16 px of an integer, against 1.5 % near one half (uniform: 6 % each). A flat
patch such as the stagnation point shares one fractional disparity, so the locking does not average out
there: as the face recedes, the recession measured there is a sawtooth of ~0.25 mm amplitude with a period of
one pixel of disparity (reduced Plasmatron rig, 1.3 px of disparity per mm of depth). Interpolation matters
at the next level: bilinear resampling (and cv2.remap's 1/32 px fixed-point positions) leave a sawtooth of a
few hundredths of a pixel, so here both images are rectified again with cubic B-splines at exact positions
and the right image is shifted along its rows with cubic B-splines too.

Method: the rectified images are normalised by their local mean and standard deviation (brightness and
contrast differences between the cameras drop out), then every pixel's d moves by Gauss-Newton steps
delta = -sum_w(e g) / sum_w(g^2), e = L(x) - R(x - d), g = dR/dx at x - d, sums over a Gaussian window. A
pixel whose refined disparity leaves +-`max_change` px of SGBM's, or whose window has no gradient, is dropped
(NaN), never kept at a locked value.
"""

from __future__ import annotations

import numpy as np


def _grey(image: np.ndarray) -> np.ndarray:
    x = np.asarray(image, np.float64)
    return x if x.ndim == 2 else x[..., :3] @ np.array([0.114, 0.587, 0.299])  # BGR


def rectify_exact(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """Grey image resampled at (map_x, map_y) (float64, px) by cubic B-spline; NaN outside the image."""
    from scipy.ndimage import map_coordinates

    grey = _grey(image)
    out = map_coordinates(grey, [map_y, map_x], order=3, mode="nearest")
    h, w = grey.shape
    outside = (map_x < 0) | (map_y < 0) | (map_x > w - 1) | (map_y > h - 1)
    return np.where(outside, np.nan, out)


def _normalised(x: np.ndarray, sigma: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    x = np.nan_to_num(x, nan=float(np.nanmean(x)))
    mean = gaussian_filter(x, sigma)
    var = gaussian_filter(x * x, sigma) - mean * mean
    return (x - mean) / np.sqrt(np.maximum(var, 1.0))


def _row_spline(coeffs: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cubic B-spline (row-wise coefficients) and its x-derivative at positions x (h, w), clamped to the row."""
    h, w = coeffs.shape
    x = np.clip(x, 0.0, w - 1.0)
    i = np.floor(x).astype(np.int64)
    t = x - i
    rows = np.arange(h)[:, None]
    b = [(1 - t) ** 3 / 6, (3 * t**3 - 6 * t**2 + 4) / 6, (-3 * t**3 + 3 * t**2 + 3 * t + 1) / 6, t**3 / 6]
    db = [-((1 - t) ** 2) / 2, (3 * t**2 - 4 * t) / 2, (-3 * t**2 + 2 * t + 1) / 2, t**2 / 2]
    value = np.zeros_like(x)
    slope = np.zeros_like(x)
    for k in range(4):
        c = coeffs[rows, np.clip(i + k - 1, 0, w - 1)]
        value += b[k] * c
        slope += db[k] * c
    return value, slope


def refine_disparity(left: np.ndarray, right: np.ndarray, disparity: np.ndarray, window_sigma: float = 2.0,
                     iterations: int = 6, max_change: float = 1.0) -> np.ndarray:
    """Refined disparity (h, w) px (d = x_left - x_right) of two rectified grey images (float, NaN outside),
    NaN where SGBM's was NaN or the refinement failed."""
    from scipy.ndimage import gaussian_filter, spline_filter1d

    norm_l, norm_r = _normalised(left, 3 * window_sigma), _normalised(right, 3 * window_sigma)
    coeffs = spline_filter1d(norm_r, order=3, axis=1, mode="mirror")
    h, w = disparity.shape
    valid = np.isfinite(disparity) & np.isfinite(left)
    d0 = np.where(valid, disparity, 0.0).astype(np.float64)
    d = d0.copy()
    xs = np.arange(w, dtype=float)[None, :]
    g2 = np.zeros_like(d)
    for _ in range(iterations):
        warped, g = _row_spline(coeffs, xs - d)
        e = norm_l - warped
        eg = gaussian_filter(e * g, window_sigma)
        g2 = gaussian_filter(g * g, window_sigma)
        # R(x - d - delta) ~ R(x - d) - delta g, so the residual becomes e + delta g: delta = -sum(e g) / sum(g^2)
        step = np.where(g2 > 1e-6, eg / np.maximum(g2, 1e-6), 0.0)
        d = d - np.clip(step, -0.5, 0.5)
    x_right = xs - d
    bad = ~valid | (np.abs(d - d0) > max_change) | (g2 <= 1e-6) | (x_right < 0) | (x_right > w - 1)
    return np.where(bad, np.nan, d)


def refine_right_disparity(left: np.ndarray, right: np.ndarray, disparity_right: np.ndarray, **kwargs) -> np.ndarray:
    """The right image's disparity map (on the right grid, d = x_left - x_right as the left map's) refined the
    same way, with the roles of the images swapped: right(x) = left(x + d)."""
    return -refine_disparity(right, left, -np.asarray(disparity_right, np.float64), **kwargs)


def exact_pair(left: np.ndarray, right: np.ndarray, maps=None) -> tuple[np.ndarray, np.ndarray]:
    """Both rectified grey images (float64) resampled from the originals by cubic B-spline at the exact map
    positions `maps` = ((map_x, map_y) left, (map_x, map_y) right); maps None: the images are already rectified."""
    if maps is None:
        return _grey(left), _grey(right)
    (lx, ly), (rx, ry) = maps
    return rectify_exact(left, lx, ly), rectify_exact(right, rx, ry)


def homography_maps(H: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(map_x, map_y) (h, w) float64: the original pixel that a homography-rectified pixel (cv2.warpPerspective
    with H, original -> rectified) comes from."""
    w, h = size
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    src = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(np.asarray(H, np.float64)).T
    return src[..., 0] / src[..., 2], src[..., 1] / src[..., 2]


def dropped_fraction(before: np.ndarray, after: np.ndarray) -> float:
    """Fraction of the pixels with a disparity `before` that have none `after` the refinement."""
    had = np.isfinite(before)
    return float((had & ~np.isfinite(after)).sum() / max(int(had.sum()), 1))


def refinement_terms(left: np.ndarray, right: np.ndarray, disparity: np.ndarray, window_sigma: float = 2.0):
    """The per-pixel quantities of `refine_disparity`'s last Gauss-Newton step at `disparity`, for its noise
    model (`dstereo.stereo.disparity_noise`): the residual e = L(x) - R(x - d) and the gradient g of the normalised
    images at x - d, and the local standard deviations (grey levels) the left image and the warped right image
    were divided by. NaN-free; where `disparity` is NaN the values are taken at d = 0 (the caller masks them)."""
    from scipy.ndimage import gaussian_filter, spline_filter1d

    def local_std(x):
        x = np.nan_to_num(x, nan=float(np.nanmean(x)))
        mean = gaussian_filter(x, 3 * window_sigma)
        return np.sqrt(np.maximum(gaussian_filter(x * x, 3 * window_sigma) - mean * mean, 1.0))

    norm_r = _normalised(right, 3 * window_sigma)
    coeffs = spline_filter1d(norm_r, order=3, axis=1, mode="mirror")
    w = disparity.shape[1]
    xs = np.arange(w, dtype=float)[None, :] - np.nan_to_num(np.asarray(disparity, np.float64))
    warped, g = _row_spline(coeffs, xs)
    s_right = local_std(right)
    cols = np.clip(np.rint(xs), 0, w - 1).astype(np.int64)
    e = _normalised(left, 3 * window_sigma) - warped
    return e, g, local_std(left), s_right[np.arange(disparity.shape[0])[:, None], cols]
