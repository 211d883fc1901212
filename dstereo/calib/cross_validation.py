"""Cross-validation of a camera calibration's uncertainty: disjoint halves of the views, calibrated separately.

If the uncertainty is honest, two calibrations from disjoint halves differ by about what their covariances
predict. Each split's two halves are compared by `uncertainty.camera_diff.projection_diff`, the statistic `dstereo
diff` computes on two written cameras (the module docstring there): the point at `range` on each grid pixel's ray
through half A, moved by the rigid transform fitted between the halves (weighted by the inverse of the two halves'
pose-compensated map variances, so the fit is held by the pixels both calibrations know, not by extrapolated
image corners), projected by half B; against the first-order prediction from both halves' marginal lens
covariances with what the fit absorbs removed. `cross_validation/split_<k>/a` and `/b` in the results folder hold
each split's halves as camera files, so `dstereo diff` on them reads the split's figures (tests check to 1e-9).
Every figure is taken over the grid pixels inside both halves' corners' fields (`camera_diff.corner_field` of each
half's own corners, written with it as `field`): beyond them the maps are a lower bound, and no comparison of two
calibrations sharing a lens model can check them (a misfit both share cancels in their difference; docs/validation.md,
the render). The pixels outside are read apart (`diagnosis`): the pooled ratio there over the one inside, against
the band a right prediction's quotient falls in (`band_if_right`, the same draws over the same pixels).

A split's ratio is its weighted rms difference over the rms prediction, divided by the prediction's own typical
value (`camera_diff.expected_log_ratio`: one dominant mode makes a right prediction's raw ratio typically 0.53):
its log has mean 0 when the prediction is right, so the geometric mean over splits reads 1 (`ratio_raw` keeps the
undivided one). Per pixel the 2 x 2 block of the prediction gives the Mahalanobis distance (median 1.18 if
right). `cross_validate` repeats the split over random halvings and pools them (geometric mean of the ratios,
median of all Mahalanobis distances).

Even so, a dozen splits of a dozen views are a noisy test: the splits share their views. `cross_validate`
therefore also simulates the whole procedure under the full set's own uncertainty model (each view's score drawn
with the covariance the tool claims, both halves' errors from the same draws, every split as computed here) and
reports the band in which a right prediction's pooled statistics fall on these very views and splits
(`band_if_right`): a verdict outside the acceptance band but inside that one says the test cannot tell. The two
halves' pose-compensated maps alone give a further prediction, sigma_A^2 + sigma_B^2 per pixel (`ratio_vs_maps`):
blind to what the fit absorbs, it reads near the ratio_raw where the weighted fit recovers the boards' frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dstereo.calib.mono import _run
from dstereo.calib.problem import WARP_NAMES
from dstereo.uncertainty.camera_diff import (GRID, LensCamera, ProjectionDiff,  # noqa: F401
                                             corner_field, expected_log_ratio, projection_diff)
from dstereo.uncertainty.covariance import covariance, joint_covariance, scaled_inverse
from dstereo.errors import DstereoError
from dstereo.models.distortion import lens_model
from dstereo.uncertainty.projection import (CAMERA_NAMES, FISHEYE_CAMERA_NAMES, mean_board_distance, model_key)
from dstereo.uncertainty.view_effects import view_effects
from dstereo.solver.lm import LMOptions

# The band the issue asks for, and the Mahalanobis median of a right prediction (median of sqrt(chi^2_2)).
RATIO_BAND = (0.67, 1.5)
MAHALANOBIS_PERFECT = float(np.sqrt(2.0 * np.log(2.0)))
MAHALANOBIS_MAX = 1.8
# d'C^-1 d / G of the lens parameters, mean over splits: 1 if right; the real sets read 1.1-1.9 and synthetic right
# predictions 0.86-1.24, so beyond 3 the parameters' own +- are not what the halves show
PARAMETER_CHI2_MAX = 3.0
NULL_DRAWS = 400  # simulated cross-validations for `band_if_right` (its 5 % and 95 % points to ~+-2 % in the log)
NULL_BAND = (5.0, 95.0)  # percentiles of the band a right prediction reads
MIN_HALF_VIEWS = 4  # fewer views than this per half do not constrain a camera with distortion


@dataclass
class HalfSolution:
    """One half's solve: intrinsics (`CAMERA_NAMES` order, 12), its free-parameter values, marginal and joint
    covariances, its views' poses, convergence."""

    params: np.ndarray
    values: np.ndarray
    cov: np.ndarray
    joint: np.ndarray
    poses: np.ndarray
    converged: bool
    rms: float
    std_ratio: float = 1.0  # median over its parameters of std with the views' effects / Jacobian std
    # its uncertainty model, for `band_if_right`: per used view Q_v = R_v R_v' (the score covariance it claims) and
    # the lens rows of S^-1 (error = gain @ sum_v t_v), both at its own solution
    score_roots: np.ndarray | None = None
    lens_gain: np.ndarray | None = None
    field: np.ndarray | None = None  # (gh, gw) bool: its corners' field on the cross-validation's grid (`corner_field`)


