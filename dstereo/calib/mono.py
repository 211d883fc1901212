"""One camera from chessboard views: full-set solve and the batched solve of every image subset.

The solver's shared vector is `Camera.free_vector()` = [fx, fy, cx, cy, <free distortion coefficients>];
each view contributes its pose (rvec, tvec): the K = 1 case of `calib/problem.py`, whose compiled solver (cached
per free set and shapes) serves the full set and every subset.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from dstereo.calib.init_fisheye import initial_guess_fisheye
from dstereo.calib.init_zhang import initial_guess
from dstereo.calib.subset_solve import SubsetStart, solve_frame_subsets
from dstereo.calib.solution import Solution, per_view_rms
from dstereo.calib.subsets import SubsetPlan, SubsetSolutions
from dstereo.uncertainty.covariance import conditioning, covariance, scaled_inverse
from dstereo.errors import DstereoError
from dstereo.calib.problem import (WARP_NAMES, WARP_SIZE, Problem, chunk_rows, frame_linearize, frame_residual, lens_functions,  # noqa: F401
                                   residual_weights, run, shared_data)
from dstereo.models.camera import INTRINSIC_NAMES, Camera
from dstereo.models.distortion import Distortion, coeff_slots, lens_model
from dstereo.solver.lm import STATUS_TEXT, LMOptions


def _problem(free: tuple[str, ...], board_warp: bool = False) -> Problem:
    return Problem.of([tuple(free)], board_warp=board_warp)


def view_residual_for(free: tuple[str, ...]):
    """One view's residuals (2n,) as (g, pose, obs (n, 2), (obj, coeffs (8,))): the problem's frame, K = 1."""
    res = frame_residual(_problem(free))
    return lambda g, pose, obs_v, shared: res(g, pose, obs_v[None], (shared[0], jnp.zeros((1, 4)), shared[1][None]))


def view_linearize_for(free: tuple[str, ...]):
    """`view_residual_for`'s residuals and transposed Jacobian (G + 6, 2n) (`problem.frame_linearize`)."""
    lin = frame_linearize(_problem(free))
    return lambda g, pose, obs_v, shared: lin(g, pose, obs_v[None], (shared[0], jnp.zeros((1, 4)), shared[1][None]))


def _shared(obj: np.ndarray):
    return shared_data(obj, np.zeros(4), np.zeros(8))


def _residual_weights(inliers: np.ndarray) -> np.ndarray:
    """(..., V, n) corner inlier mask -> (..., V, 2n) residual weights in the residual's (x, y) per point order."""
    return residual_weights(np.asarray(inliers)[..., None, :])


def _run(free, options, g0, p0, obs, weight, lambda0, shared, normal0=None, r_weight=None, board_warp=None,
         rows=None):
    """`problem.run` for one camera: obs (B, V, n, 2) as K = 1 frames."""
    # a device array comes from `solve_subsets`, already put there as K = 1 frames (B, V, 1, n, 2)
    obs = obs if isinstance(obs, jax.Array) else np.asarray(obs, float)[:, :, None]
    # the shared vector's length tells whether it carries the board's sag (4 + free, or 2 more)
    warp = np.shape(g0)[-1] == 4 + len(free) + WARP_SIZE if board_warp is None else board_warp
    return run(_problem(free, warp), options, g0, p0, obs, weight, lambda0, shared, normal0,
               np.ones(np.shape(weight) + (2 * np.shape(obs)[3],)) if r_weight is None else r_weight, rows)


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
    board_warp: bool = False,
    alone: bool = False,
) -> Solution:
    """Calibrate from all views: closed-form start, then the structured LM to convergence.

    `inliers` (V, n) bool: corners to fit (the others, outliers, weigh 0; default all). `start`: (shared vector,
    (V, 6) poses) of the same views to start from (an earlier mask's solve) instead of the closed form.
    `board_warp`: solve the board's sag too (`problem.sag_basis`; two more shared parameters, last).
    `alone`: no masked subsets of these views follow (none, or gathered ones), so the solve runs in a program of
    its own for one problem instead of padded to the subsets' chunk (16 copies computed); default False shares
    the subsets' program (one compile)."""
    obj, obs = np.asarray(obj, float), np.asarray(obs, float)
    _check_views(obj, obs)
    t0 = time.perf_counter()
    mask = np.ones(obs.shape[:2], bool) if inliers is None else np.asarray(inliers, bool)
    if start is not None:
        g0, p0, lam = np.asarray(start[0], float), np.asarray(start[1], float), 1e-6
        if board_warp and len(g0) == 4 + len(free):
            g0 = np.concatenate([g0, np.zeros(WARP_SIZE)])
    else:
        fish = lens_model(tuple(free)) in ("fisheye", "splined")
        # Zhang's homographies assume a pinhole; a fisheye starts from the equidistant lens that best fits the views
        # (and so does the splined lens, whose stereographic base matches the equidistant one near the axis, and
        # which may be a fisheye)
        k0, p0 = initial_guess_fisheye(obj, obs, image_size) if fish else initial_guess(obj, obs, image_size)
        g0, lam = np.concatenate([k0, np.zeros(len(free) + WARP_SIZE * board_warp)]), options.lambda0
    shared = _shared(obj)
    # A view without inlier corners (rejected whole) takes no part: weight 0, its pose carried unchanged
    out = _run(free, options, g0[None], p0[None], obs[None], mask.any(axis=1)[None].astype(float), np.array([lam]),
               shared, r_weight=_residual_weights(mask)[None], rows=1 if alone else None)
    out = jax.tree_util.tree_map(lambda a: a[0], out)
    sol = _solution_from(out, obj, obs, tuple(free), image_size, mask)
    sol.timings["solve_s"] = time.perf_counter() - t0
    if not np.isfinite(sol.rms):
        raise DstereoError(
            f"calibration failed ({STATUS_TEXT[sol.status]}); check the pattern size and remove images whose "
            "corners are ordered differently"
        )
    return sol  # may be unconverged (sol.status < 0): callers report it, never hide it


