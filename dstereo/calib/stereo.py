"""Stereo rig calibration: full-set solve in two modes and the batched solve of stereo-pair subsets.

The solver's shared vector is the rig, g = [RVx, RVy, RVz, Tx, Ty, Tz] (x_right = R x_left + T, R as an
axis-angle vector, T in the board unit), plus in joint mode both cameras' intrinsics and free distortion
coefficients; each stereo pair contributes its board pose in the left camera (rvec, tvec of T_left_board),
and its residuals are both cameras' reprojection errors of that pose.

- mode "fixed": intrinsics and distortion held at the individual calibrations (the thesis's path, as
  cv2.stereoCalibrate with CALIB_FIX_INTRINSIC);
- mode "joint": everything refined together, starting from the fixed-intrinsic solution.

Compiled functions are cached per (mode, free sets, options), so one process compiles each once.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from dstereo.calib.init_zhang import homography, pose_from_homography
from dstereo.calib.mono import CameraSolution
from dstereo.calib.problem import Problem, batched_residuals, frame_linearize, frame_residual, residual_weights, run, \
    shared_data
from dstereo.calib.subset_solve import SubsetStart, solve_frame_subsets
from dstereo.calib.subsets import SubsetPlan
from dstereo.uncertainty.covariance import Conditioning, conditioning, scaled_inverse
from dstereo.uncertainty.view_effects import solve_covariance
from dstereo.errors import DstereoError
from dstereo.models.camera import INTRINSIC_NAMES, Camera
from dstereo.models.distortion import lens_model, undistort
from dstereo.models.pose import rodrigues, rotation_vectors
from dstereo.models.rig import RIG_NAMES, essential_matrix, fundamental_matrix
from dstereo.solver.lm import STATUS_TEXT, LMOptions

# Thesis Figure 5.14's stereo step parameters, the named columns of a subset table.
STEP_COLUMNS: tuple[str, ...] = ("stereo_re", "Tnorm", "Tx", "Ty", "Tz", "RVnorm", "RVx", "RVy", "RVz")
MODES = ("fixed", "joint")


def _names(problem: Problem) -> tuple[str, ...]:
    """The shared vector's names: the rig, then (joint mode) each camera's intrinsics, prefixed by its side."""
    names = RIG_NAMES
    for side, spec in zip(("left", "right"), problem.cameras):
        if spec.refined:
            names += tuple(f"{side}.{n}" for n in INTRINSIC_NAMES + spec.free)
    return names


def view_residual_for(problem: Problem):
    """Residuals (4n,) of one stereo pair, obs (2, n, 2) [left, right]: the problem's frame residual, K = 2."""
    return frame_residual(problem)


def view_linearize_for(problem: Problem):
    """Residuals and transposed Jacobian of one pair (`problem.frame_linearize`)."""
    return frame_linearize(problem)


def _solve(problem: Problem, options: LMOptions, g0, p0, data, shared, r_w):
    """One full-set solve of pairs data (V, 2, n, 2) with residual weights (V, 4n), through the one runner."""
    out = run(problem, options, np.asarray(g0, float)[None], np.asarray(p0, float)[None],
              np.asarray(data, float)[None], np.ones((1, len(p0))), np.array([options.lambda0]), shared,
              r_weight=np.asarray(r_w, float)[None])
    return jax.tree_util.tree_map(lambda a: a[0], out)


@jax.jit
def _rig_matrices(rig, k_left, k_right):
    """R, E, F of a rig vector (one compiled call instead of dozens of eager ones)."""
    E = essential_matrix(rig[:3], rig[3:6])
    return rodrigues(rig[:3]), E, fundamental_matrix(k_left, k_right, E)


@functools.lru_cache(maxsize=None)
def _normalised_points():
    from dstereo.runtime import aot, buckets  # kept on disk: a new process skips tracing it (the final solution's start)

    one = jax.vmap(undistort, in_axes=(None, 0))
    # one program per bucket of view counts (runtime/buckets.py): the views padded with copies of the first
    return buckets.per_row(aot.jit(lambda k, coeffs, q: jax.vmap(one, in_axes=(None, 0))(coeffs, (q - k[2:4]) / k[0:2]),
                                   "calib.stereo.normalised_points", ()), (2,), kind=("normalised_points", ()))