def _names_of(model: str) -> tuple[str, ...]:
    """The 12 slots of a half's `params` for a lens model (fisheye: cv2.fisheye's D in the first four)."""
    return FISHEYE_CAMERA_NAMES if model == "fisheye" else CAMERA_NAMES


def _lens_names(full) -> tuple[str, ...]:
    """The solve's intrinsics and distortion names (a board sag, when solved, is not the camera's)."""
    return tuple(n for n in full.names if n not in WARP_NAMES)


def solve_halves(full, obj, obs, weights: np.ndarray, options: LMOptions = LMOptions()) -> list[HalfSolution]:
    """Solve the problems given by view `weights` (K, V) (1 = used, 0 = left out) from the full-set solution
    `full` (a one-camera `calib.solution.Solution`), in the full set's compiled solver (same shapes: no second
    compile). `obs` is
    (V, n, 2), shared by all problems, or (K, V, n, 2), one set of corners per problem (a Monte Carlo)."""
    from dstereo.calib.mono import _residual_weights, _shared, chunk_rows

    obj, obs = np.asarray(obj, float), np.asarray(obs, float)
    n_views, n_pts = obs.shape[-3:-1]
    rows = chunk_rows(n_views, n_pts)
    # The halves fit the corners the full set fitted: outliers rejected there weigh 0 here too.
    inliers = np.ones((n_views, n_pts), bool) if full.inliers is None else full.camera_inliers()
    shared = _shared(obj)
    lens = _lens_names(full)
    free = tuple(full.camera().dist.free)
    free_idx = [_names_of(lens_model(free)).index(n) for n in lens]
    keep = np.arange(len(lens))  # the lens parameters lead the shared vector; a board sag (last) is marginalised
    out = []
    for c in range(0, len(weights), rows):
        w = np.asarray(weights[c: c + rows], float)
        k = len(w)
        res = _run(free, options, np.repeat(full.values[None], k, 0), np.repeat(full.poses[None], k, 0),
                   obs[c: c + k] if obs.ndim == 4 else np.repeat(obs[None], k, 0), w, np.full(k, options.lambda0), shared,
                   r_weight=np.repeat(_residual_weights(inliers)[None], k, 0))
        for i in range(k):
            m = int(np.count_nonzero(w[i]))
            g = len(full.values)
            sse, n_res = float(res.sse[i]), 2 * int(inliers[w[i] > 0].sum())
            params = np.zeros(12)
            params[free_idx] = res.g[i][keep]
            # each half carries its own views' effects, as every calibration's uncertainty the tool reports
            dof = n_res - g - 6 * m
            normal = np.asarray(res.normal[i])
            # a half that did not converge, or left a view's pose undetermined (measured: fisheye640's rational
            # model without outlier rejection), gets no covariance; cross_validate refuses it
            converged = bool(res.status[i] > 0) and _poses_determined(normal[w[i] > 0], g)
            if not converged:
                out.append(HalfSolution(params, np.asarray(res.g[i]), np.full((len(keep),) * 2, np.nan),
                                        np.full((len(keep) + 6 * m,) * 2, np.nan), np.asarray(res.p[i])[w[i] > 0],
                                        False, float("nan")))
                continue
            effects = view_effects(normal, g, sse / max(dof, 1), dof, w[i]) if dof > 0 else None
            cov = (covariance(np.asarray(res.schur[i]), sse, n_res, g + 6 * m) if effects is None else effects.cov)
            joint = (joint_covariance(normal, g, sse, n_res, w[i]) if effects is None
                     else effects.joint(normal, w[i]))
            # marginalising the sag = dropping its rows and columns (shared first, then the poses)
            kept = np.r_[keep, np.arange(g, len(joint))]
            out.append(HalfSolution(
                params=params, values=np.asarray(res.g[i]), cov=cov[np.ix_(keep, keep)], joint=joint[np.ix_(kept, kept)],
                poses=np.asarray(res.p[i])[w[i] > 0], converged=True,
                rms=float(np.sqrt(sse / (m * n_pts))),
                std_ratio=1.0 if effects is None else float(np.median(effects.std_ratio)),
                **({} if effects is None else _model_of(effects, len(lens)))))
    return out


