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
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from dstereo.calib.init_zhang import homography, pose_from_homography
from dstereo.calib.mono import CameraSolution, calibrate_full
from dstereo.calib.subsets import SubsetPlan, plan_subsets
from dstereo.uncertainty.covariance import Conditioning, conditioning, covariance, scaled_inverse
from dstereo.errors import DstereoError
from dstereo.io.corners import Detection, detect_folder
from dstereo.io.stereo_files import DroppedPair, StereoDetection, detect_pairs, image_files
from dstereo.models.camera import INTRINSIC_NAMES, Camera, project_jacobian
from dstereo.models.distortion import COEFF_NAMES, PRESETS, undistort, with_free
from dstereo.models.pose import rodrigues
from dstereo.models.rig import essential_matrix, fundamental_matrix, pair_residual
from dstereo.solver.lm import COMPILE_OPTIONS, STATUS_TEXT, LMOptions, solve_structured, solve_structured_batch

RIG_NAMES: tuple[str, ...] = ("RVx", "RVy", "RVz", "Tx", "Ty", "Tz")
# Thesis Figure 5.14's stereo step parameters, the named columns of a subset table.
STEP_COLUMNS: tuple[str, ...] = ("stereo_re", "Tnorm", "Tx", "Ty", "Tz", "RVnorm", "RVx", "RVy", "RVz")
MODES = ("fixed", "joint")


class _Spec(NamedTuple):
    """Static configuration of a stereo solve: which parameters the shared vector holds."""

    joint: bool
    free_left: tuple[str, ...] = ()
    free_right: tuple[str, ...] = ()

    def names(self) -> tuple[str, ...]:
        if not self.joint:
            return RIG_NAMES
        return (RIG_NAMES + tuple(f"left.{n}" for n in INTRINSIC_NAMES + self.free_left)
                + tuple(f"right.{n}" for n in INTRINSIC_NAMES + self.free_right))

    def unpack(self, g, shared):
        """(obj, k_l, coeffs_l, k_r, coeffs_r) with the free entries of g written over the shared ones."""
        obj, k_l, c_l, k_r, c_r = shared
        if self.joint:
            n_l = len(self.free_left)
            k_l, k_r = g[6:10], g[10 + n_l:14 + n_l]
            c_l = with_free(c_l, self.free_left, g[10:10 + n_l])
            c_r = with_free(c_r, self.free_right, g[14 + n_l:])
        return obj, k_l, c_l, k_r, c_r


@functools.lru_cache(maxsize=None)
def view_residual_for(spec: _Spec):
    """Residuals (4n,) of one stereo pair: left camera (n, 2) then right camera (n, 2), ravelled."""

    def view_residual(g, pose, obs_v, shared):
        obj, k_l, c_l, k_r, c_r = spec.unpack(g, shared)
        return pair_residual(k_l, c_l, k_r, c_r, g[:6], pose, obj, obs_v[0], obs_v[1])

    return view_residual


@functools.lru_cache(maxsize=None)
def view_linearize_for(spec: _Spec):
    """Residuals and Jacobian [d/dg, d/dpose] of one pair by the chain rule (as `mono.view_linearize_for`):
    per point the hand-written d q / d(k, coeffs, p_cam), the frame changes' derivatives once per view."""
    idx_l = [COEFF_NAMES.index(n) for n in spec.free_left]
    idx_r = [COEFF_NAMES.index(n) for n in spec.free_right]

    def linearize(g, pose, obs_v, shared):
        obj, k_l, c_l, k_r, c_r = spec.unpack(g, shared)
        n = obj.shape[0]
        eye = jnp.broadcast_to(jnp.eye(3), (n, 3, 3))
        board_rot = lambda rv: obj @ rodrigues(rv).T  # noqa: E731
        p_l = board_rot(pose[:3]) + pose[3:6]
        d_pose_l = jnp.concatenate([jax.jacfwd(board_rot)(pose[:3]), eye], axis=2)  # (n, 3, 6)
        rig_rot = lambda rv: p_l @ rodrigues(rv).T  # noqa: E731
        p_r = rig_rot(g[:3]) + g[3:6]
        d_rig_r = jnp.concatenate([jax.jacfwd(rig_rot)(g[:3]), eye], axis=2)  # (n, 3, 6)
        d_pose_r = jnp.einsum("ij,njk->nik", rodrigues(g[:3]), d_pose_l)
        q_l, dk_l, dc_l, dp_l = jax.vmap(project_jacobian, in_axes=(None, None, 0))(k_l, c_l, p_l)
        q_r, dk_r, dc_r, dp_r = jax.vmap(project_jacobian, in_axes=(None, None, 0))(k_r, c_r, p_r)
        mul = lambda a, b: jnp.einsum("nij,njk->nik", a, b)  # noqa: E731
        zeros = lambda cols: jnp.zeros((n, 2, cols))  # noqa: E731
        left = [zeros(6)]
        right = [mul(dp_r, d_rig_r)]
        if spec.joint:
            cam_l = [dk_l, dc_l[:, :, idx_l]]
            cam_r = [dk_r, dc_r[:, :, idx_r]]
            left += cam_l + [zeros(4 + len(idx_r))]
            right += [zeros(4 + len(idx_l))] + cam_r
        left.append(mul(dp_l, d_pose_l))
        right.append(mul(dp_r, d_pose_r))
        jac = jnp.concatenate([jnp.concatenate(left, axis=2), jnp.concatenate(right, axis=2)], axis=0)
        r = jnp.concatenate([(q_l - obs_v[0]).ravel(), (q_r - obs_v[1]).ravel()])
        return r, jac.reshape(4 * n, -1).T  # the solver takes the Jacobian transposed

    return linearize