def _solution_from(out, obj, obs, free, image_size, mask) -> Solution:
    """The K = 1 `Solution`: the camera's views as frames of one camera, its names without a camera label."""
    warp = len(out.g) == 4 + len(free) + WARP_SIZE
    names = INTRINSIC_NAMES + tuple(free) + (WARP_NAMES if warp else ())
    g = out.g
    coeffs = np.zeros(len(coeff_slots(free)))  # 8, or a splined lens's knots
    coeffs[[coeff_slots(free).index(n) for n in free]] = g[4:4 + len(free)]
    n_params = len(g) + 6 * int(mask.any(axis=1).sum())
    cov = covariance(out.schur, float(out.sse), int(out.n_residuals), n_params)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    resid = np.asarray(out.residuals).reshape(obs.shape)[:, None]  # (V, 1, n, 2)
    visible = np.ones((len(obs), 1), bool)
    camera = Camera(jax.device_put(np.array(g[:4], float)), Distortion(jax.device_put(coeffs), tuple(free)),
                    tuple(image_size))
    return Solution(
        names=names, values=g, std=std, cov=cov, cameras=[camera], rvecs=np.zeros((1, 3)), T=np.zeros((1, 3)),
        poses=out.p, visible=visible, rms=float(np.sqrt(out.sse / max(int(mask.sum()), 1))),
        per_view_rms=per_view_rms(resid, mask[:, None], visible), residuals=resid, iterations=int(out.iterations),
        status=int(out.status), normal=np.asarray(out.normal),
        conditioning=conditioning(out.schur, names, g, std, image_size),
        inliers=None if mask.all() else mask[:, None], std_jacobian=std,
    )


def solve_subsets(
    obj: np.ndarray,
    obs: np.ndarray,
    plan: SubsetPlan,
    start: Solution,
    options: LMOptions = LMOptions(lambda0=1e-6),
    progress=None,
    n_threads: int | None = None,
    plan_size: int | None = None,
) -> SubsetSolutions:
    """Refine every subset of `plan` in fixed-size vmapped chunks, starting from the full-set solution.

    Starting at the full-set optimum puts every subset a few iterations from its own optimum; each subset
    still converges to its own least-squares solution (tests check this against cv2.calibrateCamera).
    How (masked or gathered frames, chunks, threads, the start's linearisation reused): `subset_solve`.

    A board sag solved by the full set is HELD there in the subsets: the board is one physical object in every
    view, so its shape is best known from all of them, and a subset re-estimating it from m views would add only
    its estimation noise to the camera's parameters (the thesis's subsets held it too, at zero). The subsets then
    solve the flat problem on the sagged board: the same corners, the full set's linearisation without the two sag
    rows (exact: the same point), and each pass ~30 % cheaper (4845 subsets 2.28 -> 1.75 s measured with the sag
    solved and on a flat board). Their sag columns hold the full set's value with std 0.
    """
    index = np.asarray(plan.index)
    m = index.shape[1]
    obs = np.asarray(obs, float)
    # The full set's outlier mask: a corner rejected there is left out of every subset too
    r_weight = _residual_weights(np.ones(obs.shape[:2], bool) if start.inliers is None else start.inliers[:, 0])
    normal = None if start.normal is None else (start.residuals.reshape(len(obs), -1), start.normal)
    free = tuple(start.camera().dist.free)
    values, sag = np.asarray(start.values, float), start.board_sag
    if sag is not None:
        from dstereo.calib.problem import sagged_board

        obj = sagged_board(obj, sag)
        g = len(values)
        keep = np.r_[np.arange(g - WARP_SIZE), np.arange(g, start.normal.shape[-1])] if normal is not None else None
        normal = None if normal is None else (normal[0], normal[1][:, keep][:, :, keep])
        values = values[:-WARP_SIZE]
    t0 = time.perf_counter()
    out = solve_frame_subsets(_problem(free), obs[:, None], r_weight, _shared(obj), index,
                              SubsetStart(values, start.poses, normal), options, progress, n_threads, plan_size)
    n_points = out.n_residuals / 2  # inlier corners, views counted with their weights
    n_params = len(values) + 6 * m
    sigma2 = out.sse / (out.n_residuals - n_params)
    cov_diag = np.diagonal(scaled_inverse(out.schur), axis1=1, axis2=2)
    std = np.sqrt(np.maximum(cov_diag * sigma2[:, None], 0.0))
    g_out = np.asarray(out.g)
    if sag is not None:
        g_out = np.c_[g_out, np.repeat(np.asarray(sag, float)[None], len(g_out), 0)]
        std = np.c_[std, np.zeros((len(std), WARP_SIZE))]
    return SubsetSolutions(
        plan=plan, names=start.names, values=g_out, std=std,
        rms=np.sqrt(out.sse / n_points), iterations=out.iterations, status=out.status,
        timings={"solve_s": time.perf_counter() - t0},
    )