# --- start ---------------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=None)
def _normalised_fisheye_points():
    from dstereo.models.fisheye import undistort_points

    return jax.jit(jax.vmap(lambda k, d, q: undistort_points(k, d, q)[0], in_axes=(None, None, 0)))


def board_poses(camera: Camera, obj: np.ndarray, obs: np.ndarray) -> np.ndarray:
    """(V, 6) T_cam_board of each view for a known camera: homography of the undistorted, normalised corners
    (through the camera's own lens model: pinhole + distortion, or fisheye)."""
    if lens_model(tuple(camera.dist.free)) == "fisheye":
        xy = np.asarray(_normalised_fisheye_points()(camera.k, camera.dist.coeffs[:4], np.asarray(obs, float)))
        if not np.isfinite(xy).all():
            raise DstereoError("board pose: corners at or beyond 90 degrees from the fisheye camera's axis; leave "
                               "those views out")
    else:
        xy = np.asarray(_normalised_points()(camera.k, camera.dist.coeffs, np.asarray(obs, float)))
    return np.stack([pose_from_homography(homography(obj[:, :2], v), np.eye(3)) for v in xy])


def initial_rig(left: Camera, right: Camera, obj: np.ndarray, obs_left: np.ndarray,
                obs_right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rig (6,), board poses in the left camera (V, 6)): the median of the per-pair relative poses."""
    p_l, p_r = board_poses(left, obj, obs_left), board_poses(right, obj, obs_right)
    from scipy.spatial.transform import Rotation  # here: a one-camera run imports this module, not scipy's

    r_l, r_r = Rotation.from_rotvec(p_l[:, :3]), Rotation.from_rotvec(p_r[:, :3])
    r_rl = r_r * r_l.inv()
    t_rl = p_r[:, 3:] - r_rl.apply(p_l[:, 3:])
    rvecs = rotation_vectors(r_rl.as_matrix())
    return np.concatenate([np.median(rvecs, axis=0), np.median(t_rl, axis=0)]), p_l


# --- full set --------------------------------------------------------------------------------------------------


@dataclass
class StereoSolution:
    """A stereo solve on one set of pairs. `values`/`std` follow `names` (rig first, then joint intrinsics)."""

    mode: str
    names: tuple[str, ...]
    values: np.ndarray  # (G,)
    std: np.ndarray  # (G,) standard deviations: a full solve's with the pairs' effects (`view_effects`)
    cov: np.ndarray  # (G, G) the same
    left: Camera  # intrinsics used (fixed mode) or refined (joint mode)
    right: Camera
    rvec: np.ndarray  # (3,) R as an axis-angle vector
    R: np.ndarray  # (3, 3)
    T: np.ndarray  # (3,)
    E: np.ndarray  # (3, 3) [T]x R
    F: np.ndarray  # (3, 3) K2^-T E K1^-1, F[2, 2] = 1
    poses: np.ndarray  # (V, 6) T_left_board per pair
    rms: float  # sqrt(SSE / (2 V n)): cv2.stereoCalibrate's RMS over both cameras' corners
    per_pair_rms: np.ndarray  # (V,) both cameras' corners of each pair
    residuals: np.ndarray  # (V, 2, n, 2) projected - observed, [left, right]
    iterations: int
    status: int
    conditioning: Conditioning
    inliers: np.ndarray | None = None  # (V, 2, n) bool: corners the solve used [left, right] (None: all)
    timings: dict = field(default_factory=dict)
    cov_jacobian: np.ndarray | None = None  # (G, G) the Jacobian's alone (independent corner noise)

    @property
    def converged(self) -> bool:
        return self.status > 0

    @property
    def status_text(self) -> str:
        return STATUS_TEXT[self.status]

    @property
    def stereo_re(self) -> float:
        """Thesis 4.2.2.2: the mean over pairs of each pair's RMS reprojection error (px)."""
        return float(np.mean(self.per_pair_rms))

    @property
    def baseline(self) -> float:
        return float(np.linalg.norm(self.T))

    @property
    def std_jacobian(self) -> np.ndarray | None:
        return None if self.cov_jacobian is None else np.sqrt(np.maximum(np.diag(self.cov_jacobian), 0.0))

    @property
    def baseline_std(self) -> float:
        """Standard deviation of |T| (first-order propagation of the T covariance, `cov`)."""
        return _norm_std(self.T, self.cov[3:6, 3:6])

    @property
    def baseline_std_jacobian(self) -> float:
        """The same from the Jacobian covariance alone (a subset's std is that kind)."""
        return _norm_std(self.T, (self.cov if self.cov_jacobian is None else self.cov_jacobian)[3:6, 3:6])

    @property
    def angle_std(self) -> float:
        """Standard deviation of |rvec| (rad), from `cov`."""
        return _norm_std(self.rvec, self.cov[0:3, 0:3])

    def columns(self) -> dict[str, float]:
        """The thesis's stereo step parameters (`STEP_COLUMNS`) of this solve."""
        return {k: float(v[0]) for k, v in _step_columns(self.values[None], np.array([self.stereo_re])).items()}

    def as_dict(self) -> dict[str, float]:
        return dict(zip(self.names, map(float, self.values)))