@functools.lru_cache(maxsize=None)
def _full_solver(spec: _Spec, options: LMOptions):
    res, lin = view_residual_for(spec), view_linearize_for(spec)
    return jax.jit(lambda g0, p0, obs, shared, r_weight: solve_structured(res, g0, p0, obs, shared, options, lin,
                                                                        r_weight=r_weight),
                   compiler_options=COMPILE_OPTIONS)


@functools.lru_cache(maxsize=None)
def _batch_solver(spec: _Spec, options: LMOptions):
    res, lin = view_residual_for(spec), view_linearize_for(spec)

    def batch(g0, p0, obs, shared, r_weight):  # one start g0 for every problem
        return solve_structured_batch(res, jnp.broadcast_to(g0, (p0.shape[0], *g0.shape)), p0, obs, shared, options,
                                      lin, r_weight=r_weight)

    return jax.jit(batch, compiler_options=COMPILE_OPTIONS)


@functools.lru_cache(maxsize=None)
def _residuals_fn(spec: _Spec):
    """(C, V) pairs -> (C, V, 4n) residuals; the full set is C = 1."""
    per_view = jax.vmap(view_residual_for(spec), in_axes=(None, 0, 0, None))
    return jax.jit(jax.vmap(per_view, in_axes=(0, 0, 0, None)))


@jax.jit
def _rig_matrices(rig, k_left, k_right):
    """R, E, F of a rig vector (one compiled call instead of dozens of eager ones)."""
    E = essential_matrix(rig[:3], rig[3:6])
    return rodrigues(rig[:3]), E, fundamental_matrix(k_left, k_right, E)


@functools.lru_cache(maxsize=None)
def _normalised_points():
    one = jax.vmap(undistort, in_axes=(None, 0))
    return jax.jit(lambda k, coeffs, q: jax.vmap(one, in_axes=(None, 0))(coeffs, (q - k[2:4]) / k[0:2]))


# --- start ---------------------------------------------------------------------------------------------------


def board_poses(camera: Camera, obj: np.ndarray, obs: np.ndarray) -> np.ndarray:
    """(V, 6) T_cam_board of each view for a known camera: homography of the undistorted, normalised corners."""
    xy = np.asarray(_normalised_points()(camera.k, camera.dist.coeffs, jnp.asarray(obs, float)))
    return np.stack([pose_from_homography(homography(obj[:, :2], v), np.eye(3)) for v in xy])


