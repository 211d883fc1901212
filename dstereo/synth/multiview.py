"""K-camera rigs with different cameras around a board volume, partial visibility, and their truth (issue 17).

The rig's cameras differ in focal length, principal point, distortion, image size and mounting roll (one camera
hangs upside down, so OpenCV numbers its corners from the opposite board corner). They stand on an arc around a
volume in which the board moves; a frame is one board pose, seen by the cameras that see the whole board face-on
enough (`poses.board_visible`). Every frame is seen by at least two cameras and each camera misses a share of
the frames: the board out of its view or too oblique, or its image left out (a dropped frame) until the share
reaches the camera's target.

Frame of reference: camera 0's ("ref"). `T_cam_ref[k]` maps ref coordinates into camera k
(x_cam_k = R_k x_ref + T_k, the `R_i`, `T_i` of `cameras.yml`), `poses_ref_board[f]` the board into ref.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from dstereo.errors import DstereoError
from dstereo.models.camera import Camera
from dstereo.synth.board import Board, object_points
from dstereo.synth.poses import board_visible, compose, invert, look_at, pose_from_rt, pose_matrix
from dstereo.synth.rays import camera_rays
from dstereo.synth.render import render_board
from dstereo.synth.sensor import RenderOptions
from dstereo.synth.truth import camera_truth

# The board's area integral per pixel is exact (board.board_reflectance), so one sample per pixel is already
# anti-aliased; the 1 px blur keeps cornerSubPix unbiased (scenes.CALIBRATION_OPTIONS) at a sixth of its cost.
MULTIVIEW_OPTIONS = RenderOptions(supersample=1, defocus_sigma_px=1.0)
# 9 x 6 inner corners: 10 x 7 squares, whose opposite corner squares differ in colour (io.corner_order).
MULTIVIEW_BOARD = Board((9, 6), 20.0, 20.0)

# (name, image size, fx, fy/fx, principal point offset from the centre (px), k1, k2, p1, p2, k3, roll (deg),
#  arc angle (deg), height (mm)). Sizes 640x480..800x600 keep renders fast; focal lengths make the board fill
#  roughly a third to two thirds of each image at the arc's radius.
CAMERA_SPECS = (
    ("cam0", (640, 480), 820.0, 1.0004, (4.0, -3.0), -0.12, 0.16, 0.0005, -0.0004, 0.0, 0.0, -8.0, 0.0),
    ("cam1", (800, 600), 1150.0, 0.9995, (-6.0, 5.0), 0.06, -0.12, -0.0003, 0.0006, 0.0, 0.0, 22.0, -90.0),
    ("cam2", (720, 540), 930.0, 1.0008, (3.0, 7.0), -0.2, 0.3, 0.0002, 0.0003, 0.0, 180.0, -34.0, 70.0),
    ("cam3", (640, 480), 760.0, 1.0, (-5.0, -4.0), -0.05, 0.08, -0.0006, -0.0002, 0.0, 0.0, 44.0, 40.0),
)
ARC_RADIUS_MM = 900.0
VOLUME_HALF_MM = (200.0, 130.0, 150.0)  # board centre: uniform in this box around the arc's centre


@dataclass(frozen=True)
class MultiviewRig:
    """K cameras; `T_cam_ref` (K, 6) as (rvec, tvec), camera 0 the reference (zeros)."""

    names: tuple[str, ...]
    cameras: tuple[Camera, ...]
    T_cam_ref: np.ndarray

    def to_truth(self) -> dict:
        mats = [pose_matrix(p) for p in self.T_cam_ref]
        return {"names": list(self.names), "cameras": [camera_truth(c) for c in self.cameras],
                "T_cam_ref": np.asarray(self.T_cam_ref).tolist(), "R": [m[:3, :3].tolist() for m in mats],
                "T": [m[:3, 3].tolist() for m in mats]}


def _camera(spec) -> tuple[str, Camera, float, float, float]:
    name, (w, h), fx, aspect, (dx, dy), k1, k2, p1, p2, k3, roll, arc, height = spec
    cam = Camera.create(fx, fx * aspect, (w - 1) / 2 + dx, (h - 1) / 2 + dy, (k1, k2, p1, p2, k3), image_size=(w, h))
    return name, cam, roll, arc, height


def ring_rig(n_cameras: int) -> MultiviewRig:
    """The first `n_cameras` (2..4) of CAMERA_SPECS on an arc of radius ARC_RADIUS_MM aimed at its centre."""
    if not 2 <= n_cameras <= len(CAMERA_SPECS):
        raise DstereoError(f"ring_rig: n_cameras={n_cameras}; choose 2 to {len(CAMERA_SPECS)}")
    names, cams, world = [], [], []
    centre = np.array([0.0, 0.0, ARC_RADIUS_MM])
    for spec in CAMERA_SPECS[:n_cameras]:
        name, cam, roll, arc, height = _camera(spec)
        a = np.radians(arc)
        eye = centre + ARC_RADIUS_MM * np.array([np.sin(a), 0.0, -np.cos(a)]) + np.array([0.0, height, 0.0])
        aimed = look_at(eye, centre)
        # Roll about the optical axis: the camera's own frame turns, so the image turns the other way.
        rolled = compose(np.r_[0.0, 0.0, np.radians(roll), np.zeros(3)], aimed)  # rvec of a turn about z
        names.append(name)
        cams.append(cam)
        world.append(rolled)
    t_world_ref = invert(world[0])
    return MultiviewRig(tuple(names), tuple(cams), np.stack([compose(t, t_world_ref) for t in world]))


def _volume_centre_ref(rig: MultiviewRig) -> tuple[np.ndarray, np.ndarray]:
    """The arc's centre and the mean viewing direction towards it (unit), in the ref frame."""
    centres = np.stack([-pose_matrix(t)[:3, :3].T @ pose_matrix(t)[:3, 3] for t in rig.T_cam_ref])
    axes = np.stack([pose_matrix(t)[:3, :3].T @ np.array([0.0, 0.0, 1.0]) for t in rig.T_cam_ref])
    # The point nearest to every optical axis (least squares): where the cameras are aimed.
    a = sum(np.eye(3) - np.outer(v, v) for v in axes)
    b = sum((np.eye(3) - np.outer(v, v)) @ c for v, c in zip(axes, centres))
    target = np.linalg.solve(a, b)
    mean_axis = axes.mean(axis=0)
    return target, mean_axis / np.linalg.norm(mean_axis)