def _norm_std(v: np.ndarray, cov: np.ndarray) -> float:
    n = np.linalg.norm(v)
    grad = v / n if n > 0 else np.zeros_like(v)
    return float(np.sqrt(max(grad @ cov @ grad, 0.0)))


def _step_columns(values: np.ndarray, stereo_re: np.ndarray) -> dict[str, np.ndarray]:
    rv, t = values[:, 0:3], values[:, 3:6]
    return {
        "stereo_re": stereo_re, "Tnorm": np.linalg.norm(t, axis=1), "Tx": t[:, 0], "Ty": t[:, 1], "Tz": t[:, 2],
        "RVnorm": np.linalg.norm(rv, axis=1), "RVx": rv[:, 0], "RVy": rv[:, 1], "RVz": rv[:, 2],
    }


def _check_pairs(obj: np.ndarray, obs_left: np.ndarray, obs_right: np.ndarray) -> None:
    for side, obs in (("left", obs_left), ("right", obs_right)):
        if obs.ndim != 3 or obs.shape[1:] != (obj.shape[0], 2):
            raise DstereoError(f"stereo corners ({side}): expected (pairs, {obj.shape[0]}, 2) image points, "
                               f"got {obs.shape}")
    if obs_left.shape[0] != obs_right.shape[0]:
        raise DstereoError(f"stereo corners: {obs_left.shape[0]} left views but {obs_right.shape[0]} right views; "
                           "each stereo pair needs the board in both images")
    if obs_left.shape[0] < 1:
        raise DstereoError("stereo calibration: no stereo pair shows the board in both cameras")


def _spec_for(mode: str, left: Camera, right: Camera) -> Problem:
    """The K = 2 problem of a mode: "fixed" holds both cameras' intrinsics, "joint" refines them."""
    if mode not in MODES:
        raise DstereoError(f"stereo mode '{mode}' is unknown; use one of {list(MODES)}")
    return Problem.of([tuple(left.dist.free), tuple(right.dist.free)], refined=mode == "joint")


def _shared(obj, left: Camera, right: Camera):
    return shared_data(obj, np.stack([np.asarray(left.k), np.asarray(right.k)]),
                       np.stack([np.asarray(left.dist.coeffs), np.asarray(right.dist.coeffs)]))


def _g0(problem: Problem, rig: np.ndarray, left: Camera, right: Camera) -> np.ndarray:
    if not problem.cameras[0].refined:
        return np.asarray(rig, float)
    return np.concatenate([rig, np.asarray(left.free_vector()), np.asarray(right.free_vector())])


