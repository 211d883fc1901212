"""Single-camera projection uncertainty: how far the pixel of a point may move under the calibration's uncertainty.

Two methods, both first order in the solve's covariance (sigma^2 (J'J)^-1, sigma^2 the unbiased noise estimate):

POSE-COMPENSATED (the default; mrcal's "mean-frames" formulation). What a calibration delivers to a user is how a
point fixed in the world projects, and the world is only known through the boards: an intrinsics error that the
boards' poses absorb (a principal-point shift is mostly a rotation of the camera) does not move the projection of
a board-fixed point. For pixel q, the point p at distance `range` along q's estimated ray is mapped into each
calibration view's board frame with the estimated poses, p_i = T_board_i_cam p (held fixed); under perturbed
parameters it comes back as the mean over views of T'_cam_board_i p_i and projects through the perturbed
intrinsics: q'(theta, poses) = project(theta, mean_i T'_cam_board_i p_i). Its covariance is J C J^T with C the
JOINT covariance of the intrinsics and every view pose (`uncertainty.covariance.joint_covariance`, the cross terms
included) and J = d q' / d (theta, poses).

INTRINSICS-ONLY (the thesis-era map, `method="intrinsics-only"`): p is held fixed in the camera frame and only the
marginal intrinsics covariance is propagated. Near the image centre it is pessimistic (it counts as projection
error the part of an intrinsics error that a pose absorbs); cross-validation does not support it.

Pixels whose ray cannot be found are MASKED (NaN std, `mask` False) and counted: where the distortion model is not
monotonic along the radius (a polynomial fitted to the used field bends back beyond it, so one pixel has two rays)
or where the Newton inversion does not reproduce the pixel. No unconverged inversion yields a number.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import jax
import jax.numpy as jnp
import numpy as np

from dstereo.errors import DstereoError
from dstereo.uncertainty.view_effects import reported_covariance, solution_effects
from dstereo.uncertainty.view_scatter import inliers_of, solution_view_scatter, sse_of
from dstereo.models import fisheye, splined
from dstereo.models.camera import INTRINSIC_NAMES, project
from dstereo.models.distortion import COEFF_NAMES, FISHEYE_SLOTS, distort, lens_model, undistort
from dstereo.models.pose import rodrigues, rotation_matrix

CAMERA_NAMES: tuple[str, ...] = INTRINSIC_NAMES + COEFF_NAMES
FISHEYE_CAMERA_NAMES: tuple[str, ...] = INTRINSIC_NAMES + FISHEYE_SLOTS  # fisheye: cv2.fisheye's D in coeffs[:4]
METHODS = ("pose-compensated", "intrinsics-only")
NOTES = {
    "pose-compensated": ("pose-compensated (mrcal's mean-frames method): a point at the given range on each pixel's "
                         "ray is held fixed in the calibration boards' frame; the joint covariance of intrinsics and "
                         "board poses is propagated"),
    "intrinsics-only": ("intrinsics only: a point at the given range on each pixel's ray is held fixed in the camera "
                        "frame; compensation by the board poses is not included, so the map is pessimistic near "
                        "the centre"),
}
NOTE = NOTES["intrinsics-only"]  # kept for callers of the old name
# A pixel counts as inverted when its ray projects back within this (px). Newton converges quadratically to
# ~1e-12 px in float64; 1e-6 px leaves room for rounding and catches any iteration stopped short.
ROUND_TRIP_PX = 1e-6
NEWTON_ITERATIONS = 40
RADIAL_SAMPLES = 64  # radii from 0 to FOLD_MARGIN x the ray's, where d r_distorted / d r must stay positive
# A fold (or a pole of the rational model's denominator) just beyond the ray makes the pixel's projection
# infinitely sensitive there and gives the pixel a second ray (mrcal's unprojection found one on the fisheye set,
# 1.28 px against 1392 px here): the monotonic stretch must reach 10 % past the ray.
FOLD_MARGIN = 1.1


def _undistorted(k, coeffs, q, iterations: int = NEWTON_ITERATIONS):
    return undistort(coeffs, (q - k[2:4]) / k[0:2], iterations)


def _invertible(k, coeffs, q, x):
    """True where x is q's one ray: the round trip holds and the distortion is monotonic (radially, the rational
    denominator positive) from the centre to FOLD_MARGIN x the ray's radius, and the 2 x 2 Jacobian keeps its
    orientation at x, so no other ray nearby maps to the same pixel."""
    back = k[:2] * distort(coeffs, x) + k[2:4]
    ok_trip = jnp.all(jnp.isfinite(back)) & (jnp.linalg.norm(back - q) < ROUND_TRIP_PX)
    r = jnp.linalg.norm(x)
    direction = x / jnp.maximum(r, 1e-300)
    radial = lambda s: jnp.dot(distort(coeffs, s * direction), direction)  # noqa: E731
    radii = jnp.linspace(0.0, FOLD_MARGIN, RADIAL_SAMPLES) * r
    slopes = jax.vmap(jax.grad(radial))(radii)
    r2 = radii ** 2
    den = 1.0 + coeffs[5] * r2 + coeffs[6] * r2 ** 2 + coeffs[7] * r2 ** 3  # rational model: no pole before it
    a = jax.jacfwd(distort, argnums=1)(coeffs, x)
    det = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
    return ok_trip & jnp.all(slopes > 0) & jnp.all(den > 0) & (det > 0) & jnp.all(jnp.isfinite(x))


def _splined_grid(model: str) -> tuple[int, int]:
    """(NX, NY) of a model key 'splined:NXxNY' (`model_key`)."""
    nx, ny = model.split(":")[1].split("x")
    return int(nx), int(ny)


def model_key(names) -> str:
    """The lens model of a camera's parameter names as the compiled maps' key: pinhole, fisheye, splined:NXxNY."""
    coeffs = tuple(n for n in names if n not in INTRINSIC_NAMES and not n.startswith("board_sag"))
    model = lens_model(coeffs)
    if model == "splined":
        nx, ny = splined.grid_of(coeffs)
        return f"splined:{nx}x{ny}"
    return model


def _point(k, coeffs, q, range_, model: str = "pinhole"):
    """The point at `range_` along q's ray and whether the ray was found (fisheye, splined: the model's own
    inverse, with its convergence check; fisheye: in front of the camera)."""
    if model.startswith("splined"):
        ray, ok = splined.unproject(k, coeffs, q, *_splined_grid(model))
        return range_ * ray, ok
    if model == "fisheye":
        ray, ok = fisheye.unproject(k, coeffs[:4], q)
        ok = ok & jnp.all(jnp.isfinite(ray)) & (ray[2] > 0)
        return range_ * jnp.where(ok, ray, jnp.nan), ok
    x = _undistorted(k, coeffs, q)
    ray = jnp.append(x, 1.0)
    return range_ * ray / jnp.linalg.norm(ray), _invertible(k, coeffs, q, x)


def pixel_ray(k, coeffs, q, model: str = "pinhole"):
    """(unit ray of pixel `q` through the lens `model`, whether it was found): `_point` at range 1."""
    return _point(k, coeffs, q, 1.0, model)


def _project(k, coeffs, p, model: str = "pinhole"):
    if model.startswith("splined"):
        return splined.project(k, coeffs, p, *_splined_grid(model))
    return fisheye.project(k, coeffs[:4], p) if model == "fisheye" else project(k, coeffs, p)


def pixel_covariance(params, index: tuple[int, ...], cov, q, range_, model: str = "pinhole"):
    """Intrinsics-only: 2 x 2 covariance (px^2) of the projection of the point at distance `range_` along pixel
    q's ray, and whether the ray was found. params (12,) = fx fy cx cy k1..k6; `index` (static) the positions of
    the covariance's parameters."""
    k, coeffs = params[:4], params[4:]
    p, ok = _point(k, coeffs, q, range_, model)
    idx = jnp.array(index)
    full = lambda theta: params.at[idx].set(theta)  # noqa: E731
    jac = jax.jacfwd(lambda theta: _project(full(theta)[:4], full(theta)[4:], p, model))(params[idx])
    return jac @ cov @ jac.T, ok


