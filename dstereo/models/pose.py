"""Rigid pose as an axis-angle (Rodrigues) vector plus translation: `T_cam_world`, maps world -> camera."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


def rodrigues(rvec: Float[Array, "3"], xp=jnp) -> Float[Array, "3 3"]:
    """Rotation matrix of an axis-angle vector, with finite value and gradient at zero rotation.

    Near zero the series of sin(t)/t and (1-cos t)/t^2 replaces the closed form; the double `where` keeps
    the unused branch from producing NaN gradients. `xp=np` evaluates the same formulas in numpy (host-side
    helpers below: no program to trace and fetch in a new process).
    """
    t2 = xp.dot(rvec, rvec)
    small = t2 < 1e-12
    t2_safe = xp.where(small, 1.0, t2)
    t = xp.sqrt(t2_safe)
    a = xp.where(small, 1.0 - t2 / 6.0, xp.sin(t) / t)
    b = xp.where(small, 0.5 - t2 / 24.0, (1.0 - xp.cos(t)) / t2_safe)
    kx = xp.array([
        [0.0, -rvec[2], rvec[1]],
        [rvec[2], 0.0, -rvec[0]],
        [-rvec[1], rvec[0], 0.0],
    ])
    return xp.eye(3) + a * kx + b * (kx @ kx)


def rodrigues_jacobian(rvec: Float[Array, "3"]) -> tuple[Float[Array, "3 3"], Float[Array, "3 3 3"]]:
    """`rodrigues(rvec)` and d R_ij / d rvec_k, written out elementwise (no matrix products).

    R = c I + a K + b r r' with a = sin t / t, b = (1 - cos t) / t^2, c = cos t, K = [r]x, t^2 = r.r; every
    coefficient is a function of s = t^2, so d/d r_k = 2 r_k d/ds. Solvers linearise every view with this;
    by hand it traces and compiles several times faster than `jax.jacfwd(rodrigues)` (tests compare them).
    """
    s = jnp.sum(rvec * rvec)
    small = s < 1e-8
    s_safe = jnp.where(small, 1.0, s)
    t = jnp.sqrt(s_safe)
    # Series below t = 1e-4 (truncation ~ s^3 / 5040); the closed forms lose < 1e-8 relative above it.
    a = jnp.where(small, 1.0 - s / 6.0 + s * s / 120.0, jnp.sin(t) / t)
    b = jnp.where(small, 0.5 - s / 24.0 + s * s / 720.0, (1.0 - jnp.cos(t)) / s_safe)
    da = jnp.where(small, -1.0 / 6.0 + s / 60.0, (jnp.cos(t) - a) / (2.0 * s_safe))  # d a / d s
    db = jnp.where(small, -1.0 / 24.0 + s / 360.0, (0.5 * a - b) / s_safe)  # d b / d s
    eye = np.eye(3)
    kmat = -(_EPS[:, :, 0] * rvec[0] + _EPS[:, :, 1] * rvec[1] + _EPS[:, :, 2] * rvec[2])  # [r]x
    rr = rvec[:, None] * rvec[None, :]
    rot = (1.0 - b * s) * eye + a * kmat + b * rr  # cos t = 1 - b s
    # d/d r_k of each coefficient is 2 r_k d/ds (d cos t / ds = -a / 2); d K_ij / d r_k = -eps_ijk
    d_rot = (2.0 * (-0.5 * a * eye + da * kmat + db * rr)[:, :, None] * rvec[None, None, :] - a * _EPS
             + b * (eye[:, None, :] * rvec[None, :, None] + rvec[:, None, None] * eye[None, :, :]))
    return rot, d_rot


_EPS = np.zeros((3, 3, 3))  # Levi-Civita symbol
for _i, _j, _k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    _EPS[_i, _j, _k], _EPS[_i, _k, _j] = 1.0, -1.0


def _log_rotation(rmat, xp):
    """Axis-angle vector of a rotation matrix (angle in [0, pi]), the one inverse of `rodrigues`.

    Below ~120 degrees (trace >= every diagonal entry) theta = atan2(|w|, (tr - 1) / 2) on the skew part w,
    accurate to rounding at small angles (arccos of the trace is not); above it the skew part vanishes at pi,
    so the axis comes from the unit quaternion divided by its largest vector component (Shepperd), accurate
    up to and at 180 degrees. Unused branches see safe inputs, so gradients stay finite (also at identity).
    `xp`: jax.numpy (`log_rotation`) or numpy (`rotation_vector`), the same formulas.
    """
    tr = xp.trace(rmat)
    diag = xp.diagonal(rmat)
    near_pi = xp.max(diag) > tr
    axis = xp.argmax(diag)
    small_angle = _log_small_angle(rmat, xp)
    candidates = xp.stack([_log_from_axis(rmat, tr, a, near_pi & (axis == a), xp) for a in range(3)])
    return xp.where(near_pi, candidates[axis], small_angle)


@jax.jit
def log_rotation(rmat: Float[Array, "3 3"]) -> Float[Array, "3"]:
    """Axis-angle vector of a rotation matrix (angle in [0, pi]), the one inverse of `rodrigues` (`_log_rotation`)."""
    return _log_rotation(rmat, jnp)


def _log_small_angle(rmat, xp):
    w = 0.5 * xp.array([rmat[2, 1] - rmat[1, 2], rmat[0, 2] - rmat[2, 0], rmat[1, 0] - rmat[0, 1]])
    s2 = w @ w
    small = s2 < 1e-24  # series of theta / sin(theta); the double `where` keeps gradients finite at identity
    s = xp.sqrt(xp.where(small, 1.0, s2))
    theta = xp.arctan2(s, 0.5 * (xp.trace(rmat) - 1.0))
    return w * xp.where(small, 1.0 + s2 / 6.0, theta / s)


def _log_from_axis(rmat, tr, a: int, selected, xp):
    """Shepperd's quaternion (w, v) from its component v[a] (the largest), then 2 atan2(|v|, w) v / |v|."""
    b, c = (a + 1) % 3, (a + 2) % 3
    m = xp.where(selected, 1.0 + 2.0 * rmat[a, a] - tr, 1.0)  # > 1 when selected: 4 v[a]^2 >= 1
    va = 0.5 * xp.sqrt(m)
    parts = {a: va, b: (rmat[b, a] + rmat[a, b]) / (4.0 * va), c: (rmat[c, a] + rmat[a, c]) / (4.0 * va)}
    v = xp.stack([parts[0], parts[1], parts[2]])
    w = (rmat[c, b] - rmat[b, c]) / (4.0 * va)
    sign = xp.where(w < 0, -1.0, 1.0)  # the quaternion with w >= 0: angle in [0, pi]
    w, v = sign * w, sign * v
    s = xp.sqrt(v @ v)  # >= 1/2 here
    return v * (2.0 * xp.arctan2(s, w) / s)