def calibrate_stereo(
    obj: np.ndarray,
    obs_left: np.ndarray,
    obs_right: np.ndarray,
    left: Camera,
    right: Camera,
    mode: str = "fixed",
    options: LMOptions = LMOptions(),
    inliers: np.ndarray | None = None,
) -> StereoSolution:
    """Calibrate the rig from all pairs: obj (n, 3) board points, obs_* (V, n, 2) corners of each pair.
    `inliers` (V, 2, n) bool [left, right]: the corners that count (the cameras' outlier masks; default all).

    `left`/`right` are the individual calibrations (their `dist.free` says which coefficients the joint mode
    refines). Start: median of the per-pair relative poses; then the structured LM with intrinsics fixed; in
    joint mode a second LM over everything from there. The result may be unconverged (`status` < 0).
    """
    obj, obs_left, obs_right = (np.asarray(a, float) for a in (obj, obs_left, obs_right))
    _check_pairs(obj, obs_left, obs_right)
    spec = _spec_for(mode, left, right)
    t0 = time.perf_counter()
    rig0, poses0 = initial_rig(left, right, obj, obs_left, obs_right)
    data = np.stack([obs_left, obs_right], axis=1)  # (V, 2, n, 2)
    shared = _shared(obj, left, right)
    mask = _pair_mask(inliers, obs_left.shape)
    r_w = pair_weights(mask)
    out = _solve(_spec_for("fixed", left, right), options, rig0, poses0, data, shared, r_w)
    iterations = int(out.iterations)
    if spec.cameras[0].refined:
        out = _solve(spec, options, _g0(spec, np.asarray(out.g), left, right), out.p, data, shared, r_w)
        iterations += int(out.iterations)
    out = jax.tree_util.tree_map(np.array, out)
    sol = _solution_from(out, spec, mode, obj, data, left, right, iterations, mask)
    sol.timings["solve_s"] = time.perf_counter() - t0
    if not np.isfinite(sol.rms):
        raise DstereoError(f"stereo calibration failed ({STATUS_TEXT[sol.status]}); check that the left and right "
                           "images of each pair show the board in the same corner order")
    return sol


def _pair_mask(inliers, shape) -> np.ndarray:
    """(V, 2, n) bool from `inliers` or all True; a pair with no inlier corner at all keeps its corners (its
    pose would be undetermined)."""
    mask = np.ones((shape[0], 2, shape[1]), bool) if inliers is None else np.array(inliers, bool)
    mask[~mask.any(axis=(1, 2))] = True
    return mask


def pair_weights(mask: np.ndarray) -> np.ndarray:
    """(..., V, 2, n) corner mask -> (..., V, 4n) residual weights in the frame residual's order."""
    return residual_weights(mask)


def cameras_from(spec: Problem, g: np.ndarray, left: Camera, right: Camera) -> tuple[Camera, Camera]:
    """The cameras a solution's shared vector describes (the inputs themselves in fixed mode)."""
    if not spec.cameras[0].refined:
        return left, right
    n_l = spec.cameras[0].size
    return left.with_free_vector(jnp.asarray(g[6:6 + n_l])), right.with_free_vector(jnp.asarray(g[6 + n_l:]))


def _solution_from(out, spec: Problem, mode: str, obj, data, left: Camera, right: Camera,
                   iterations: int, mask: np.ndarray) -> StereoSolution:
    g = out.g
    names = _names(spec)
    # the +- reported: with the pairs' effects (`uncertainty/view_effects.py`), the Jacobian one beside it
    cov, jac, _ = solve_covariance(out, len(g) + out.p.size)
    cam_l, cam_r = cameras_from(spec, g, left, right)
    shared = _shared(obj, left, right)
    resid = np.asarray(batched_residuals(spec)(g[None], out.p[None], data[None], shared))[0]
    n = obj.shape[0]
    resid = resid.reshape(len(out.p), 2, n, 2)
    R, E, F = (np.array(a) for a in _rig_matrices(jnp.asarray(g[:6]), cam_l.k, cam_r.k))
    return StereoSolution(
        mode=mode, names=names, values=g, std=np.sqrt(np.maximum(np.diag(cov), 0.0)), cov=cov,
        cov_jacobian=jac, left=cam_l,
        right=cam_r, rvec=g[:3].copy(), R=R, T=g[3:6].copy(), E=E, F=F,
        poses=out.p, rms=float(np.sqrt(out.sse / max(int(mask.sum()), 1))),
        per_pair_rms=np.sqrt(np.sum(np.sum(resid ** 2, axis=3) * mask, axis=(1, 2))
                             / np.maximum(mask.sum(axis=(1, 2)), 1)),
        residuals=resid, iterations=iterations, status=int(out.status), conditioning=conditioning(out.schur, names),
        inliers=None if mask.all() else mask,
    )


# --- subsets ---------------------------------------------------------------------------------------------------


