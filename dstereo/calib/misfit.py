"""Structured residuals: does the lens model leave a pattern across the image?

A model that fits leaves residuals that are noise: their mean over any image region is zero within
sigma / sqrt(count). A model too simple for the lens (a fisheye with the 5-coefficient model) leaves the same
displacement wherever the image is reached by several views. The image is cut into CELLS (8 x 6) and each
cell's mean residual vector m_c over its n_c inlier corners (at least MIN_PER_CELL) is tested against zero.
The fit itself absorbs part of any pattern, so a well-fitted model lands below the reference, not above.

Real corners are not independent (one view's detection errors correlate, a board that is not flat gives each
view its own pattern), so the noise a cell mean is tested against is its scatter between the views that reach
the cell: a per-view component tau^2 (pooled over all cells, so well determined) is added to the corners'
noise sigma^2 / n, and sum_c |m_c|^2 / var(m_c) ~ chi^2(2 C). A lens misfit is the same displacement at the
same place in every view and stands out against this; per-view errors raise tau^2 instead. A warning needs
both P < P_WARN and a visible pattern: the cell means' RMS beyond the noise floor at least SHARE_WARN of the
residual RMS.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import chdtrc  # chi2.sf itself; scipy.stats's import costs ~0.7 s CPU, measured

CELLS = (8, 6)
MIN_PER_CELL = 5
MIN_VIEWS = 2  # views reaching a cell: its mean's scatter between views enters the noise it is tested against
# Measured on the shared real sets (8 x 6 cells, inlier corners): well-fitted models (5-coefficient, rational,
# fisheye) p >= 1e-4 but one pathological rational solve (opencv_stereo left, scaled condition 7e300, already
# flagged as not identifiable) at 7e-10, share <= 0.28; models too simple: k1 alone on rig640 right p = 1e-8
# (k1,k2 fits it: 0.147 -> 0.138 px), on opencv_stereo right 4e-25; k1 or k1,k2 on fisheye640 <= 9e-24.
P_WARN = 1e-6
SHARE_WARN = 0.25


@dataclass
class ResidualPattern:
    statistic: float  # sum over cells and coordinates of z^2 (each cell mean's t against its between-view scatter)
    dof: int  # 2 x cells used
    p_value: float
    systematic_px: float  # sqrt((sum n_c |m_c|^2 - 2 C sigma^2) / N): the cell means' RMS beyond noise, per corner
    rms_px: float  # residual RMS per corner (both coordinates) of the corners binned
    cells_used: int
    cell_mean: np.ndarray  # (rows, cols, 2) px, NaN where a cell has too few corners

    @property
    def share(self) -> float:
        return self.systematic_px / self.rms_px if self.rms_px > 0 else 0.0

    @property
    def significant(self) -> bool:
        return self.p_value < P_WARN and self.share >= SHARE_WARN

    def message(self, model: str) -> str | None:
        if not self.significant:
            return None
        return (f"model {model} leaves a systematic residual pattern across the image: cell means (8 x 6 cells) "
                f"{self.systematic_px:.3f} px RMS against a residual RMS of {self.rms_px:.3f} px "
                f"(chi^2 = {self.statistic:.0f} for {self.dof} dof, p = {self.p_value:.1g}); the lens model is too "
                "simple for this lens: try a richer one (--model rational, or --model fisheye for a wide-angle lens)")

    def as_dict(self) -> dict:
        return {"cells": list(CELLS), "cells_used": self.cells_used, "chi2": self.statistic, "dof": self.dof,
                "p_value": self.p_value, "systematic_px": self.systematic_px, "rms_px": self.rms_px,
                "systematic_share": self.share, "significant": self.significant,
                "thresholds": {"p": P_WARN, "share": SHARE_WARN}}


def residual_pattern(obs: np.ndarray, residuals: np.ndarray, image_size: tuple[int, int], sigma: float,
                     inliers: np.ndarray | None = None) -> ResidualPattern:
    """Bin the residual vectors (V, n, 2) at the observed corners (V, n, 2) px into CELLS and test each cell's
    mean against the scatter of that mean between views (module docstring); `inliers` (V, n) leaves rejected
    corners out. `sigma` (px per coordinate) gives the noise floor of the systematic share."""
    obs, residuals = np.asarray(obs, float), np.asarray(residuals, float)
    n_v = obs.shape[0]
    mask = np.ones(obs.shape[:2], bool) if inliers is None else np.asarray(inliers, bool)
    cols, rows = CELLS
    ci = np.clip((obs[..., 0] / image_size[0] * cols).astype(int), 0, cols - 1)
    ri = np.clip((obs[..., 1] / image_size[1] * rows).astype(int), 0, rows - 1)
    cell = np.where(mask, ri * cols + ci, rows * cols)  # outliers to a bin of their own, dropped
    n_cells = rows * cols
    # per view and cell: corner count and mean residual
    vc = (np.arange(n_v)[:, None] * (n_cells + 1) + cell).ravel()
    cnt = np.bincount(vc, minlength=n_v * (n_cells + 1)).reshape(n_v, -1)[:, :n_cells]
    sums = np.stack([np.bincount(vc, residuals[..., k].ravel(), minlength=n_v * (n_cells + 1))
                     .reshape(n_v, -1)[:, :n_cells] for k in range(2)], axis=2)
    has = cnt > 0
    views = has.sum(axis=0)
    count = cnt.sum(axis=0)
    used = (views >= MIN_VIEWS) & (count >= MIN_PER_CELL)
    mean = np.full((n_cells, 2), np.nan)
    u = np.where(has[..., None], sums / np.maximum(cnt, 1)[..., None], 0.0)  # (V, C, 2) per-view cell means
    mean[used] = u[:, used].sum(axis=0) / views[used, None]
    inv_n = np.where(has, 1.0 / np.maximum(cnt, 1), 0.0)[:, used].sum(axis=0)  # sum_v 1 / n_vc
    dev = np.sum(np.where(has[:, used, None], (u[:, used] - mean[None, used]) ** 2, 0.0), axis=(0, 2))
    frac = 1.0 - 1.0 / views[used]
    # Pooled between-view component tau^2 (per coordinate) beyond the corners' own noise, from every cell's
    # scatter of its per-view means: E[dev_c] = 2 (1 - 1/V_c) (sigma^2 sum_v 1/n_vc + V_c tau^2).
    tau2 = max(0.0, float(np.sum(dev) - 2 * sigma ** 2 * np.sum(frac * inv_n))
               / max(2.0 * float(np.sum(views[used] - 1)), 1.0))
    var = (sigma ** 2 * inv_n + views[used] * tau2) / views[used] ** 2  # of each cell mean, per coordinate
    z2 = float(np.sum(np.sum(mean[used] ** 2, axis=1) / var))
    dof = 2 * int(used.sum())
    energy = float(np.sum(count[used] * np.sum(mean[used] ** 2, axis=1)))
    n = max(int(count[used].sum()), 1)
    # the systematic part beyond what noise alone puts into the cell means (2 sigma^2 per cell)
    excess = max(energy - dof * sigma ** 2, 0.0)
    r2 = np.sum(residuals ** 2, axis=2)[mask & used.take(np.minimum(cell, n_cells - 1))]
    rms = float(np.sqrt(np.mean(r2))) if r2.size else 0.0
    return ResidualPattern(z2, dof, float(chdtrc(dof, z2)) if dof else 1.0, float(np.sqrt(excess / n)),
                           rms, int(used.sum()), mean.reshape(rows, cols, 2))


def solution_pattern(obs: np.ndarray, sol) -> ResidualPattern:
    """`residual_pattern` of a one-camera `calib.solution.Solution` on its views `obs`, sigma from its inlier
    residuals."""
    from dstereo.calib.outliers import noise_sigma

    mask = np.ones(obs.shape[:2], bool) if sol.inliers is None else sol.camera_inliers()
    residuals = sol.residuals[:, 0]
    sigma = noise_sigma(residuals, mask, len(sol.values) + 6 * int(mask.any(axis=1).sum()))
    return residual_pattern(obs, residuals, sol.camera().image_size, sigma, mask)


def neighbour_correlation(obs: np.ndarray, residuals: np.ndarray, inliers: np.ndarray | None = None
                          ) -> tuple[float, float]:
    """(rho, z): how alike the residual vectors of neighbouring corners of one view are. Each inlier corner is
    paired with its nearest inlier corner of the same view; rho = sum r_i . r_j / sum |r_i|^2 over the pairs, and
    z = sum r_i . r_j / sqrt(sum (r_i . r_j)^2) (about N(0, 1) when corner errors are independent: each product
    then has mean 0). A lens model that does not fit leaves residuals that vary smoothly over the board (rho near
    1); detection noise alone leaves rho near 0. The coarse cell test (`residual_pattern`) misses a misfit whose
    poses absorb a different part in each view; this one does not care where in the image it is."""
    obs, residuals = np.asarray(obs, float), np.asarray(residuals, float)
    mask = np.ones(obs.shape[:2], bool) if inliers is None else np.asarray(inliers, bool)
    dots, norms = [], []
    for v in range(len(obs)):
        p, r = obs[v][mask[v]], residuals[v][mask[v]]
        if len(p) < 2:
            continue
        d2 = np.sum((p[:, None] - p[None]) ** 2, axis=-1)
        np.fill_diagonal(d2, np.inf)
        j = np.argmin(d2, axis=1)
        dots.append(np.sum(r * r[j], axis=1))
        norms.append(np.sum(r * r, axis=1))
    if not dots:
        return float("nan"), float("nan")
    dots, norms = np.concatenate(dots), np.concatenate(norms)
    return float(dots.sum() / max(norms.sum(), 1e-300)), float(dots.sum() / max(np.sqrt(np.sum(dots ** 2)), 1e-300))