def pose_compensated_covariance(params, index: tuple[int, ...], poses, cov, q, range_, model: str = "pinhole",
                                view_weight=None):
    """Pose-compensated: as `pixel_covariance` with `cov` the joint (G + 6V) covariance of the intrinsics
    (`index`) and the V poses (rvec, tvec of T_cam_board, rows of `poses`) in that order. `view_weight` (V,) 1 for
    the calibration's views, 0 for padding (`runtime/buckets.py`: out of the mean over views, and its rows and
    columns of `cov` 0); default all 1."""
    k, coeffs = params[:4], params[4:]
    p, ok = _point(k, coeffs, q, range_, model)
    rot = jax.vmap(rodrigues)(poses[:, :3])
    p_board = jnp.einsum("vji,vj->vi", rot, p[None] - poses[:, 3:])  # R_i^T (p - t_i): fixed in each board
    idx = jnp.array(index)
    # q(theta) = project(intrinsics, mean_v(R(r_v) p_board_v + t_v)): the Jacobian by the chain rule, each view's
    # (3, 6) block on its own (6 tangents each), not forward mode over all G + 6V parameters through every view
    # (G + 6V tangents through V views: 85 ms of the results folder's map for 20 views, measured; this ~10x less).
    back = lambda pv, pb: rodrigues(pv[:3]) @ pb + pv[3:]  # noqa: E731
    d_back = jax.vmap(jax.jacfwd(back))(poses, p_board)  # (V, 3, 6)
    w = jnp.ones(len(poses)) if view_weight is None else view_weight
    share = w / jnp.sum(w)  # each view's share of the mean
    p_mean = jnp.sum(share[:, None] * jax.vmap(back)(poses, p_board), axis=0)

    def q_of(theta, point):
        full = params.at[idx].set(theta)
        return _project(full[:4], full[4:], point, model)

    j_int, j_point = jax.jacfwd(q_of, argnums=(0, 1))(params[idx], p_mean)  # (2, G), (2, 3)
    j_pose = jnp.einsum("ij,vjk->ivk", j_point, d_back * share[:, None, None]).reshape(2, -1)
    jac = jnp.concatenate([j_int, j_pose], axis=1)
    return jac @ cov @ jac.T, ok


