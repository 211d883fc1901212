"""Refine a stereo rig from observations of a reference object of known geometry.

`refine_rig(calib, reference, q_left, q_right)` solves for the correction of `correction.py` (rotation 3,
baseline scale, baseline direction 2, optionally both focal lengths) plus the object's nuisance parameters, and
returns the corrected calibration with standard deviations, residual RMS before/after and a conditioning flag.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from dstereo.errors import DstereoError
from dstereo.models.stereo_calibration import StereoCalibration
from dstereo.reference import residuals as res
from dstereo.reference.correction import PARAM_NAMES, RigBase, free_indices
from dstereo.reference.mesh import refine_mesh
from dstereo.reference.objects import Board, Distances, Mesh, Sphere
from dstereo.reference.refinement import Refinement, poorly_determined, refinement_from_solution  # noqa: F401
from dstereo.reference.solve import solve
from dstereo.reference.sphere_fit import LIMB_DEG, facing, fit_sphere, sphere_inliers
from dstereo.reference.triangulation import matches_with_rays, triangulated  # noqa: F401 - public here too

ANGLE_SCALE = 1e-3  # typical size of the rotation / direction / relative corrections the solver is scaled by

def _scale_for(free: tuple[int, ...], nuisance_scale: np.ndarray) -> np.ndarray:
    return np.concatenate([np.full(len(free), ANGLE_SCALE), nuisance_scale])


def _board_problem(calib, board: Board, q_left, q_right, base, free):
    from dstereo.calib.board_poses import board_poses
    from dstereo.models.camera import Camera

    obj = board.object_points()
    q_left, q_right = np.asarray(q_left, float), np.asarray(q_right, float)
    if q_left.ndim == 2:
        q_left, q_right = q_left[None], q_right[None]
    n = obj.shape[0]
    if q_left.shape != q_right.shape or q_left.shape[1:] != (n, 2):
        raise DstereoError(f"board {board.pattern[0]}x{board.pattern[1]}: need ({n}, 2) corners per view in both "
                           f"images, got {q_left.shape} and {q_right.shape}")
    cam = Camera.create(*calib.k1, coeffs=calib.D1)
    poses = board_poses(cam, obj, q_left)
    scale = np.tile(np.r_[np.ones(3), np.full(3, max(np.abs(poses[:, 3:]).max(), 1.0))], len(poses))
    data = (base, jnp.asarray(obj), jnp.asarray(q_left), jnp.asarray(q_right))
    return res.board_residuals, np.r_[np.zeros(len(free)), poses.ravel()], data, _scale_for(free, scale), "px"



def _sphere_problem(calib, sphere: Sphere, q_left, q_right, base, free):
    # Near the silhouette SGBM's fronto-parallel windows and foreground fattening bias the depth outwards; on the
    # rendered sphere of the tests that moved the free-fit diameter by +0.2..0.7 %, while the points facing the
    # cameras (within 70 deg) fit within 0.05 %. A visible cap fixes the radius through its curvature, so a
    # biased rim matters much more than its share of the points.
    points = triangulated(calib, q_left, q_right)
    keep = sphere_inliers(points)
    centre, _ = fit_sphere(points[keep])
    keep &= facing(points, centre, [np.zeros(3), -calib.R.T @ calib.T], LIMB_DEG)
    if keep.sum() < 20:
        raise DstereoError(f"sphere: only {keep.sum()} matched points lie on a sphere; check the images, the matching "
                           "and the depth range")
    centre, _ = fit_sphere(points[keep])
    # dropped matches stay in with weight 0 and the position of a kept one: one compiled residual per match count
    q_left, q_right = (np.where(keep[:, None], q, q[np.argmax(keep)]) for q in (np.asarray(q_left, float),
                                                                             np.asarray(q_right, float)))
    data = (base, matches_with_rays(calib, q_left, q_right), jnp.asarray(sphere.radius), jnp.asarray(keep, float))
    scale = np.full(3, max(np.abs(centre).max(), 1.0))
    return res.sphere_residuals, np.r_[np.zeros(len(free)), centre], data, _scale_for(free, scale), "mm"


def _distance_problem(calib, dist: Distances, q_left, q_right, base, free):
    q_left, q_right = np.asarray(q_left, float), np.asarray(q_right, float)
    if q_left.shape != q_right.shape or q_left.shape[0] < dist.n_points:
        raise DstereoError(f"distances name {dist.n_points} points but {q_left.shape[0]} left and "
                           f"{q_right.shape[0]} right marks were given")
    p0 = triangulated(calib, q_left, q_right)
    data = (base, jnp.asarray(q_left), jnp.asarray(q_right), dist.pairs, dist.lengths,
            float(dist.sigma_px), float(dist.sigma_mm))
    scale = np.full(p0.size, max(np.abs(p0).max(), 1.0))
    return res.distance_residuals, np.r_[np.zeros(len(free)), p0.ravel()], data, _scale_for(free, scale), "whitened"


def refine_rig(calib: StereoCalibration, reference, q_left, q_right, focal: bool = False,
               fixed: tuple[str, ...] = ()) -> Refinement:
    """Correct `calib` so that the reference reconstructed from the observations matches its known geometry.

    Observations (raw pixels of the original images): a Board's inner corners (n, 2) or (V, n, 2) per image; a
    Sphere's or Mesh's matched pixel pairs (n, 2) (`dense.dense_matches`); the marked points (m, 2) of Distances.
    `focal` also frees both focal lengths; `fixed` holds named corrections (of `PARAM_NAMES`) at zero.
    """
    base = RigBase.from_calibration(calib)
    free = free_indices(focal, tuple(fixed))
    names = tuple(PARAM_NAMES[i] for i in free)
    if isinstance(reference, Mesh):
        return refine_mesh(calib, reference, q_left, q_right, base, free)
    builders = {Board: _board_problem, Sphere: _sphere_problem, Distances: _distance_problem}
    if type(reference) not in builders:
        raise DstereoError(f"reference {type(reference).__name__}: use Board, Sphere, Distances or Mesh")
    fn, x0, data, scale, unit = builders[type(reference)](calib, reference, q_left, q_right, base, free)
    sol = solve(fn, x0, data, free, names, scale=scale, whitened=isinstance(reference, Distances))
    out = refinement_from_solution(calib, type(reference).__name__.lower(), free, sol, unit)
    if isinstance(reference, Sphere):
        keep = np.asarray(data[3]) > 0
        q_l, q_r = np.asarray(data[1][0])[keep], np.asarray(data[1][1])[keep]
        out.checks["sphere"] = {"matches": int(np.shape(q_left)[0]), "inliers": int(keep.sum()),
                                "free_fit_diameter_before_mm": 2 * fit_sphere(triangulated(calib, q_l, q_r))[1],
                                "free_fit_diameter_after_mm": 2 * fit_sphere(triangulated(out.calibration, q_l,
                                                                                            q_r))[1],
                                "known_diameter_mm": float(reference.diameter)}
    if isinstance(reference, Board):
        out.checks["board_metric"] = {"before": board_metric_check(calib, reference, q_left, q_right),
                                      "after": board_metric_check(out.calibration, reference, q_left, q_right)}
    return out


def board_metric_check(calib: StereoCalibration, board: Board, q_left, q_right) -> dict:
    """Triangulate the corners with `calib` and compare neighbour spacings with the square size: the
    reconstruction's view of the board (mean and std of spacing / square - 1, in %; planarity RMS, mm)."""
    cols, rows = board.pattern
    q_left, q_right = np.asarray(q_left, float).reshape(-1, 2), np.asarray(q_right, float).reshape(-1, 2)
    p = triangulated(calib, q_left, q_right).reshape(-1, rows, cols, 3)
    spacing = np.concatenate([np.linalg.norm(np.diff(p, axis=2), axis=-1).ravel(),
                              np.linalg.norm(np.diff(p, axis=1), axis=-1).ravel()])
    rel = spacing / float(board.square) - 1.0
    flat = []
    for view in p.reshape(p.shape[0], -1, 3):
        c = view - view.mean(axis=0)
        flat.append(np.linalg.svd(c, full_matrices=False)[1][-1] / np.sqrt(len(c)))
    return {"spacing_error_mean_percent": 100 * float(rel.mean()), "spacing_error_std_percent": 100 * float(rel.std()),
            "planarity_rms_mm": float(np.sqrt(np.mean(np.square(flat))))}