def initial_rig(left: Camera, right: Camera, obj: np.ndarray, obs_left: np.ndarray,
                obs_right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rig (6,), board poses in the left camera (V, 6)): the median of the per-pair relative poses."""
    p_l, p_r = board_poses(left, obj, obs_left), board_poses(right, obj, obs_right)
    r_l, r_r = Rotation.from_rotvec(p_l[:, :3]), Rotation.from_rotvec(p_r[:, :3])
    r_rl = r_r * r_l.inv()
    t_rl = p_r[:, 3:] - r_rl.apply(p_l[:, 3:])
    rvecs = r_rl.as_rotvec()
    return np.concatenate([np.median(rvecs, axis=0), np.median(t_rl, axis=0)]), p_l


# --- full set --------------------------------------------------------------------------------------------------


@dataclass
class StereoSolution:
    """A stereo solve on one set of pairs. `values`/`std` follow `names` (rig first, then joint intrinsics)."""

    mode: str
    names: tuple[str, ...]
    values: np.ndarray  # (G,)
    std: np.ndarray  # (G,) Jacobian standard deviations
    cov: np.ndarray  # (G, G)
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
    def baseline_std(self) -> float:
        """Jacobian standard deviation of |T| (first-order propagation of the T covariance)."""
        return _norm_std(self.T, self.cov[3:6, 3:6])

    @property
    def angle_std(self) -> float:
        """Jacobian standard deviation of |rvec| (rad)."""
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


def _spec_for(mode: str, left: Camera, right: Camera) -> _Spec:
    if mode not in MODES:
        raise DstereoError(f"stereo mode '{mode}' is unknown; use one of {list(MODES)}")
    return _Spec(True, tuple(left.dist.free), tuple(right.dist.free)) if mode == "joint" else _Spec(False)


def _shared(obj, left: Camera, right: Camera):
    return (jnp.asarray(obj, float), jnp.asarray(left.k, float), jnp.asarray(left.dist.coeffs, float),
            jnp.asarray(right.k, float), jnp.asarray(right.dist.coeffs, float))


def _g0(spec: _Spec, rig: np.ndarray, left: Camera, right: Camera) -> np.ndarray:
    if not spec.joint:
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
    data = jnp.stack([jnp.asarray(obs_left), jnp.asarray(obs_right)], axis=1)  # (V, 2, n, 2)
    shared = _shared(obj, left, right)
    fixed = _Spec(False)
    mask = _pair_mask(inliers, obs_left.shape)
    r_w = jnp.asarray(pair_weights(mask))
    out = _full_solver(fixed, options)(jnp.asarray(rig0), jnp.asarray(poses0), data, shared, r_w)
    iterations = int(out.iterations)
    if spec.joint:
        out = _full_solver(spec, options)(jnp.asarray(_g0(spec, np.asarray(out.g), left, right)), out.p, data, shared,
                                          r_w)
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
    """(..., V, 2, n) corner mask -> (..., V, 4n) residual weights in `view_residual_for`'s order."""
    return np.repeat(mask.astype(float), 2, axis=-1).reshape(*mask.shape[:-2], -1)


def cameras_from(spec: _Spec, g: np.ndarray, left: Camera, right: Camera) -> tuple[Camera, Camera]:
    """The cameras a solution's shared vector describes (the inputs themselves in fixed mode)."""
    if not spec.joint:
        return left, right
    n_l = 4 + len(spec.free_left)
    return left.with_free_vector(jnp.asarray(g[6:6 + n_l])), right.with_free_vector(jnp.asarray(g[6 + n_l:]))


