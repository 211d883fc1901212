"""The projection difference of two calibrations of one camera, the transform between them fitted, and what their
covariances predict of it (`dstereo diff`, and each split of `--cross-validate`).

The difference. A grid of pixels q spans the image; the point at `range` along q's ray through camera A is moved
by a rigid transform T_BA and projected through camera B: e(q) = project_B(T_BA p_A(q)) - q. A camera frame is
fixed by its calibration's boards and intrinsics, not by the housing, so two calibrations of one camera differ by
an unknown small motion; T_BA is fitted (6 degrees of freedom at a finite range, as mrcal's implied transform: the
boards' distance absorbs part of a focal difference; the rotation alone at an infinite range). Pixels where
either camera has no ray (a model that folds back, a fisheye ray behind the camera) are left out, of the fit and
of every statistic.

The weights. The fit minimises sum_q w_q |e(q)|^2 with w_q = 1 / (trace C_A(q) + trace C_B(q)) of the two
cameras' pose-compensated maps (from their joint covariances with their board poses, or their written maps at
this range and grid; uniform where a camera has neither), as mrcal weights its implied transform by the
projection uncertainty. Unweighted, the image corners, where each calibration extrapolates its lens model and two
calibrations differ by tens of pixels, hold the fit and leave pixel-sized residuals in the centre that both
calibrations know to a tenth of a pixel; weighted, the pixels both know hold it. The ratio is weighted alike.

The prediction, first order. With theta_A = theta + dA and theta_B = theta + dB independent, each with its
calibration's covariance C_A, C_B of its lens parameters (the marginal one: every board pose solved out):
sqrt(W) e = P sqrt(W) (F_A dA + F_B dB), F_X = d e / d theta_X at the fitted transform and P = I - J (J' J)^+ J'
with J = sqrt(W) d e / d T_BA: the projection that removes what the (weighted) fit absorbs. So Cov(e) follows from
pf_X = P sqrt(W) F_X and C_X = R_X R_X'. Its 2 x 2 block at a pixel gives that pixel's Mahalanobis distance
sqrt(e' C^+ e) (sqrt(chi^2_2) if right: median 1.18).

Why not the pose-compensated maps alone. A map's covariance at q is that of the projection of a point held fixed
in the boards' frame: F dtheta plus the motion of the boards' mean frame, which is rigid to first order. P
removes every rigid motion, so P (the maps' full covariance) P' is the prediction above. But a map file holds
only each pixel's 2 x 2 block, not the covariance between pixels that P needs; their sum sigma_A^2 + sigma_B^2
counts what the fit absorbs (`ratio_vs_maps` reads it against the difference: 0.6-1.2x the prediction's reading
on the shared cameras, docs/validation.md).

The statistics. `ratio_raw` = sqrt(sum w |e|^2 / sum w trace C), the observed over the predicted weighted rms.
Stacked over the grid, sum w |e|^2 = sum_i lambda_i z_i^2 (lambda the eigenvalues of the weighted Cov(e), z
standard normal): when one mode carries most of it, one comparison's raw ratio is about |z| for one normal z,
whose typical value exp(E ln|z|) = 0.53, not 1. `ratio` divides by the typical value computed from the lambdas
(`expected_log_ratio`): its log has mean 0 when the prediction is right. `band()` simulates differences from the
prediction itself: where a right prediction's `ratio` and median Mahalanobis fall on this grid (5-95 %).

Where the statistic is taken: the corners' field. A calibration's map claims something only where its corners were
(within FIELD_STEPS grid steps of an observed corner: `corner_field`; in grid steps, so that the same views at
another image resolution mark the same field); beyond, its value comes from the lens model's shape,
extrapolated, and first order says nothing about a model that does not have the lens's shape there (the map is then
a lower bound). Each written map carries that field (`field` in projection_uncertainty.npz and
calibration_covariance.npz); given the two cameras' fields, the ratio, the Mahalanobis median, their typical value and
their band are taken over the pixels inside both (the fit still spans the grid, weighted as above), and the pixels
outside are read separately: the pooled ratio sqrt(sum w |e|^2 / sum w trace C) inside and outside, and the band a
right prediction's outside / inside quotient falls in (simulated from the same draws, over the same pixels).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from dstereo.errors import DstereoError
from dstereo.models import splined
from dstereo.models.camera import INTRINSIC_NAMES
from dstereo.models.pose import rodrigues
from dstereo.uncertainty.projection import CAMERA_NAMES, FISHEYE_CAMERA_NAMES, _project, _splined_grid, pixel_ray

FIT_ITERATIONS = 12  # Gauss-Newton steps of the transform fit from the identity (small motions: 4-6 converge)
BAND = (5.0, 95.0)  # percentiles of `ProjectionDiff.band`
BAND_DRAWS = 4000  # simulated right predictions for the bands (their 5 % and 95 % points to ~+-2 %)
MAHALANOBIS_PERFECT = float(np.sqrt(2.0 * np.log(2.0)))  # median of sqrt(chi^2_2)
GRID = (32, 24)  # columns, rows: the grid of a results folder's projection_uncertainty.npz
# A grid pixel within this many grid steps of an observed corner is inside the calibrated field (`corner_field`):
# every grid pixel next to a corner (a corner lies within 0.71 steps of its nearest grid pixel) and the next ring,
# so a board's inside is one field, not a lace; 31 px on GRID over a 640-pixel-wide image.
FIELD_STEPS = 1.5


def slot_names(model: str) -> tuple[str, ...]:
    """The names of a camera vector's slots (fx fy cx cy, then the lens model's coefficient slots)."""
    if model == "fisheye":
        return FISHEYE_CAMERA_NAMES
    if model.startswith("splined"):
        return INTRINSIC_NAMES + splined.knot_names(*_splined_grid(model))
    return CAMERA_NAMES


@dataclass(frozen=True)
class LensCamera:
    """One calibrated camera for a difference: `params` (4 + slots,) fx fy cx cy then its lens model's coefficient
    slots (`slot_names`); `cov` (G, G) the marginal covariance of the parameters `names` (None: not known);
    `joint` (G + 6V, G + 6V) and `poses` (V, 6) the joint covariance with its calibration's board poses, for its
    pose-compensated map (None: not known); `map_trace` (gh, gw) its map's trace (px^2) on the difference's grid
    where only the map is known (a written projection_uncertainty.npz at the same range and grid)."""

    model: str
    params: np.ndarray
    names: tuple[str, ...] = ()
    cov: np.ndarray | None = None
    image_size: tuple[int, int] | None = None
    label: str = ""
    joint: np.ndarray | None = None
    poses: np.ndarray | None = None
    map_trace: np.ndarray | None = None

    def __post_init__(self):
        slots = slot_names(self.model)
        if len(self.params) != len(slots):
            raise DstereoError(f"{self.label or 'camera'}: {len(self.params)} parameters for a {self.model} lens, "
                               f"which has {len(slots)}")
        unknown = [n for n in self.names if n not in slots]
        if unknown:
            raise DstereoError(f"{self.label or 'camera'}: covariance names {unknown} are not parameters of a "
                               f"{self.model} lens")
        if self.cov is not None and np.shape(self.cov) != (len(self.names),) * 2:
            raise DstereoError(f"{self.label or 'camera'}: covariance {np.shape(self.cov)} for {len(self.names)} "
                               "parameter names")
        if self.joint is not None and (self.poses is None or np.shape(self.joint) != (len(self.names)
                                                                                     + 6 * len(self.poses),) * 2):
            raise DstereoError(f"{self.label or 'camera'}: joint covariance {np.shape(self.joint)} does not match "
                               f"{len(self.names)} parameters and {0 if self.poses is None else len(self.poses)} "
                               "poses")

    @property
    def index(self) -> tuple[int, ...]:
        slots = slot_names(self.model)
        return tuple(slots.index(n) for n in self.names)

    def pose_compensated_trace(self, range_: float, grid: tuple[int, int], image_size) -> np.ndarray | None:
        """(gh, gw) trace (px^2) of its pose-compensated map at `range_` on `grid` (NaN where masked), from its
        joint covariance, else its given `map_trace`; None when it has neither."""
        if self.joint is None:
            return self.map_trace
        from dstereo.uncertainty.projection import projection_uncertainty_map

        k, coeffs = self.params[:4], self.params[4:]
        pmap = projection_uncertainty_map(k, coeffs, self.names, self.joint, image_size, range_, grid,
                                          poses=self.poses)
        return np.trace(pmap.cov, axis1=-2, axis2=-1)


def _found_ray(params, q, model: str):
    """(unit ray of pixel q through the camera `params`, whether it was found): the model's own inverse, a
    value only (no derivative is taken through its iterations)."""
    k, c = jax.lax.stop_gradient(params[:4]), jax.lax.stop_gradient(params[4:])
    v0, ok = pixel_ray(k, c, q, model)
    ok = ok & jnp.all(jnp.isfinite(v0))
    v0 = jnp.where(ok, v0, jnp.array([0.0, 0.0, 1.0]))
    return v0 / jnp.linalg.norm(v0), ok


def _ray(params, q, v0, model: str):
    """The ray of pixel q as a function of the camera `params`, from its value v0 (`_found_ray`): one Newton step
    on the projection in the ray's tangent plane leaves the value unchanged at the root and gives the
    implicit-function derivative d ray / d params."""
    k, c = params[:4], params[4:]
    a = jnp.where(jnp.abs(v0[0]) < 0.9, jnp.array([1.0, 0.0, 0.0]), jnp.array([0.0, 1.0, 0.0]))
    e1 = a - jnp.dot(a, v0) * v0
    e1 = e1 / jnp.linalg.norm(e1)
    e2 = jnp.cross(v0, e1)
    ray_at = lambda s: (v0 + s[0] * e1 + s[1] * e2) / jnp.linalg.norm(v0 + s[0] * e1 + s[1] * e2)  # noqa: E731
    f = lambda s: _project(k, c, ray_at(s), model)  # noqa: E731
    zero = jnp.zeros(2)
    return ray_at(-jnp.linalg.solve(jax.jacfwd(f)(zero), f(zero) - q))


def _residual(params_a, params_b, t, q, rays, models, rotation_only):
    """e(q) (N, 2): A's ray point moved by T_BA, projected by B; lengths in units of the range."""
    ray = jax.vmap(lambda qq, v0: _ray(params_a, qq, v0, models[0]))(q, rays)
    rot = rodrigues(t[:3])
    p_b = ray @ rot.T + (0.0 if rotation_only else t[3:])  # at range r: r (R v + t / r); projections ignore r
    return jax.vmap(lambda p: _project(params_b[:4], params_b[4:], p, models[1]))(p_b) - q


