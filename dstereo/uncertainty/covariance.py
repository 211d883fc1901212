"""Parameter covariance from the Schur complement, and an identifiability report.

cov(g) = sigma^2 S^-1 with S the Schur complement of J'J on the shared parameters (exactly the g-block of
(J'J)^-1) and sigma^2 = SSE / (residuals - free parameters), the unbiased noise estimate. When S is near
singular, standard deviations are meaningless: `conditioning` says so and names the parameters involved.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Scaled (correlation-form) condition number above which the shared parameters are not all identifiable.
ILL_CONDITIONED = 1e10
# A wild fit: a parameter not determined (sigma above WILD_SIGMA of its value: not 2-sigma from zero) at a value
# no lens needs, with cancelling partners. The condition number misses these (webcams, rational model:
# k1 = 138 +- 168, k3 = -590 +- 588 at scaled condition 7e7-1.6e9). Radial / rational / fisheye coefficients of
# normalised coordinates are O(0.01-1) for real lenses (a well-determined k = 20 in a rational pair is fine:
# only large *and* undetermined values count); tangential ones are < 0.01 (decentring of a few microns).
WILD_SIGMA = 0.5
WILD_VALUE = {"k": 1.0, "p": 0.1, "fk": 1.0}
# Intrinsics: a focal length uncertain by more than this share of itself is no calibration.
WILD_FOCAL_SIGMA = 0.05


def scaled_inverse(schur: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive matrix after Jacobi scaling.

    Parameters differ by 10^6 in scale (fx vs k3), so the raw matrix's condition number (up to ~1e16 at narrow
    fields of view) would make a pseudo-inverse cut real, weakly determined directions and report standard
    deviations far too small. Scaled to unit diagonal, only true near-degeneracies remain.
    A matrix that is not finite (a subset whose solve diverged) or whose decomposition fails gets NaN, so its
    standard deviations read as unknown instead of stopping the whole batch with LinAlgError.
    """
    schur = np.asarray(schur, float)
    d = np.sqrt(np.maximum(np.diagonal(schur, axis1=-2, axis2=-1), 1e-300))
    outer = d[..., :, None] * d[..., None, :]
    with np.errstate(invalid="ignore"):  # inf / inf in a diverged subset: NaN, handled below
        scaled = schur / outer
    if np.isfinite(scaled).all():
        try:
            return np.linalg.pinv(scaled, rcond=1e-15, hermitian=True) / outer
        except np.linalg.LinAlgError:
            pass  # one matrix of the batch failed: invert them one by one below
    flat = scaled.reshape(-1, *scaled.shape[-2:])
    inv = np.stack([_pinv_or_nan(m) for m in flat]).reshape(scaled.shape)
    return inv / outer


def _pinv_or_nan(m: np.ndarray) -> np.ndarray:
    if not np.isfinite(m).all():
        return np.full_like(m, np.nan)
    try:
        return np.linalg.pinv(m, rcond=1e-15, hermitian=True)
    except np.linalg.LinAlgError:
        return np.full_like(m, np.nan)


def covariance(schur: np.ndarray, sse: float, n_residuals: int, n_params: int) -> np.ndarray:
    dof = n_residuals - n_params
    sigma2 = sse / dof if dof > 0 else np.nan
    return sigma2 * scaled_inverse(schur)


def _coeff_kind(name: str) -> str | None:
    base = name.split(".")[-1]  # a stereo joint solve names them left.k1, right.p2
    for kind in ("fk", "k", "p"):
        if base.startswith(kind) and base[len(kind):].isdigit():
            return kind
    return None


def wild_parameters(names, values, std, image_size=None) -> list[tuple[str, float, float, str]]:
    """(name, value, sigma, why) of each parameter whose fit is wild (see WILD_SIGMA, WILD_VALUE)."""
    out = []
    for n, v, s in zip(names, np.asarray(values, float), np.asarray(std, float)):
        base, kind = n.split(".")[-1], _coeff_kind(n)
        if not np.isfinite(v) or not np.isfinite(s):
            out.append((n, float(v), float(s), "not finite"))
        elif kind is not None and abs(v) > WILD_VALUE[kind] and s > WILD_SIGMA * abs(v):
            out.append((n, float(v), float(s), f"undetermined at a value (|{base}| > {WILD_VALUE[kind]:g}) no lens "
                                               "needs"))
        elif base in ("fx", "fy") and (v <= 0 or s > WILD_FOCAL_SIGMA * v):
            out.append((n, float(v), float(s), f"focal length not positive or uncertain by > {WILD_FOCAL_SIGMA:.0%}"))
        elif base in ("cx", "cy") and image_size is not None:
            size = image_size[0] if base == "cx" else image_size[1]
            if not 0 <= v <= size or s > 0.25 * size:
                out.append((n, float(v), float(s), f"principal point outside the image (0..{size}) or uncertain "
                                                   "by > 1/4 of it"))
    return out


