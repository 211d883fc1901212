"""Per-pixel disparity noise (rectified px) and a check of it against the scatter of the data themselves.

Model (`disparity_sigma_map`). The sub-pixel refinement (`dstereo.stereo.subpixel`) estimates d by weighted least
squares over a Gaussian window w: delta = -sum(w e g) / sum(w g^2), e = L(x) - R(x - d) on images normalised
by their local std, g = dR/dx. Both images' noise enters the residual (var(e) is twice one image's), and the
estimate's variance is the weighted least-squares sandwich

    sigma_d^2 = sum(F^2 g^2 var(e)) / (sum(w g^2))^2

(not var(e) / sum(w g^2): that holds for unit weights only). F = w for one pass; the refinement makes K = 6
passes in which each pixel's step averages its neighbours' residuals at THEIR disparities, so the passes
deconvolve step by step and F = I - (I - w)^K (`iterated_kernel`; sum F^2 is 3.6x sum w^2 for K = 6, and
the measured scatter on a pure-noise shift follows it: 0.018 px predicted 0.019). var(e) is measured where
the matcher sees it: the local mean square of the converged residuals (corrected for the share of a pure
noise residual the fit leaves), at least both images' 8-bit quantisation, so interpolation of fine texture,
foreshortening, camera differences and compression count as well as sensor noise; neighbouring residuals
that are correlated (resampling, demosaicing, compression) multiply the variance by sum(rho_e rho_g) over
lags (`correlation_gain`; 1 for white noise, and it halves the underprediction on JPEG boards). g is the
measured gradient, noise and all (`sandwich_sigma`; subtracting the noise's share of g^2 overpredicted a
low-contrast texture 1.5x). The image noise alone (grey levels, per brightness: shot noise grows with it) is
estimated from each ORIGINAL image by Immerkaer's method (the 3 x 3 operator N, sum N^2 = 36, cancels
smooth content: N * I / 6 is the noise) over the flattest 8 x 8 tiles, and reported (summary.json).
SGBM without refinement: SGBM's pixel-locked parabola fit and its smoothness penalties do not follow a
window formula; its error is measured against the refinement run on the same pair (`sgbm_sigma`).
Measured (experiments/results/disparity_noise.md): the model alone is close on renders and on Middlebury's
SGBM path, optimistic by 1.2-4x on real JPEG chessboards; the check below sets the level.

Check (`plane_check`). Over tiles of the disparity map where the surface is smooth (a quadratic in (u, v) fits,
which is exact for a plane: its disparity is affine on a rectified pair), the robust std of the residuals is
compared with the predicted sigma_d on the same pixels. The fit absorbs part of the noise, the more so the
more correlated it is (neighbouring pixels share the matching window), so the prediction is multiplied by the
fraction kappa that survives the same fit on a simulated field with the model's correlation. Tiles with
under half their pixels or more than 10 % outliers (edges, occlusions) are not used. The median ratio
observed / predicted over the tiles is reported and the map is scaled by it: the model sets each pixel's sigma
relative to the others, the data set the level. Far from 1 (outside CHECK_BAND) that is said in a warning,
with the figures (relief of the surface within a tile counts as scatter: a rough surface reads as noise).
With too few smooth tiles the model's values stay, with a warning that they are unverified.
"""

from __future__ import annotations

import functools

import numpy as np

MAD_TO_STD = 1.4826
CHECK_BAND = (0.67, 1.5)  # ratio observed / predicted beyond which the model is said to be off
SGBM_FLOOR_PX = 0.1  # SGBM's error where no refinement reference exists at all (renders: 0.1-0.13 px)
QUANT_PX = (1.0 / 16.0) / np.sqrt(12.0)  # SGBM's 1/16 px steps, uniform
TILE = 32


def _grey(image: np.ndarray) -> np.ndarray:
    x = np.asarray(image, np.float64)
    return x if x.ndim == 2 else x[..., :3] @ np.array([0.114, 0.587, 0.299])  # BGR


# --- image noise ------------------------------------------------------------------------------------------------


