"""Sparse matches and the fundamental matrix for the uncalibrated path (thesis 4.2.2.4).

SIFT detection and descriptor matching are OpenCV's (the edge); the ratio test, the normalised 8-point
algorithm and RANSAC around it are numpy, written here. F maps left to right: x2^T F x1 = 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dstereo.errors import DstereoError


@dataclass(frozen=True)
class Matches:
    """Matched pixel positions (n, 2) in the left and right image, with the SIFT descriptor distance ratio."""

    left: np.ndarray
    right: np.ndarray
    ratio: np.ndarray


def match_sift(left: np.ndarray, right: np.ndarray, ratio: float = 0.75, max_features: int = 0) -> Matches:
    """SIFT keypoints of two images matched by nearest descriptor, kept when best < ratio x second best."""
    import cv2

    sift = cv2.SIFT_create(nfeatures=max_features)
    kp1, des1 = sift.detectAndCompute(_grey(left), None)
    kp2, des2 = sift.detectAndCompute(_grey(right), None)
    if des1 is None or des2 is None or len(kp1) < 8 or len(kp2) < 8:
        raise DstereoError(
            f"SIFT found {len(kp1)} and {len(kp2)} keypoints; the images need more texture (at least 8 each)"
        )
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(des1, des2, k=2)
    keep = [(m.queryIdx, m.trainIdx, m.distance / max(n.distance, 1e-12)) for m, n in
            (p for p in pairs if len(p) == 2) if m.distance < ratio * n.distance]
    if len(keep) < 8:
        raise DstereoError(f"only {len(keep)} matches pass the ratio test {ratio}; raise the ratio or add texture")
    q, t, r = (np.array(c) for c in zip(*keep))
    pts1 = np.array([kp1[i].pt for i in q], dtype=float)
    pts2 = np.array([kp2[i].pt for i in t], dtype=float)
    return Matches(pts1, pts2, r)


def _grey(image: np.ndarray) -> np.ndarray:
    import cv2

    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def _normaliser(p: np.ndarray) -> np.ndarray:
    """(..., n, 2) -> (..., 3, 3): centroid to 0 and mean distance sqrt(2), as OpenCV's 8-point."""
    c = p.mean(axis=-2, keepdims=True)
    s = np.sqrt(2.0) / np.linalg.norm(p - c, axis=-1).mean(axis=-1)
    T = np.zeros(p.shape[:-2] + (3, 3))
    T[..., 0, 0] = T[..., 1, 1] = s
    T[..., 0, 2] = -s * c[..., 0, 0]
    T[..., 1, 2] = -s * c[..., 0, 1]
    T[..., 2, 2] = 1.0
    return T


