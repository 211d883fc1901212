"""The covariance of what a pair file (stereo.yml) carries: both cameras' intrinsics and the pair's rig, from the
rig's one joint solve (`pair_covariance`)."""

from __future__ import annotations

import numpy as np


JOINT_STRUCTURE = "joint: both cameras and the rig from one joint solve (full-set)"


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