def _candidate(rng: np.random.Generator, rig: MultiviewRig, board: Board, max_tilt_deg: float) -> np.ndarray:
    """T_ref_board: centre uniform in the volume, facing a random camera's direction, tilted and rolled at random."""
    target, _ = _volume_centre_ref(rig)
    centre = target + rng.uniform(-1.0, 1.0, 3) * np.array(VOLUME_HALF_MM)
    k = rng.integers(len(rig.cameras))
    m = pose_matrix(rig.T_cam_ref[k])
    cam_centre = -m[:3, :3].T @ m[:3, 3]
    z = centre - cam_centre  # board +z points away from the camera it faces (its front faces that camera)
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z) if abs(z[1]) < 0.9 else np.cross([1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    facing = np.stack([x, np.cross(z, x), z], axis=1)
    tilt = np.radians(max_tilt_deg) * np.sqrt(rng.uniform())
    phi = rng.uniform(0.0, 2 * np.pi)
    r_tilt = Rotation.from_rotvec(tilt * np.array([np.cos(phi), np.sin(phi), 0.0])).as_matrix()
    r_roll = Rotation.from_rotvec([0.0, 0.0, rng.uniform(-np.pi, np.pi)]).as_matrix()
    rmat = facing @ r_tilt @ r_roll
    return pose_from_rt(rmat, centre - rmat @ board.centre())


def _seen(rig: MultiviewRig, board: Board, pose_ref_board, margin_px: float, max_view_deg: float) -> np.ndarray:
    return np.array([board_visible(cam, compose(t, pose_ref_board), board, margin_px, max_view_deg)
                     for cam, t in zip(rig.cameras, rig.T_cam_ref)])


def multiview_poses(
    rig: MultiviewRig, board: Board, n_frames: int = 60, seed: int = 0, missing: tuple[float, float] = (0.2, 0.4),
    max_tilt_deg: float = 35.0, max_view_deg: float = 55.0, margin_px: float = 6.0, tries: int = 4000,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(poses (F, 6) T_ref_board, visible (F, K) bool, left_out (F, K) bool) with the module's visibility rules.

    Each camera k draws a target missing share in `missing`; a candidate pose is kept when at least two cameras
    see it and no camera's geometric misses exceed its target. Cameras still short of their target then lose
    frames at random (`left_out`: seen, but the image is left out) among frames that keep two other cameras.
    """
    rng = np.random.default_rng(seed)
    n_cams = len(rig.cameras)
    target = np.floor(rng.uniform(*missing, n_cams) * n_frames).astype(int)
    poses, seen = [], []
    for _ in range(tries):
        if len(poses) == n_frames:
            break
        pose = _candidate(rng, rig, board, max_tilt_deg)
        vis = _seen(rig, board, pose, margin_px, max_view_deg)
        misses = np.sum(~np.array(seen, bool).reshape(-1, n_cams), axis=0) + ~vis
        if vis.sum() >= 2 and np.all(misses <= target):
            poses.append(pose)
            seen.append(vis)
    if len(poses) < n_frames:
        raise DstereoError(f"multiview_poses: only {len(poses)} of {n_frames} frames found in {tries} tries; "
                           "widen `missing` or `max_view_deg`")
    seen = np.array(seen)
    left_out = np.zeros_like(seen)
    for k in rng.permutation(n_cams):
        for f in rng.permutation(n_frames):
            visible = seen & ~left_out
            if np.sum(~visible[:, k]) >= target[k]:
                break
            if visible[f, k] and visible[f].sum() > 2:
                left_out[f, k] = True
    visible = seen & ~left_out
    short = np.sum(~visible, axis=0) < np.floor(missing[0] * n_frames)
    if np.any(short):
        raise DstereoError(f"multiview_poses: cameras {np.flatnonzero(short).tolist()} miss fewer than "
                           f"{missing[0]:.0%} of the frames; use more cameras or a smaller `missing`")
    return np.stack(poses), visible, left_out


@dataclass
class MultiviewSet:
    """images[k][f]: uint8 image or None where camera k misses frame f; `truth` as in `multiview_set`."""

    rig: MultiviewRig
    frame_names: list[str]
    images: list[list[np.ndarray | None]]
    truth: dict


def multiview_set(n_cameras: int = 3, n_frames: int = 60, seed: int = 0, board: Board = MULTIVIEW_BOARD,
                  options: RenderOptions = MULTIVIEW_OPTIONS) -> MultiviewSet:
    """Render `ring_rig(n_cameras)` viewing `board` at `multiview_poses`; noise-free but for 8-bit quantisation.

    `truth`: rig (cameras, T_cam_ref, R, T), board, `poses_ref_board` (F, 6), `visible` / `left_out` (F, K),
    `object_points` (n, 3) mm and `corners` (F, K, n, 2) true pixels (NaN where not visible).
    """
    rig = ring_rig(n_cameras)
    poses, visible, left_out = multiview_poses(rig, board, n_frames, seed)
    names = [f"frame_{f:03d}" for f in range(n_frames)]
    n_pts = board.pattern[0] * board.pattern[1]
    corners = np.full((n_frames, n_cameras, n_pts, 2), np.nan)
    images: list[list[np.ndarray | None]] = []
    for k, (cam, t_cam_ref) in enumerate(zip(rig.cameras, rig.T_cam_ref)):
        rays = camera_rays(cam, options.supersample)
        centre = rays if options.supersample == 1 else camera_rays(cam, 1)
        row: list[np.ndarray | None] = []
        for f, pose in enumerate(poses):
            if not visible[f, k]:
                row.append(None)
                continue
            image, view = render_board(cam, compose(t_cam_ref, pose), board, options, seed=[seed, k, f], rays=rays,
                                       centre_rays=centre)
            corners[f, k] = view["corners"]
            row.append(image)
        images.append(row)
    truth = {
        "kind": "multiview_set", "rig": rig.to_truth(), "frames": names, "seed": seed,
        "board": {"pattern": list(board.pattern), "square": board.square, "border": board.border},
        "render": options.to_truth(), "poses_ref_board": poses, "visible": visible, "left_out": left_out,
        "object_points": object_points(board.pattern, board.square), "corners": corners,
    }
    return MultiviewSet(rig, names, images, truth)


def multiview_corners(rig: MultiviewRig, board: Board, poses: np.ndarray, visible: np.ndarray, sag=None,
                      noise_px: float = 0.0, seed: int = 0) -> np.ndarray:
    """(F, K, n, 2) the board's true corners in every camera that sees each frame (NaN elsewhere), without
    rendering: `true_corners` through each camera's pose, the board sagged by `sag`, plus Gaussian noise of
    `noise_px` per coordinate."""
    from dstereo.synth.board import true_corners

    rng = np.random.default_rng(seed)
    n = board.pattern[0] * board.pattern[1]
    out = np.full((len(poses), len(rig.cameras), n, 2), np.nan)
    for f, pose in enumerate(poses):
        for k, (cam, t_cam_ref) in enumerate(zip(rig.cameras, rig.T_cam_ref)):
            if visible[f, k]:
                q = true_corners(cam, compose(t_cam_ref, pose), board.pattern, board.square, sag)
                out[f, k] = q + rng.normal(0.0, noise_px, q.shape)
    return out