@dataclass
class StereoSubsetSolutions:
    """Per-subset stereo results, rows aligned with `plan.index` (indices into the solution's pairs)."""

    plan: SubsetPlan
    names: tuple[str, ...]
    values: np.ndarray  # (C, G)
    std: np.ndarray  # (C, G) Jacobian standard deviations of each subset's own solve
    norm_std: np.ndarray  # (C, 2) Jacobian standard deviations of |T| and |rvec|
    rms: np.ndarray  # (C,) sqrt(SSE / (2 m n))
    stereo_re: np.ndarray  # (C,) mean of the per-pair RMS (thesis)
    iterations: np.ndarray
    status: np.ndarray
    timings: dict = field(default_factory=dict)

    @property
    def converged(self) -> np.ndarray:
        return self.status > 0

    def columns(self) -> dict[str, np.ndarray]:
        """The thesis's stereo step parameters (`STEP_COLUMNS`), one value per subset."""
        return _step_columns(self.values, self.stereo_re)


def solve_stereo_subsets(
    obj: np.ndarray,
    obs_left: np.ndarray,
    obs_right: np.ndarray,
    plan: SubsetPlan,
    start: StereoSolution,
    options: LMOptions = LMOptions(lambda0=1e-6),
    progress=None,
) -> StereoSubsetSolutions:
    """Solve every subset of pairs in `plan` with the one subset runner (`subset_solve`), starting from the
    full-set solution (same mode and cameras as `start`); each subset converges to its own least-squares
    solution."""
    obj, obs_left, obs_right = (np.asarray(a, float) for a in (obj, obs_left, obs_right))
    _check_pairs(obj, obs_left, obs_right)
    problem = _spec_for(start.mode, start.left, start.right)
    index = np.asarray(plan.index)
    n_sub, m = index.shape
    shared = _shared(obj, start.left, start.right)
    data = np.stack([obs_left, obs_right], axis=1)
    mask = _pair_mask(start.inliers, obs_left.shape)  # the full set's outlier mask, in every subset
    r_w = pair_weights(mask)
    t0 = time.perf_counter()
    out = solve_frame_subsets(problem, data, r_w, shared, index, SubsetStart(start.values, start.poses), options,
                              progress)
    # each subset's own poses, in its pairs' order (a masked solve returns every pair's, the others unchanged)
    poses = out.p if out.p.shape[1] == m else np.take_along_axis(out.p, index[:, :, None], axis=1)
    re = np.concatenate([_pair_rms(problem, out.g[c:c + 256], poses[c:c + 256], data[index[c:c + 256]],
                                   r_w[index[c:c + 256]], shared) for c in range(0, n_sub, 256)])
    n_points = out.n_residuals / 2  # inlier corners of both cameras
    sigma2 = out.sse / (out.n_residuals - (out.g.shape[1] + 6 * m))
    cov = scaled_inverse(out.schur) * sigma2[:, None, None]
    norm_std = np.array([[_norm_std(g[3:6], c[3:6, 3:6]), _norm_std(g[0:3], c[0:3, 0:3])]
                         for g, c in zip(out.g, cov)])
    return StereoSubsetSolutions(
        plan=plan, names=start.names, values=out.g,
        std=np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0)), norm_std=norm_std,
        rms=np.sqrt(out.sse / n_points), stereo_re=re, iterations=out.iterations,
        status=out.status, timings={"solve_s": time.perf_counter() - t0},
    )


def _pair_rms(problem, g, poses, data, w, shared) -> np.ndarray:
    """(C,) thesis stereo_re of each subset: the mean over its pairs of each pair's RMS over its inlier corners."""
    r = np.asarray(batched_residuals(problem)(g, poses, data, shared)) * w  # (C, m, 4n), outliers zeroed
    return np.mean(np.sqrt(np.sum(r ** 2, axis=2) / (np.sum(w, axis=2) / 2)), axis=1)


# --- folders -----------------------------------------------------------------------------------------------------


def camera_from_solution(sol: CameraSolution) -> Camera:
    """The `Camera` model of an individual calibration (its free set is what the joint mode refines)."""
    fx, fy, cx, cy = (float(v) for v in sol.values[:4])
    return Camera.create(fx, fy, cx, cy, sol.coeffs, sol.free, sol.image_size)
