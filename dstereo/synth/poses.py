"""Rigid-pose helpers (numpy side) and a generator of good calibration pose sets (thesis section 5.3.2.4).

A pose is a (6,) vector (rvec, tvec) of `T_a_b`, which maps coordinates in frame b into frame a. These
helpers build truth on the host with the one rotation exp/log of `dstereo.models.pose` (compiled host calls).
"""

from __future__ import annotations

from typing import Sequence

import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from dstereo.errors import DstereoError
from dstereo.models.camera import Camera
from dstereo.models.pose import rotation_matrix, rotation_vector
from dstereo.synth.board import Board
from dstereo.synth.rays import project_points, unproject_points


def pose_matrix(pose) -> np.ndarray:
    """(4, 4) homogeneous matrix of a (6,) pose."""
    pose = np.asarray(pose, float).reshape(6)
    m = np.eye(4)
    m[:3, :3] = rotation_matrix(pose[:3])
    m[:3, 3] = pose[3:]
    return m


def pose_from_matrix(m: np.ndarray) -> np.ndarray:
    """(6,) pose of a (4, 4) or (3, 4) rigid matrix (rotation angle < pi)."""
    return pose_from_rt(m[:3, :3], m[:3, 3])


def pose_from_rt(rmat: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """(6,) pose of OpenCV's (R, T) pair, e.g. stereoCalibrate's T_right_left."""
    rvec = rotation_vector(rmat)
    return np.concatenate([rvec, np.asarray(tvec, float).reshape(3)])


def compose(pose_a_b, pose_b_c) -> np.ndarray:
    """T_a_c = T_a_b o T_b_c."""
    return pose_from_matrix(pose_matrix(pose_a_b) @ pose_matrix(pose_b_c))


def invert(pose_a_b) -> np.ndarray:
    """T_b_a."""
    return pose_from_matrix(np.linalg.inv(pose_matrix(pose_a_b)))


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """T_cam_world of a camera at `eye` whose optical axis (+z) points at `target`; image y runs along -`up`."""
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(-up, z)
    if np.linalg.norm(x) < 1e-12:
        raise DstereoError(f"look_at: up {up.tolist()} is parallel to the viewing direction; choose another up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r_cam_world = np.stack([x, y, z])
    return pose_from_rt(r_cam_world, -r_cam_world @ eye)


def _project_many(camera: Camera, pose_cam_world, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, 2) pixels and (n,) depths of world points; numpy in and out."""
    m = pose_matrix(pose_cam_world)
    p_cam = pts @ m[:3, :3].T + m[:3, 3]
    q = project_points(camera.k, camera.dist.coeffs, jnp.asarray(p_cam), camera.lens)
    return np.asarray(q), p_cam[:, 2]


def _board_samples(board: Board, per_edge: int = 12) -> np.ndarray:
    """Points along the printed board's outline plus the inner corners (board frame)."""
    outline = board.outline()
    t = np.linspace(0.0, 1.0, per_edge, endpoint=False)[:, None]
    edges = [outline[i] + t * (outline[(i + 1) % 4] - outline[i]) for i in range(4)]
    inner = board.geometry.object_points()
    return np.concatenate(edges + [inner])


def board_visible(camera: Camera, pose_cam_board, board: Board, margin_px: float, max_view_deg: float) -> bool:
    """Whole printed board inside the image by `margin_px`, in front of the camera, and seen at most
    `max_view_deg` away from face-on (angle between the board normal and the line of sight to its centre).

    The forward projection is checked against the exact inverse of the distortion, so points beyond the
    distortion's invertible range (where strong lenses fold back into the image) count as not visible.
    """
    w, h = camera.image_size
    pts = _board_samples(board)
    q, depth = _project_many(camera, pose_cam_board, pts)
    if np.any(depth <= 0) or not np.all(np.isfinite(q)):
        return False
    lo, hi = margin_px, np.array([w - 1, h - 1]) - margin_px
    if not np.all((q >= lo) & (q <= hi)):
        return False
    rays = np.asarray(unproject_points(camera.k, camera.dist.coeffs, jnp.asarray(q), camera.lens))
    m = pose_matrix(pose_cam_board)
    p_cam = pts @ m[:3, :3].T + m[:3, 3]
    if np.max(np.abs(rays - p_cam[:, :2] / p_cam[:, 2:3])) > 1e-9:
        return False
    centre = m[:3, :3] @ board.centre() + m[:3, 3]
    cos_view = abs(m[:3, 2] @ centre) / np.linalg.norm(centre)
    return bool(cos_view >= np.cos(np.radians(max_view_deg)))


# Image anchors (fractions of width, height) cycled through so the set covers the centre, corners and edges.
ANCHORS = np.array([
    [0.5, 0.5], [0.18, 0.18], [0.82, 0.18], [0.82, 0.82], [0.18, 0.82],
    [0.5, 0.18], [0.82, 0.5], [0.5, 0.82], [0.18, 0.5],
])


def _candidate_pose(rng: np.random.Generator, camera: Camera, board: Board, anchor: np.ndarray, fill: float,
                    max_tilt_deg: float, max_roll_deg: float) -> np.ndarray:
    """T_cam_board with the board centre on the ray through `anchor` (pixels), tilted and rolled at random."""
    w, _ = camera.image_size
    outline = board.outline()
    board_width = np.linalg.norm(outline[1] - outline[0])
    depth = float(camera.k[0]) * board_width / (fill * w)
    xy = np.asarray(unproject_points(camera.k, camera.dist.coeffs, jnp.asarray(anchor, float)[None], camera.lens))[0]
    ray = np.array([xy[0], xy[1], 1.0])
    tilt = np.radians(max_tilt_deg) * np.sqrt(rng.uniform())  # more large tilts than a uniform draw gives
    axis_angle = rng.uniform(0.0, 2 * np.pi)
    roll = np.radians(max_roll_deg) * rng.uniform(-1.0, 1.0)
    r_tilt = rotation_matrix(tilt * np.array([np.cos(axis_angle), np.sin(axis_angle), 0.0]))
    r_roll = rotation_matrix([0.0, 0.0, roll])
    rmat = r_tilt @ r_roll
    tvec = depth * ray - rmat @ board.centre()
    return pose_from_rt(rmat, tvec)


def board_pose_set(
    cameras: Sequence[Camera],
    rig: Sequence,
    board: Board,
    n_views: int,
    seed: int,
    max_tilt_deg: float = 45.0,
    max_roll_deg: float = 20.0,
    fill: tuple[float, float] = (0.35, 0.6),
    margin_px: float = 6.0,
    tries: int = 400,
) -> np.ndarray:
    """(n_views, 6) board poses T_cam0_board that every camera of a rig sees whole (thesis 5.3.2.4).

    `rig[i]` is T_cam_i_cam0 (the identity for camera 0; for a stereo pair, T_right_left). Views cycle through
    anchors at the image centre, corners and edge midpoints of camera 0, so together they cover the whole
    field including the corners where distortion is largest; each board is tilted up to `max_tilt_deg` about a
    random in-plane axis and rolled up to `max_roll_deg` (kept moderate so corner detectors keep a consistent
    ordering). The board's width fills a random fraction `fill` of the image width. A rejected candidate is
    drawn again with its anchor pulled towards the centre, deterministically from `seed`.
    """
    if len(cameras) != len(rig):
        raise DstereoError(f"board_pose_set: {len(cameras)} cameras but {len(rig)} rig poses")
    rng = np.random.default_rng(seed)
    cam0 = cameras[0]
    size = np.array(cam0.image_size, float)
    centre = (size - 1) / 2
    poses = []
    for i in range(n_views):
        anchor = ANCHORS[i % len(ANCHORS)] * (size - 1)
        for attempt in range(tries):
            pull = min(1.0, attempt / (0.5 * tries))
            target = anchor + pull * (centre - anchor) + rng.normal(0.0, 0.02, 2) * size
            pose = _candidate_pose(rng, cam0, board, target, rng.uniform(*fill), max_tilt_deg, max_roll_deg)
            if all(
                board_visible(cam, compose(t_cam_cam0, pose), board, margin_px, max_tilt_deg + 15.0)
                for cam, t_cam_cam0 in zip(cameras, rig)
            ):
                poses.append(pose)
                break
        else:
            raise DstereoError(
                f"board_pose_set: no pose of the {board.pattern} board with square {board.square} mm fits every "
                f"camera for view {i} after {tries} tries; use a smaller square or a smaller `fill`"
            )
    return np.stack(poses)


def corner_coverage(points: np.ndarray, image_size: tuple[int, int]) -> dict[str, float]:
    """Share of image points in each region of thesis Fig. 5.7 (quadrants and the central half), in %."""
    w, h = image_size
    u, v = points[:, 0] / (w - 1), points[:, 1] / (h - 1)
    n = max(len(points), 1)
    return {
        "upper_left": 100.0 * np.sum((u < 0.5) & (v < 0.5)) / n,
        "lower_left": 100.0 * np.sum((u < 0.5) & (v >= 0.5)) / n,
        "upper_right": 100.0 * np.sum((u >= 0.5) & (v < 0.5)) / n,
        "lower_right": 100.0 * np.sum((u >= 0.5) & (v >= 0.5)) / n,
        "centre": 100.0 * np.sum((np.abs(u - 0.5) < 0.25) & (np.abs(v - 0.5) < 0.25)) / n,
    }


def wide_board_poses(board: Board, n_views: int, seed: int, max_off_axis_deg: float = 65.0,
                     distance_mm: tuple[float, float] = (300.0, 450.0), max_tilt_deg: float = 30.0,
                     max_corner_deg: float = 80.0) -> np.ndarray:
    """(n_views, 6) T_cam_board for a wide lens: the board's centre `distance_mm` away, up to `max_off_axis_deg`
    off the optical axis (the first view on it, the others in a spiral of azimuths), facing the camera, then
    tilted up to `max_tilt_deg` about a random in-plane axis, drawn again until every corner lies within
    `max_corner_deg` of the axis; deterministic from `seed`. (`board_pose_set` aims through image pixels with a
    pinhole's sense of size and puts the boards of a 180-degree lens at its rim.)"""
    rng = np.random.default_rng(seed)
    x0, y0, x1, y1 = board.squares_extent()
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    corners = board.geometry.object_points()
    out = []
    for i in range(n_views):
        for _ in range(100):
            pose = _wide_pose(rng, i, n_views, max_off_axis_deg, distance_mm, max_tilt_deg, centre)
            p = corners @ rotation_matrix(pose[:3]).T + pose[3:]
            if np.degrees(np.arccos(p[:, 2] / np.linalg.norm(p, axis=1))).max() <= max_corner_deg:
                break
        else:
            raise DstereoError(f"wide_board_poses: view {i}: no tilt keeps the board within {max_corner_deg} deg of "
                               "the axis; lower max_off_axis_deg or the board's size")
        out.append(pose)
    return np.array(out)


def _wide_pose(rng, i, n_views, max_off_axis_deg, distance_mm, max_tilt_deg, centre) -> np.ndarray:
    """One draw of `wide_board_poses`'s view i."""
    off = 0.0 if i == 0 else np.radians(max_off_axis_deg) * np.sqrt(i / max(n_views - 1, 1))
    az = 2.399963 * i  # the golden angle: azimuths that never repeat
    z = np.array([np.sin(off) * np.cos(az), np.sin(off) * np.sin(az), np.cos(off)])
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    r_face = np.stack([x, np.cross(z, x), z], axis=1)  # board axes in the camera frame, its normal along the ray
    axis = rng.normal(size=2)
    tilt = Rotation.from_rotvec(np.radians(rng.uniform(-max_tilt_deg, max_tilt_deg))
                                * np.r_[axis / np.linalg.norm(axis), 0.0]).as_matrix()
    r = r_face @ tilt
    t = rng.uniform(*distance_mm) * z - r @ centre
    return np.concatenate([np.asarray(rotation_vector(r)), t])