def _poses_determined(normal: np.ndarray, g: int) -> bool:
    """Every view's 6 x 6 pose block finite and invertible (Jacobi-scaled condition below 1e12; the real views
    read 1e3-1e4, a board the model cannot place exactly singular)."""
    if not np.isfinite(normal).all():
        return False
    blocks = normal[:, g: g + 6, g: g + 6]
    d = np.sqrt(np.maximum(np.diagonal(blocks, axis1=1, axis2=2), 1e-300))
    return bool(np.all(np.linalg.cond(blocks / (d[:, :, None] * d[:, None, :])) < 1e12))


def _model_of(effects, n_lens: int) -> dict:
    """A half's claimed score covariances Q_v = (sigma^2 + tau) S_v + S_v Omega S_v as roots, and its lens gain.
    Jacobi-scaled before the square root: raw, fx and k3 differ by 10^6 and eigh would lose a rational model's
    weak directions."""
    sv = effects.s_views
    s_total = sv.sum(axis=0)
    q = (effects.sigma2 + effects.tau) * sv + (sv * effects.omega) @ sv
    d = np.sqrt(np.maximum(np.diag(s_total), 1e-300))
    lam, vec = np.linalg.eigh(q / (d[:, None] * d[None, :]))
    roots = vec * np.sqrt(np.maximum(lam, 0.0))[:, None, :] * d[:, None]
    return {"score_roots": roots, "lens_gain": scaled_inverse(s_total)[:n_lens]}


def half_camera(h: HalfSolution, names, image_size, label: str = "") -> LensCamera:
    """A half's camera for `camera_diff.projection_diff`: its intrinsics, marginal and joint covariances, poses."""
    model = model_key(tuple(names))
    return LensCamera(model, np.asarray(h.params, float), tuple(names), h.cov, tuple(image_size), label,
                      joint=h.joint, poses=h.poses)


@dataclass
class SplitResult:
    """One split's comparison: the figures of its `projection` (`camera_diff.ProjectionDiff`, the statistic `dstereo
    diff` computes on the halves' written files), on its grid (gh, gw)."""

    diff: np.ndarray  # (gh, gw, 2) px, NaN where masked
    cov: np.ndarray  # (gh, gw, 2, 2) px^2 predicted
    mahalanobis: np.ndarray  # (gh, gw)
    ratio: float  # weighted rms observed / predicted, divided by its typical value if right (1 if right, in the log)
    ratio_vs_maps: float  # the same against the two halves' pose-compensated maps alone (blind to the fit)
    transform: np.ndarray  # (6,) rvec, t of T_BA
    covered: np.ndarray | None = None  # (gh, gw) grid pixels inside its corners' field (`corner_field`)
    parameter_chi2: float = float("nan")  # d' (C_A + C_B)^-1 d / G of the lens parameters' difference d (1 if right)
    ratio_raw: float = float("nan")  # undivided: about 0.53-0.7 in the geometric mean of a right prediction
    modes: float = float("nan")  # effective number of modes of C, sum(lambda)^2 / sum(lambda^2)
    projection: ProjectionDiff | None = None
    weight: np.ndarray | None = None  # (gh, gw) each pixel's weight in the fit and the ratio (`camera_diff`)
    # (G,) each lens parameter's squared difference over its predicted variance, d_i^2 / (C_A + C_B)_ii (1 if right)
    parameter_excess: np.ndarray | None = None


