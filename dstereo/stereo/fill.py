"""Confidence-aware fill of the pixels the matcher left without a disparity (issue 30): an edge-aware local
plane fit, with each filled pixel's own disparity sigma, and the pixels too uncertain to fill left empty.

For an unmatched pixel p, the matched pixels q of a window around it are weighted by how alike their colours are
(w_q = exp(-|I_q - I_p| / COLOUR_SCALE), mean absolute difference over the channels, 8-bit levels): pixels of
another surface usually differ in colour, so the window's plane is mostly the surface p lies on (an edge-aware
fit, the support-weight idea of Yoon & Kweon 2006 applied to a plane d = a + b du + c dv as in the
slanted-plane fills of segment-based stereo). Two re-weightings (Tukey's biweight on the residuals, at 4.685
robust stds) drop mismatches and the other surface's pixels that pass the colour test.

The sigma of a fill (px) follows from what its error is made of. The fill at p is a weighted sum of the matched
disparities of its window, sum_q h_q d_q (h the fit's intercept row: the sum of h is 1, a plane is reproduced
exactly), so its error is (a) the matched pixels' own errors carried through the fit, sum_q h_q n_q, plus (b)
the true surface's departure from the window's plane, at p and in the fit. Measured against Middlebury's truth
(5 scenes, as is and relit), (a) is nearly all of it: the matched errors near a hole are correlated over the
window (their correlation 0.6-0.9 within 3 px, where the fit's weight lies), so they do not average away. Hence

    sigma^2 = (sum_q h_q sigma_q)^2 + max(s^2 - kappa^2 sigma_w^2, 0) (1 + (A^-1)_00)

- sigma_q: each matched pixel's disparity noise, the per-pixel model of `disparity_noise` (SGBM's local deviation
  from the sub-pixel refinement, `sgbm_sigma`; the refinement's own sandwich sigma, `refined_sigma`, where the
  disparity was refined); carried as if common to the window (the upper end of (a));
- s^2: the window's weighted residual variance about its plane (sum w r^2 / sum w, scaled by n_eff / (n_eff - 3),
  n_eff = (sum w)^2 / sum w^2); sigma_w^2 = sum w sigma_q^2 / sum w, the matching noise's variance there;
- kappa^2: the share of the matching noise's variance that a plane fit over the window leaves in its residuals
  (the rest moves the plane, and is in the first term). It depends on the noise's correlation, so it is
  measured on the image itself: over windows of the matched map, the plane-fit residual variance of the field
  SGBM-minus-refinement (the matching error as `sgbm_sigma` sees it) over that field's variance (Middlebury
  0.57-0.65 on the rank-cost maps; on the true errors about 0.5-0.6); for a refined disparity, of a simulated field
  correlated as the refinement's noise (`disparity_noise.iterated_kernel`);
- so s^2 - kappa^2 sigma_w^2 is the surface's own relief about the plane (and mismatches the biweight kept), the
  spread of a new point about it, and (A^-1)_00 the plane's own variance at p in units of it (A the weighted
  normal matrix in (1, du, dv)).
A pixel is filled only when that sigma is at most `max_sigma` px and its window holds at least MIN_SUPPORT weight
on matched pixels around it, at least MIN_SIDE_SUPPORT of it on each side (left, right, above, below: a hole is
interpolated, a rim never extended); the rest stay NaN. The fill uses matched pixels only (a fill never feeds
another). What no window can see: a hole at a depth edge whose support lies on the wrong surface, or a
matched neighbourhood that is itself wrong (SGBM's fattening at an occlusion, its smooth false matches on a
blank wall with the grey-level cost); those fills are off by pixels whatever their sigma, which is why the
default `max_sigma` is 0.7 px (fills up to it: observed / predicted 0.71-1.36 on Middlebury's rank-cost rows,
experiments/results/middlebury_lighting.md; beyond it their share grows: 1.4-1.6 at 1 px on Piano and Pipes).
Checked against ground truth in experiments/middlebury_lighting.py and on renders in tests/stereo/test_fill.py.
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
KAPPA_WINDOWS = 2000  # windows over which the noise's residual share kappa^2 is measured (a mean to ~2 %)
MIN_KAPPA_WINDOWS = 50  # fewer: kappa^2 = 0 (the whole scatter taken as relief: the larger sigma)
CHUNK = 4096  # unmatched pixels per vectorised block (memory ~ CHUNK x window samples x 8 bytes, a few x)


@dataclass(frozen=True)
class Fill:
    """A disparity map with its unmatched pixels filled where possible: `disparity` (h, w) px, `filled` (h, w)
    bool, `sigma` (h, w) px (the fill's sigma on filled pixels, NaN elsewhere)."""

    disparity: np.ndarray
    filled: np.ndarray
    sigma: np.ndarray
    kappa2: float = 0.0  # the matching noise's share left in a window's plane-fit residuals (`noise_left_share`)
    kappa_windows: int = 0  # the windows it was measured on

    def summary(self, max_sigma: float) -> dict:
        matched = int(np.isfinite(self.disparity).sum() - self.filled.sum())
        s = self.sigma[self.filled]
        return {"enabled": True, "filled_pixels": int(self.filled.sum()), "matched_pixels": matched,
                "max_sigma_px": max_sigma,
                "sigma_px": {"median": float(np.median(s)), "p90": float(np.percentile(s, 90))} if s.size else None,
                "kappa2": self.kappa2, "kappa2_windows": self.kappa_windows,
                "method": "edge-aware local plane fit on matched pixels (dstereo.stereo.fill); a filled pixel "
                          "carries its own sigma (the matched pixels' noise carried through the fit and the "
                          "surface's relief about it) and the flag `filled`"}


def _colours(image: np.ndarray) -> np.ndarray:
    return (image[..., None] if image.ndim == 2 else image).astype(np.int16)


def _colour_weights(channels: int) -> np.ndarray:
    """exp(-mean |difference| / COLOUR_SCALE) for every summed absolute difference 0..255 channels (a table: the
    weights of a window are looked up, not exponentiated)."""
    return np.exp(-np.arange(255 * channels + 1) / channels / COLOUR_SCALE).astype(np.float32)


def _fit_block(disp_pad, col_planes, sm_pad, ys, xs, oy, ox, centre_col, kappa2):
    """Weighted robust plane at each (ys, xs) (padded coordinates) from the samples at offsets (oy, ox):
    (prediction px, sigma px, support). `col_planes`: the padded image's channels, each flattened (int16);
    `sm_pad`: the matched pixels' disparity noise (px), padded as `disp_pad`. A pixel
    whose colour weights alone (before the biweight, which only lowers them) miss MIN_SUPPORT or MIN_SIDE_SUPPORT
    is not fitted (NaN, inf, 0: it could not be filled), so the fits are spent on pixels that can be."""
    width = disp_pad.shape[1]
    flat = (ys[:, None] + oy) * width + (xs[:, None] + ox)  # (n, k) indices into the padded maps
    d = disp_pad.ravel()[flat]  # (n, k) float32
    ok = np.isfinite(d)
    difference = np.zeros(flat.shape, np.int16)  # summed |colour difference| to the centre, channel by channel
    for ch, plane in enumerate(col_planes):
        difference += np.abs(plane[flat] - centre_col[:, ch, None])
    w0 = _colour_weights(len(col_planes))[difference] * ok
    side_masks = np.stack([ox < 0, ox > 0, oy < 0, oy > 0], axis=1).astype(np.float32)
    can = (w0.sum(axis=1) >= MIN_SUPPORT) & ((w0 @ side_masks).min(axis=1) >= MIN_SIDE_SUPPORT)
    pred, sigma, support = np.full(len(ys), np.nan), np.full(len(ys), np.inf), np.zeros(len(ys))
    if can.any():
        sm = sm_pad.ravel()[flat[can]]
        pred[can], sigma[can], support[can] = _fit(d[can], ok[can], w0[can], sm, oy, ox, side_masks, kappa2)
    return pred, sigma, support


def _fit(d, ok, w0, sm, oy, ox, side_masks, kappa2):
    """The robust plane fit of `_fit_block` on samples d (n, k) px with colour weights w0 and matched noise sm.
    The normal equations are sums of w, w du, ... over the window: matrix products with the fixed offset vectors.
    float32 sums over at most a few hundred samples of disparities below a few thousand px keep ~1e-4 px, far
    below any sigma."""
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
    a_inv = np.linalg.inv(A)
    hat = w * (a_inv[:, 0, :].astype(np.float32) @ basis)  # the intercept's row: prediction = sum hat d
    sm = np.where(ok & np.isfinite(sm), sm, np.float32(0.0))
    carried = (hat * sm).sum(axis=1, dtype=np.float64)  # the matched noise, common to the window, through the fit
    noise2 = (w * sm * sm).sum(axis=1, dtype=np.float64) / np.maximum(support, 1e-300)
    relief2 = np.maximum(s2 - kappa2 * noise2, 0.0)
    var = carried ** 2 + relief2 * (1.0 + a_inv[:, 0, 0])
    sigma = np.where(n_eff > 4.0, np.sqrt(var), np.inf)
    # surrounded: support on each side (left, right, above, below), so a fill interpolates a hole and never
    # extends a surface past its rim into what lies beyond it (measured: a rendered fisheye plane's rim
    # extended into the background put its RMS at 12 mm against 7.5 allowed)
    support = np.where((w @ side_masks).min(axis=1) >= MIN_SIDE_SUPPORT, support, 0.0)
    return coef[:, 0], sigma, support


def _lattice_counts(matched: np.ndarray, half: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """(fewest matched samples on any side, matched samples in all) of each pixel's window of offsets
    -half..half step stride (the centre left out), sides as in `_fit` (left, right, above, below). A sample's
    weight is at most 1, so a pixel with fewer than MIN_SUPPORT samples, or none on a side, cannot be filled."""
    from scipy.ndimage import correlate1d

    lattice = np.zeros(2 * half + 1, np.float32)
    lattice[::stride] = 1.0
    before, after, centre = lattice.copy(), lattice.copy(), np.zeros_like(lattice)
    before[half:], after[:half + 1], centre[half] = 0.0, 0.0, 1.0
    m = matched.astype(np.float32)
    count = lambda x, k, axis: correlate1d(x, k, axis=axis, mode="constant", cval=0.0)  # noqa: E731
    rows, cols = count(m, lattice, 0), count(m, lattice, 1)
    sides = [count(rows, before, 1), count(rows, after, 1), count(cols, before, 0), count(cols, after, 0)]
    column = count(count(m, lattice - centre, 0), centre, 1)
    return np.minimum.reduce(sides), sides[0] + sides[1] + column


def _predict(disparity: np.ndarray, cols: np.ndarray, matched_sigma: np.ndarray, kappa2: float, ys: np.ndarray,
             xs: np.ndarray, max_sigma: float):
    """(prediction px, sigma px) at the pixels (ys, xs) from the matched (finite) pixels of `disparity`, each from
    the smallest window of PASSES whose fit has a sigma of at most `max_sigma` and MIN_SUPPORT (NaN, inf where
    none has). A pass skips the pixels whose window could not reach MIN_SUPPORT or MIN_SIDE_SUPPORT even at full
    weight (`_lattice_counts`)."""
    pred, sigma = np.full(len(ys), np.nan), np.full(len(ys), np.inf)
    todo = np.arange(len(ys))
    for half, stride in PASSES:
        fewest, total = _lattice_counts(np.isfinite(disparity), half, stride)
        tried = todo[(fewest[ys[todo], xs[todo]] >= 1.0) & (total[ys[todo], xs[todo]] >= MIN_SUPPORT)]
        r = np.arange(-half, half + 1, stride)
        oy, ox = (a.ravel() for a in np.meshgrid(r, r, indexing="ij"))
        keep = (oy != 0) | (ox != 0)
        oy, ox = oy[keep], ox[keep]
        disp_pad = np.pad(disparity.astype(np.float32), half, constant_values=np.nan)
        col_planes = [np.pad(cols[..., ch], half, mode="edge").ravel() for ch in range(cols.shape[2])]
        sm_pad = np.pad(matched_sigma.astype(np.float32), half, constant_values=np.nan)
        taken = np.zeros(len(ys), bool)
        for start in range(0, len(tried), CHUNK):
            i = tried[start:start + CHUNK]
            y, x = ys[i], xs[i]
            with np.errstate(invalid="ignore", divide="ignore"):  # an empty window: NaN sigma, never accepted
                p, sig, support = _fit_block(disp_pad, col_planes, sm_pad, y + half, x + half, oy, ox, cols[y, x],
                                             kappa2)
            good = (sig <= max_sigma) & (support >= MIN_SUPPORT)
            pred[i[good]], sigma[i[good]] = p[good], sig[good]
            taken[i[good]] = True
        todo = todo[~taken[todo]]
    return pred, sigma


def noise_left_share(error_field: np.ndarray, seed: int = 0) -> tuple[float, int]:
    """(kappa^2, windows): the share of a matching-error field's variance that a plane fit over the fill's first
    window (PASSES[0], unit weights) leaves in its residuals, over up to KAPPA_WINDOWS windows at least 80 %
    finite (kappa^2 = mean residual variance / mean square of the field about its median there; values clipped to
    +-2 px, a mismatch is not noise). (0, n) with fewer than MIN_KAPPA_WINDOWS windows: nothing subtracted."""
    half, stride = PASSES[0]
    r = np.arange(-half, half + 1, stride)
    oy, ox = (a.ravel() for a in np.meshgrid(r, r, indexing="ij"))
    field = np.clip(error_field - np.nanmedian(error_field), -2.0, 2.0) if np.isfinite(error_field).any() \
        else error_field
    ok = np.isfinite(field)
    ok[:half], ok[-half:], ok[:, :half], ok[:, -half:] = False, False, False, False
    ys, xs = np.nonzero(ok)
    if not len(ys):
        return 0.0, 0
    pick = np.random.default_rng(seed).choice(len(ys), min(4 * KAPPA_WINDOWS, len(ys)), replace=False)
    v = field[ys[pick][:, None] + oy, xs[pick][:, None] + ox]
    m = np.isfinite(v)
    full = m.mean(axis=1) >= 0.8
    v, m = np.where(m, v, 0.0)[full][:KAPPA_WINDOWS], m[full][:KAPPA_WINDOWS].astype(float)
    if len(v) < MIN_KAPPA_WINDOWS:
        return 0.0, int(len(v))
    basis = np.stack([np.ones_like(ox), ox, oy], axis=1).astype(float)  # (k, 3)
    a = np.einsum("nk,ki,kj->nij", m, basis, basis)
    coef = np.linalg.solve(a, ((m * v) @ basis)[..., None])[..., 0]
    resid = (v - coef @ basis.T) * m
    n = m.sum(axis=1)
    left = (resid ** 2).sum(axis=1) / np.maximum(n - 3.0, 1.0)  # unbiased for the window's 3 fitted terms
    total = (v ** 2).sum(axis=1) / n
    return float(np.clip(left.mean() / max(total.mean(), 1e-12), 0.0, 1.0)), int(len(v))


def matched_noise(left_rect: np.ndarray, right_rect: np.ndarray, disparity: np.ndarray, block_size: int,
                  exact=None) -> tuple[np.ndarray, float, int, str]:
    """(sigma_q (h, w) px of the matched pixels, kappa^2, its windows, how): the disparity noise of
    `disparity_noise` before any plane-check scaling (the model's own level: the check's tiles read a surface's
    relief as noise). SGBM's disparity: `sgbm_sigma`, and kappa^2 from the SGBM-minus-refinement field it uses;
    a refined one (`exact`: the float rectified pair it was refined on): `refined_sigma`, and kappa^2 from a
    simulated field correlated as the refinement's noise."""
    from dstereo.stereo.disparity_noise import iterated_kernel, refined_sigma, sgbm_sigma
    from dstereo.stereo.pair_result import grey

    if exact is None:
        from dstereo.stereo.subpixel import refine_disparity

        left, right = (grey(x).astype(np.float64) for x in (left_rect, right_rect))
        refined = refine_disparity(left, right, disparity)
        sigma = sgbm_sigma(left, right, disparity, block_size, refined=refined)
        kappa2, windows = noise_left_share(disparity - refined)
        return sigma, kappa2, windows, "SGBM's local deviation from the sub-pixel refinement (sgbm_sigma)"
    from scipy.ndimage import correlate

    sigma = refined_sigma(*exact, disparity)
    white = np.random.default_rng(1).normal(size=(320, 320))
    kappa2, windows = noise_left_share(correlate(white, iterated_kernel(2.0, 6), mode="reflect")[32:-32, 32:-32])
    return sigma, kappa2, windows, "the sub-pixel refinement's sandwich sigma (refined_sigma)"


def fill_disparity(disparity: np.ndarray, image: np.ndarray, outside: np.ndarray | None = None,
                   max_sigma: float = 0.7, matched_sigma: np.ndarray | None = None, kappa2: float = 0.0,
                   kappa_windows: int = 0) -> Fill:
    """Fill the NaN pixels of `disparity` (h, w) px from the matched ones around them (see the module); `image`
    the rectified left image (h, w) or (h, w, 3) uint8; `outside` (h, w) bool pixels with no source (never
    filled); `matched_sigma` (h, w) px the matched pixels' disparity noise and `kappa2` its share left in a
    window's residuals (`matched_noise`; None: no noise known, the window's whole scatter is the sigma's)."""
    todo = ~np.isfinite(disparity)
    if outside is not None:
        todo &= ~outside
    cols = _colours(image)
    if matched_sigma is None:
        matched_sigma, kappa2 = np.zeros(disparity.shape, np.float32), 0.0
    ys, xs = np.nonzero(todo)
    pred, sig = _predict(disparity, cols, matched_sigma, kappa2, ys, xs, max_sigma)
    good = np.isfinite(sig)
    out = disparity.astype(np.float32).copy()
    sigma = np.full(disparity.shape, np.nan)
    out[ys[good], xs[good]] = pred[good]
    sigma[ys[good], xs[good]] = sig[good]
    return Fill(out, np.isfinite(sigma), sigma, kappa2, kappa_windows)


def fill_wanted(config, summary: dict) -> tuple[bool, str]:
    """(fill?, why) for `config.fill`: True / False as given (`--fill` / `--no-fill`); None (the default): fill the
    rank cost's maps (`summary['search_range']['matching_cost']`), not the grey levels'. Why, measured on the five
    shared Middlebury scenes as they are and relit (experiments/results/middlebury_lighting.md): the rank cost
    leaves weak texture unmatched (density 73-91 %, the grey levels 81-96 %) with its holes bounded by right
    matches, and the fill's sigma holds there (observed / predicted 0.71-1.36 on all 10 rows); the grey levels'
    holes border their own false matches (a blank wall, SGBM's fattening at occlusions), which no window sees:
    filled, observed / predicted 0.83-5.97 (Piano 5.97, Pipes 4.33), and still 1.2-3.9 when filled from only the
    pixels both costs agree on, so they are left empty. Where that leaves the default sparse (the grey levels' map
    under 80 % dense), `stereo.density_check` also matches the rank transforms and fills them, and keeps that map
    when denser and its fills hold against the grey levels' matches: the fill still runs on rank-cost maps only."""
    if config.fill is not None:
        return bool(config.fill), "given (--fill)" if config.fill else "given (--no-fill)"
    cost = ((summary.get("search_range") or {}).get("matching_cost") or {}).get("cost")
    if cost == "rank":
        return True, ("auto: the rank cost's map (it leaves weak texture unmatched, its holes bounded by right "
                      "matches: the fill recovers them with their own sigma)")
    return False, (f"auto: the {cost or 'matching'} cost's map (its holes border its own false matches, which a "
                   "fill would spread with too small a sigma): left as matched; --fill forces it")


def fill_unmatched(name: str, left_rect: np.ndarray, right_rect: np.ndarray, disparity: np.ndarray,
                   outside: np.ndarray, config, summary: dict, timings: dict, exact=None
                   ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(disparity, filled mask, fill sigma px) after `fill_disparity` when `fill_wanted` (summary['fill'] says
    what it did and why); the disparity as it is and (None, None) without it. `exact`: the float rectified pair a
    refined disparity was refined on (None: SGBM's disparity, its grey pair from left_rect, right_rect). A map
    with no matched pixel is left as it is (the pipeline refuses it)."""
    import time

    wanted, why = fill_wanted(config, summary)
    if not wanted or not np.isfinite(disparity).any():
        summary["fill"] = {"enabled": wanted, "why": why, "filled_pixels": 0}
        return disparity, None, None
    t0 = time.perf_counter()
    sigma_q, kappa2, windows, how = matched_noise(left_rect, right_rect, disparity, summary["sgbm"]["block_size"],
                                                  exact)
    done = fill_disparity(disparity, left_rect, outside, config.fill_max_sigma, sigma_q, kappa2, windows)
    timings["fill_s"] = time.perf_counter() - t0
    summary["fill"] = done.summary(config.fill_max_sigma) | {  # its time: timings_s.fill_s
        "why": why, "matched_noise": how + ", before the plane check's scaling",
        "kappa2_how": f"plane fits over {2 * PASSES[0][0] + 1} x {2 * PASSES[0][0] + 1} px windows of the matching "
                      "error field: residual variance / the field's variance"}
    return done.disparity, done.filled, done.sigma