def _solution_from(out, spec: _Spec, mode: str, obj, data, left: Camera, right: Camera,
                   iterations: int, mask: np.ndarray) -> StereoSolution:
    g = out.g
    names = spec.names()
    cov = covariance(out.schur, float(out.sse), int(out.n_residuals), len(g) + out.p.size)
    cam_l, cam_r = cameras_from(spec, g, left, right)
    shared = _shared(obj, left, right)
    resid = np.asarray(_residuals_fn(spec)(jnp.asarray(g)[None], jnp.asarray(out.p)[None], data[None], shared))[0]
    n = obj.shape[0]
    resid = resid.reshape(len(out.p), 2, n, 2)
    R, E, F = (np.array(a) for a in _rig_matrices(jnp.asarray(g[:6]), cam_l.k, cam_r.k))
    return StereoSolution(
        mode=mode, names=names, values=g, std=np.sqrt(np.maximum(np.diag(cov), 0.0)), cov=cov, left=cam_l,
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
    chunk: int = 32,  # jaxlib 0.10.2 CPU deadlocks on this while-loop at 64-wide batches (mono.solve_subsets)
    options: LMOptions = LMOptions(lambda0=1e-6),
    progress=None,
) -> StereoSubsetSolutions:
    """Solve every subset of pairs in `plan` in fixed-size vmapped chunks, starting from the full-set solution
    (same mode and cameras as `start`); each subset converges to its own least-squares solution."""
    obj, obs_left, obs_right = (np.asarray(a, float) for a in (obj, obs_left, obs_right))
    _check_pairs(obj, obs_left, obs_right)
    spec = _spec_for(start.mode, start.left, start.right)
    index = plan.index
    n_sub, m = index.shape
    n_pad = (-n_sub) % chunk
    padded = np.concatenate([index, np.repeat(index[:1], n_pad, axis=0)]) if n_pad else index
    solver, residuals = _batch_solver(spec, options), _residuals_fn(spec)
    shared = _shared(obj, start.left, start.right)
    data = jnp.stack([jnp.asarray(obs_left), jnp.asarray(obs_right)], axis=1)
    poses, g0 = jnp.asarray(start.poses), jnp.asarray(start.values)
    mask = _pair_mask(start.inliers, obs_left.shape)  # the full set's outlier mask, in every subset
    r_w = jnp.asarray(pair_weights(mask))
    outs, re = [], []
    t0 = time.perf_counter()
    for c in range(0, len(padded), chunk):
        idx = jnp.asarray(padded[c: c + chunk])
        out = solver(g0, poses[idx], data[idx], shared, r_w[idx])
        w = np.asarray(r_w[idx])
        r = np.asarray(residuals(out.g, out.p, data[idx], shared)) * w  # (chunk, m, 4n), outliers zeroed
        re.append(np.mean(np.sqrt(np.sum(r ** 2, axis=2) / (np.sum(w, axis=2) / 2)), axis=1))
        outs.append(jax.tree_util.tree_map(np.array, out))
        if progress is not None:
            progress(min(c + chunk, n_sub), n_sub)
    out = jax.tree_util.tree_map(lambda *a: np.concatenate(a)[:n_sub], *outs)
    n_points = out.n_residuals / 2  # inlier corners of both cameras
    sigma2 = out.sse / (out.n_residuals - (out.g.shape[1] + 6 * m))
    cov = scaled_inverse(out.schur) * sigma2[:, None, None]
    norm_std = np.array([[_norm_std(g[3:6], c[3:6, 3:6]), _norm_std(g[0:3], c[0:3, 0:3])]
                         for g, c in zip(out.g, cov)])
    return StereoSubsetSolutions(
        plan=plan, names=start.names, values=out.g,
        std=np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0)), norm_std=norm_std,
        rms=np.sqrt(out.sse / n_points), stereo_re=np.concatenate(re)[:n_sub], iterations=out.iterations,
        status=out.status, timings={"solve_s": time.perf_counter() - t0},
    )


# --- folders -----------------------------------------------------------------------------------------------------


def camera_from_solution(sol: CameraSolution) -> Camera:
    """The `Camera` model of an individual calibration (its free set is what the joint mode refines)."""
    fx, fy, cx, cy = (float(v) for v in sol.values[:4])
    return Camera.create(fx, fy, cx, cy, sol.coeffs, sol.free, sol.image_size)


@dataclass
class StereoCalibrationResult:
    """Individual calibrations, the rig on all pairs and (optionally) on subsets of pairs. Nothing printed."""

    detection: StereoDetection  # the stereo pairs, their corners and the dropped pairs
    mono_left: CameraSolution  # individual calibrations (full set)
    mono_right: CameraSolution
    mono_detection_left: Detection  # the images the individual calibrations used
    mono_detection_right: Detection
    stereo: StereoSolution
    subsets: StereoSubsetSolutions | None = None
    timings: dict = field(default_factory=dict)

    @property
    def pairs(self) -> list[tuple[str, str]]:
        return self.detection.pairs

    @property
    def dropped(self) -> list[DroppedPair]:
        return self.detection.dropped

    def to_dict(self) -> dict:
        """JSON-ready summary: cameras, rig with Jacobian standard deviations, E, F, per-pair errors."""
        s = self.stereo
        cams = {side: {"fx": float(c.k[0]), "fy": float(c.k[1]), "cx": float(c.k[2]), "cy": float(c.k[3]),
                       "coeffs": dict(zip(COEFF_NAMES, map(float, c.dist.coeffs))), "free": list(c.dist.free),
                       "image_size": list(c.image_size)} for side, c in (("left", s.left), ("right", s.right))}
        out = {
            "mode": s.mode, "status": s.status_text, "iterations": s.iterations, "cameras": cams,
            "R": s.R, "rvec": s.rvec, "T": s.T, "E": s.E, "F": s.F,
            "parameters": {n: {"value": float(v), "std": float(e)} for n, v, e in zip(s.names, s.values, s.std)},
            "baseline": {"value": s.baseline, "std": s.baseline_std},
            "rotation_angle_rad": {"value": float(np.linalg.norm(s.rvec)), "std": s.angle_std},
            "rms_px": s.rms, "stereo_re_px": s.stereo_re, "conditioning": s.conditioning.message(),
            "pairs": [{"left": a, "right": b, "rms_px": float(e)} for (a, b), e in zip(self.pairs, s.per_pair_rms)],
            "dropped": [{"left": d.left, "right": d.right, "reason": d.reason} for d in self.dropped],
            "individual": {side: {"rms_px": m.rms, "status": m.status_text, "images": len(m.poses),
                                  **{n: {"value": float(v), "std": float(e)}
                                     for n, v, e in zip(m.names, m.values, m.std)}}
                           for side, m in (("left", self.mono_left), ("right", self.mono_right))},
        }
        if self.subsets is not None:
            sub, ok = self.subsets, self.subsets.converged
            cols = sub.columns()
            out["subsets"] = {"plan": sub.plan.describe(), "per_set": int(sub.plan.index.shape[1]),
                              "converged": int(ok.sum()), "total": len(ok),
                              **{k: {"mean": float(np.mean(v[ok])), "std": float(np.std(v[ok], ddof=1))}
                                 for k, v in cols.items() if ok.sum() > 1}}
        return out