def compare_halves(a: HalfSolution, b: HalfSolution, names, image_size, range_: float,
                   grid: tuple[int, int] = GRID, corners: np.ndarray | None = None) -> SplitResult:
    """Half B's camera against half A's by `camera_diff.projection_diff` (the module docstring there), with the
    halves' own covariances, over the pixels inside both halves' corners' fields (`HalfSolution.field`, as their
    written files carry them); `corners` (n, 2) instead: one field for both (every observed corner)."""
    from dstereo.uncertainty.camera_diff import grid_pixels

    u, v, _ = grid_pixels(image_size, grid)
    if corners is not None:
        covered = corner_field(u, v, corners)
    elif a.field is not None and b.field is not None:
        covered = np.asarray(a.field, bool) & np.asarray(b.field, bool)
    else:
        covered = None
    d = projection_diff(half_camera(a, names, image_size, "half A"), half_camera(b, names, image_size, "half B"),
                        range_, grid, tuple(image_size), field=covered)
    if d.cov is None:
        raise DstereoError("cross-validation: a half's covariance is missing")
    dp = a.values[: len(a.cov)] - b.values[: len(b.cov)]  # the lens parameters lead the shared vector
    # scaled first: fx and k3 differ by 10^6, and a plain pseudo-inverse of the sum loses the small directions
    chi2 = float(dp @ scaled_inverse(a.cov + b.cov) @ dp / len(dp))
    excess = dp ** 2 / np.maximum(np.diag(a.cov + b.cov), 1e-300)
    return SplitResult(d.diff, d.cov, d.mahalanobis, d.ratio, d.ratio_vs_maps, d.transform, covered, chi2,
                       d.ratio_raw, d.modes, d, d.weight, excess)


@dataclass(frozen=True)
class BandIfRight:
    """Where the pooled statistics of a right prediction fall on these views and splits (`band_if_right`)."""

    ratio: tuple[float, float]  # NULL_BAND percentiles of the geometric-mean ratio
    mahalanobis: tuple[float, float]  # ... of the median Mahalanobis distance
    ratio_median: float
    mahalanobis_median: float
    pass_rate: float  # share of right predictions that the acceptance (RATIO_BAND, MAHALANOBIS_MAX) passes
    draws: int
    # NULL_BAND percentiles of the pooled ratios outside the corners' fields over inside them (None: no field, or
    # no pixel outside), and of the pooled ratio outside: what a right prediction reads where the model extrapolates
    outside_over_inside: tuple[float, float] | None = None
    outside: tuple[float, float] | None = None

    def contains(self, ratio: float, mahalanobis: float) -> bool:
        return self.ratio[0] <= ratio <= self.ratio[1] and self.mahalanobis[0] <= mahalanobis <= self.mahalanobis[1]

    def summary(self) -> dict:
        return {"percentiles": list(NULL_BAND), "ratio": list(self.ratio), "mahalanobis": list(self.mahalanobis),
                "ratio_median": self.ratio_median, "mahalanobis_median": self.mahalanobis_median,
                "acceptance_pass_rate": self.pass_rate, "draws": self.draws,
                "ratio_pooled_outside_corner_field": None if self.outside is None else list(self.outside),
                "outside_over_inside": None if self.outside_over_inside is None else list(self.outside_over_inside)}


