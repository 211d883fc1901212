"""One camera from chessboard views: full-set solve and the batched solve of every image subset.

The solver's shared vector is `Camera.free_vector()` = [fx, fy, cx, cy, <free distortion coefficients>];
each view contributes its pose (rvec, tvec). Compiled functions are cached per (free set, shapes), so a
test suite or a CLI run compiles each once.
"""

from __future__ import annotations

import functools
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from dstereo.calib.init_fisheye import initial_guess_fisheye
from dstereo.calib.init_zhang import initial_guess
from dstereo.calib.subsets import SubsetPlan
from dstereo.uncertainty.covariance import Conditioning, conditioning, covariance, scaled_inverse
from dstereo.errors import DstereoError
from dstereo.models import camera, fisheye
from dstereo.models.camera import INTRINSIC_NAMES
from dstereo.models.distortion import coeff_slots, lens_model, with_free
from dstereo.models.pose import rodrigues, rodrigues_jacobian
from dstereo.jax_workarounds import CALL_POINTS, MAX_CHUNK, MAX_CONCURRENT_CALLS
from dstereo.solver.lm import COMPILE_OPTIONS, STATUS_TEXT, LMOptions, solve_structured_batch


def lens_functions(free: tuple[str, ...]):
    """(project, project_jacobian) of the lens model that `free` names, both on (k, coeffs (8,), p_cam): the
    fisheye model reads its k1..k4 from the first four slots (`distortion.coeff_slots`)."""
    if lens_model(free) == "fisheye":
        return (lambda k, c, p: fisheye.project(k, c[:4], p)), (lambda k, c, p: fisheye.project_jacobian(k, c[:4], p))
    return camera.project, camera.project_jacobian


@functools.lru_cache(maxsize=None)
def view_residual_for(free: tuple[str, ...]):
    """Residual of one view (2n,) for a given free distortion set; cached so jit sees one function."""
    project, _ = lens_functions(free)

    def view_residual(g, pose, obs_v, shared):
        obj, base_coeffs = shared
        coeffs = with_free(base_coeffs, free, g[4:])
        # One rotation per view, not per point: the pose Jacobian is then formed once, too.
        p_cam = obj @ rodrigues(pose[:3]).T + pose[3:6]
        q = jax.vmap(project, in_axes=(None, None, 0))(g[:4], coeffs, p_cam)
        return (q - obs_v).ravel()

    return view_residual


@functools.lru_cache(maxsize=None)
def view_linearize_for(free: tuple[str, ...]):
    """Residuals and transposed Jacobian of one view by the chain rule: per point the hand-written d q /
    d(k, coeffs, p_cam) (`camera.project_jacobian`), and d R / d rvec once per view (`pose.rodrigues_jacobian`).

    Written on whole coordinate arrays (3, n) rather than vmapped per point, with the free coefficients
    picked by static slices: the view is then a few elementwise loops, which traces and compiles about
    twice as fast as per-point vmaps and autodiff (compile time dominates a cold calibration);
    `tests/test_engine.py` checks it against autodiff and finite differences.
    """
    cols = [coeff_slots(free).index(n) for n in free]
    _, project_jacobian = lens_functions(free)

    def linearize(g, pose, obs_v, shared):
        obj, base_coeffs = shared
        coeffs = with_free(base_coeffs, free, g[4:])
        rot, d_rot = rodrigues_jacobian(pose[:3])  # (3, 3), (3, 3, 3): d R_ij / d rvec_k
        o = obj.T  # (3, n)
        # Products over 3-vectors as sums of broadcasts: XLA's CPU dot emitter compiles tiny dots into far
        # more code than these fused loops.
        p_cam = sum(rot[:, j, None] * o[j] for j in range(3)) + pose[3:6, None]  # (3, n)
        dpc_drot = sum(d_rot[:, j, :, None] * o[j] for j in range(3))  # (3 i, 3 k, n): d p_cam_i / d rvec_k
        q, dk, dc, dp = project_jacobian(g[:4], coeffs, p_cam)  # (2, n), (2, 4, n), (2, 8 or 4, n), (2, 3, n)
        dp_drot = sum(dp[:, i, None, :] * dpc_drot[None, i] for i in range(3))  # (2, 3, n)
        rows = jnp.concatenate([dk, *(dc[:, c:c + 1] for c in cols), dp_drot, dp, (q - obs_v.T)[:, None]], axis=1)
        # (2, G + 7, n) -> one row per parameter and the residuals last, in the model's order (n, 2)
        rows = jnp.transpose(rows, (1, 2, 0)).reshape(rows.shape[1], -1)
        return rows[-1], rows[:-1]

    return linearize