@functools.lru_cache(maxsize=None)
def _map_fn(index: tuple[int, ...], method: str = "intrinsics-only", model: str = "pinhole"):
    if method == "intrinsics-only":
        one = lambda params, poses, w, cov, q, r: pixel_covariance(params, index, cov, q, r, model)  # noqa: E731
    else:
        one = lambda params, poses, w, cov, q, r: pose_compensated_covariance(  # noqa: E731
            params, index, poses, cov, q, r, model, w)
    from dstereo.runtime import aot  # kept on disk: a new process skips tracing it (~1 s, the most of any program)

    return aot.jit(jax.vmap(one, in_axes=(None, None, None, None, 0, None)), "uncertainty.projection.map",
                   (index, method, model))


def _padded_views(poses, cov, n_params: int):
    """(poses, view weights, joint covariance) with the views padded to their bucket (`runtime/buckets.py`, one
    compiled map for every view count of a bucket): copies of the first pose, weight 0, zero rows and columns."""
    from dstereo.runtime import buckets

    n = len(poses)
    size = buckets.views(n)
    weight = np.r_[np.ones(n), np.zeros(size - n)]
    if size == n:
        return poses, weight, cov
    full = np.zeros((n_params + 6 * size,) * 2)
    full[:len(cov), :len(cov)] = cov
    return buckets.pad_rows(poses, size), weight, full


