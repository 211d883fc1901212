"""Dense matches for the sphere and mesh references: SGBM on the rectified pair, mapped back to raw pixels.

The refinement needs observations that do not depend on the rig being refined: each valid disparity gives a
rectified pixel pair (u, v) <-> (u - d, v), and the rectification it was found with maps both back to the
original (distorted) images. Those raw pixel pairs are then triangulated with the corrected rig. SGBM searches
along rectified rows only, so its matches carry no information on the vertical (epipolar) misalignment a
rotation error causes: a dense reference constrains the rig through the reconstructed shape only, and rounds of
re-rectification with the corrected rig let the matcher follow the correction. The search range is the
reconstruction's (`dstereo.stereo.search_range`); a pair whose scene still runs off it is refused, not matched short.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from dstereo.errors import DstereoError
from dstereo.models.stereo_calibration import StereoCalibration
from dstereo.models.camera import project


@jax.jit
def _to_raw(k, coeffs, R, P, uv):
    inv = jnp.linalg.inv(P[:, :3] @ R)
    rays = jnp.concatenate([uv, jnp.ones((uv.shape[0], 1))], axis=1) @ inv.T
    return jax.vmap(lambda p: project(k, coeffs, p))(rays)


def dense_matches(calib: StereoCalibration, left: np.ndarray, right: np.ndarray, config=None,
                  max_points: int = 4000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(q_left, q_right) raw pixel pairs (n, 2) of up to `max_points` valid SGBM matches (a seeded random subset)."""
    from dstereo.stereo.reconstruct import ReconstructionConfig, reconstruct_calibrated

    if calib.rectified:
        raise DstereoError(f"calibration {calib.source}: an already rectified (Middlebury) pair has no rig to refine")
    result = reconstruct_calibrated(calib, left, right, config or ReconstructionConfig())
    _refuse_saturated(result)
    v, u = np.nonzero(_trusted(result))
    if len(u) < 50:
        raise DstereoError("dense matching found fewer than 50 valid pixels on the reference; give it texture, set "
                           "the depth range (`z_min`/`z_max`) or check the calibration's image size")
    keep = np.sort(np.random.default_rng(seed).permutation(len(u))[:max_points])
    u, v = u[keep].astype(float), v[keep].astype(float)
    d = result.disparity[v.astype(int), u.astype(int)].astype(float)
    m = result.matrices
    q_l = _to_raw(jnp.asarray(calib.k1), jnp.asarray(calib.D1), jnp.asarray(m["R1"]), jnp.asarray(m["P1"]),
                  jnp.asarray(np.c_[u, v]))
    q_r = _to_raw(jnp.asarray(calib.k2), jnp.asarray(calib.D2), jnp.asarray(m["R2"]), jnp.asarray(m["P2"]),
                  jnp.asarray(np.c_[u - d, v]))
    return np.asarray(q_l), np.asarray(q_r)


def _trusted(result) -> np.ndarray:
    """Valid pixels fit for a refinement: not within 1 px of either end of the search range (where SGBM pins what it
    cannot match) and not in the left band of max-disparity columns that SGBM only matches because the pair was
    padded (`dstereo.stereo.disparity._sgbm`; its matches there are mostly the background's). Density matters less here
    than outliers: the refinement's fit is least squares."""
    d = result.disparity
    s = result.summary["search_range"]
    ds = np.sign(result.matrices["Q"][3, 2]) * d
    u = np.arange(d.shape[1])[None, :]
    inner = (ds > s["min_disparity"] + 1) & (ds < s["max_disparity"] - 1)
    return np.isfinite(d) & inner & (u >= max(s["max_disparity"], 0))


def _refuse_saturated(result) -> None:
    """Matches cut off by the disparity search range would bias the refinement: refuse them (the reconstruction
    has already widened a range it chose itself; what is left is a user's range or a scene beyond the image)."""
    search = result.summary.get("search_range") or {}
    if (search.get("saturation") or {}).get("saturated_low") or (search.get("saturation") or {}).get("saturated_high"):
        text = next((w for w in result.warnings if "search range" in w), "the scene runs off the search range")
        raise DstereoError(f"dense matching: {text}")


def refine_dense(calib: StereoCalibration, left: np.ndarray, right: np.ndarray, reference, focal: bool = False,
                 fixed: tuple[str, ...] = (), config=None, rounds: int = 3, max_points: int = 4000):
    """Sphere or Mesh reference from one image pair: match, refine, re-rectify with the corrected rig and match
    again (`rounds` at most; stops when a round's correction is within its standard deviation, or when a free
    parameter is poorly determined (`refine.poorly_determined`): re-matching on a wild guess would only hurt).

    The returned Refinement's `theta` is the total correction from `calib`; its standard deviations and
    conditioning are those of the last round; `rms_before` is the first round's."""
    from dstereo.reference.correction import theta_between
    from dstereo.reference.correction import PARAM_NAMES
    from dstereo.reference.refine import poorly_determined, refine_rig

    current, first, done = calib, None, 0
    for done in range(1, rounds + 1):
        q_l, q_r = dense_matches(current, left, right, config, max_points)
        out = refine_rig(current, reference, q_l, q_r, focal=focal, fixed=fixed)
        first = first or out
        current = out.calibration
        free = [PARAM_NAMES.index(n) for n in out.free]
        if poorly_determined(out) or np.all(np.abs(out.theta[free]) <= out.std[free]):
            break
    sol = dataclasses.replace(out.solution, rms_before=first.solution.rms_before)
    out = dataclasses.replace(out, theta=theta_between(calib, current), solution=sol, baseline_before_mm=calib.baseline)
    out.checks["rounds"] = done
    return out
