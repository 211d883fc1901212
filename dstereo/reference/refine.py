"""Refine a stereo rig from observations of a reference object of known geometry.

`refine_rig(calib, reference, q_left, q_right)` solves for the correction of `correction.py` (rotation 3,
baseline scale, baseline direction 2, optionally both focal lengths) plus the object's nuisance parameters, and
returns the corrected calibration with standard deviations, residual RMS before/after and a conditioning flag.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from dstereo.errors import DstereoError
from dstereo.io.calib_files import StereoCalibration
from dstereo.reference import residuals as res
from dstereo.reference.correction import PARAM_NAMES, RigBase, apply, corrected_calibration, free_indices
from dstereo.reference.objects import Board, Distances, Mesh, Sphere
from dstereo.reference.solve import Solution, solve

# A free parameter whose standard deviation exceeds these is reported as not determined by the reference.
POOR_ANGLE_DEG = 0.1
POOR_RELATIVE = 0.005
ANGLE_SCALE = 1e-3  # typical size of the rotation / direction / relative corrections the solver is scaled by


@dataclass
class Refinement:
    """The result: `theta` / `std` over `PARAM_NAMES` (zeros where not free), the corrected calibration."""

    reference: str
    free: tuple[str, ...]
    theta: np.ndarray
    std: np.ndarray
    cov: np.ndarray  # of the free parameters, in `free` order
    calibration: StereoCalibration
    solution: Solution
    residual_unit: str
    nuisance: np.ndarray
    baseline_before_mm: float
    checks: dict = field(default_factory=dict)

    def report(self) -> dict:
        """JSON-ready summary: the correction in deg / % / mm / px with standard deviations, residuals, flags."""
        th = self.theta
        sd = np.where(np.isin(PARAM_NAMES, self.free), self.std, np.nan)  # NaN -> null: held, not estimated
        s, baseline_mm = self.solution, self.baseline_before_mm
        k_l, k_r = self.calibration.k1, self.calibration.k2
        out = {
            "reference": self.reference,
            "free_parameters": list(self.free),
            "rotation_right_camera_deg": {ax: {"value": float(np.degrees(th[i])), "std": float(np.degrees(sd[i]))}
                                          for i, ax in enumerate("xyz")},
            "baseline": {"percent": 100 * float(th[3]), "std_percent": 100 * float(sd[3]),
                         "mm": float(th[3] * baseline_mm), "std_mm": float(sd[3] * baseline_mm),
                         "before_mm": float(baseline_mm), "after_mm": float(self.calibration.baseline)},
            "baseline_direction_deg": {n: {"value": float(np.degrees(th[i])), "std": float(np.degrees(sd[i]))}
                                       for i, n in ((4, "a"), (5, "b"))},
            "residual_rms": {"before": s.rms_before, "after": s.rms_after, "unit": self.residual_unit},
            "sigma": s.sigma, "residuals": s.n_residuals, "dof": s.dof, "iterations": s.steps,
            "converged": s.converged,
            "poorly_determined": poorly_determined(self),
            "conditioning": {"identifiable": s.conditioning.identifiable,
                             "condition_number": s.conditioning.condition_number,
                             "weak_parameters": s.conditioning.weak_parameters,
                             "max_correlation": list(s.conditioning.max_correlation),
                             "message": s.conditioning.message()},
            "checks": self.checks,
        }
        if "focal_left" in self.free:
            out["focal"] = {side: {"percent": 100 * float(th[i]), "std_percent": 100 * float(sd[i]),
                                   "px": float(k[0] - k[0] / (1 + th[i])), "std_px": float(sd[i] * k[0] / (1 + th[i]))}
                            for side, i, k in (("left", 6, k_l), ("right", 7, k_r))}
        return out


def poorly_determined(ref: "Refinement") -> list[str]:
    """Free parameters the observations leave undetermined: std > 0.1 deg (angles) or > 0.5 % (baseline, focal)."""
    angle = {"w_x", "w_y", "w_z", "dir_a", "dir_b"}
    return [n for n in ref.free if ref.std[PARAM_NAMES.index(n)] > (np.radians(POOR_ANGLE_DEG) if n in angle
                                                                    else POOR_RELATIVE)]


def _scale_for(free: tuple[int, ...], nuisance_scale: np.ndarray) -> np.ndarray:
    return np.concatenate([np.full(len(free), ANGLE_SCALE), nuisance_scale])


def _board_problem(calib, board: Board, q_left, q_right, base, free):
    from dstereo.calib.stereo import board_poses
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


@jax.jit
def _triangulate_base(base: RigBase, matches) -> jax.Array:
    return res.triangulate(*apply(base, jnp.zeros(len(PARAM_NAMES))), *matches, focal=False)


def matches_with_rays(calib, q_left, q_right) -> tuple:
    """(q_l, q_r, xy0_l, xy0_r) as the dense residuals take them: raw pixels and their undistorted normalised
    coordinates under `calib` (the starts of `residuals.triangulate`'s rays)."""
    q_l, q_r = jnp.asarray(q_left, float), jnp.asarray(q_right, float)
    return (q_l, q_r, res.undistorted(jnp.asarray(calib.k1), jnp.asarray(calib.D1), q_l),
            res.undistorted(jnp.asarray(calib.k2), jnp.asarray(calib.D2), q_r))


def _triangulated(calib, q_left, q_right) -> np.ndarray:
    """Midpoint triangulation of raw pixel pairs with `calib` (left camera frame, mm)."""
    return np.asarray(_triangulate_base(RigBase.from_calibration(calib), matches_with_rays(calib, q_left, q_right)))


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic least-squares sphere (centre, radius) of (n, 3) points: |p|^2 = 2 c.p + (r^2 - |c|^2)."""
    a = np.c_[2 * points, np.ones(len(points))]
    sol, *_ = np.linalg.lstsq(a, np.sum(points**2, axis=1), rcond=None)
    c = sol[:3]
    return c, float(np.sqrt(sol[3] + c @ c))


def sphere_inliers(points: np.ndarray, rounds: int = 4, k: float = 5.0) -> np.ndarray:
    """Mask of points within k robust standard deviations (1.4826 MAD) of a free-radius sphere fit, refitted
    `rounds` times: drops mismatches and background before the least squares."""
    finite = np.all(np.isfinite(points), axis=1)
    keep = finite
    for _ in range(rounds):
        c, r = fit_sphere(points[keep])
        dist = np.abs(np.linalg.norm(points - c, axis=1) - r)
        keep = finite & (dist <= max(k * 1.4826 * np.median(dist[keep]), 1e-12))
    return keep


def facing(points: np.ndarray, centre: np.ndarray, camera_centres: list[np.ndarray], max_deg: float) -> np.ndarray:
    """Mask of sphere points whose outward normal is within `max_deg` of the line of sight to every camera."""
    n = (points - centre) / np.linalg.norm(points - centre, axis=1, keepdims=True)
    ok = np.ones(len(points), bool)
    for c in camera_centres:
        v = (c - points) / np.linalg.norm(c - points, axis=1, keepdims=True)
        ok &= np.sum(n * v, axis=1) >= np.cos(np.radians(max_deg))
    return ok


LIMB_DEG = 70.0  # sphere points seen more obliquely than this are dropped (see _sphere_problem)


def _sphere_problem(calib, sphere: Sphere, q_left, q_right, base, free):
    # Near the silhouette SGBM's fronto-parallel windows and foreground fattening bias the depth outwards; on the
    # rendered sphere of the tests that moved the free-fit diameter by +0.2..0.7 %, while the points facing the
    # cameras (within 70 deg) fit within 0.05 %. A visible cap fixes the radius through its curvature, so a
    # biased rim matters much more than its share of the points.
    points = _triangulated(calib, q_left, q_right)
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
    p0 = _triangulated(calib, q_left, q_right)
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
        from dstereo.reference.mesh import refine_mesh

        return refine_mesh(calib, reference, q_left, q_right, base, free)
    builders = {Board: _board_problem, Sphere: _sphere_problem, Distances: _distance_problem}
    if type(reference) not in builders:
        raise DstereoError(f"reference {type(reference).__name__}: use Board, Sphere, Distances or Mesh")
    fn, x0, data, scale, unit = builders[type(reference)](calib, reference, q_left, q_right, base, free)
    sol = solve(fn, x0, data, free, names, scale=scale, whitened=isinstance(reference, Distances))
    out = finish(calib, type(reference).__name__.lower(), free, sol, unit)
    if isinstance(reference, Sphere):
        keep = np.asarray(data[3]) > 0
        q_l, q_r = np.asarray(data[1][0])[keep], np.asarray(data[1][1])[keep]
        out.checks["sphere"] = {"matches": int(np.shape(q_left)[0]), "inliers": int(keep.sum()),
                                "free_fit_diameter_before_mm": 2 * fit_sphere(_triangulated(calib, q_l, q_r))[1],
                                "free_fit_diameter_after_mm": 2 * fit_sphere(_triangulated(out.calibration, q_l,
                                                                                            q_r))[1],
                                "known_diameter_mm": float(reference.diameter)}
    if isinstance(reference, Board):
        out.checks["board_metric"] = {"before": board_metric_check(calib, reference, q_left, q_right),
                                      "after": board_metric_check(out.calibration, reference, q_left, q_right)}
    return out


def finish(calib, kind: str, free: tuple[int, ...], sol: Solution, unit: str) -> Refinement:
    theta = np.zeros(len(PARAM_NAMES))
    std = np.zeros(len(PARAM_NAMES))
    theta[list(free)] = sol.x[: len(free)]
    std[list(free)] = np.sqrt(np.maximum(np.diag(sol.cov), 0.0))
    return Refinement(kind, tuple(PARAM_NAMES[i] for i in free), theta, std, sol.cov,
                      corrected_calibration(calib, theta), sol, unit, sol.x[len(free):], calib.baseline)


def board_metric_check(calib: StereoCalibration, board: Board, q_left, q_right) -> dict:
    """Triangulate the corners with `calib` and compare neighbour spacings with the square size: the
    reconstruction's view of the board (mean and std of spacing / square - 1, in %; planarity RMS, mm)."""
    cols, rows = board.pattern
    q_left, q_right = np.asarray(q_left, float).reshape(-1, 2), np.asarray(q_right, float).reshape(-1, 2)
    p = _triangulated(calib, q_left, q_right).reshape(-1, rows, cols, 3)
    spacing = np.concatenate([np.linalg.norm(np.diff(p, axis=2), axis=-1).ravel(),
                              np.linalg.norm(np.diff(p, axis=1), axis=-1).ravel()])
    rel = spacing / float(board.square) - 1.0
    flat = []
    for view in p.reshape(p.shape[0], -1, 3):
        c = view - view.mean(axis=0)
        flat.append(np.linalg.svd(c, full_matrices=False)[1][-1] / np.sqrt(len(c)))
    return {"spacing_error_mean_percent": 100 * float(rel.mean()), "spacing_error_std_percent": 100 * float(rel.std()),
            "planarity_rms_mm": float(np.sqrt(np.mean(np.square(flat))))}