@dataclass
class ProjectionUncertaintyMap:
    """Grid over the image: pixel centres `u` (gw,), `v` (gh,), covariances (gh, gw, 2, 2) px^2, worst-direction
    std (gh, gw) px, at `range_` (the board's length unit); `mask` (gh, gw) True where the ray was found (std and
    cov are NaN elsewhere)."""

    u: np.ndarray
    v: np.ndarray
    cov: np.ndarray
    std: np.ndarray
    range_: float
    note: str = NOTE
    mask: np.ndarray | None = None
    method: str = "intrinsics-only"
    view_scatter: object | None = None  # `view_scatter.ViewScatter` of the solve (kappa, its alarm)
    covariance: str = "jacobian"  # or "per-view random effects" (`view_effects`): which covariance it maps

    @property
    def masked(self) -> int:
        return 0 if self.mask is None else int(np.size(self.mask) - np.count_nonzero(self.mask))

    def summary(self) -> dict:
        good = self.std[np.isfinite(self.std)]
        stats = ({"min": float(good.min()), "median": float(np.median(good)), "max": float(good.max())}
                 if good.size else {"min": None, "median": None, "max": None})
        stats["pixels_without_ray"] = int(self.std.size - good.size)  # masked, or no finite covariance
        out = {"method": self.method, "range": self.range_, "std_px": stats, "grid": [len(self.u), len(self.v)],
               "masked_pixels": self.masked, "note": self.note}
        out["covariance"] = self.covariance
        if self.view_scatter is not None:
            out["view_scatter"] = self.view_scatter.summary()
        return out

    def at(self, uv) -> float:
        """Std (px) at the grid pixel nearest to `uv` (NaN where masked)."""
        return float(self.std[np.argmin(np.abs(self.v - uv[1])), np.argmin(np.abs(self.u - uv[0]))])


def _grid(image_size, grid):
    w, h = image_size
    u = np.linspace(0.0, w - 1.0, grid[0])
    v = np.linspace(0.0, h - 1.0, grid[1])
    return u, v, np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)


def projection_uncertainty_map(k, coeffs, names, cov, image_size: tuple[int, int], range_: float,
                               grid: tuple[int, int] = (32, 24), poses=None,
                               method: str | None = None) -> ProjectionUncertaintyMap:
    """The map of the module docstring on a `grid` (columns, rows) of pixel centres spanning the image.

    k (4,), coeffs (8,) the camera; `names` its intrinsics (fx fy cx cy + free coefficients, as a one-camera
    `calib.solution.Solution` names them); `range_` > 0 in the board's length unit. Pose-compensated (default
    when `poses` (V, 6) are given): `cov` is the joint (G + 6V) covariance of the intrinsics and poses; intrinsics-only:
    `cov` is the (G, G) intrinsics covariance.
    """
    method = method or ("pose-compensated" if poses is not None else "intrinsics-only")
    if method not in METHODS:
        raise DstereoError(f"projection uncertainty method {method!r}: use one of {', '.join(METHODS)}")
    if not np.isfinite(range_) or range_ <= 0:
        raise DstereoError(f"projection uncertainty range {range_}: give a positive distance (board unit)")
    model = model_key(names)
    known = (FISHEYE_CAMERA_NAMES if model == "fisheye" else
             INTRINSIC_NAMES + tuple(names[4:]) if model.startswith("splined") else CAMERA_NAMES)
    unknown = [n for n in names if n not in known or not n]
    if unknown:
        raise DstereoError(f"projection uncertainty: unknown camera parameter(s) {unknown}; use {list(CAMERA_NAMES)} "
                           f"or {list(FISHEYE_CAMERA_NAMES[:8])}")
    index = tuple(known.index(n) for n in names)
    cov = np.asarray(cov, float)
    if method == "pose-compensated":
        if poses is None:
            raise DstereoError("pose-compensated projection uncertainty needs the calibration's view poses")
        poses = np.asarray(poses, float)
        if cov.shape != (len(index) + 6 * len(poses),) * 2:
            raise DstereoError(f"pose-compensated projection uncertainty: covariance {cov.shape} does not match "
                               f"{len(index)} intrinsics + {len(poses)} poses (joint covariance expected)")
        poses, weight, cov = _padded_views(poses, cov, len(index))
    else:
        poses, weight = np.zeros((1, 6)), np.ones(1)
    # numpy in: an eager jnp.concatenate or jnp.asarray compiles (or fetches) a small program per shape in a new
    # process (jax 0.10's `stage`), ~10-30 ms each
    params = np.concatenate([np.asarray(k, float), np.asarray(coeffs, float)])
    u, v, q = _grid(image_size, grid)
    if method == "pose-compensated":
        from dstereo.runtime import buckets  # what jobs/prebuild.py builds ahead: this map at every view count

        buckets.note("projection_map", (index, method, model, params, np.asarray(q, float), float(range_)),
                     tag=(index, method, model, len(q)))
    cov_q, ok = _map_fn(index, method, model)(params, np.asarray(poses, float), weight, cov, np.asarray(q, float),
                                              float(range_))
    cov_q, ok = np.array(cov_q), np.asarray(ok) & np.all(np.isfinite(np.asarray(cov_q)), axis=(1, 2))
    cov_q[~ok] = np.nan
    std = np.full(len(q), np.nan)
    std[ok] = np.sqrt(np.maximum(np.linalg.eigvalsh(cov_q[ok])[:, -1], 0.0))
    gh, gw = grid[1], grid[0]
    return ProjectionUncertaintyMap(u, v, cov_q.reshape(gh, gw, 2, 2), std.reshape(gh, gw), float(range_),
                                    NOTES[method], ok.reshape(gh, gw), method)


