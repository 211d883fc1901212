"""The covariance of what a pair file (stereo.yml) carries: both cameras' intrinsics and the pair's rig, from the
rig's one joint solve (`pair_covariance`); and how a fixed-intrinsics rig moves with its held intrinsics
(`rig_sensitivity`, the bound a test of the fixed-mode pair solver needs)."""

from __future__ import annotations

import numpy as np


JOINT_STRUCTURE = "joint: both cameras and the rig from one joint solve (full-set)"


def rig_sensitivity(obj, obs_left, obs_right, solution) -> np.ndarray:
    """A = d rig / d (left, right intrinsics) (6, G_l + G_r) of a fixed-intrinsics solve of two cameras (a
    `calib.solution.Solution`, mode "fixed", K = 2, every frame seen by both): how the rig that fits the
    pairs moves when the held intrinsics move, -S_rr^-1 S_rk with S the Schur complement of J^T J (board poses
    eliminated) of the pairs' residuals, at the solution."""
    import jax
    import jax.numpy as jnp

    from dstereo.models.rig import pair_residual

    (left, right), n_l = solution.cameras, len(solution.cameras[0].free_vector())
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


PAIR_STRUCTURE = ("joint (a rig of K cameras, K >= 2): both cameras' intrinsics and the pair's rig from the rig's one joint solve of "
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
    solve (`calib.solution.Solution`, mode "joint") carries, in stereo.yml's names (left.fx.., right..,
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
