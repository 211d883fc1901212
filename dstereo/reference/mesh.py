"""A known mesh as the reference: ICP-style alternation between choosing triangles and a least-squares solve.

Each round: triangulate the dense matches with the current rig, bring them into the mesh frame with the current
pose, pick for each point the nearest of the 8 triangles whose centroids are closest (scipy KD-tree; exact
point-to-triangle distance by clamped barycentric projection onto each candidate's plane and edges), then solve
rig correction + mesh pose on the point-to-plane residuals of those triangles (`residuals.mesh_residuals`).
Points farther than 5 robust standard deviations from the mesh get weight zero, and so do points whose
triangle is seen more obliquely than `sphere_fit.LIMB_DEG` from either camera: near a silhouette SGBM biases depth
outwards (as for the sphere reference; with those points in, the baseline of the tests' rendered sphere came out
0.0 to 0.5 % short depending on which matches were sampled, 13 times its standard deviation). Scope: one
pair, rigid mesh, a start pose good to a few mm / degrees (ICP's basin); no coarse registration.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from dstereo.errors import DstereoError
from dstereo.models.pose import rodrigues
from dstereo.reference import residuals as res
from dstereo.reference.correction import PARAM_NAMES, corrected_calibration
from dstereo.reference.objects import Mesh
from dstereo.reference.refinement import refinement_from_solution
from dstereo.reference.solve import solve
from dstereo.reference.sphere_fit import LIMB_DEG
from dstereo.reference.triangulation import matches_with_rays, triangulated


def _closest_on_triangles(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Closest points (n, k, 3) on triangles tri (n, k, 3, 3) to points p (n, 3): plane projection if inside,
    else the closest point on the three edges."""
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    q = p[:, None] - np.sum((p[:, None] - a) * n, axis=-1, keepdims=True) * n
    inside = np.ones(q.shape[:2], bool)
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= np.sum(np.cross(v - u, q - u) * n, axis=-1) >= 0
    best, best_d = q.copy(), np.full(q.shape[:2], np.inf)
    for u, v in ((a, b), (b, c), (c, a)):
        t = np.clip(np.sum((p[:, None] - u) * (v - u), axis=-1) / np.sum((v - u) ** 2, axis=-1), 0.0, 1.0)
        e = u + t[..., None] * (v - u)
        d = np.linalg.norm(p[:, None] - e, axis=-1)
        better = d < best_d
        best[better], best_d[better] = e[better], d[better]
    return np.where(inside[..., None], q, best)


def nearest_triangles(mesh: Mesh, p_mesh: np.ndarray, k: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For points in the mesh frame: (a vertex (n, 3), unit normal (n, 3), distance (n,)) of the nearest triangle."""
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    tri = v[f]
    _, idx = cKDTree(tri.mean(axis=1)).query(p_mesh, k=min(k, len(f)))
    idx = idx.reshape(len(p_mesh), -1)
    closest = _closest_on_triangles(p_mesh, tri[idx])
    dist = np.linalg.norm(closest - p_mesh[:, None], axis=-1)
    j = idx[np.arange(len(p_mesh)), np.argmin(dist, axis=1)]
    normal = np.cross(tri[j, 1] - tri[j, 0], tri[j, 2] - tri[j, 0])
    return tri[j, 0], normal / np.linalg.norm(normal, axis=1, keepdims=True), dist.min(axis=1)


def facing_cameras(points: np.ndarray, normals: np.ndarray, camera_centres: list[np.ndarray],
                   max_deg: float) -> np.ndarray:
    """Mask of points whose surface normal (either orientation) is within `max_deg` of the line of sight to every
    camera."""
    ok = np.ones(len(points), bool)
    for c in camera_centres:
        v = (c - points) / np.linalg.norm(c - points, axis=1, keepdims=True)
        ok &= np.abs(np.sum(normals * v, axis=1)) >= np.cos(np.radians(max_deg))
    return ok


def refine_mesh(calib, mesh: Mesh, q_left, q_right, base, free, rounds: int = 8):
    """Refinement of `calib` against `mesh`: alternate nearest-triangle matching and the solve, `rounds` at most."""
    names = tuple(PARAM_NAMES[i] for i in free)
    matches = matches_with_rays(calib, q_left, q_right)
    theta, pose = np.zeros(len(free)), np.asarray(mesh.pose0, float)
    first = None
    for _ in range(rounds):
        full = np.zeros(len(PARAM_NAMES))
        full[list(free)] = theta
        points = triangulated(corrected_calibration(calib, full), q_left, q_right)
        rot = np.asarray(rodrigues(jnp.asarray(pose[:3])))
        p_mesh = (points - pose[3:]) @ rot
        v0, normal, dist = nearest_triangles(mesh, p_mesh)
        keep = dist <= max(5 * 1.4826 * np.median(dist), 1e-9)
        keep &= facing_cameras(points, normal @ rot.T, [np.zeros(3), -calib.R.T @ calib.T], LIMB_DEG)
        if keep.sum() < 20:
            raise DstereoError(f"mesh: only {keep.sum()} points lie near the mesh; check its start pose (pose0)")
        w = keep[:, None].astype(float)
        data = (base, matches, jnp.asarray(v0 * w), jnp.asarray(normal * w))  # weight 0: residual 0
        x0 = np.r_[theta, pose]
        scale = np.r_[np.full(len(free), 1e-3), np.ones(3), np.full(3, max(np.abs(pose[3:]).max(), 1.0))]
        sol = solve(res.mesh_residuals, x0, data, free, names, scale=scale)
        first = first or sol
        step = sol.x - x0
        theta, pose = sol.x[: len(free)], sol.x[len(free):]
        if np.max(np.abs(step[: len(free)])) < 1e-9:
            break
    sol = dataclasses.replace(sol, rms_before=first.rms_before)
    out = refinement_from_solution(calib, "mesh", free, sol, "mm")
    out.checks["mesh"] = {"points": int(len(points)), "inliers": int(keep.sum())}
    return out
