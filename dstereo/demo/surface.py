"""The reconstructed surface against the true depth maps: ray-wise errors, a rigid fit, error statistics and the
surface's slope."""

from __future__ import annotations

import functools

import numpy as np


def bilinear(image: np.ndarray, q: np.ndarray) -> np.ndarray:
    """image (h, w) at pixels q (n, 2) (x, y; pixel centres at integers); NaN where a neighbour is NaN or q lies
    outside [0, w - 1] x [0, h - 1]."""
    h, w = image.shape
    inside = np.all(np.isfinite(q), axis=1) & (q[:, 0] >= 0) & (q[:, 1] >= 0) & (q[:, 0] <= w - 1) & (q[:, 1] <= h - 1)
    qc = np.where(inside[:, None], q, 0.0)
    x0 = np.minimum(np.floor(qc[:, 0]).astype(int), w - 2)
    y0 = np.minimum(np.floor(qc[:, 1]).astype(int), h - 2)
    fx, fy = qc[:, 0] - x0, qc[:, 1] - y0
    top = image[y0, x0] * (1 - fx) + image[y0, x0 + 1] * fx
    bottom = image[y0 + 1, x0] * (1 - fx) + image[y0 + 1, x0 + 1] * fx
    return np.where(inside, top * (1 - fy) + bottom * fy, np.nan)


@functools.cache
def _projector():
    import jax

    from dstereo.models.camera import project

    return jax.jit(jax.vmap(project, in_axes=(None, None, 0)))


def ray_errors(p: np.ndarray, camera, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance (n,) mm of points p (n, 3; left camera frame) from the true surface along the true left
    camera's ray through each (NaN off the sample), and their pixels (n, 2) in the true camera."""
    q = np.asarray(_projector()(camera.k, camera.dist.coeffs, p))
    return (p[:, 2] - bilinear(depth, q)) * np.linalg.norm(p, axis=1) / p[:, 2], q


def rigid_fit(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) minimising |R a + t - b| over point pairs (n, 3) (Kabsch)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))])
    r = vt.T @ d @ u.T
    return r, cb - r @ ca


def _stats(err: np.ndarray) -> dict:
    if not err.size:
        return {"rms_mm": float("nan")}
    a = np.abs(err)
    return {"rms_mm": float(np.sqrt(np.mean(err**2))), "mean_mm": float(np.mean(err)), "std_mm": float(np.std(err)),
            "median_abs_mm": float(np.median(a)), "p95_abs_mm": float(np.percentile(a, 95)),
            "over_1mm": int((a > 1.0).sum())}


def surface_errors(points: np.ndarray, camera, depth: np.ndarray, fit_iterations: int = 5) -> dict:
    """Errors (mm) of reconstructed points (h, w, 3; left camera frame) against the true surface, along the
    true left camera's rays (`ray_errors`), as they are and after the rigid motion that best fits them onto
    the surface (`shape_*`: what is left once the pose of the whole cloud is taken out; each fit pairs the
    points with the surface points on their current rays; the domed face is a spherical cap, so the fitted
    motion itself is not unique and is not reported). `coverage` is the fraction of the sample's pixels
    in the left image that a point lands on; points landing off the sample are counted, not measured."""
    p = points.reshape(-1, 3).astype(float)
    p = p[np.all(np.isfinite(p), axis=1) & (p[:, 2] > 0)]
    err, q = ray_errors(p, camera, depth)
    on = np.isfinite(err)
    r, t, pts = np.eye(3), np.zeros(3), p[on]
    for _ in range(fit_iterations):
        moved = pts @ r.T + t
        e, _ = ray_errors(moved, camera, depth)
        ok = np.isfinite(e)
        r, t = rigid_fit(pts[ok], moved[ok] * (1.0 - e[ok] / np.linalg.norm(moved[ok], axis=1))[:, None])
    fitted, _ = ray_errors(pts @ r.T + t, camera, depth)
    face = np.isfinite(depth)
    hit = np.zeros_like(face)
    u, v = np.rint(q[on]).astype(int).T
    hit[v, u] = True
    shape = _stats(fitted[np.isfinite(fitted)])
    return {"points": int(len(p)), "on_sample": int(on.sum()), "off_sample": int((~on).sum()),
            "coverage": float((hit & face).sum() / max(face.sum(), 1)), **_stats(err[on]),
            "shape_rms_mm": shape["rms_mm"], "shape_median_abs_mm": shape.get("median_abs_mm", float("nan"))}


def rms_slope(depth: np.ndarray, focal_px: float) -> float:
    """RMS over the sample of its depth slope |grad Z| per mm across the view (edges, where a neighbour is
    background, excluded): how much a sideways shift of the cloud shows as depth error."""
    gy, gx = np.gradient(depth)
    slope = np.hypot(gx, gy) * focal_px / depth
    return float(np.sqrt(np.nanmean(slope**2)))