def band_if_right(halves, sols: list[HalfSolution], splits: list[SplitResult], draws: int = NULL_DRAWS,
                  seed: int = 0):
    """Simulate the cross-validation as if every half's stated uncertainty were right: each view v draws one
    standard normal z_v (G,), shared by every half that holds it (so the splits are as correlated as the real
    ones); half H's score of v is t_v = R_v z_v with its claimed Q_v = R_v R_v' (`_model_of`: the view effects
    where fitted, sigma^2 S_v otherwise), its lens error [S_H^-1 sum_{v in H} t_v], and each split's difference,
    ratio and Mahalanobis distances as `compare_halves` computes them (over the corners' fields), and the pooled
    ratios inside and outside the fields from the same draws. First order, as the prediction itself. None where a
    half kept no model."""
    if any(h.score_roots is None for h in sols) or any(x.projection is None for x in splits):
        return None
    n_views, g = max(int(max(a.max(), b.max())) for a, b in halves) + 1, sols[0].score_roots.shape[1]
    z = np.random.default_rng(seed).normal(size=(draws, n_views, g))
    log_ratio, maha = np.zeros((draws, len(splits))), []
    num_in, num_out, den_in, den_out = np.zeros(draws), np.zeros(draws), 0.0, 0.0
    for k, ((a, b), x) in enumerate(zip(halves, splits)):
        err = [np.einsum("vij,dvj->di", h.score_roots, z[:, part]) @ h.lens_gain.T
               for h, part in ((sols[2 * k], a), (sols[2 * k + 1], b))]
        ratio_k, maha_k, (n_in, n_out) = x.projection.simulate(*err, per_pixel=True, pooled=True)
        log_ratio[:, k] = np.log(ratio_k)
        maha.append(maha_k)
        if x.covered is not None:
            num_in, num_out = num_in + n_in, num_out + n_out
            den_in += x.projection.pooled(x.covered)[1]
            den_out += x.projection.pooled(~x.covered)[1]
    ratio = np.exp(log_ratio.mean(axis=1))
    median = np.median(np.concatenate(maha, axis=1), axis=1)
    passed = (ratio >= RATIO_BAND[0]) & (ratio <= RATIO_BAND[1]) & (median <= MAHALANOBIS_MAX)
    lo, hi = NULL_BAND
    quotient = outside = None
    if den_in > 0 and den_out > 0:
        r_out = np.sqrt(num_out / den_out)
        outside = tuple(map(float, np.percentile(r_out, [lo, hi])))
        quotient = tuple(map(float, np.percentile(r_out / np.sqrt(num_in / den_in), [lo, hi])))
    return BandIfRight(tuple(map(float, np.percentile(ratio, [lo, hi]))),
                       tuple(map(float, np.percentile(median, [lo, hi]))), float(np.median(ratio)),
                       float(np.median(median)), float(np.mean(passed)), draws, quotient, outside)