@functools.lru_cache(maxsize=None)
def _compiled(models: tuple[str, str], index_a: tuple[int, ...], index_b: tuple[int, ...], rotation_only: bool):
    """Compiled: (e, ok, J_T, F_A, F_B, t) for grid pixels q and their fit weights; the Jacobians' rows are
    multiplied by sqrt(weight) (the weighted fit's space) and are zero where a pixel is not `ok`."""
    ia, ib = np.array(index_a, int), np.array(index_b, int)
    n_t = 3 if rotation_only else 6

    def run(params_a, params_b, q, weight):
        rays, ok_a = jax.vmap(lambda qq: _found_ray(params_a, qq, models[0]))(q)
        ok = ok_a & jax.vmap(lambda qq: _found_ray(params_b, qq, models[1])[1])(q) & (weight > 0)
        res = lambda pa, pb, t: _residual(pa, pb, t, q, rays, models, rotation_only)  # noqa: E731
        ok = ok & jnp.all(jnp.isfinite(res(params_a, params_b, jnp.zeros(n_t))), axis=1)
        root_w = jnp.repeat(jnp.where(ok, jnp.sqrt(jnp.where(ok, weight, 1.0)), 0.0), 2)
        scaled = lambda m: jnp.where(root_w.reshape((-1,) + (1,) * (m.ndim - 1)) > 0,  # noqa: E731
                                     m * root_w.reshape((-1,) + (1,) * (m.ndim - 1)), 0.0)

        def gn(_, t):
            r = scaled(res(params_a, params_b, t).ravel())
            jt = scaled(jax.jacfwd(lambda tt: res(params_a, params_b, tt).ravel())(t))
            return t - jnp.linalg.pinv(jt.T @ jt, rtol=1e-12, hermitian=True) @ (jt.T @ r)

        t = jax.lax.fori_loop(0, FIT_ITERATIONS, gn, jnp.zeros(n_t))
        e = res(params_a, params_b, t)
        jt = scaled(jax.jacfwd(lambda tt: res(params_a, params_b, tt).ravel())(t))
        fa = scaled(jax.jacfwd(lambda th: res(params_a.at[ia].set(th), params_b, t).ravel())(params_a[ia]))
        fb = scaled(jax.jacfwd(lambda th: res(params_a, params_b.at[ib].set(th), t).ravel())(params_b[ib]))
        return e, ok & jnp.all(jnp.isfinite(e), axis=1), jt, fa, fb, t

    from dstereo.runtime import aot  # kept on disk: a new process skips tracing it

    return aot.jit(run, "uncertainty.camera_diff", (models, index_a, index_b, rotation_only))


