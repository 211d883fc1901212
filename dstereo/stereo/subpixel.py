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

import weakref

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


class _PerImage:
    """What the refinement derives from one rectified image (local mean/std normalisation, row spline
    coefficients), kept while that image lives: `refine_disparity` and its noise model (`refinement_terms`, via
    `dstereo.stereo.disparity_noise`) see the same pair and would otherwise derive it twice (8 of a frame's 26
    Gaussian filters). Only read-only arrays are remembered (`exact_pair` makes its pair read-only), so an image
    changed in place is never served stale values; entries go when their image is freed."""

    def __init__(self):
        self.values: dict[tuple, object] = {}

    def get(self, x: np.ndarray, what: str, arg, compute):
        if not isinstance(x, np.ndarray) or x.flags.writeable:
            return compute()
        key = (id(x), what, arg)
        if key not in self.values:
            if not any(k[0] == id(x) for k in self.values):
                weakref.finalize(x, self._drop, id(x))
            self.values[key] = compute()
        return self.values[key]

    def _drop(self, ident: int) -> None:
        for key in [k for k in self.values if k[0] == ident]:
            del self.values[key]


_PER_IMAGE = _PerImage()


def _local_stats(x: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """(x normalised by its local mean and std, that std (grey levels, at least 1)) over a Gaussian of sigma px."""
    from scipy.ndimage import gaussian_filter

    def compute():
        y = np.nan_to_num(x, nan=float(np.nanmean(x)))
        mean = gaussian_filter(y, sigma)
        std = np.sqrt(np.maximum(gaussian_filter(y * y, sigma) - mean * mean, 1.0))
        return (y - mean) / std, std

    return _PER_IMAGE.get(x, "local_stats", sigma, compute)


def _normalised(x: np.ndarray, sigma: float) -> np.ndarray:
    return _local_stats(x, sigma)[0]


def _row_coefficients(x: np.ndarray, sigma: float) -> np.ndarray:
    """Row-wise cubic B-spline coefficients of the normalised image, padded by its edge columns (1 left, 2
    right) so that `_row_spline` reads the 4 taps of a clamped position without clipping each index."""
    from scipy.ndimage import spline_filter1d

    def compute():
        coeffs = spline_filter1d(_normalised(x, sigma), order=3, axis=1, mode="mirror")
        return np.pad(coeffs, ((0, 0), (1, 2)), mode="edge")

    return _PER_IMAGE.get(x, "row_coefficients", sigma, compute)


ROW_BLOCK = 32  # rows per block of `_row_spline`: its ~60 array passes stay in cache (2x faster at 640 x 480)


def _row_spline(padded: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cubic B-spline (row-wise coefficients, edge-padded as `_row_coefficients`) and its x-derivative at
    positions x (h, w), clamped to the row; computed in blocks of ROW_BLOCK rows (each pixel's arithmetic is the
    same either way)."""
    value, slope = np.empty_like(x, dtype=float), np.empty_like(x, dtype=float)
    for r in range(0, x.shape[0], ROW_BLOCK):
        value[r:r + ROW_BLOCK], slope[r:r + ROW_BLOCK] = _row_spline_block(padded[r:r + ROW_BLOCK], x[r:r + ROW_BLOCK])
    return value, slope


def _row_spline_block(padded: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`_row_spline` of a block of rows. Tap k of position i reads coefficient clip(i + k - 1, 0, w - 1), i.e.
    padded column i + k."""
    h, wp = padded.shape
    w = wp - 3
    x = np.clip(x, 0.0, w - 1.0)
    i = np.floor(x).astype(np.int64)
    t = x - i
    flat = padded.ravel()
    base = i + (np.arange(h) * wp)[:, None]
    # the same expressions as the B-spline basis written out (each power computed once, not per term)
    s, t2, t3 = 1 - t, t**2, t**3
    b = [s**3 / 6, (3 * t3 - 6 * t2 + 4) / 6, (-3 * t3 + 3 * t2 + 3 * t + 1) / 6, t3 / 6]
    db = [-(s**2) / 2, (3 * t2 - 4 * t) / 2, (-3 * t2 + 2 * t + 1) / 2, t2 / 2]
    value = np.zeros_like(x)
    slope = np.zeros_like(x)
    for k in range(4):
        c = flat.take(base + k)
        value += b[k] * c
        slope += db[k] * c
    return value, slope


def refine_disparity(left: np.ndarray, right: np.ndarray, disparity: np.ndarray, window_sigma: float = 2.0,
                     iterations: int = 6, max_change: float = 1.0) -> np.ndarray:
    """Refined disparity (h, w) px (d = x_left - x_right) of two rectified grey images (float, NaN outside),
    NaN where SGBM's was NaN or the refinement failed."""
    from scipy.ndimage import gaussian_filter

    norm_l, coeffs = _normalised(left, 3 * window_sigma), _row_coefficients(right, 3 * window_sigma)
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
        pair = _grey(left), _grey(right)
        if any(np.shares_memory(p, o) for p, o in zip(pair, (left, right))):  # a grey float64 input as it is
            pair = tuple(p.copy() for p in pair)
    else:
        (lx, ly), (rx, ry) = maps
        pair = rectify_exact(left, lx, ly), rectify_exact(right, rx, ry)
    for p in pair:  # read-only: the refinement and its noise model share what they derive from it (`_PerImage`)
        p.flags.writeable = False
    return pair


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
    norm_l, s_left = _local_stats(left, 3 * window_sigma)
    s_right = _local_stats(right, 3 * window_sigma)[1]
    w = disparity.shape[1]
    xs = np.arange(w, dtype=float)[None, :] - np.nan_to_num(np.asarray(disparity, np.float64))
    warped, g = _row_spline(_row_coefficients(right, 3 * window_sigma), xs)
    cols = np.clip(np.rint(xs), 0, w - 1).astype(np.int64)
    e = norm_l - warped
    return e, g, s_left, s_right[np.arange(disparity.shape[0])[:, None], cols]