@dataclass
class CrossValidation:
    splits: list[SplitResult]
    range_: float
    halves: list[tuple[list[int], list[int]]]
    u: np.ndarray
    v: np.ndarray
    std_ratios: list[float] | None = None  # per half (A, B of split 0, ...): `HalfSolution.std_ratio`
    band: BandIfRight | None = None  # where a right prediction's statistics fall here (`band_if_right`)
    solutions: list[HalfSolution] | None = None  # the halves (A, B of split 0, ...), written for `dstereo diff`
    names: tuple[str, ...] = ()  # their lens parameters (the covariances' order)
    image_size: tuple[int, int] | None = None
    grid: tuple[int, int] = GRID

    def half_cameras(self, k: int) -> tuple[LensCamera, LensCamera]:
        """Split k's two halves as `dstereo diff` reads them back from their files."""
        return tuple(half_camera(self.solutions[2 * k + i], self.names, self.image_size, f"split {k + 1} half {h}")
                     for i, h in enumerate("AB"))

    @property
    def ratio(self) -> float:  # geometric mean over splits, each divided by its typical value if right
        return float(np.exp(np.mean(np.log([s.ratio for s in self.splits]))))

    @property
    def ratio_raw(self) -> float:
        """Geometric mean of the undivided sqrt(mean |e|^2 / mean trace C): about 0.53 for a right prediction
        with one dominant mode per split (kept for comparison with earlier results)."""
        return float(np.exp(np.mean(np.log([s.ratio_raw for s in self.splits]))))

    @property
    def ratio_pooled(self) -> float:
        """sqrt(sum w |e|^2 / sum w trace C) over all splits' pixels (each split's weights): unbiased in the
        squares, where the geometric mean of per-split ratios of a few dominant modes sits below 1 even when the
        prediction is right."""
        return self._pooled(True if self.splits[0].covered is not None else None)

    def _pooled(self, inside: bool | None) -> float:
        """The pooled ratio over every valid pixel (None), inside each split's corners' field (True) or outside
        it (False)."""
        num = den = 0.0
        for s in self.splits:
            where = (np.ones(s.diff.shape[:2], bool) if inside is None or s.covered is None else
                     s.covered if inside else ~s.covered)
            ok = np.isfinite(s.diff[..., 0]) & where
            w = np.ones(ok.shape) if s.weight is None else s.weight
            num += float(np.sum(w[ok] * np.sum(s.diff[ok] ** 2, axis=-1)))
            den += float(np.sum(w[ok] * np.trace(s.cov[ok], axis1=-2, axis2=-1)))
        return float(np.sqrt(num / den)) if den > 0 else float("nan")

    def covered_figures(self) -> dict | None:
        """Pooled ratio and median Mahalanobis over the grid pixels inside both halves' corners' fields (where
        the calibrations have data and the statistic is taken; outside them the model is extrapolated)."""
        if self.splits[0].covered is None or not self.splits[0].covered.any():
            return None
        return {"pixels": [int(s.covered.sum()) for s in self.splits], "ratio_pooled_rms": self._pooled(True),
                "mahalanobis_median": self.mahalanobis_median}

    def diagnosis(self) -> dict | None:
        """Where and in what the halves differ beyond the prediction, from the splits alone (no further solve):
        the pooled ratio inside the corners' fields and outside them (where the lens model is extrapolated), their
        quotient against the band a right prediction's falls in (`band_if_right`), and each lens parameter's
        d_i^2 / (C_A + C_B)_ii averaged over the splits (1 if right), largest first. None without the fields."""
        if self.splits[0].covered is None or not self.splits[0].covered.any():
            return None
        outside_any = any((~s.covered & np.isfinite(s.diff[..., 0])).any() for s in self.splits)
        inside, outside = self._pooled(True), (self._pooled(False) if outside_any else float("nan"))
        band = None if self.band is None else self.band.outside_over_inside
        out = {"ratio_pooled_inside_corner_field": inside, "ratio_pooled_outside_corner_field": outside,
               "outside_over_inside": outside / inside,
               "outside_over_inside_band_if_right": None if band is None else list(band),
               "ratio_pooled_outside_band_if_right": None if self.band is None or self.band.outside is None
               else list(self.band.outside),
               "extrapolation_excess": None if band is None or not np.isfinite(outside) else
               bool(outside / inside > band[1])}
        if self.splits[0].parameter_excess is not None and self.names:
            mean = np.mean([s.parameter_excess for s in self.splits], axis=0)
            order = np.argsort(-mean)
            out["parameter_variance_ratio"] = {self.names[i]: float(mean[i]) for i in order}
        return out

    def _diagnosis_text(self) -> str:
        """The figures that name an out-of-band prediction's likely cause (`diagnosis`), as a clause."""
        d = self.diagnosis()
        if d is None:
            return ""
        inside, outside = d["ratio_pooled_inside_corner_field"], d["ratio_pooled_outside_corner_field"]
        text = (f"; pooled over the splits the halves read {inside:.2f} inside the corners' fields (where the "
                f"statistic is taken) and {outside:.2f} outside them")
        band = d["outside_over_inside_band_if_right"]
        if np.isfinite(outside) and band is not None:
            text += (f", outside / inside {outside / inside:.2f} (a right prediction {band[0]:.2f}-{band[1]:.2f} "
                     "here)")
            if d["extrapolation_excess"]:
                text += (": larger where the lens model is extrapolated (the likely cause is the model's shape "
                         "beyond the views, e.g. a radial profile the coefficients follow only where the corners are; "
                         "the maps there are a lower bound; add views that reach the image corners, or compare "
                         "another `model`)")
        top = list(d.get("parameter_variance_ratio", {}).items())[:3]
        if top:
            text += ("; the lens parameters differ most beyond their +- in " + ", ".join(
                f"{n} {v:.2g}x" for n, v in top) + " (squared difference / predicted variance, mean over splits, 1 if "
                "right)")
        return text

    def median_maps(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(observed |difference|, predicted rms difference, Mahalanobis) per grid pixel, medians over the splits
        (px, px, 1): the three maps of plots/cross_validation.png."""
        observed = np.sqrt(np.nanmedian(np.stack([np.sum(x.diff ** 2, axis=-1) for x in self.splits]), axis=0))
        predicted = np.sqrt(np.nanmedian(np.stack([np.trace(x.cov, axis1=-2, axis2=-1) for x in self.splits]),
                                         axis=0))
        return observed, predicted, np.nanmedian(np.stack([x.mahalanobis for x in self.splits]), axis=0)

    @property
    def parameter_chi2(self) -> float:
        """Mean over splits of d' C^-1 d / G in the lens parameters themselves (1 if right): the prediction
        checked before any projection; the pixel ratio can differ when differences lie along directions a
        projection hardly sees (correlated focal and distortion)."""
        return float(np.mean([s.parameter_chi2 for s in self.splits]))

    @property
    def ratio_vs_maps(self) -> float:
        return float(np.exp(np.nanmean(np.log([s.ratio_vs_maps for s in self.splits]))))

    @property
    def mahalanobis_median(self) -> float:
        """Over the statistic's pixels (inside both halves' corners' fields where known)."""
        return float(np.nanmedian(np.concatenate([
            (s.mahalanobis if s.covered is None else np.where(s.covered, s.mahalanobis, np.nan)).ravel()
            for s in self.splits])))

    @property
    def trusted(self) -> bool:
        return RATIO_BAND[0] <= self.ratio <= RATIO_BAND[1] and self.mahalanobis_median <= MAHALANOBIS_MAX

    @property
    def consistent(self) -> bool | None:
        """Do both pooled statistics lie where a right prediction's fall on these views (None: not simulated)?"""
        return None if self.band is None else self.band.contains(self.ratio, self.mahalanobis_median)

    def _band_text(self) -> str:
        if self.band is None:
            return ""
        b = self.band
        return (f"; a right prediction reads {b.ratio[0]:.2f}-{b.ratio[1]:.2f} and {b.mahalanobis[0]:.2f}-"
                f"{b.mahalanobis[1]:.2f} here ({NULL_BAND[0]:g}-{NULL_BAND[1]:g} %, simulated on these views and "
                f"splits; it passes this test in {100 * b.pass_rate:.0f} % of draws)")

    def verdict(self) -> str:
        head = (f"cross-validation over {len(self.splits)} random half splits: observed/predicted difference "
                f"{self.ratio:.2f} (geometric mean, 1 if right; band {RATIO_BAND[0]}-{RATIO_BAND[1]}), median "
                f"Mahalanobis {self.mahalanobis_median:.2f} (1.18 if right, limit {MAHALANOBIS_MAX}); in the lens "
                f"parameters d'C^-1 d / G = {self.parameter_chi2:.2f} (1 if right)" + self._band_text())
        if not self.trusted and self.consistent:
            side = "above" if self.ratio > 1 else "below"
            return (head + f": outside the acceptance band ({side}) but where a right prediction falls on so few "
                    "views: the test cannot tell here; more views (or more splits) would decide")
        if self.trusted:
            if self.parameter_chi2 > PARAMETER_CHI2_MAX:
                return (head + ": the projection's uncertainty can be trusted, the single parameters' +- cannot "
                        f"(the halves' parameters differ {self.parameter_chi2:.3g}x more than predicted in d'C^-1 d: "
                        "cancelling parameters, e.g. a rational model's k1..k6; read the projection, not the values)")
            if self.consistent is False:  # passes the band, yet beyond where a right prediction falls here
                b = self.band
                beyond = self.ratio > b.ratio[1] if not b.ratio[0] <= self.ratio <= b.ratio[1] else \
                    self.mahalanobis_median > b.mahalanobis[1]  # the statistic that left its band, and to which side
                lean = "optimistic" if beyond else "pessimistic"
                return (head + ": the uncertainty can be trusted within the acceptance band, though it leans "
                        f"{lean}: beyond where a right prediction falls on these views"
                        + (self._diagnosis_text() if beyond else ""))
            return head + ": the uncertainty can be trusted"
        if self.ratio > 1 or self.mahalanobis_median > MAHALANOBIS_MAX:
            return (head + ": the uncertainty can NOT be trusted, it is optimistic (errors larger than predicted); "
                    "likely causes: outlier corners, a non-flat board, a distortion model that does not fit the lens, "
                    "or too few views per half" + self._diagnosis_text())
        return (head + ": the uncertainty can NOT be trusted, it is pessimistic (the halves agree better than the +- "
                "says: it errs on the safe side; the views' effects, fitted from few views, may be overestimated)")

    def summary(self) -> dict:
        return {"splits": len(self.splits), "range": self.range_, "ratio_geometric_mean": self.ratio,
                "ratios": [s.ratio for s in self.splits], "ratio_raw_geometric_mean": self.ratio_raw,
                "ratios_raw": [s.ratio_raw for s in self.splits],
                "effective_modes": [s.modes for s in self.splits], "ratio_pooled_rms": self.ratio_pooled,
                "ratio_vs_pose_compensated_maps": self.ratio_vs_maps,
                "parameter_chi2_mean": self.parameter_chi2,
                "parameter_chi2": [s.parameter_chi2 for s in self.splits],
                "mahalanobis_median": self.mahalanobis_median,
                "mahalanobis_medians": [float(np.nanmedian(s.mahalanobis if s.covered is None
                                                           else s.mahalanobis[s.covered])) for s in self.splits],
                "inside_corner_field": self.covered_figures(), "diagnosis": self.diagnosis(),
                "trusted": self.trusted, "consistent_with_right_prediction": self.consistent,
                "band_if_right": None if self.band is None else self.band.summary(),
                "verdict": self.verdict(), "view_effects_std_ratios": self.std_ratios,
                "halves": [[list(map(int, a)), list(map(int, b))] for a, b in self.halves]}


def cross_validate(full, obj, obs, image_size, splits: int = 6, seed: int = 0, range_: float | None = None,
                   grid: tuple[int, int] = GRID) -> CrossValidation:
    """`splits` random halvings of the views of the full-set solve `full`, each half calibrated from the
    full-set start; see the module docstring."""
    if full.camera().lens == "splined":
        raise DstereoError("`cross_validate`: not available for the splined model yet; use it with the pinhole or "
                           "fisheye models")
    n_views = len(obs)
    if n_views < 2 * MIN_HALF_VIEWS:
        raise DstereoError(f"`cross_validate`: {n_views} views; two disjoint halves need at least "
                           f"{2 * MIN_HALF_VIEWS} (add views or leave out `cross_validate`)")
    if splits < 1:
        raise DstereoError(f"cross-validation splits {splits}: give at least 1 (4 or more to pool)")
    rng = np.random.default_rng(seed)
    halves, weights = [], []
    for _ in range(splits):
        perm = rng.permutation(n_views)
        a, b = np.sort(perm[: n_views // 2]), np.sort(perm[n_views // 2:])
        halves.append((a, b))
        for part in (a, b):
            w = np.zeros(n_views)
            w[part] = 1.0
            weights.append(w)
    sols = solve_halves(full, obj, obs, np.array(weights))
    bad = [i for i, s in enumerate(sols) if not s.converged]
    if bad:
        raise DstereoError(f"cross-validation: {len(bad)} half calibration(s) did not converge; the views do not "
                           "constrain the model in halves (add views or use a simpler `model`)")
    if range_ is None:
        range_ = mean_board_distance(full.poses, obj)
    w, h = image_size
    from dstereo.uncertainty.camera_diff import grid_pixels

    u, v, _ = grid_pixels(image_size, grid)
    obs_arr = np.asarray(obs, float)
    for k, (a, b) in enumerate(halves):  # each half's own corners' field, as its written files carry it
        sols[2 * k].field = corner_field(u, v, obs_arr[a])
        sols[2 * k + 1].field = corner_field(u, v, obs_arr[b])
    results = [compare_halves(sols[2 * i], sols[2 * i + 1], _lens_names(full), image_size, range_, grid)
               for i in range(splits)]
    return CrossValidation(results, float(range_), halves, np.linspace(0.0, w - 1.0, grid[0]),
                           np.linspace(0.0, h - 1.0, grid[1]), [s.std_ratio for s in sols],
                           band_if_right(halves, sols, results, seed=seed), sols, _lens_names(full),
                           tuple(image_size), tuple(grid))
