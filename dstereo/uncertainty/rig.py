"""The covariance of what stereo.yml carries (both cameras' intrinsics and the rig), for a finished stereo
calibration job: the joint solve's, or in fixed mode the individual calibrations' carried into the rig through
the rig's sensitivity to the held intrinsics."""

from __future__ import annotations

import numpy as np


FIXED_STRUCTURE = ("fixed mode, propagated: each camera's intrinsics covariance from its individual (mono) full-set "
                   "solve (left and right independent), and the rig's as the fixed-intrinsics stereo solve's plus the "
                   "intrinsics errors carried into the rig (A C_k A^T, A = d rig / d intrinsics at the stereo "
                   "optimum), "
                   "with the cross terms A C_k; assumes the stereo corners' noise independent of the individual "
                   "solves'. Values in this file are the final ones; the covariance is that of the solves on the "
                   "surviving views and pairs (the full-set solves when all survive)")
BLOCK_STRUCTURE = ("block-diagonal (left, right, rig): each camera's intrinsics from its individual (mono) full-set "
                   "solve, the rig from the stereo solve with the intrinsics held fixed; no correlations")
JOINT_STRUCTURE = "joint: both cameras and the rig from one joint solve (full-set)"


def rig_sensitivity(obj, obs_left, obs_right, solution) -> np.ndarray:
    """A = d rig / d (left, right intrinsics) (6, G_l + G_r) of a fixed-intrinsics stereo solve: how the rig
    that fits the pairs moves when the held intrinsics move, -S_rr^-1 S_rk with S the Schur complement of
    J^T J (board poses eliminated) of the pairs' residuals, at the solution."""
    import jax
    import jax.numpy as jnp

    from dstereo.models.rig import pair_residual

    left, right, n_l = solution.left, solution.right, len(solution.left.free_vector())
    per_pair = jax.vmap(pair_residual, in_axes=(None, None, None, None, None, 0, None, 0, 0))
    obj, obs_l, obs_r = (jnp.asarray(a, float) for a in (obj, obs_left, obs_right))

    def residuals(x):
        cam_l, cam_r = left.with_free_vector(x[6:6 + n_l]), right.with_free_vector(x[6 + n_l:x.size - poses.size])
        return per_pair(cam_l.k, cam_l.dist.coeffs, cam_r.k, cam_r.dist.coeffs, x[:6],
                        x[x.size - poses.size:].reshape(-1, 6), obj, obs_l, obs_r).ravel()

    poses = np.asarray(solution.poses, float)
    x = np.concatenate([solution.values[:6], np.asarray(left.free_vector()), np.asarray(right.free_vector()),
                        poses.ravel()])
    jac = np.asarray(jax.jit(jax.jacfwd(residuals))(jnp.asarray(x)))
    scale = np.linalg.norm(jac, axis=0)
    jac = jac / scale  # Jacobi scaling: fx (px) next to k3 spans many decades
    n_g = x.size - poses.size
    jg, jp = jac[:, :n_g], jac[:, n_g:]
    schur = jg.T @ jg - jg.T @ jp @ np.linalg.solve(jp.T @ jp, jp.T @ jg)
    a = -np.linalg.solve(schur[:6, :6], schur[:6, 6:])
    return a * scale[:6, None] ** -1 * scale[None, 6:n_g]


