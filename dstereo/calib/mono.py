"""One camera from chessboard views: full-set solve and the batched solve of every image subset.

The solver's shared vector is `Camera.free_vector()` = [fx, fy, cx, cy, <free distortion coefficients>];
each view contributes its pose (rvec, tvec). Compiled functions are cached per (free set, shapes), so a
test suite or a CLI run compiles each once.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from dstereo.calib.init_zhang import initial_guess
from dstereo.calib.subsets import SubsetPlan
from dstereo.calib.uncertainty import Conditioning, conditioning, covariance, scaled_inverse
from dstereo.errors import DstereoError
from dstereo.models.camera import INTRINSIC_NAMES, project
from dstereo.models.pose import rodrigues
from dstereo.models.distortion import COEFF_NAMES
from dstereo.solver.lm import STATUS_TEXT, LMOptions, solve_structured


@functools.lru_cache(maxsize=None)
def view_residual_for(free: tuple[str, ...]):
    """Residual of one view (2n,) for a given free distortion set; cached so jit sees one function."""
    free_idx = jnp.array([COEFF_NAMES.index(n) for n in free], dtype=int)

    def view_residual(g, pose, obs_v, shared):
        obj, base_coeffs = shared
        coeffs = base_coeffs.at[free_idx].set(g[4:]) if free else base_coeffs
        # One rotation per view, not per point: the pose Jacobian is then formed once, too.
        p_cam = obj @ rodrigues(pose[:3]).T + pose[3:6]
        q = jax.vmap(project, in_axes=(None, None, 0))(g[:4], coeffs, p_cam)
        return (q - obs_v).ravel()

    return view_residual


@functools.lru_cache(maxsize=None)
def view_linearize_for(free: tuple[str, ...]):
    """Residuals and Jacobian of one view by the chain rule: per point, reverse-mode d q / d(k, coeffs,
    p_cam) (2 outputs, so two backward passes), then d p_cam / d pose formed once per view. Several times
    faster than forward-mode through the whole view; `tests/test_engine.py` checks they agree."""
    free_idx = jnp.array([COEFF_NAMES.index(n) for n in free], dtype=int)

    def linearize(g, pose, obs_v, shared):
        obj, base_coeffs = shared
        coeffs = base_coeffs.at[free_idx].set(g[4:]) if free else base_coeffs
        rot_obj = lambda rvec: obj @ rodrigues(rvec).T  # noqa: E731
        p_cam = rot_obj(pose[:3]) + pose[3:6]
        d_rot = jax.jacfwd(rot_obj)(pose[:3])  # (n, 3, 3): d p_cam / d rvec
        q, (dk, dc, dp) = jax.vmap(_value_and_jacrev, in_axes=(None, None, 0))(g[:4], coeffs, p_cam)
        d_pose = jnp.concatenate([jnp.einsum("nij,njk->nik", dp, d_rot), dp], axis=2)  # (n, 2, 6)
        jac = jnp.concatenate([dk, dc[:, :, free_idx], d_pose], axis=2) if free else jnp.concatenate([dk, d_pose], 2)
        n = obj.shape[0]
        return (q - obs_v).ravel(), jac.reshape(2 * n, -1)

    return linearize


def _value_and_jacrev(k, coeffs, p_cam):
    q, vjp = jax.vjp(project, k, coeffs, p_cam)
    rows = jax.vmap(vjp)(jnp.eye(2))  # two backward passes: (2, 4), (2, 8), (2, 3)
    return q, rows


@functools.lru_cache(maxsize=None)
def _residuals_fn(free: tuple[str, ...]):
    return jax.jit(jax.vmap(view_residual_for(free), in_axes=(None, 0, 0, None)))


@functools.lru_cache(maxsize=None)
def _full_solver(free: tuple[str, ...], options: LMOptions):
    res, lin = view_residual_for(free), view_linearize_for(free)
    return jax.jit(lambda g0, p0, obs, shared: solve_structured(res, g0, p0, obs, shared, options, lin))


@functools.lru_cache(maxsize=None)
def _batch_solver(free: tuple[str, ...], options: LMOptions):
    res, lin = view_residual_for(free), view_linearize_for(free)
    one = lambda g0, p0, obs, shared: solve_structured(res, g0, p0, obs, shared, options, lin)  # noqa: E731
    return jax.jit(jax.vmap(one, in_axes=(None, 0, 0, None)))


@dataclass
class CameraSolution:
    """A solve on one set of views. Values and standard deviations are keyed by parameter name."""

    names: tuple[str, ...]
    values: np.ndarray  # (G,) shared parameters in `names` order
    std: np.ndarray  # (G,) Jacobian standard deviations
    cov: np.ndarray  # (G, G)
    coeffs: np.ndarray  # (8,) all distortion coefficients, OpenCV order
    poses: np.ndarray  # (V, 6) rvec, tvec per view
    rms: float  # sqrt(SSE / points), OpenCV's reprojection error
    per_view_rms: np.ndarray  # (V,)
    residuals: np.ndarray  # (V, n, 2) observed - projected... sign: projected - observed
    iterations: int
    status: int
    conditioning: Conditioning
    free: tuple[str, ...]
    image_size: tuple[int, int]
    timings: dict = field(default_factory=dict)

    @property
    def converged(self) -> bool:
        return self.status > 0

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
) -> CameraSolution:
    """Calibrate from all views: closed-form start, then the structured LM to convergence."""
    obj, obs = np.asarray(obj, float), np.asarray(obs, float)
    _check_views(obj, obs)
    t0 = time.perf_counter()
    k0, p0 = initial_guess(obj, obs, image_size)
    g0 = np.concatenate([k0, np.zeros(len(free))])
    shared = (jnp.asarray(obj), jnp.zeros(8))
    out = _full_solver(tuple(free), options)(jnp.asarray(g0), jnp.asarray(p0), jnp.asarray(obs), shared)
    out = jax.tree_util.tree_map(np.asarray, out)
    sol = _solution_from(out, obj, obs, tuple(free), image_size)
    sol.timings["solve_s"] = time.perf_counter() - t0
    if not np.isfinite(sol.rms):
        raise DstereoError(
            f"calibration failed ({STATUS_TEXT[sol.status]}); check the pattern size and remove images whose "
            "corners are ordered differently"
        )
    return sol  # may be unconverged (sol.status < 0): callers report it, never hide it


def _solution_from(out, obj, obs, free, image_size) -> CameraSolution:
    names = INTRINSIC_NAMES + tuple(free)
    g = out.g
    coeffs = np.zeros(8)
    coeffs[[COEFF_NAMES.index(n) for n in free]] = g[4:]
    n_params = len(g) + out.p.size
    cov = covariance(out.schur, float(out.sse), int(out.n_residuals), n_params)
    resid = np.asarray(_residuals_fn(tuple(free))(jnp.asarray(g), jnp.asarray(out.p), jnp.asarray(obs), (jnp.asarray(obj), jnp.zeros(8))))
    resid = resid.reshape(obs.shape)
    n_points = obs.shape[0] * obs.shape[1]
    return CameraSolution(
        names=names, values=g, std=np.sqrt(np.maximum(np.diag(cov), 0.0)), cov=cov, coeffs=coeffs, poses=out.p,
        rms=float(np.sqrt(out.sse / n_points)),
        per_view_rms=np.sqrt(np.mean(np.sum(resid ** 2, axis=2), axis=1)),
        residuals=resid, iterations=int(out.iterations), status=int(out.status),
        conditioning=conditioning(out.schur, names), free=free, image_size=tuple(image_size),
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
    chunk: int = 32,  # jaxlib 0.10.2 CPU deadlocks on this while-loop at 64 x 17 views (README)
    options: LMOptions = LMOptions(lambda0=1e-6),
    progress=None,
) -> SubsetSolutions:
    """Refine every subset of `plan` in fixed-size vmapped chunks, starting from the full-set solution.

    Starting at the full-set optimum puts every subset a few iterations from its own optimum; each subset
    still converges to its own least-squares solution (tests check this against cv2.calibrateCamera).
    """
    free = start.free
    index = plan.index
    n_sub, m = index.shape
    n_pad = (-n_sub) % chunk
    padded = np.concatenate([index, np.repeat(index[:1], n_pad, axis=0)]) if n_pad else index
    solver = _batch_solver(tuple(free), options)
    shared = (jnp.asarray(obj, float), jnp.zeros(8))
    obs_j, poses_j, g0 = jnp.asarray(obs, float), jnp.asarray(start.poses), jnp.asarray(start.values)
    outs = []
    t0 = time.perf_counter()
    for c in range(0, len(padded), chunk):
        idx = jnp.asarray(padded[c: c + chunk])
        out = solver(g0, poses_j[idx], obs_j[idx], shared)
        outs.append(jax.tree_util.tree_map(np.asarray, out))
        if progress is not None:
            progress(min(c + chunk, n_sub), n_sub)
    out = jax.tree_util.tree_map(lambda *a: np.concatenate(a)[:n_sub], *outs)
    n_points = m * obj.shape[0]
    n_params = len(g0) + 6 * m
    sigma2 = out.sse / (out.n_residuals - n_params)
    cov_diag = np.diagonal(scaled_inverse(out.schur), axis1=1, axis2=2)
    return SubsetSolutions(
        plan=plan, names=start.names, values=out.g, std=np.sqrt(np.maximum(cov_diag * sigma2[:, None], 0.0)),
        rms=np.sqrt(out.sse / n_points), iterations=out.iterations, status=out.status,
        timings={"solve_s": time.perf_counter() - t0},
    )