def rotation_matrix(rvec) -> np.ndarray:
    """Host side: `rodrigues` as a writable numpy (3, 3), the same formulas in numpy (~10 us a call; a compiled
    JAX call costs about that too, but its first call in a process traces and fetches a program: ~0.1 s of a new
    process's calibration, measured, as does `rotation_vector`'s)."""
    return np.array(rodrigues(np.asarray(rvec, float).reshape(3), np), float)


def rotation_vector(rmat) -> np.ndarray:
    """Host side: `log_rotation` as a writable numpy (3,), the same formulas in numpy."""
    return np.array(_log_rotation(np.asarray(rmat, float).reshape(3, 3), np), float)


_log_many = jax.jit(jax.vmap(log_rotation))


def rotation_vectors(rmats) -> np.ndarray:
    """Host side: `log_rotation` of (..., 3, 3) matrices at once, as a writable numpy (..., 3). The matrices are
    padded with identities to a power of two (a program per size compiled ~0.1-0.5 s each, and a calibration
    passes a few counts: views, frames, subsets), numpy in (jnp.asarray compiles a staging program per shape)."""
    rmats = np.asarray(rmats, float)
    flat = rmats.reshape(-1, 3, 3)
    n = len(flat)
    size = 1 << max(n - 1, 0).bit_length()
    padded = np.concatenate([flat, np.broadcast_to(np.eye(3), (size - n, 3, 3))]) if size > n else flat
    return np.array(_log_many(np.ascontiguousarray(padded)), float)[:n].reshape(*rmats.shape[:-2], 3)


def transform(rvec: Float[Array, "3"], tvec: Float[Array, "3"], p: Float[Array, "3"]) -> Float[Array, "3"]:
    """R(rvec) p + t for one point."""
    return rodrigues(rvec) @ p + tvec


class Pose(eqx.Module):
    """`T_cam_world`: rvec (3,) axis-angle, tvec (3,) in the board/world unit."""

    rvec: Float[Array, "3"]
    tvec: Float[Array, "3"]

    def apply(self, p: Float[Array, "3"]) -> Float[Array, "3"]:
        return transform(self.rvec, self.tvec, p)

    def as_vector(self) -> Float[Array, "6"]:
        return jnp.concatenate([self.rvec, self.tvec])

    @classmethod
    def from_vector(cls, v: Float[Array, "6"]) -> "Pose":
        return cls(v[:3], v[3:6])
