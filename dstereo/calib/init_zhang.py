"""Closed-form start for a planar-target calibration (Zhang 2000), numpy (and the one rotation log of
`dstereo.models.pose`): no OpenCV calibration call.

Per view a homography board -> image (normalised DLT); then the focal lengths from the orthonormality of
the rotation's first two columns, with the principal point held at the image centre (two unknowns from
2 equations per view: stable already with 2-3 views, unlike the full 5-unknown form); then each view's pose
from K^-1 H. Distortion starts at zero; the LM solve does the rest.
"""

from __future__ import annotations

import numpy as np

from dstereo.errors import DstereoError
from dstereo.models.pose import rotation_vector


def _normaliser(pts: np.ndarray) -> np.ndarray:
    mean = pts.mean(axis=0)
    scale = np.sqrt(2.0) / max(np.mean(np.linalg.norm(pts - mean, axis=1)), 1e-12)
    return np.array([[scale, 0, -scale * mean[0]], [0, scale, -scale * mean[1]], [0, 0, 1.0]])


def homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """3x3 H with dst ~ H src, from (n, 2) point pairs, normalised DLT (Hartley)."""
    ts, td = _normaliser(src), _normaliser(dst)
    s = (np.column_stack([src, np.ones(len(src))]) @ ts.T)[:, :2]
    d = (np.column_stack([dst, np.ones(len(dst))]) @ td.T)[:, :2]
    zeros, ones = np.zeros(len(s)), np.ones(len(s))
    ax = np.column_stack([-s[:, 0], -s[:, 1], -ones, zeros, zeros, zeros, d[:, 0] * s[:, 0], d[:, 0] * s[:, 1], d[:, 0]])
    ay = np.column_stack([zeros, zeros, zeros, -s[:, 0], -s[:, 1], -ones, d[:, 1] * s[:, 0], d[:, 1] * s[:, 1], d[:, 1]])
    _, _, vt = np.linalg.svd(np.vstack([ax, ay]), full_matrices=False)  # U of 2n x 2n is not needed
    h = vt[-1].reshape(3, 3)
    h = np.linalg.inv(td) @ h @ ts
    return h / h[2, 2]


def focal_lengths(homographies: list[np.ndarray], cx: float, cy: float) -> tuple[float, float]:
    """fx, fy from h1'w h2 = 0 and h1'w h1 = h2'w h2 with w = diag(1/fx^2, 1/fy^2, 1), pp known."""
    shift = np.array([[1.0, 0, -cx], [0, 1.0, -cy], [0, 0, 1.0]])
    rows, rhs = [], []
    for h in homographies:
        hc = shift @ h
        h1, h2 = hc[:, 0], hc[:, 1]
        rows.append([h1[0] * h2[0], h1[1] * h2[1]])
        rhs.append(-h1[2] * h2[2])
        rows.append([h1[0] ** 2 - h2[0] ** 2, h1[1] ** 2 - h2[1] ** 2])
        rhs.append(-(h1[2] ** 2 - h2[2] ** 2))
    a = np.array(rows)
    b = np.array(rhs)
    scale = np.linalg.norm(a, axis=0)
    sol = np.linalg.lstsq(a / scale, b, rcond=None)[0] / scale
    if np.any(sol <= 0):
        raise DstereoError(
            "calibration start: the board views do not constrain the focal length (all views nearly "
            "fronto-parallel?); add views with the board tilted 20-45 degrees"
        )
    return float(1.0 / np.sqrt(sol[0])), float(1.0 / np.sqrt(sol[1]))


def pose_from_homography(h: np.ndarray, kmat: np.ndarray) -> np.ndarray:
    """(6,) rvec, tvec of T_cam_board from H = K [r1 r2 t], rotation projected onto SO(3)."""
    m = np.linalg.solve(kmat, h)
    lam = 1.0 / np.linalg.norm(m[:, 0])
    if m[2, 2] * lam < 0:  # the board must lie in front of the camera
        lam = -lam
    r1, r2, t = lam * m[:, 0], lam * m[:, 1], lam * m[:, 2]
    u, _, vt = np.linalg.svd(np.column_stack([r1, r2, np.cross(r1, r2)]))
    rot = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return np.concatenate([rotation_vector(rot), t])


def initial_guess(obj: np.ndarray, obs: np.ndarray, image_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """obj (n, 3) planar z=0 board, obs (V, n, 2) -> k (4,) and poses (V, 6)."""
    cx, cy = (image_size[0] - 1) / 2.0, (image_size[1] - 1) / 2.0
    hs = [homography(obj[:, :2], o) for o in obs]
    fx, fy = focal_lengths(hs, cx, cy)
    kmat = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    poses = np.stack([pose_from_homography(h, kmat) for h in hs])
    return np.array([fx, fy, cx, cy]), poses