def _block_rms(grey: np.ndarray, block: int = 8):
    """Immerkaer's noise response N * I / 6 as RMS per block x block tile, the tiles' mean brightness, and
    whether the tile is free of saturated pixels."""
    from scipy.ndimage import convolve, maximum_filter, minimum_filter

    kernel = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]])
    resp = convolve(grey, kernel, mode="reflect") / 6.0
    top = 255.0 if grey.max() <= 255 else float(grey.max())
    ok = (maximum_filter(grey, 3) < top) & (minimum_filter(grey, 3) > 0)  # saturated pixels carry no noise
    ok[[0, -1], :] = ok[:, [0, -1]] = False
    h, w = (grey.shape[0] // block) * block, (grey.shape[1] // block) * block

    def tiles(x):
        return x[:h, :w].reshape(h // block, block, w // block, block).swapaxes(1, 2).reshape(-1, block * block)

    return (np.sqrt(np.mean(tiles(resp) ** 2, axis=1)), tiles(grey).mean(axis=1), tiles(ok).all(axis=1))


@functools.lru_cache(maxsize=None)
def _percentile_of_white(q: float) -> float:
    """The q-th percentile of the tiles' RMS on unit white noise (the estimator's calibration)."""
    rms, _, _ = _block_rms(np.random.default_rng(2).normal(128.0, 1.0, (512, 512)))
    return float(np.percentile(rms, q))


def image_noise(image: np.ndarray, bins: int = 6, q: float = 10.0, min_tiles: int = 40):
    """(brightness levels, noise std per level) in grey levels of an image: Immerkaer's estimator (module
    docstring) per 8 x 8 tile, and in each brightness bin the q-th percentile of the tiles over the same
    percentile on pure white noise (the flattest tiles carry the least texture; texture everywhere makes this
    an overestimate, which the residual term and the plane check bound)."""
    rms, level, ok = _block_rms(_grey(image))
    if ok.sum() < min_tiles:
        ok[:] = True
    rms, level = rms[ok], level[ok]
    nb = int(np.clip(len(rms) // (2 * min_tiles), 1, bins))
    edges = np.quantile(level, np.linspace(0, 1, nb + 1))
    idx = np.clip(np.searchsorted(edges, level, side="right") - 1, 0, nb - 1)
    centres, sigmas = [], []
    for b in range(nb):
        if (idx == b).sum() >= min_tiles // 2:
            centres.append(float(np.median(level[idx == b])))
            sigmas.append(float(np.percentile(rms[idx == b], q)) / _percentile_of_white(q))
    floor = 1.0 / np.sqrt(12.0)  # 8-bit quantisation is noise of at least this
    return np.array(centres), np.maximum(np.array(sigmas), floor)


def noise_map(image: np.ndarray, levels: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
    """(h, w) noise std (grey levels) of every pixel of `image` (any grid), from its local brightness."""
    from scipy.ndimage import uniform_filter

    grey = np.nan_to_num(_grey(image), nan=float(np.nanmean(_grey(image))))
    return np.interp(uniform_filter(grey, 3), levels, sigmas)


# --- the sandwich over a window ---------------------------------------------------------------------------------


def _gauss_kernel(sigma: float) -> np.ndarray:
    radius = int(4.0 * sigma + 0.5)  # scipy.ndimage.gaussian_filter's truncate=4
    x = np.arange(-radius, radius + 1, dtype=float)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def _window_sums(x: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    from scipy.ndimage import correlate1d

    return correlate1d(correlate1d(x, kernel, axis=0, mode="reflect"), kernel, axis=1, mode="reflect")


@functools.lru_cache(maxsize=None)
def iterated_kernel(window_sigma: float, iterations: int) -> np.ndarray:
    """2-D kernel F = I - (I - W)^K of K Jacobi-like Gauss-Newton passes. Each pixel's step averages the
    residuals its neighbours have at THEIR disparities, so the passes solve W (g^2 delta + g n) = 0 for the
    error field delta step by step: one pass gives delta = -W (g n) / g^2 (the textbook window average), K
    passes give -F (g n) / g^2, which keeps more of the noise's fine detail (sum F^2 > sum W^2)."""
    from scipy.ndimage import gaussian_filter

    r = 4 * int(4.0 * window_sigma + 0.5)
    delta = np.zeros((2 * r + 1, 2 * r + 1))
    delta[r, r] = 1.0
    rest = delta.copy()  # (I - W)^k applied to the impulse
    for _ in range(iterations):
        rest = rest - gaussian_filter(rest, window_sigma, mode="constant")
    return delta - rest


def sandwich_sigma(g: np.ndarray, var_e: np.ndarray, kernel: np.ndarray, spread: np.ndarray | None = None):
    """sqrt(sum(F^2 g^2 var_e)) / sum(w g^2), w the window (1-D separable `kernel`), F the 2-D kernel that
    spreads the residuals into the estimate (`spread`, default w). g is the gradient as measured, noise and
    all: at the fixed point sum(w e(d) g) = 0 the estimate's error is -sum(w e0 g) / sum(w g^2) with the
    measured g in both sums (its noise is uncorrelated with e at the same position)."""
    a = _window_sums(g * g, kernel)
    if spread is None:
        b = _window_sums(g * g * var_e, kernel ** 2)
    else:
        b = _fft_correlate(g * g * var_e, spread ** 2)
    return np.sqrt(np.maximum(b, 0.0)) / np.maximum(a, 1e-12)


def _fft_correlate(x: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """x correlated with a (symmetric) 2-D kernel, reflected at the borders, by FFT (a 65 x 65 kernel directly
    would cost 4225 multiplications per pixel)."""
    from scipy.signal import fftconvolve

    r = kernel.shape[0] // 2
    padded = np.pad(x, r, mode="symmetric")
    return fftconvolve(padded, kernel[::-1, ::-1], mode="valid")


def _masked_smooth(x: np.ndarray, ok: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian average of x over the pixels `ok` (normalised convolution); NaN where none is near."""
    from scipy.ndimage import gaussian_filter

    num = gaussian_filter(np.where(ok, x, 0.0), sigma)
    den = gaussian_filter(ok.astype(float), sigma)
    return np.where(den > 1e-3, num / np.maximum(den, 1e-12), np.nan)


def refined_sigma(left: np.ndarray, right: np.ndarray, disparity: np.ndarray, window_sigma: float = 2.0,
                  iterations: int = 6) -> np.ndarray:
    """sigma_d (h, w) px of `subpixel.refine_disparity`'s result on the rectified grey pair.

    var(e) is the residuals' own local mean square after the fit (Gaussian of the window's size), divided by
    the share of a pure-noise residual the fit leaves (1 - 2 F(0) + sum F^2), at least the 8-bit quantisation
    of both images: what the two images do not share (noise, and interpolation of fine texture,
    foreshortening on slants, camera differences, compression) scatters the estimate alike. The image noise
    estimated from each image alone (`image_noise`) gives only the noise's part of it (and the variance of
    the gradient's noise that is removed); on renders it overestimates the noise of fully textured images
    (1.9 DN for 1 DN: fine texture passes Immerkaer's operator), so it is not used as a floor."""
    from dstereo.stereo.subpixel import refinement_terms

    e, g, s_l, s_r = refinement_terms(left, right, disparity, window_sigma)
    spread = iterated_kernel(window_sigma, iterations)
    c = spread.shape[0] // 2
    left_share = 1.0 - 2.0 * spread[c, c] + float(np.sum(spread ** 2))
    posterior = _masked_smooth(e * e, np.isfinite(disparity), window_sigma) / left_share
    quantisation = (1.0 / 12.0) * (1.0 / s_l ** 2 + 1.0 / s_r ** 2)  # 8-bit steps of both images
    var_e = np.fmax(posterior, quantisation)
    sigma = sandwich_sigma(g, var_e, _gauss_kernel(window_sigma), spread)
    return sigma * np.sqrt(correlation_gain(e, g, np.isfinite(disparity)))


def _autocorrelation(x: np.ndarray, ok: np.ndarray, lags: int) -> np.ndarray:
    """(2 lags + 1, 2 lags + 1) normalised autocorrelation of x over the pixels `ok` (mean removed)."""
    x = np.where(ok, x - np.mean(x[ok]), 0.0)
    h, w = x.shape
    out = np.zeros((2 * lags + 1, 2 * lags + 1))
    n = float(np.sum(x * x))
    for a in range(0, lags + 1):
        for b in range(-lags if a > 0 else 0, lags + 1):
            u = x[max(a, 0):h + min(a, 0), max(b, 0):w + min(b, 0)]
            v = x[max(-a, 0):h + min(-a, 0), max(-b, 0):w + min(-b, 0)]
            # lag (-a, -b) multiplies the same pairs, u and v swapped: the same products, the same sum
            out[a + lags, b + lags] = out[lags - a, lags - b] = float(np.sum(u * v)) / max(n, 1e-300)
    return out


def correlation_gain(e: np.ndarray, g: np.ndarray, ok: np.ndarray, lags: int = 3) -> float:
    """The factor by which sum(F^2 g^2 var(e)) understates var(sum(F g e)) when neighbouring residuals are
    correlated (resampled, demosaiced or compressed images; misfits spanning pixels): sum over lags of
    rho_e rho_g, the residual's and the gradient's autocorrelations (1 for independent residuals).
    Clipped to [1, 16]."""
    if ok.sum() < 100:
        return 1.0
    return float(np.clip(np.sum(_autocorrelation(e, ok, lags) * _autocorrelation(g, ok, lags)), 1.0, 16.0))


def sgbm_sigma(left: np.ndarray, right: np.ndarray, disparity: np.ndarray, block_size: int,
               refined: np.ndarray | None = None) -> np.ndarray:
    """sigma_d (h, w) px of SGBM's own sub-pixel disparity. SGBM's error is measured against the sub-pixel
    refinement run on the same pair as a reference (it is 2-3x more accurate on textured surfaces, and its own
    sigma is `refined_sigma`): sigma^2 = local mean of (d_SGBM - d_refined)^2 - sigma_refined^2 (independent
    errors; SGBM's smoothness penalties keep it apart from the refinement's noise on weak texture), the local
    mean over a Gaussian of `block_size` px, at least SGBM's 1/16 px steps. Where the refinement drops pixels, the mean comes from the
    neighbours, else the map's median deviation is used (with the refined model's sigma at SGBM's d).
    `refined`: `subpixel.refine_disparity(left, right, disparity)` when the caller has it already."""
    from dstereo.stereo.subpixel import refine_disparity

    refined = refine_disparity(left, right, disparity) if refined is None else refined
    ok = np.isfinite(refined) & np.isfinite(disparity)
    dev2 = (disparity - refined) ** 2
    local = _masked_smooth(dev2, ok, float(block_size))
    if ok.any():
        local = np.where(np.isfinite(local), local, float(np.median(dev2[ok])))
    else:
        local = np.full(disparity.shape, SGBM_FLOOR_PX ** 2)
    # d_SGBM - d_ref = e_SGBM - e_ref: var_SGBM + var_ref if the two errors were independent, var_SGBM - var_ref
    # if SGBM's were the reference's plus its own; they see the same images, so the mean square itself
    return np.sqrt(np.maximum(local, QUANT_PX ** 2))


# --- the check on the data --------------------------------------------------------------------------------------


def _median(x: np.ndarray) -> float:
    """np.median of a 1-D float array, the same value (the same partition, the middle two summed and halved,
    NaN if any is NaN) without its generic-axis overhead, which was most of `plane_check`'s time (~750 calls
    per 640x480 pair)."""
    n = len(x)
    kth = [n // 2 - 1, n // 2] if n % 2 == 0 else [(n - 1) // 2]
    part = np.partition(x, kth + [-1])
    if np.isnan(part[-1]):
        return np.nan
    return part[n // 2] if n % 2 else (part[n // 2 - 1] + part[n // 2]) / 2


def _tile_fit(d: np.ndarray, tile: int):
    """Robust quadratic fit over one tile: (residual robust std, kept mask) or None for a tile with edges."""
    ok = np.isfinite(d)
    if ok.mean() < 0.5:  # half the tile: the refinement drops textureless pixels (a chessboard's squares)
        return None
    v, u = np.nonzero(ok)
    x, y = (u - tile / 2) / tile, (v - tile / 2) / tile
    a = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1)
    z = d[ok].astype(float)
    keep = np.ones(len(z), bool)
    for _ in range(2):
        coef, *_ = np.linalg.lstsq(a[keep], z[keep], rcond=None)
        r = z - a @ coef
        s = MAD_TO_STD * _median(np.abs(r[keep] - _median(r[keep])))
        keep = np.abs(r) <= max(4.0 * s, 1e-9)
    if keep.mean() < 0.9:
        return None
    mask = np.zeros_like(ok)
    mask[v[keep], u[keep]] = True
    return MAD_TO_STD * float(_median(np.abs(r[keep] - _median(r[keep])))), mask


@functools.lru_cache(maxsize=None)
def fit_survival(kind: str, scale: float, tile: int = TILE) -> float:
    """kappa: the robust std of the tile-fit residuals of a unit-std noise field correlated like the model's
    (`kind` 'gauss' sigma = scale px, or 'box' of scale px), i.e. the part of the noise the fit leaves."""
    from scipy.ndimage import gaussian_filter, uniform_filter

    rng = np.random.default_rng(1)
    n = 8 * tile
    white = rng.normal(size=(n + 64, n + 64))
    if kind == "iterated":  # the refinement's K passes (`iterated_kernel`) of a Gaussian window of `scale` px
        from scipy.ndimage import correlate

        field = correlate(white, iterated_kernel(scale, 6), mode="reflect")
    else:
        field = gaussian_filter(white, scale) if kind == "gauss" else uniform_filter(white, int(scale))
    field = field[32:-32, 32:-32]
    field /= field.std()
    out = [_tile_fit(field[i:i + tile, j:j + tile], tile) for i in range(0, n, tile) for j in range(0, n, tile)]
    return float(np.median([o[0] for o in out if o is not None]))


def _masked_medians(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """np.median of each row's values under `mask` (rows of (n, m)): the same values (sorted, the middle one or
    the middle two summed and halved), NaN for a row with none."""
    k = mask.sum(axis=1)
    ordered = np.sort(np.where(mask, x, np.inf), axis=1)  # the masked-out values sort last
    rows = np.arange(len(x))
    lo = ordered[rows, np.maximum((k - 1) // 2, 0)]
    hi = ordered[rows, np.maximum(k // 2, 0)]
    return np.where(k == 0, np.nan, np.where(k % 2 == 1, lo, (lo + hi) / 2))


def _tile_fits(d: np.ndarray, tile: int):
    """`_tile_fit` of many tiles at once (d: (n, tile * tile), NaN where not usable): (robust std per tile, NaN
    for a tile it refuses; kept-pixel masks (n, tile * tile)). The same robust passes and medians; each
    quadratic solved by its normal equations (batched) instead of one lstsq per tile, which agrees to rounding
    (the 6 x 6 system of a tile at least half full is well conditioned: x, y in [-0.5, 0.5])."""
    n = len(d)
    std, masks = np.full(n, np.nan), np.zeros(d.shape, bool)
    ok_all = np.isfinite(d)
    used = np.flatnonzero(ok_all.mean(axis=1) >= 0.5)  # half the tile, as `_tile_fit`
    if not len(used):
        return std, masks
    ok = ok_all[used]
    k = np.arange(tile * tile)
    x, y = (k % tile - tile / 2) / tile, (k // tile - tile / 2) / tile
    a = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1)  # (m, 6)
    products = (a[:, :, None] * a[:, None, :]).reshape(len(k), 36)
    z = np.where(ok, d[used], 0.0)
    keep, r = ok, z
    for _ in range(2):
        w = keep.astype(float)
        normal = (w @ products).reshape(-1, 6, 6)
        coef = np.linalg.solve(normal, ((w * z) @ a)[..., None])[..., 0]
        r = z - coef @ a.T
        med = _masked_medians(r, keep)
        spread = MAD_TO_STD * _masked_medians(np.abs(r - med[:, None]), keep)
        keep = ok & (np.abs(r) <= np.maximum(4.0 * spread, 1e-9)[:, None])
    good = keep.sum(axis=1) / ok.sum(axis=1) >= 0.9
    found = MAD_TO_STD * _masked_medians(np.abs(r - _masked_medians(r, keep)[:, None]), keep)
    std[used] = np.where(good, found, np.nan)
    masks[used] = keep & good[:, None]
    return std, masks


def plane_check(disparity: np.ndarray, sigma_d: np.ndarray, kind: str, scale: float, tile: int = TILE,
                min_tiles: int = 6) -> dict:
    """Observed scatter about local quadratic fits vs the predicted sigma_d on the same pixels (module
    docstring): {'ratio': median observed / predicted, 'tiles', 'pixels', 'observed_px', 'predicted_px', ...};
    ratio None when fewer than `min_tiles` smooth tiles were found. Tiles in row order, all fitted at once
    (`_tile_fits`)."""
    kappa = fit_survival(kind, scale, tile)
    h, w = disparity.shape
    ny, nx = h // tile, w // tile

    def tiles(x):
        return x[:ny * tile, :nx * tile].reshape(ny, tile, nx, tile).swapaxes(1, 2).reshape(ny * nx, tile * tile)

    s = tiles(np.asarray(sigma_d, float))
    std, masks = _tile_fits(np.where(np.isfinite(s), tiles(np.asarray(disparity, float)), np.nan), tile)
    ratios, obs, pred, pixels = [], [], [], 0
    for t in np.flatnonzero(np.isfinite(std)):
        p = kappa * float(np.sqrt(np.mean(s[t][masks[t]] ** 2)))
        if p > 0:
            ratios.append(std[t] / p)
            obs.append(std[t] / kappa)
            pred.append(p / kappa)
            pixels += int(masks[t].sum())
    out = {"tiles": len(ratios), "pixels": pixels, "tile_px": tile, "fit_survival_kappa": kappa,
           "band": list(CHECK_BAND), "method": "robust std of residuals about quadratic fits of d(u, v) over "
           f"{tile} x {tile} px tiles without edges, / (kappa x RMS predicted sigma_d there); median over tiles"}
    if len(ratios) < min_tiles:
        return out | {"ratio": None, "note": f"only {len(ratios)} smooth tiles (need {min_tiles}): not checked"}
    r = np.array(ratios)
    return out | {"ratio": float(np.median(r)), "ratio_p25_p75": [float(np.percentile(r, 25)),
                                                                   float(np.percentile(r, 75))],
                  "observed_px": float(np.median(obs)), "predicted_px": float(np.median(pred))}


# --- the whole map for a reconstruction --------------------------------------------------------------------------


def disparity_sigma_map(originals, rectified, disparity: np.ndarray, refined: bool, block_size: int,
                        configured: float | None = None, name: str = "pair", report_image_noise: bool = True):
    """(sigma_d (h, w) px, NaN where disparity is; info dict for summary.json; warnings) of one pair.

    originals: the two input images (the image noise is measured on them, before resampling smooths it);
    rectified: the grey float rectified pair the disparity was measured on (the exact cubic pair when
    `refined`); configured: a user's --disparity-sigma (a constant map, still checked). `report_image_noise`
    False: the originals' noise, which only the report shows, is not estimated (info['image_noise_dn'] None)."""
    # reported: the sensor's share of what the matcher sees
    levels = [image_noise(img) for img in originals] if report_image_noise else None
    valid = np.isfinite(disparity)
    if configured is not None:
        sigma = np.full(disparity.shape, float(configured))
        basis = "configured (--disparity-sigma), constant"
    elif refined:
        sigma = refined_sigma(*rectified, disparity)
        basis = ("per pixel: weighted least-squares sandwich of the sub-pixel refinement's Gauss-Newton step "
                 "(Gaussian window sigma 2 px, 6 passes) with the residual variance of both images "
                 "(dstereo.stereo.disparity_noise)")
    else:
        sigma = sgbm_sigma(*rectified, disparity, block_size)
        basis = ("per pixel: SGBM's local RMS deviation from the sub-pixel refinement run as a reference, with "
                 "the refinement's own sandwich sigma in quadrature (dstereo.stereo.disparity_noise)")
    sigma = np.where(valid, sigma, np.nan)
    kind, scale = ("iterated", 2.0) if refined else ("box", float(block_size))
    check = plane_check(disparity, sigma, kind, scale)
    warnings, scaled = [], 1.0
    ratio = check.get("ratio")
    if ratio is not None and not (np.isfinite(ratio) and ratio > 0):
        # a scatter of 0 px is no measurement of the noise (a map flat within its tiles: SGBM's blocks far too
        # large, or one disparity everywhere): scaling by it would make every sigma 0
        warnings.append(f"{name}: the disparity noise check found a scatter of {check.get('observed_px', ratio):.3g} "
                        f"px about local surface fits ({check['tiles']} smooth tiles), no measure of the noise (the "
                        "disparity map is flat within its tiles); the per-point sigmas are the model's, not scaled, "
                        "unverified; check disparity.png and the SGBM settings")
        check = check | {"ratio_refused": ratio if np.isfinite(ratio) else None, "ratio": None,
                         "note": "scatter of 0 px: not used to scale"}
    elif ratio is not None:
        # the model gives each pixel's sigma relative to the others; the level is what the data show
        scaled = ratio
        sigma = sigma * ratio
        if not CHECK_BAND[0] <= ratio <= CHECK_BAND[1]:
            warnings.append(
                f"{name}: the disparity noise model is off on this scene: the scatter about local surface fits "
                f"({check['tiles']} smooth {TILE} x {TILE} px tiles, {check['observed_px']:.3g} px) is "
                f"{ratio:.2f}x the predicted {check['predicted_px']:.3g} px; the per-point sigmas are scaled by "
                f"{ratio:.2f} (the surface's own relief within a tile counts as noise)")
    else:
        warnings.append(f"{name}: the disparity noise could not be checked on the data ({check['note']}); the "
                        "per-point sigmas are the model's, unverified")
    ok = sigma[valid]
    info = {"basis": basis, "configured_px": configured, "scaled_by": scaled,
            "image_noise_dn": None if levels is None else [
                {"brightness": lv[0].round(2).tolist(), "sigma": lv[1].round(4).tolist()} for lv in levels],
            "sigma_d_px": {"median": float(np.median(ok)), "p05": float(np.percentile(ok, 5)),
                           "p95": float(np.percentile(ok, 95))} if ok.size else None,
            "plane_check": check}
    return sigma, info, warnings


def point_sigma_vectors(points: np.ndarray, disparity: np.ndarray, Q: np.ndarray, sigma_d: np.ndarray,
                        matrices: dict | None = None) -> np.ndarray:
    """(h, w, 3) the random displacement (1 sigma, mm) of every point along its ray, original left frame: the
    Q reprojection scales a point by 1 / W, W = Q[3,2] d + Q[3,3], so dp/dd = -p Q[3,2] / W. Its component
    along any direction a is that direction's random std (a recession height: a = the sample axis). A spherical
    rectification's `matrices` (`projection`, P1, P2): the range along the left ray moves by
    |d r_L / d d| = r_R / (fx |sin(psi_L - psi_R)|) per px (`triangulate.spherical_range_rate`), not through Q."""
    if matrices is not None and str(matrices.get("projection", "pinhole")) == "spherical":
        from dstereo.stereo.triangulate import spherical_range_rate

        p = np.asarray(points, float)
        rate = np.asarray(spherical_range_rate(np.asarray(disparity, float), np.asarray(matrices["P1"]),
                                               np.asarray(matrices["P2"])))
        unit = p / np.linalg.norm(p, axis=-1, keepdims=True)
        return unit * (rate * np.asarray(sigma_d, float))[..., None]
    w = Q[3, 2] * np.asarray(disparity, float) + Q[3, 3]
    return np.asarray(points, float) * (np.abs(Q[3, 2] / w) * np.asarray(sigma_d, float))[..., None]