@dataclass
class Conditioning:
    condition_number: float  # of the scale-free (unit-diagonal) Schur complement
    identifiable: bool  # condition number below ILL_CONDITIONED and no wild parameter
    weak_parameters: list[str]  # those loading on the near-null directions, and the wild ones
    max_correlation: tuple[str, str, float]
    wild: list[tuple[str, float, float, str]] = field(default_factory=list)  # `wild_parameters`

    def message(self) -> str:
        if self.identifiable:
            return f"well conditioned (scaled condition number {self.condition_number:.2g}, no wild parameter)"
        wild = ""
        if self.wild:
            figures = "; ".join(f"{n} = {v:.4g} +- {s:.3g} ({why})" for n, v, s, why in self.wild)
            wild = f"wild fit: {figures}. These values are not determined by the views (cancelling parameters)"
        if self.condition_number <= ILL_CONDITIONED:
            return (f"{wild}, at scaled condition number {self.condition_number:.2g}; use a smaller distortion "
                    "model (or --model auto, which chooses by held-out error), or add views that fill the image corners")
        return (
            f"not identifiable from these views: scaled condition number {self.condition_number:.2g} "
            f"(> {ILL_CONDITIONED:.0e}); weakly determined: {', '.join(self.weak_parameters)}. "
            + (f"{wild}. " if wild else "") + "Their standard deviations are not meaningful; use a simpler "
            "distortion model (or --model auto, which chooses by held-out error) or add views that fill the image corners"
        )


def conditioning(schur: np.ndarray, names: tuple[str, ...], values=None, std=None, image_size=None) -> Conditioning:
    """Condition number and weak directions of `schur`; with `values` and their `std`, the wild-fit test."""
    d = np.sqrt(np.maximum(np.diag(schur), 1e-300))
    scaled = schur / np.outer(d, d)
    evals, evecs = np.linalg.eigh(scaled)
    cond = float(evals[-1] / max(evals[0], 1e-300))
    weak_dirs = evecs[:, evals < evals[-1] / ILL_CONDITIONED]
    weak = [names[i] for i in range(len(names)) if weak_dirs.size and np.max(np.abs(weak_dirs[i])) > 0.2]
    corr = np.linalg.pinv(scaled, hermitian=True)
    cd = np.sqrt(np.maximum(np.diag(corr), 1e-300))
    with np.errstate(over="ignore", invalid="ignore"):  # a singular candidate model (--model auto tries several)
        corr = np.nan_to_num(corr / np.outer(cd, cd), nan=1.0, posinf=1.0, neginf=-1.0)
    corr = np.clip(corr, -1.0, 1.0)  # a correlation; rounding in a near-singular pinv can leave it past +-1
    np.fill_diagonal(corr, 0.0)
    i, j = np.unravel_index(np.argmax(np.abs(corr)), corr.shape)
    wild = [] if values is None else wild_parameters(names, values, std, image_size)
    weak += [w[0] for w in wild if w[0] not in weak]
    return Conditioning(cond, cond <= ILL_CONDITIONED and not wild, weak, (names[i], names[j], float(corr[i, j])),
                        wild)


def joint_normal(normal: np.ndarray, n_shared: int, weight: np.ndarray | None = None) -> np.ndarray:
    """J'J of (shared parameters, pose of view 0, pose of view 1, ...) assembled from the solver's per-view blocks.

    `normal` (V, P+1, P+1) is each view's [J r]'[J r] (P = n_shared + 6; the last row/column is the residual):
    the shared block is the sum over views, each view adds its own 6 x 6 pose block and its shared-pose cross
    terms, and poses of different views never share a residual (zero blocks). Views with `weight` 0 are left out.
    """
    normal = np.asarray(normal, float)
    keep = np.arange(len(normal)) if weight is None else np.flatnonzero(np.asarray(weight) > 0)
    g, n = n_shared, len(keep)
    out = np.zeros((g + 6 * n, g + 6 * n))
    for j, v in enumerate(keep):
        w = 1.0 if weight is None else float(weight[v])
        m = w * normal[v, : g + 6, : g + 6]
        s = slice(g + 6 * j, g + 6 * j + 6)
        out[:g, :g] += m[:g, :g]
        out[:g, s], out[s, :g], out[s, s] = m[:g, g:], m[g:, :g], m[g:, g:]
    return out


def joint_covariance(normal: np.ndarray, n_shared: int, sse: float, n_residuals: int,
                     weight: np.ndarray | None = None, prior: np.ndarray | None = None) -> np.ndarray:
    """Covariance of (shared parameters, all view poses) of a solve, sigma^2 (J'J)^-1 with the unbiased sigma^2
    of `covariance`; its shared block equals `covariance(schur, ...)` (the Schur complement's inverse). `prior`
    (G, G): the information a prior on the shared vector adds (a splined lens's), as in the solve."""
    jtj = joint_normal(normal, n_shared, weight)
    if prior is not None:
        jtj[:n_shared, :n_shared] += prior
    return covariance(jtj, sse, n_residuals, len(jtj))