def eight_point(p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """Normalised 8-point F (rank 2, F[2,2] = 1 where possible) from >= 8 matches; batched over leading axes."""
    p1 = np.asarray(p1, dtype=float)
    p2 = np.asarray(p2, dtype=float)
    T1, T2 = _normaliser(p1), _normaliser(p2)
    h1 = np.concatenate([p1, np.ones(p1.shape[:-1] + (1,))], axis=-1) @ np.swapaxes(T1, -1, -2)
    h2 = np.concatenate([p2, np.ones(p2.shape[:-1] + (1,))], axis=-1) @ np.swapaxes(T2, -1, -2)
    a = (h2[..., :, :, None] * h1[..., :, None, :]).reshape(p1.shape[:-1] + (9,))
    _, _, vt = np.linalg.svd(np.swapaxes(a, -1, -2) @ a)  # 9 x 9 normal equations, like OpenCV
    F = vt[..., -1, :].reshape(p1.shape[:-2] + (3, 3))
    u, s, vt = np.linalg.svd(F)
    s[..., 2] = 0.0
    F = np.swapaxes(T2, -1, -2) @ (u * s[..., None, :]) @ vt @ T1
    f22 = F[..., 2:3, 2:3]
    return np.where(np.abs(f22) > np.finfo(np.float32).eps, F / np.where(f22 == 0, 1.0, f22), F)


def sampson_distance(F: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """First-order geometric error (px) of each match under F (batched over F's leading axes)."""
    h1 = np.concatenate([p1, np.ones((len(p1), 1))], axis=1)
    h2 = np.concatenate([p2, np.ones((len(p2), 1))], axis=1)
    Fx1 = h1 @ np.swapaxes(F, -1, -2)  # (..., n, 3)
    Ftx2 = h2 @ F
    num = np.sum(h2 * Fx1, axis=-1) ** 2
    den = Fx1[..., 0] ** 2 + Fx1[..., 1] ** 2 + Ftx2[..., 0] ** 2 + Ftx2[..., 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-300))


@dataclass(frozen=True)
class FundamentalFit:
    F: np.ndarray
    inliers: np.ndarray
    iterations: int
    rms: float  # Sampson distance of the inliers, px


def ransac_fundamental(
    p1: np.ndarray,
    p2: np.ndarray,
    threshold: float = 1.0,
    confidence: float = 0.999,
    max_iterations: int = 5000,
    seed: int = 0,
    batch: int = 256,
) -> FundamentalFit:
    """Robust F: RANSAC over normalised 8-point samples (Sampson distance < threshold px), then refits on all
    inliers until the inlier set stops changing. Deterministic for a given seed."""
    p1 = np.asarray(p1, dtype=float).reshape(-1, 2)
    p2 = np.asarray(p2, dtype=float).reshape(-1, 2)
    n = len(p1)
    if n < 8 or len(p2) != n:
        raise DstereoError(f"fundamental matrix: need >= 8 matches in both images, got {n} and {len(p2)}")
    rng = np.random.default_rng(seed)
    best_count, best = -1, None
    needed, done = max_iterations, 0
    while done < min(needed, max_iterations):
        idx = np.argsort(rng.random((batch, n)), axis=1)[:, :8]
        with np.errstate(all="ignore"):
            Fs = eight_point(p1[idx], p2[idx])
            counts = np.sum(sampson_distance(Fs, p1, p2) < threshold, axis=-1)
        counts[~np.all(np.isfinite(Fs), axis=(1, 2))] = -1
        i = int(np.argmax(counts))
        if counts[i] > best_count:
            best_count, best = int(counts[i]), Fs[i]
            w = best_count / n
            needed = int(np.ceil(np.log(1 - confidence) / np.log(max(1 - w**8, 1e-12)))) if w < 1 else 0
        done += batch
    if best is None or best_count < 8:
        raise DstereoError(f"fundamental matrix: no consistent model among {n} matches; check the image pair")
    inliers = sampson_distance(best, p1, p2) < threshold
    for _ in range(10):
        F = eight_point(p1[inliers], p2[inliers])
        new = sampson_distance(F, p1, p2) < threshold
        if new.sum() < 8 or np.array_equal(new, inliers):
            break
        inliers = new
    d = sampson_distance(F, p1[inliers], p2[inliers])
    return FundamentalFit(F, inliers, done, float(np.sqrt(np.mean(d**2))))


def relative_pose(F: np.ndarray, K1: np.ndarray, K2: np.ndarray, p1: np.ndarray, p2: np.ndarray):
    """(R, t) with x_right = R x_left + t, |t| = 1, from F and both camera matrices: the decomposition of
    E = K2^T F K1 that puts the most matches in front of both cameras (distortion ignored)."""
    from dstereo.stereo.triangulate import triangulate_rays

    E = K2.T @ F @ K1
    U, _, Vt = np.linalg.svd(E)
    U = U * np.sign(np.linalg.det(U))
    Vt = Vt * np.sign(np.linalg.det(Vt))
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    v1 = np.c_[p1, np.ones(len(p1))] @ np.linalg.inv(K1).T
    v2 = np.c_[p2, np.ones(len(p2))] @ np.linalg.inv(K2).T
    best, best_count = None, -1
    for R in (U @ W @ Vt, U @ W.T @ Vt):
        for t in (U[:, 2], -U[:, 2]):
            X = np.asarray(triangulate_rays(-R.T @ t, v1, v2 @ R))
            count = int(np.sum((X[:, 2] > 0) & ((X @ R.T + t)[:, 2] > 0)))
            if count > best_count:
                best, best_count = (R, t), count
    return best