# Problems per compiled call: as many as fit CALL_POINTS corner observations, at most MAX_CHUNK, at most
# MAX_CONCURRENT_CALLS at once (a jaxlib CPU-runtime hang; see dstereo/jax_workarounds.py).


def chunk_rows(n_views: int, n_points: int) -> int:
    """Problems per compiled call for views of `n_points` corners (fixed per shape, so one compile)."""
    return int(max(1, min(MAX_CHUNK, CALL_POINTS // max(1, n_views * n_points))))


def _threads(requested: int | None) -> int:
    env = os.environ.get("DSTEREO_THREADS")
    n = requested or (int(env) if env and env.isdigit() else None) or os.cpu_count() or 1
    return max(1, min(n, MAX_CONCURRENT_CALLS))


@functools.lru_cache(maxsize=None)
def _solver(free: tuple[str, ...], options: LMOptions):
    """The one compiled program behind the full set and every subset: CHUNK problems of V views, each with
    its own start, view weights (0 = left out), corner weights (0 = an outlier) and initial damping. The full
    set and subsets of the same images share its shape, so a calibration with subsets compiles once (compile
    time dominates a cold run), whatever the outlier mask."""
    res, lin = view_residual_for(free), view_linearize_for(free)

    def batch(g0, p0, obs, weight, lambda0, normal0, r_weight, shared):
        return solve_structured_batch(res, g0, p0, obs, shared, options, lin, weight, lambda0, normal0, r_weight)

    return jax.jit(batch, compiler_options=COMPILE_OPTIONS)


def _residual_weights(inliers: np.ndarray) -> np.ndarray:
    """(..., V, n) corner inlier mask -> (..., V, 2n) residual weights in the residual's (x, y) per point order."""
    return np.repeat(np.asarray(inliers, float), 2, axis=-1)


def _run(free, options, g0, p0, obs, weight, lambda0, shared, normal0=None, r_weight=None):
    """Call the compiled solver on one chunk given as per-problem numpy arrays (leading axis <= chunk_rows).

    `normal0 = (r, m)`, per problem, is the linearisation at (g0, p0) from an earlier solve (`LMResult.residuals`
    and `.normal`); the solver then skips linearising the start. Without it, the same compiled program
    linearises the start itself (a traced flag, not a second compile). An argument that is already a device
    array is taken as it is, at the chunk's full size: subsets pass what all their chunks share once.
    `weight` is always per chunk and gives the number of problems. `r_weight` (per problem (V, 2n), default
    all 1): the corners' residual weights, 0 for an outlier."""
    n, (n_views, n_pts) = len(weight), np.shape(obs)[1:3]
    rows = chunk_rows(n_views, n_pts)

    def prep(a):
        if isinstance(a, jax.Array):
            return a
        a = np.asarray(a, float)
        # numpy in, not jnp.asarray: that compiles a small staging program per new shape (~10 ms each, measured)
        return np.ascontiguousarray(np.concatenate([a, np.repeat(a[:1], rows - n, axis=0)]) if n < rows else a)

    n_p1 = np.shape(g0)[1] + 7  # shared parameters + 6 pose parameters + the residual column
    given = normal0 is not None
    if not given:
        normal0 = (np.zeros((n, n_views, 2 * n_pts)), np.zeros((n, n_views, n_p1, n_p1)))
    key = options._replace(lambda0=0.0)  # lambda0 is traced, not compiled in
    if r_weight is None:
        r_weight = np.ones((n, n_views, 2 * n_pts))
    args = [prep(a) for a in (g0, p0, obs, weight, lambda0, *normal0, r_weight)]
    out = _solver(tuple(free), key)(*args[:5], (*args[5:7], np.full(rows, given)), args[7], shared)
    return jax.tree_util.tree_map(lambda a: np.asarray(a)[:n], out)


@dataclass
class CameraSolution:
    """A solve on one set of views. Values and standard deviations are keyed by parameter name."""

    names: tuple[str, ...]
    values: np.ndarray  # (G,) shared parameters in `names` order
    std: np.ndarray  # (G,) Jacobian standard deviations
    cov: np.ndarray  # (G, G)
    coeffs: np.ndarray  # (8,) all distortion coefficients, OpenCV order (fisheye: cv2.fisheye's D in [:4])
    poses: np.ndarray  # (V, 6) rvec, tvec per view
    rms: float  # sqrt(SSE / points), OpenCV's reprojection error, over the inlier corners
    per_view_rms: np.ndarray  # (V,) over each view's inlier corners
    residuals: np.ndarray  # (V, n, 2) projected - observed, outliers' included
    iterations: int
    status: int
    conditioning: Conditioning
    free: tuple[str, ...]
    image_size: tuple[int, int]
    timings: dict = field(default_factory=dict)
    normal: np.ndarray | None = None  # (V, P+1, P+1) per view [J r]'[J r] at the solution: subsets start from it
    inliers: np.ndarray | None = None  # (V, n) bool: corners the solve used (None: all); subsets use the same

    @property
    def converged(self) -> bool:
        return self.status > 0

    @property
    def lens_model(self) -> str:
        return lens_model(self.free)

    @property
    def status_text(self) -> str:
        return STATUS_TEXT[self.status]

    @property
    def camera_matrix(self) -> np.ndarray:
        fx, fy, cx, cy = self.values[:4]
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def as_dict(self) -> dict[str, float]:
        return dict(zip(self.names, map(float, self.values)))


def _check_views(obj: np.ndarray, obs: np.ndarray) -> None:
    if obs.ndim != 3 or obs.shape[2] != 2 or obs.shape[1] != obj.shape[0]:
        raise DstereoError(f"corners: expected (views, {obj.shape[0]}, 2) image points, got {obs.shape}")
    if obs.shape[0] < 3:
        raise DstereoError(
            f"images: only {obs.shape[0]} usable board views; a calibration needs at least 3 (better 10-20 "
            "at varied tilts)"
        )


def calibrate_full(
    obj: np.ndarray,
    obs: np.ndarray,
    image_size: tuple[int, int],
    free: tuple[str, ...] = ("k1", "k2", "p1", "p2", "k3"),
    options: LMOptions = LMOptions(),
    inliers: np.ndarray | None = None,
    start: tuple[np.ndarray, np.ndarray] | None = None,
) -> CameraSolution:
    """Calibrate from all views: closed-form start, then the structured LM to convergence.

    `inliers` (V, n) bool: corners to fit (the others, outliers, weigh 0; default all). `start`: (shared vector,
    (V, 6) poses) of the same views to start from (an earlier mask's solve) instead of the closed form."""
    obj, obs = np.asarray(obj, float), np.asarray(obs, float)
    _check_views(obj, obs)
    t0 = time.perf_counter()
    mask = np.ones(obs.shape[:2], bool) if inliers is None else np.asarray(inliers, bool)
    if start is not None:
        g0, p0, lam = np.asarray(start[0], float), np.asarray(start[1], float), 1e-6
    else:
        fish = lens_model(tuple(free)) == "fisheye"
        # Zhang's homographies assume a pinhole; a fisheye starts from the equidistant lens that best fits the views
        k0, p0 = initial_guess_fisheye(obj, obs, image_size) if fish else initial_guess(obj, obs, image_size)
        g0, lam = np.concatenate([k0, np.zeros(len(free))]), options.lambda0
    shared = (np.asarray(obj, float), np.zeros(8))  # numpy: no eager JAX op (each compiles on first use)
    # A view without inlier corners (rejected whole) takes no part: weight 0, its pose carried unchanged
    out = _run(free, options, g0[None], p0[None], obs[None], mask.any(axis=1)[None].astype(float), np.array([lam]),
               shared, r_weight=_residual_weights(mask)[None])
    out = jax.tree_util.tree_map(lambda a: a[0], out)
    sol = _solution_from(out, obj, obs, tuple(free), image_size, mask)
    sol.timings["solve_s"] = time.perf_counter() - t0
    if not np.isfinite(sol.rms):
        raise DstereoError(
            f"calibration failed ({STATUS_TEXT[sol.status]}); check the pattern size and remove images whose "
            "corners are ordered differently"
        )
    return sol  # may be unconverged (sol.status < 0): callers report it, never hide it


def _solution_from(out, obj, obs, free, image_size, mask) -> CameraSolution:
    names = INTRINSIC_NAMES + tuple(free)
    g = out.g
    coeffs = np.zeros(8)
    coeffs[[coeff_slots(free).index(n) for n in free]] = g[4:]
    n_params = len(g) + 6 * int(mask.any(axis=1).sum())
    cov = covariance(out.schur, float(out.sse), int(out.n_residuals), n_params)
    resid = np.asarray(out.residuals).reshape(obs.shape)
    n_in = np.maximum(mask.sum(axis=1), 1)
    return CameraSolution(
        names=names, values=g, std=np.sqrt(np.maximum(np.diag(cov), 0.0)), cov=cov, coeffs=coeffs, poses=out.p,
        rms=float(np.sqrt(out.sse / max(int(mask.sum()), 1))),
        per_view_rms=np.sqrt(np.sum(np.sum(resid ** 2, axis=2) * mask, axis=1) / n_in),
        residuals=resid, iterations=int(out.iterations), status=int(out.status), normal=np.asarray(out.normal),
        conditioning=conditioning(out.schur, names, g, np.sqrt(np.maximum(np.diag(cov), 0.0)), image_size),
        free=free, image_size=tuple(image_size), inliers=None if mask.all() else mask,
    )


@dataclass
class SubsetSolutions:
    """Per-subset results, rows aligned with `plan.index`."""

    plan: SubsetPlan
    names: tuple[str, ...]
    values: np.ndarray  # (C, G)
    std: np.ndarray  # (C, G) Jacobian standard deviations of each subset's own solve
    rms: np.ndarray  # (C,)
    iterations: np.ndarray  # (C,)
    status: np.ndarray  # (C,)
    timings: dict = field(default_factory=dict)

    @property
    def converged(self) -> np.ndarray:
        return self.status > 0


def solve_subsets(
    obj: np.ndarray,
    obs: np.ndarray,
    plan: SubsetPlan,
    start: CameraSolution,
    options: LMOptions = LMOptions(lambda0=1e-6),
    progress=None,
    threads: int | None = None,
) -> SubsetSolutions:
    """Refine every subset of `plan` in fixed-size vmapped chunks, starting from the full-set solution.

    Starting at the full-set optimum puts every subset a few iterations from its own optimum; each subset
    still converges to its own least-squares solution (tests check this against cv2.calibrateCamera).
    A subset is the full set with the other views weighted 0, so it reuses the full set's compiled solver,
    unless subsets are less than half the set: then carrying the unused views would cost more than a second
    compile, and the subsets' views are gathered instead. Chunks run on `threads` threads (default: one per
    core, at most 2, or DSTEREO_THREADS); XLA runs one chunk's loop mostly on one core.
    """
    free = start.free
    index = np.asarray(plan.index)
    n_sub, m = index.shape
    n_views = len(obs)
    obs, poses = np.asarray(obs, float), np.asarray(start.poses, float)
    shared = (np.asarray(obj, float), np.zeros(8))
    gathered = 2 * m < n_views
    # The full set's outlier mask: a corner rejected there is left out of every subset too
    r_weight = _residual_weights(np.ones(obs.shape[:2], bool) if start.inliers is None else start.inliers)

    # The full set's linearisation at its solution (the subsets' start), per view and unweighted: every
    # subset reuses it instead of linearising its start again (one pass of about six saved).
    normal = None if start.normal is None else (start.residuals.reshape(n_views, -1), start.normal)

    if not gathered:
        # Every chunk of a masked plan shares the start, views and linearisation; only the weights differ.
        # Put them on the device once, at the full chunk size, instead of copying them for every chunk.
        full_rows = chunk_rows(n_views, obs.shape[1])
        put = lambda a: jax.device_put(np.ascontiguousarray(np.broadcast_to(a, (full_rows, *np.shape(a)))))  # noqa: E731
        common = (put(start.values), put(poses), put(obs))
        lam_all = put(np.float64(options.lambda0))
        normal_all = None if normal is None else tuple(put(a) for a in normal)
        r_weight_all = put(r_weight)

    def chunk_args(rows):
        c = len(rows)
        if gathered:
            g0 = np.broadcast_to(start.values, (c, len(start.values)))
            start_ne = None if normal is None else tuple(a[rows] for a in normal)
            return (g0, poses[rows], obs[rows], np.ones((c, m)), np.full(c, options.lambda0)), start_ne, r_weight[rows]
        weight = np.zeros((c, n_views))
        np.add.at(weight, (np.arange(c)[:, None], rows), 1.0)  # counts: bootstrap resamples repeat views
        return (*common, weight, lam_all), normal_all, r_weight_all

    def run(rows):
        args, start_ne, r_w = chunk_args(rows)
        # Per-view linearisations and residuals are not kept per subset (C=5000: ~400 MB).
        return _run(free, options, *args, shared, start_ne, r_w)._replace(normal=None, residuals=None)

    t0 = time.perf_counter()
    rows = chunk_rows(m if gathered else n_views, obs.shape[1])
    chunks = [index[c: c + rows] for c in range(0, n_sub, rows)]
    workers = min(_threads(threads), len(chunks))
    outs, done = [], 0
    with ThreadPoolExecutor(workers) as pool:
        for out in pool.map(run, chunks):
            outs.append(out)
            done += len(out.status)
            if progress is not None:
                progress(done, n_sub)
    out = jax.tree_util.tree_map(lambda *a: np.concatenate(a), *outs)
    n_points = out.n_residuals / 2  # inlier corners, views counted with their weights
    n_params = len(start.values) + 6 * m
    sigma2 = out.sse / (out.n_residuals - n_params)
    cov_diag = np.diagonal(scaled_inverse(out.schur), axis1=1, axis2=2)
    return SubsetSolutions(
        plan=plan, names=start.names, values=out.g, std=np.sqrt(np.maximum(cov_diag * sigma2[:, None], 0.0)),
        rms=np.sqrt(out.sse / n_points), iterations=out.iterations, status=out.status,
        timings={"solve_s": time.perf_counter() - t0},
    )
