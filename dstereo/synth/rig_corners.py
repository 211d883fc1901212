"""Corners of a K-camera rig seeing a board, without images: the rig tests' fast cases (`synth/multiview.py`'s
rig and frames, projected exactly, Gaussian noise added), and a rig whose cameras do not expose at one moment."""

from __future__ import annotations

import jax
import numpy as np

from dstereo.models.board import sagged
from dstereo.models.camera import project_view
from dstereo.synth.board import object_points
from dstereo.synth.multiview import MULTIVIEW_BOARD, multiview_poses, ring_rig
from dstereo.synth.poses import compose

_project = jax.jit(jax.vmap(project_view, in_axes=(None, None, None, 0)))


def rig_corners(n_cameras: int = 3, n_frames: int = 24, seed: int = 0, noise_px: float = 0.1,
                shift_mm: float = 0.0, sag_mm=None, board=MULTIVIEW_BOARD) -> dict:
    """obj (n, 3) the flat board, obs (F, K, n, 2) (NaN where a camera misses the frame), visible (F, K), the rig
    and the frames' poses (F, 6) T_ref_board. `shift_mm`: each camera but the reference sees each frame's board
    moved by this much in a random direction (exposures at different moments of a moving board). `sag_mm`: (x, y)
    the board's sag (`models.board.sag_basis`) in the corners seen."""
    rig = ring_rig(n_cameras)
    # a pair sees every frame with both cameras; more cameras miss 20-40 % of the frames each
    missing = (0.0, 0.0) if n_cameras == 2 else (0.2, 0.4)
    poses, visible, _ = multiview_poses(rig, board, n_frames, seed, missing=missing)
    rng = np.random.default_rng([seed, 7])
    obj = np.asarray(object_points(board.pattern, board.square), float)
    seen_board = sagged(obj, sag_mm)
    obs = np.full((n_frames, n_cameras, len(obj), 2), np.nan)
    for f, pose in enumerate(poses):
        for c, (cam, t_cam_ref) in enumerate(zip(rig.cameras, rig.T_cam_ref)):
            if not visible[f, c]:
                continue
            seen = np.array(pose, float)
            if c > 0 and shift_mm:
                step = rng.normal(size=3)
                seen[3:] += shift_mm * step / np.linalg.norm(step)
            q = np.asarray(_project(cam.k, cam.dist.coeffs, compose(t_cam_ref, seen), seen_board))
            obs[f, c] = q + rng.normal(0.0, noise_px, q.shape)
    return {"obj": obj, "obs": obs, "visible": visible, "rig": rig, "poses": poses, "image_sizes":
            [tuple(c.image_size) for c in rig.cameras]}