def _calibrate_one(det: Detection, free: tuple[str, ...], side: str) -> CameraSolution:
    names = [n for n in det.names if n in det.corners] or sorted(det.corners)
    try:
        return calibrate_full(det.object_points, np.stack([det.corners[n] for n in names]), det.image_size, free)
    except DstereoError as exc:
        raise DstereoError(f"{side} camera: {exc}") from None


def calibrate_stereo_folders(
    left,
    right,
    pattern: tuple[int, int],
    square: float,
    free_left: tuple[str, ...] = PRESETS["default"],
    free_right: tuple[str, ...] = PRESETS["default"],
    per_set: int | None = None,
    *,
    mono_left=None,
    mono_right=None,
    mode: str = "fixed",
    cameras: tuple[Camera, Camera] | None = None,
    max_subsets: int = 2000,
    seed: int = 0,
    suffix: str | None = None,
    use_cache: bool = True,
    progress=None,
) -> StereoCalibrationResult:
    """Stereo calibration from image folders (or image lists), pairs matched by name (`io.pairing`).

    The individual calibrations use `mono_left`/`mono_right` when given (the thesis's images_left/right), else
    every image of `left`/`right` that shows the board; `cameras` skips them and fixes the intrinsics to the
    given models. Then the rig on all pairs (`mode` "fixed" or "joint") and, with `per_set` = m, on the
    C(pairs, m) subsets (at most `max_subsets`, seeded sample beyond). `progress(stage, done, total)` is called
    along the way. Errors (DstereoError): left/right counts differ, mixed image sizes in one camera, no pair
    with the board in both images, too few views.
    """
    report = (lambda stage: (lambda d, t: progress(stage, d, t))) if progress else (lambda stage: None)  # noqa: E731
    t0 = time.perf_counter()
    det = detect_pairs(left, right, pattern, square, suffix, use_cache, report("detect stereo pairs"))
    mono_dets = []
    for side, source, stereo_det in (("left", mono_left, det.left), ("right", mono_right, det.right)):
        if source is None:
            mono_dets.append(stereo_det)
            continue
        files = image_files(source, suffix)
        mono_det = detect_folder(files[0].parent, pattern, square, files=files, use_cache=use_cache,
                                 progress=report(f"detect {side}"))
        if mono_det.image_size != stereo_det.image_size:
            raise DstereoError(
                f"{side} camera: individual calibration images are {mono_det.image_size[0]}x{mono_det.image_size[1]} "
                f"but stereo images are {stereo_det.image_size[0]}x{stereo_det.image_size[1]}; one camera has one size"
            )
        mono_dets.append(mono_det)
    timings = {"detect_s": time.perf_counter() - t0}
    t1 = time.perf_counter()
    mono_l = _calibrate_one(mono_dets[0], tuple(free_left), "left")
    mono_r = _calibrate_one(mono_dets[1], tuple(free_right), "right")
    cam_l, cam_r = cameras if cameras is not None else (camera_from_solution(mono_l), camera_from_solution(mono_r))
    timings["individual_s"] = time.perf_counter() - t1
    obs_l, obs_r = det.observations()
    stereo = calibrate_stereo(det.object_points, obs_l, obs_r, cam_l, cam_r, mode)
    timings["stereo_s"] = stereo.timings["solve_s"]
    subsets = None
    if per_set is not None:
        plan = plan_subsets(len(det.pairs), per_set, cap=max_subsets, seed=seed)
        subsets = solve_stereo_subsets(det.object_points, obs_l, obs_r, plan, stereo, progress=report("subsets"))
        timings["subsets_s"] = subsets.timings["solve_s"]
    return StereoCalibrationResult(det, mono_l, mono_r, mono_dets[0], mono_dets[1], stereo, subsets, timings)