def grid_pixels(image_size, grid: tuple[int, int]):
    """(u (gw,), v (gh,), q (gh gw, 2)): pixel centres spanning the image, row-major."""
    w, h = image_size
    u, v = np.linspace(0.0, w - 1.0, grid[0]), np.linspace(0.0, h - 1.0, grid[1])
    return u, v, np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)


def corner_field(u: np.ndarray, v: np.ndarray, corners: np.ndarray, reach: float | None = None) -> np.ndarray:
    """(gh, gw) bool: the grid pixels (u (gw,), v (gh,) px) within `reach` px (default FIELD_STEPS of the grid's
    larger step) of an observed corner (..., 2) (NaN corners ignored): where a calibration measured its lens rather
    than extrapolating its model (module docstring)."""
    if reach is None:
        step = max(float(np.max(np.diff(u))) if len(u) > 1 else 0.0, float(np.max(np.diff(v))) if len(v) > 1 else 0.0)
        reach = FIELD_STEPS * step
    corners = np.asarray(corners, float).reshape(-1, 2)
    corners = corners[np.all(np.isfinite(corners), axis=1)]
    q = np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)
    if not len(corners):
        return np.zeros((len(v), len(u)), bool)
    near = np.full(len(q), np.inf)
    for c in np.array_split(corners, max(1, len(corners) // 2000)):  # (grid x 2000) at a time
        near = np.minimum(near, np.min(np.sum((q[:, None, :] - c[None]) ** 2, axis=-1), axis=1))
    return (near < reach ** 2).reshape(len(v), len(u))


def _root(cov: np.ndarray) -> np.ndarray:
    """R with R R' = cov, Jacobi-scaled before the eigen-decomposition (fx and k3 differ by 10^6)."""
    cov = np.asarray(cov, float)
    d = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    lam, vec = np.linalg.eigh(cov / np.outer(d, d))
    return d[:, None] * vec * np.sqrt(np.clip(lam, 0.0, None))[None, :]


def expected_log_ratio(lam: np.ndarray) -> float:
    """E[ln sqrt(Q / sum lambda)] for Q = sum_i lambda_i z_i^2, z_i independent standard normals (the log of the
    raw ratio when the prediction, with eigenvalues `lambda`, is right). From ln x = int_0^inf (e^-t - e^-xt)
    dt / t and E e^-Qt = prod_i (1 + 2 lambda_i t)^-1/2, integrated in s = ln t on [-30, 60] (both ends' integrands
    below 1e-13 for lambda normalised to sum 1): one lambda gives (psi(1/2) + ln 2) / 2 = -0.635, k equal ones
    (psi(k/2) + ln(2/k)) / 2, checked to 1e-12 in the tests."""
    lam = np.asarray(lam, float)
    lam = lam[lam > 0.0] / np.sum(lam[lam > 0.0])
    s = np.linspace(-30.0, 60.0, 901)
    t = np.exp(s)
    survival = np.exp(-0.5 * np.log1p(2.0 * t[:, None] * lam[None, :]).sum(axis=1))
    f = np.exp(-t) - survival
    return float(0.5 * np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(s)))


def mahalanobis(e: np.ndarray, inv_blocks: np.ndarray) -> np.ndarray:
    """sqrt(e' C^+ e) per pixel for e (..., N, 2) and the pixels' inverse 2 x 2 blocks (N, 2, 2)."""
    return np.sqrt(np.maximum(np.einsum("...ni,nij,...nj->...n", e, inv_blocks, e), 0.0))


@dataclass
class ProjectionDiff:
    """The difference of two cameras on a grid (module docstring). Arrays on the grid are (gh, gw, ...), NaN where
    a pixel is left out; the prediction's fields are None (NaN) when a camera carries no covariance."""

    u: np.ndarray
    v: np.ndarray
    range_: float  # the distance of the points (calibration unit); inf: rotation only
    diff: np.ndarray  # (gh, gw, 2) px
    ok: np.ndarray  # (gh, gw) bool
    transform: np.ndarray  # rvec (3) and translation (3, calibration unit) of T_BA
    weight: np.ndarray  # (gh, gw) the fit's and the ratio's weight per pixel (mean 1 over `ok`; 0 outside)
    weighting: str = "uniform"  # or "pose-compensated maps": where the weights came from
    map_trace: np.ndarray | None = None  # (gh, gw) trace C_A + trace C_B of the two pose-compensated maps (px^2)
    cov: np.ndarray | None = None  # (gh, gw, 2, 2) px^2, predicted
    mahalanobis: np.ndarray | None = None  # (gh, gw)
    ratio_raw: float = float("nan")  # sqrt(sum w |e|^2 / sum w trace C)
    ratio: float = float("nan")  # ratio_raw / its typical value if right: 1 if right, in the log
    typical: float = float("nan")  # exp(E ln ratio_raw) of a right prediction
    modes: float = float("nan")  # effective number of modes of Cov(e): sum(lambda)^2 / sum(lambda^2)
    lam: np.ndarray | None = None  # eigenvalues of the weighted Cov(e) (px^2), decreasing
    # for simulations of right predictions (bands, `band_if_right`): on the valid pixels' rows, in the weighted
    # space, sqrt(w) e = pf_a dA + pf_b dB; `root_w` sqrt(w) per row; inverses of the 2 x 2 blocks of Cov(e)
    pf_a: np.ndarray | None = None
    pf_b: np.ndarray | None = None
    root_a: np.ndarray | None = None  # R_A with R_A R_A' = C_A
    root_b: np.ndarray | None = None
    root_w: np.ndarray | None = None
    inv_blocks: np.ndarray | None = None
    mean_trace_w: float = float("nan")  # mean over the statistic's pixels of w trace C (px^2)
    bands: dict = field(default_factory=dict)
    # (gh, gw) bool: the pixels inside both cameras' corners' fields, where the statistic is taken (None: no field
    # known, every valid pixel); `inside_rows` the same on the simulation rows (2 per valid pixel)
    field: np.ndarray | None = None
    inside_rows: np.ndarray | None = None

    @property
    def stat_pixels(self) -> np.ndarray:
        """(gh, gw) bool: the pixels the ratio, the Mahalanobis median and their band are taken over."""
        return self.ok if self.field is None else self.ok & self.field

    def pooled(self, where: np.ndarray) -> tuple[float, float]:
        """(sum w |e|^2, sum w trace C) over the valid pixels of `where` (gh, gw): the pooled ratio's terms."""
        m = self.ok & where
        w = self.weight[m]
        return float(np.sum(w * np.sum(self.diff[m] ** 2, axis=-1))), float(np.sum(w * np.trace(self.cov[m], axis1=-2,
                                                                                                   axis2=-1)))

    def field_figures(self) -> dict | None:
        """The pooled ratio sqrt(sum w |e|^2 / sum w trace C) inside both corners' fields and outside them, their
        quotient, and where a right prediction's fall here (`band`); None without a field or a prediction."""
        if self.field is None or self.cov is None or not (self.ok & self.field).any():
            return None
        (ni, di), (no, do) = self.pooled(self.field), self.pooled(~self.field)
        inside, outside = np.sqrt(ni / di), (np.sqrt(no / do) if do > 0 else float("nan"))
        out = {"pixels_inside": int((self.ok & self.field).sum()), "pixels_outside": int((self.ok & ~self.field).sum()),
               "ratio_pooled_inside": float(inside), "ratio_pooled_outside": float(outside),
               "outside_over_inside": float(outside / inside)}
        band = self.band()
        if "outside_over_inside" in band:
            out["outside_over_inside_band_if_right"] = band["outside_over_inside"]
        return out

    @property
    def rms(self) -> float:
        """Observed rms difference over the statistic's pixels (`stat_pixels`), weighted as the ratio (px)."""
        m = self.stat_pixels
        w = self.weight[m]
        return float(np.sqrt(np.sum(w * np.sum(self.diff[m] ** 2, axis=-1)) / np.sum(w)))

    @property
    def predicted_rms(self) -> float:
        """What the prediction expects of `rms` (px), NaN without one."""
        m = self.stat_pixels
        return float(np.sqrt(self.mean_trace_w * m.sum() / np.sum(self.weight[m])))

    @property
    def ratio_vs_maps(self) -> float:
        """sqrt(sum w |e|^2 / sum w (trace C_A + trace C_B)) with the two pose-compensated maps' traces: what the
        written maps alone predict, blind to what the fit absorbs (module docstring)."""
        if self.map_trace is None:
            return float("nan")
        good = self.stat_pixels & np.isfinite(self.map_trace)
        w = self.weight[good]
        return float(np.sqrt(np.sum(w * np.sum(self.diff[good] ** 2, axis=-1)) / np.sum(w * self.map_trace[good])))

    @property
    def mahalanobis_median(self) -> float:
        return float("nan") if self.mahalanobis is None else float(np.nanmedian(self.mahalanobis[self.stat_pixels]))

    def simulate(self, err_a: np.ndarray, err_b: np.ndarray, per_pixel: bool = False, pooled: bool = False):
        """(ratio (D,), median Mahalanobis (D,)) of D simulated differences from lens errors err_a (D, G_A) and
        err_b (D, G_B), computed as for the observed one (over the statistic's pixels); `per_pixel`: each of those
        pixels' Mahalanobis distance (D, N) instead of their median; `pooled`: a third element, (sum w |e|^2
        inside the field (D,), outside it (D,)), the numerators of `pooled` (zeros outside without a field)."""
        e_w = err_a @ self.pf_a.T + err_b @ self.pf_b.T
        rows = np.ones(e_w.shape[1], bool) if self.inside_rows is None else self.inside_rows
        ratio = np.sqrt(np.mean(e_w[:, rows] ** 2, axis=1) * 2.0 / self.mean_trace_w) / self.typical
        maha = mahalanobis((e_w[:, rows] / self.root_w[rows]).reshape(len(e_w), -1, 2), self.inv_blocks[rows[::2]])
        out = (ratio, (maha if per_pixel else np.median(maha, axis=1)))
        if pooled:
            sq = e_w ** 2
            out += ((np.sum(sq[:, rows], axis=1), np.sum(sq[:, ~rows], axis=1)),)
        return out

    def band(self, draws: int = BAND_DRAWS, seed: int = 0) -> dict:
        """Where a right prediction's `ratio` and median Mahalanobis fall on this grid (BAND percentiles of
        `draws` differences drawn from the predicted covariance itself)."""
        if self.pf_a is None:
            return {}
        key = (draws, seed)
        if key not in self.bands:
            rng = np.random.default_rng(seed)
            ratio, maha, (n_in, n_out) = self.simulate(
                rng.normal(size=(draws, self.root_a.shape[1])) @ self.root_a.T,
                rng.normal(size=(draws, self.root_b.shape[1])) @ self.root_b.T, pooled=True)
            lo, hi = BAND
            self.bands[key] = {"percentiles": list(BAND), "draws": draws,
                               "ratio": [float(np.percentile(ratio, lo)), float(np.percentile(ratio, hi))],
                               "mahalanobis_median": [float(np.percentile(maha, lo)), float(np.percentile(maha, hi))]}
            if self.field is not None and (self.ok & ~self.field).any():
                (_, di), (_, do) = self.pooled(self.field), self.pooled(~self.field)
                q = np.sqrt(n_out / do) / np.sqrt(n_in / di)
                self.bands[key]["outside_over_inside"] = [float(np.percentile(q, lo)), float(np.percentile(q, hi))]
        return self.bands[key]


def fit_weights(a: LensCamera, b: LensCamera, range_: float, grid: tuple[int, int], image_size):
    """(weights (gh gw,), map traces (gh, gw) or None, weighting): 1 / (trace C_A + trace C_B) of the two
    pose-compensated maps where both cameras have one (0 where a map is masked), else uniform."""
    if np.isinf(range_):
        return np.ones(grid[0] * grid[1]), None, "uniform (an infinite range: no pose-compensated map)"
    traces = [c.pose_compensated_trace(range_, grid, image_size) for c in (a, b)]
    if any(t is None for t in traces):
        return np.ones(grid[0] * grid[1]), None, "uniform (a camera has no pose-compensated map)"
    total = traces[0] + traces[1]
    good = np.isfinite(total) & (total > 0)
    w = np.zeros(total.shape)
    w[good] = 1.0 / total[good]
    return w.ravel(), total, "pose-compensated maps"


def projection_diff(a: LensCamera, b: LensCamera, range_: float, grid: tuple[int, int] = GRID,
                    image_size: tuple[int, int] | None = None, weighted: bool = True,
                    field: np.ndarray | None = None) -> ProjectionDiff:
    """The difference of camera `b` against camera `a` at `range_` (module docstring) on a `grid` (columns, rows)
    of pixel centres of `image_size` (default a's). `weighted`: the fit and the ratio weight each pixel by
    1 / (trace C_A + trace C_B) of the cameras' pose-compensated maps where both have one (module docstring).
    `field` (gh, gw) bool: the pixels inside both cameras' corners' fields, where the statistic is taken (None:
    every valid pixel)."""
    size = image_size or a.image_size
    if size is None:
        raise DstereoError(f"{a.label or 'camera A'}: no image size; give one")
    if not (range_ > 0):
        raise DstereoError(f"distance {range_}: give a positive distance (the calibration's unit) or inf")
    rotation_only = bool(np.isinf(range_))
    u, v, q = grid_pixels(size, grid)
    gh, gw = grid[1], grid[0]
    w, map_trace, weighting = (fit_weights(a, b, range_, grid, size) if weighted else
                               (np.ones(len(q)), None, "uniform"))
    run = _compiled((a.model, b.model), a.index, b.index, rotation_only)
    w_run = w / np.mean(w[w > 0]) if np.any(w > 0) else w
    e, ok, jt, fa, fb, t = (np.array(x) for x in run(np.asarray(a.params, float), np.asarray(b.params, float),
                                                   np.asarray(q, float), w_run))
    if not ok.any():
        raise DstereoError("no pixel of the grid has a ray through both cameras; check that both files describe "
                           "the same camera")
    w = np.where(ok, w, 0.0)
    w = w / np.mean(w[ok])  # mean 1 over the valid pixels (the fit's scale is immaterial)
    t = np.concatenate([t[:3], np.zeros(3) if rotation_only else t[3:] * range_])
    e[~ok] = np.nan
    out = ProjectionDiff(u, v, float(range_), e.reshape(gh, gw, 2), ok.reshape(gh, gw), t, w.reshape(gh, gw),
                         weighting, map_trace)
    if field is not None:
        field = np.asarray(field, bool)
        if field.shape != (gh, gw):
            raise DstereoError(f"corners' field {field.shape} on a {gh} x {gw} grid")
        if not (field.ravel() & ok).any():
            raise DstereoError("no valid grid pixel lies inside both calibrations' corners' fields; the two "
                               "calibrations saw different parts of the image: calibrate with views that overlap, or "
                               "give --grid with a grid other than the files' (the files' fields are on theirs: the "
                               "statistic is then taken over the whole image, with a note)")
        out.field = field
    if a.cov is None or b.cov is None:
        return out

    def absorbed(f):  # P f: what the (weighted) transform fit leaves of a parameter change's effect
        return f - jt @ (np.linalg.pinv(jt.T @ jt, rcond=1e-12, hermitian=True) @ (jt.T @ f))

    rows = np.repeat(ok, 2)
    root_w = np.sqrt(np.repeat(w, 2))
    # the compiled Jacobians are scaled by sqrt of the weights it was given: rescale to these (mean 1 on ok)
    scale = np.sqrt(np.repeat(np.where(ok, w / np.where(w_run > 0, w_run, 1.0), 0.0), 2))[:, None]
    pf_a, pf_b = absorbed(fa) * scale, absorbed(fb) * scale
    root_a, root_b = _root(a.cov), _root(b.cov)
    lin = np.concatenate([pf_a @ root_a, pf_b @ root_b], axis=1)[rows] / root_w[rows][:, None]  # unweighted e
    n = int(ok.sum())
    blocks = np.einsum("nik,njk->nij", lin.reshape(n, 2, -1), lin.reshape(n, 2, -1))
    inv_blocks = np.linalg.pinv(blocks, hermitian=True)
    maha = np.full(len(q), np.nan)
    maha[ok] = mahalanobis(e[ok], inv_blocks)
    # the statistic's pixels (inside both fields) among the valid ones, and on the rows
    inside = np.ones(n, bool) if field is None else field.ravel()[ok]
    stat = ok & (np.ones(len(q), bool) if field is None else field.ravel())
    lin_w = (lin * root_w[rows][:, None])[np.repeat(inside, 2)]
    lam = np.clip(np.linalg.eigvalsh(lin_w.T @ lin_w), 0.0, None)[::-1]
    mean_trace_w = float(np.mean(w[stat] * np.trace(blocks[inside], axis1=1, axis2=2)))
    ratio_raw = float(np.sqrt(np.mean(w[stat] * np.sum(e[stat] ** 2, axis=1)) / mean_trace_w))
    typical = float(np.exp(expected_log_ratio(lam)))
    cov = np.full((len(q), 2, 2), np.nan)
    cov[ok] = blocks
    out.cov, out.mahalanobis = cov.reshape(gh, gw, 2, 2), maha.reshape(gh, gw)
    out.ratio_raw, out.typical, out.ratio = ratio_raw, typical, ratio_raw / typical
    out.modes, out.lam = float(lam.sum() ** 2 / np.sum(lam ** 2)), lam
    out.pf_a, out.pf_b, out.root_a, out.root_b = pf_a[rows], pf_b[rows], root_a, root_b
    out.root_w, out.inv_blocks, out.mean_trace_w = root_w[rows], inv_blocks, mean_trace_w
    out.inside_rows = None if field is None else np.repeat(inside, 2)
    return out
