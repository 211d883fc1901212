"""Confidence-aware fill of the pixels the matcher left without a disparity (issue 30): an edge-aware local
plane fit, with each filled pixel's own disparity sigma, and the pixels too uncertain to fill left empty.

For an unmatched pixel p, the matched pixels q of a window around it are weighted by how alike their colours are
(w_q = exp(-|I_q - I_p| / COLOUR_SCALE), mean absolute difference over the channels, 8-bit levels): pixels of
another surface usually differ in colour, so the window's plane is mostly the surface p lies on (an edge-aware
fit, the support-weight idea of Yoon & Kweon 2006 applied to a plane d = a + b du + c dv as in the
slanted-plane fills of segment-based stereo). Two re-weightings (Tukey's biweight on the residuals, at 4.685
robust stds) drop mismatches and the other surface's pixels that pass the colour test.

The sigma of a fill (px) is the weighted regression's prediction error for one more sample at p with the unit
weight of a pixel of p's own colour: sigma^2 = s^2 (1 + (A^-1)_00), s^2 = the weighted residual variance of the
window about its plane (sum w r^2 / sum w, scaled by n_eff / (n_eff - 3), n_eff = (sum w)^2 / sum w^2), A the
weighted normal matrix in (1, du, dv). It is larger than a matched pixel's where the window's surface is not
flat or mixes surfaces, and where p lies at the edge of its support. A pixel is filled only when that sigma is at
most `max_sigma` px and its window holds at least MIN_SUPPORT weight on matched pixels around it, at least
MIN_SIDE_SUPPORT of it on each side (left, right, above, below: a hole is interpolated, a rim never extended); the
rest stay
NaN. The fill uses matched pixels only (a fill never feeds another). The raw sigma is then scaled by `sigma_scale`'s
k, measured on the image itself by filling matched pixels hidden around the holes. Limitation: the window's
scatter is taken as the pixel's own, so where it is mostly matching noise (smooth, well-textured surfaces, which
the fit averages) the sigma overstates the error against the true surface (0.24 x on a noisy synthetic sphere
cap); on Middlebury, where surface shape and mixed surfaces dominate, observed / predicted (robust std of the
errors / RMS sigma) is 0.45-0.86, the per-pixel robust std of error / sigma 0.55-1.20 (still conservative on
Adirondack and Teddy). Checked against ground truth in
experiments/middlebury_lighting.py and on renders in tests/stereo/test_fill.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

COLOUR_SCALE = 10.0  # 8-bit levels at which a neighbour's weight falls to 1/e
MIN_SUPPORT = 8.0  # summed weight of matched pixels a fill needs (a 3 x 3 of same-coloured pixels)
MIN_SIDE_SUPPORT = 0.3  # and on each side of the pixel (a hole's, not a rim's): a third of a same-coloured pixel
BIWEIGHT_C = 4.685  # Tukey's constant: 95 % efficiency at normal residuals
MAD_TO_STD = 1.4826
# The windows tried, smallest first: (half width px, stride px); a pixel keeps the first that fills it.
PASSES = ((6, 1), (14, 2), (30, 4))
HOLDOUT_BAND = 3  # px: the band of matched pixels around the holes hidden to measure the sigma scale
HOLDOUT_PIXELS = 4000  # of them filled (a robust std to ~1.5 %)
MIN_HOLDOUT = 100  # fewer: the scale is not measured (1)
CHUNK = 4096  # unmatched pixels per vectorised block (memory ~ CHUNK x window samples x 8 bytes, a few x)


@dataclass(frozen=True)
class Fill:
    """A disparity map with its unmatched pixels filled where possible: `disparity` (h, w) px, `filled` (h, w)
    bool, `sigma` (h, w) px (the fill's sigma on filled pixels, NaN elsewhere)."""

    disparity: np.ndarray
    filled: np.ndarray
    sigma: np.ndarray
    scale: float = 1.0  # `sigma_scale`'s k, applied to every fill's raw sigma
    scale_pixels: int = 0  # the hold-out fills k was measured on

    def summary(self, max_sigma: float) -> dict:
        matched = int(np.isfinite(self.disparity).sum() - self.filled.sum())
        s = self.sigma[self.filled]
        return {"enabled": True, "filled_pixels": int(self.filled.sum()), "matched_pixels": matched,
                "max_sigma_px": max_sigma,
                "sigma_px": {"median": float(np.median(s)), "p90": float(np.percentile(s, 90))} if s.size else None,
                "method": "edge-aware local plane fit on matched pixels (dstereo.stereo.fill); a filled pixel "
                          "carries its own sigma (the fit's prediction error) and the flag `filled`"}


def _colours(image: np.ndarray) -> np.ndarray:
    return (image[..., None] if image.ndim == 2 else image).astype(np.int16)


def _colour_weights(channels: int) -> np.ndarray:
    """exp(-mean |difference| / COLOUR_SCALE) for every summed absolute difference 0..255 channels (a table: the
    weights of a window are looked up, not exponentiated)."""
    return np.exp(-np.arange(255 * channels + 1) / channels / COLOUR_SCALE).astype(np.float32)


def _fit_block(disp_pad, col_pad, ys, xs, oy, ox, centre_col):
    """Weighted robust plane at each (ys, xs) (padded coordinates) from the samples at offsets (oy, ox):
    (prediction px, raw sigma px, support). The normal equations are sums of w, w du, ... over the window: matrix
    products with the fixed offset vectors. float32 sums over at most a few hundred samples of disparities below
    a few thousand px keep ~1e-4 px, far below any sigma."""
    d = disp_pad[ys[:, None] + oy, xs[:, None] + ox]  # (n, k) float32
    c = col_pad[ys[:, None] + oy, xs[:, None] + ox]  # (n, k, ch) int16
    ok = np.isfinite(d)
    w0 = _colour_weights(c.shape[2])[np.abs(c - centre_col[:, None, :]).sum(axis=2)] * ok
    d = np.where(ok, d, np.float32(0.0))
    basis = np.stack([np.ones_like(ox), ox, oy]).astype(np.float32)  # (3, k)
    products = np.stack([basis[i] * basis[j] for i in range(3) for j in range(3)], axis=1)  # (k, 9)
    ridge = np.diag([1e-9, 1e-6, 1e-6])
    w = w0
    for step in range(3):  # weighted least squares, then two biweight re-weightings
        support = w.sum(axis=1, dtype=np.float64)
        A = (w @ products).astype(np.float64).reshape(-1, 3, 3) + ridge * (support[:, None, None] + 1.0)
        coef = np.linalg.solve(A, ((w * d) @ basis.T).astype(np.float64)[..., None])[..., 0]
        r = d - coef.astype(np.float32) @ basis
        if step == 2:
            break
        # robust scale: 1.2533 x the weighted mean |r| (= the std for normal residuals), then the biweight
        scale = 1.2533 * (w * np.abs(r)).sum(axis=1) / np.maximum(support, 1e-30) + 1e-3
        u2 = np.square(r / (BIWEIGHT_C * scale[:, None]).astype(np.float32))
        w = w0 * np.square(np.maximum(1 - u2, 0))
    n_eff = support ** 2 / np.maximum((w * w).sum(axis=1, dtype=np.float64), 1e-300)
    s2 = (w * r * r).sum(axis=1, dtype=np.float64) / np.maximum(support, 1e-300) * n_eff / np.maximum(n_eff - 3.0, 1e-3)
    lever = np.linalg.inv(A)[:, 0, 0]
    sigma = np.where(n_eff > 4.0, np.sqrt(np.maximum(s2 * (1.0 + lever), 0.0)), np.inf)
    # surrounded: support on each side (left, right, above, below), so a fill interpolates a hole and never
    # extends a surface past its rim into what lies beyond it (measured: a rendered fisheye plane's rim
    # extended into the background put its RMS at 12 mm against 7.5 allowed)
    sides = w @ np.stack([ox < 0, ox > 0, oy < 0, oy > 0], axis=1).astype(np.float32)
    support = np.where(sides.min(axis=1) >= MIN_SIDE_SUPPORT, support, 0.0)
    return coef[:, 0], sigma, support


def _predict(disparity: np.ndarray, cols: np.ndarray, ys: np.ndarray, xs: np.ndarray, accept):
    """(prediction px, raw sigma px) at the pixels (ys, xs) from the matched (finite) pixels of `disparity`, each
    from the smallest window of PASSES whose fit `accept(raw sigma, support)` takes (NaN, inf where none does)."""
    pred, sigma = np.full(len(ys), np.nan), np.full(len(ys), np.inf)
    todo = np.arange(len(ys))
    for half, stride in PASSES:
        if not len(todo):
            break
        r = np.arange(-half, half + 1, stride)
        oy, ox = (a.ravel() for a in np.meshgrid(r, r, indexing="ij"))
        keep = (oy != 0) | (ox != 0)
        oy, ox = oy[keep], ox[keep]
        disp_pad = np.pad(disparity.astype(np.float32), half, constant_values=np.nan)
        col_pad = np.pad(cols, ((half, half), (half, half), (0, 0)), mode="edge")
        taken = np.zeros(len(todo), bool)
        for start in range(0, len(todo), CHUNK):
            i = todo[start:start + CHUNK]
            y, x = ys[i], xs[i]
            with np.errstate(invalid="ignore", divide="ignore"):  # an empty window: NaN sigma, never accepted
                p, sig, support = _fit_block(disp_pad, col_pad, y + half, x + half, oy, ox, cols[y, x])
            good = accept(sig, support)
            pred[i[good]], sigma[i[good]] = p[good], sig[good]
            taken[start:start + CHUNK] = good
        todo = todo[~taken]
    return pred, sigma


def sigma_scale(disparity: np.ndarray, cols: np.ndarray, todo: np.ndarray, seed: int = 0) -> tuple[float, int]:
    """(k, pixels used): the factor that makes the raw fit sigma honest, measured on this image by hiding the
    matched pixels of a HOLDOUT_BAND px band around the unmatched ones and filling up to HOLDOUT_PIXELS of them
    from the rest: k = 1.4826 x the median |error / raw sigma| of those fills (the robust std of the normalised
    errors, 1 when the raw sigma is right), at least 1. The band is where a real fill reaches from its support."""
    import cv2

    matched = np.isfinite(disparity)
    near = cv2.dilate(todo.astype(np.uint8), np.ones((2 * HOLDOUT_BAND + 1,) * 2, np.uint8)).astype(bool)
    band = near & matched
    ys, xs = np.nonzero(band)
    if len(ys) < MIN_HOLDOUT:
        return 1.0, int(len(ys))
    pick = np.random.default_rng(seed).choice(len(ys), min(HOLDOUT_PIXELS, len(ys)), replace=False)
    hidden = np.where(band, np.nan, disparity)
    pred, raw = _predict(hidden, cols, ys[pick], xs[pick], lambda s, n: np.isfinite(s) & (n >= MIN_SUPPORT))
    ok = np.isfinite(raw) & (raw > 0)
    if ok.sum() < MIN_HOLDOUT:
        return 1.0, int(ok.sum())
    z = (pred[ok] - disparity[ys[pick][ok], xs[pick][ok]]) / raw[ok]
    return max(1.0, float(MAD_TO_STD * np.median(np.abs(z)))), int(ok.sum())


def fill_disparity(disparity: np.ndarray, image: np.ndarray, outside: np.ndarray | None = None,
                   max_sigma: float = 1.0) -> Fill:
    """Fill the NaN pixels of `disparity` (h, w) px from the matched ones around them (see the module); `image`
    the rectified left image (h, w) or (h, w, 3) uint8; `outside` (h, w) bool pixels with no source (never
    filled)."""
    todo = ~np.isfinite(disparity)
    if outside is not None:
        todo &= ~outside
    cols = _colours(image)
    k, used = sigma_scale(disparity, cols, todo)
    ys, xs = np.nonzero(todo)
    pred, raw = _predict(disparity, cols, ys, xs, lambda s, n: (k * s <= max_sigma) & (n >= MIN_SUPPORT))
    good = np.isfinite(raw)
    out = disparity.astype(np.float32).copy()
    sigma = np.full(disparity.shape, np.nan)
    out[ys[good], xs[good]] = pred[good]
    sigma[ys[good], xs[good]] = k * raw[good]
    return Fill(out, np.isfinite(sigma), sigma, k, used)


def fill_unmatched(name: str, left_rect: np.ndarray, disparity: np.ndarray, outside: np.ndarray, config,
                   summary: dict, timings: dict) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(disparity, filled mask, fill sigma px) after `fill_disparity` when `config.fill` (summary['fill'] says
    what it did); the disparity as it is and (None, None) without it. A map with no matched pixel is left as it
    is (the pipeline refuses it)."""
    import time

    if not config.fill or not np.isfinite(disparity).any():
        summary["fill"] = {"enabled": bool(config.fill), "filled_pixels": 0}
        return disparity, None, None
    t0 = time.perf_counter()
    done = fill_disparity(disparity, left_rect, outside, config.fill_max_sigma)
    timings["fill_s"] = time.perf_counter() - t0
    summary["fill"] = done.summary(config.fill_max_sigma) | {  # its time: timings_s.fill_s
        "sigma_scale": done.scale, "sigma_scale_pixels": done.scale_pixels,
        "sigma_scale_how": f"hold-out: matched pixels of a {HOLDOUT_BAND} px band around the holes hidden and "
                           "filled; the robust std of their errors / raw sigma (at least 1)"}
    return done.disparity, done.filled, done.sigma