def rig_covariance(job, propagate: bool = True, solution=None, pairs=None,
                   cameras=None) -> tuple[tuple[str, ...], np.ndarray, str]:
    """(names, covariance, structure) of every parameter stereo.yml carries: left.fx.., right.fx.., RVx..Tz.

    Mode "joint": the joint solve's covariance, reordered. Mode "fixed" (the thesis's path): the intrinsics come
    from the individual calibrations (left and right independent); the rig was fitted with them held, so their
    errors move it: cov(rig) = C_rig|k + A C_k A^T and cov(rig, k) = A C_k (`rig_sensitivity`). Without that
    (`propagate=False`, block-diagonal) the rig cannot absorb a principal-point error and the point sigmas come
    out several times too large (measured in the report of this change).
    """
    s = job.full if solution is None else solution
    if s.mode == "joint":
        names = tuple(n for n in s.names if not n.startswith(("left.", "right.")))
        order = [i for i, n in enumerate(s.names) if n.startswith("left.")] + \
            [i for i, n in enumerate(s.names) if n.startswith("right.")] + [s.names.index(n) for n in names]
        return tuple(s.names[i] for i in order), s.cov[np.ix_(order, order)], JOINT_STRUCTURE
    from scipy.linalg import block_diag

    from dstereo.uncertainty.view_effects import reported_covariance

    # `cameras`: the CameraSolutions whose covariance goes with the intrinsics used (default the full sets');
    # `pairs`: (V,) bool of the pairs `solution` was solved on (default all)
    left, right = cameras if cameras is not None else (job.left.full, job.right.full)
    # each camera's covariance as its own files report it (with the views' effects, `view_effects`), of its
    # intrinsics: a camera's own board sag is not the rig's (the rig holds the two cameras' mean, `rig_board_sag`)
    keep = [[i for i, n in enumerate(c.names) if not n.startswith("board_sag")] for c in (left, right)]
    names = (tuple(f"left.{left.names[i]}" for i in keep[0]) + tuple(f"right.{right.names[i]}" for i in keep[1])
             + tuple(s.names))
    c_k = block_diag(*(reported_covariance(c)[np.ix_(k, k)] for c, k in zip((left, right), keep)))
    if not propagate:
        return names, block_diag(c_k, s.cov), BLOCK_STRUCTURE
    obs_l, obs_r = job.detection.observations()
    if pairs is not None:
        obs_l, obs_r = obs_l[pairs], obs_r[pairs]
    a = rig_sensitivity(job.detection.object_points, obs_l, obs_r, s)
    cross = a @ c_k
    return names, np.block([[c_k, cross.T], [cross, s.cov + cross @ a.T]]), FIXED_STRUCTURE



PAIR_STRUCTURE = ("joint (N cameras): both cameras' intrinsics and the pair's rig from the rig's one joint solve of "
                  "every camera and frame (with the frames' effects), the pair's R, T propagated to first order "
                  "from the two cameras' placements in the reference")


def _relative(ext_a, ext_b):
    """(rvec, T) of camera b in camera a from both cameras' T_k_ref 6-vectors: x_b = R x_a + T."""
    import jax.numpy as jnp

    from dstereo.models.pose import log_rotation, rodrigues

    r_a, r_b = rodrigues(ext_a[:3]), rodrigues(ext_b[:3])
    r = r_b @ r_a.T
    return jnp.concatenate([log_rotation(r), ext_b[3:] - r @ ext_a[3:]])


def pair_covariance(solution, a: int, b: int) -> tuple[tuple[str, ...], np.ndarray, str]:
    """(names, covariance, structure) of what a stereo file of cameras a (left) and b (right) of a K-camera joint
    solve (`calib.multiview.MultiviewSolution`, mode "joint") carries, in stereo.yml's names (left.fx.., right..,
    RVx..Tz): the solve's covariance mapped through the linear map L from its parameters (intrinsics picked, the
    pair's rig d(R_ab, T_ab)/d(placements of a and b) by autodiff): L C L'. So a reconstruction from a `--cameras`
    pair file carries the intrinsics' and the rig's uncertainty, as one from `--left/--right`."""
    import jax

    from dstereo.models.rig import RIG_NAMES

    if solution.mode != "joint":
        raise ValueError("pair_covariance: a joint solve (intrinsics refined) carries the intrinsics' covariance")
    index = {n: i for i, n in enumerate(solution.names)}
    labels = solution.labels
    rows, names = [], []
    for side, c in (("left", a), ("right", b)):
        prefix = f"{labels[c]}."
        own = [n for n in solution.names if n.startswith(prefix) and n[len(prefix):] not in RIG_NAMES]
        for n in own:
            row = np.zeros(len(solution.names))
            row[index[n]] = 1.0
            rows.append(row)
            names.append(f"{side}.{n[len(prefix):]}")
    ext = np.concatenate([solution.rvecs, solution.T], axis=1)
    jac = np.asarray(jax.jacfwd(lambda x: _relative(x[:6], x[6:]))(np.concatenate([ext[a], ext[b]])))  # (6, 12)
    rig_rows = np.zeros((6, len(solution.names)))
    for block, c in ((jac[:, :6], a), (jac[:, 6:], b)):
        if c == 0:  # the reference's placement is fixed (zero), not a parameter
            continue
        cols = [index[f"{labels[c]}.{n}"] for n in RIG_NAMES]
        rig_rows[:, cols] += block
    lin = np.vstack([np.array(rows).reshape(-1, len(solution.names)), rig_rows])
    return tuple(names) + tuple(RIG_NAMES), lin @ np.asarray(solution.cov, float) @ lin.T, PAIR_STRUCTURE
