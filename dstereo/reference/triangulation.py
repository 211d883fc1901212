"""Midpoint triangulation of raw pixel pairs under a stereo calibration, as the reference residuals see them."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from dstereo.reference import residuals as res
from dstereo.reference.correction import PARAM_NAMES, RigBase, apply


@jax.jit
def _triangulate_base(base: RigBase, matches) -> jax.Array:
    return res.triangulate(*apply(base, jnp.zeros(len(PARAM_NAMES))), *matches, focal=False)


def matches_with_rays(calib, q_left, q_right) -> tuple:
    """(q_l, q_r, xy0_l, xy0_r) as the dense residuals take them: raw pixels and their undistorted normalised
    coordinates under `calib` (the starts of `residuals.triangulate`'s rays)."""
    q_l, q_r = jnp.asarray(q_left, float), jnp.asarray(q_right, float)
    return (q_l, q_r, res.undistorted(jnp.asarray(calib.k1), jnp.asarray(calib.D1), q_l),
            res.undistorted(jnp.asarray(calib.k2), jnp.asarray(calib.D2), q_r))


def triangulated(calib, q_left, q_right) -> np.ndarray:
    """Midpoint triangulation of raw pixel pairs with `calib` (left camera frame, mm)."""
    return np.asarray(_triangulate_base(RigBase.from_calibration(calib), matches_with_rays(calib, q_left, q_right)))