def solution_map(sol, image_size, range_: float, method: str = "pose-compensated",
                 grid: tuple[int, int] = (32, 24)) -> ProjectionUncertaintyMap:
    """The map of a one-camera `calib.solution.Solution` (a full-set solve, which carries its per-view normal
    blocks). A solved board sag is the board's, not the camera's: marginalised (its rows and columns dropped from
    the covariance)."""
    lens = np.array([i for i, n in enumerate(sol.names) if not n.startswith("board_sag")], int)
    names = tuple(sol.names[i] for i in lens)
    scatter = solution_view_scatter(sol)
    effects = solution_effects(sol)  # the views' effects: the covariance every +- of the tool carries
    if method == "pose-compensated":
        if sol.normal is None:
            raise DstereoError("pose-compensated projection uncertainty: this solve kept no per-view normal "
                               "equations; use `projection_method` intrinsics-only")
        pmap = projection_uncertainty_map(sol.values[:4], sol.camera().coeffs(), names, solution_joint(sol, effects),
                                          image_size, range_, grid, poses=sol.poses, method=method)
    else:
        cov = reported_covariance(sol)
        pmap = projection_uncertainty_map(sol.values[:4], sol.camera().coeffs(), names, cov[np.ix_(lens, lens)],
                                          image_size, range_, grid, method=method)
    return replace(pmap, view_scatter=scatter,
                   covariance="per-view random effects" if effects is not None and effects.fitted else "jacobian")


def solution_joint(sol, effects=None) -> np.ndarray:
    """(G + 6V, G + 6V) the joint covariance of a full-set solve's lens parameters and its V board poses, the
    views' effects included where fitted (`effects`: `solution_effects(sol)`, computed here when None); a solved
    board sag marginalised (its rows and columns dropped). The solve must keep its per-view normal blocks."""
    from dstereo.uncertainty.covariance import joint_covariance

    effects = solution_effects(sol) if effects is None else effects
    lens = np.array([i for i, n in enumerate(sol.names) if not n.startswith("board_sag")], int)
    joint = (effects.joint(sol.normal) if effects is not None else
             joint_covariance(sol.normal, len(sol.values), sse_of(sol), 2 * inliers_of(sol).sum(),
                              prior=knot_prior(sol.names)))
    keep = np.r_[lens, np.arange(len(sol.values), len(joint))]
    return joint[np.ix_(keep, keep)]


def knot_prior(names) -> np.ndarray | None:
    """(G, G) the information a splined lens's prior adds to the shared block of J'J (its knots follow fx fy cx cy;
    `splined.prior_rows`, as in the solve), or None for the other lens models."""
    key = model_key(names)
    if key.startswith("splined"):
        a = splined.prior_rows(*_splined_grid(key))
        out = np.zeros((len(names), len(names)))
        out[4:4 + a.shape[1], 4:4 + a.shape[1]] = a.T @ a
        return out
    return None


def mean_board_distance(poses: np.ndarray, object_points: np.ndarray) -> float:
    """Mean distance from the camera to the board centre over the views (poses (V, 6) T_cam_board)."""
    poses = np.asarray(poses, dtype=float)
    centre = np.asarray(object_points, float).mean(axis=0)
    centres = np.stack([rotation_matrix(p[:3]) @ centre + p[3:6] for p in poses])
    return float(np.mean(np.linalg.norm(centres, axis=1)))
