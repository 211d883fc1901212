"""Scene builders for demos and tests: calibration image sets, cork-sample stereo pairs, recession sequences.

Every builder is deterministic in its `seed`: board poses, speckle and sensor noise all come from numpy
Generators seeded from it. Ray grids are computed once per camera and shared by all views.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dstereo.errors import DstereoError
from dstereo.models.camera import Camera
from dstereo.synth.board import Board
from dstereo.synth.objects import Sample
from dstereo.synth.poses import board_pose_set, compose, pose_matrix
from dstereo.synth.rays import camera_rays
from dstereo.synth.recession import RecessionProfile, frame_times, profile_for_total, receded
from dstereo.synth.render import render_board, render_object
from dstereo.synth.rig import StereoRig, plasmatron_rig, sample_pose
from dstereo.synth.sensor import RenderOptions
from dstereo.synth.texture import Speckle

# A real lens never images an edge sharper than about a pixel. A perfectly box-sampled edge is aliased enough
# that cv2.cornerSubPix's gradient estimate is biased by up to ~0.08 px with the corner's sub-pixel phase, so
# calibration renders carry a 1 px Gaussian lens blur by default (noise-free; symmetric, so corners stay put).
CALIBRATION_OPTIONS = RenderOptions(supersample=2, defocus_sigma_px=1.0)
OBJECT_OPTIONS = RenderOptions(supersample=2, defocus_sigma_px=0.5)
LIGHT_WORLD = (0.25, -0.5, -1.0)  # towards the light, rig world frame: from the cameras' side, above


@dataclass
class CalibrationSet:
    """Images of one board at the same poses in each camera, with per-image truths and a set-level truth.

    `truth` holds the cameras, `T_right_left`, the board, `poses_left` (n, 6) T_left_board, `object_points`
    (m, 3) and `corners_left` / `corners_right` (n, m, 2) true pixel positions.
    """

    left: list[np.ndarray]
    right: list[np.ndarray] | None
    views_left: list[dict]
    views_right: list[dict] | None
    truth: dict = field(default_factory=dict)


def calibration_set(
    cam_left: Camera,
    cam_right: Camera | None = None,
    T_right_left=None,
    pattern: tuple[int, int] = (9, 6),
    square: float = 3.75,
    border: float | None = None,
    n_views: int = 12,
    seed: int = 0,
    options: RenderOptions = CALIBRATION_OPTIONS,
    max_tilt_deg: float = 45.0,
    fill: tuple[float, float] = (0.35, 0.6),
    poses: np.ndarray | None = None,
) -> CalibrationSet:
    """Render `n_views` good board poses (`poses.board_pose_set`) in one camera or both cameras of a rig.

    `square` and `border` in mm (border defaults to one square; 3.75 mm squares as in the thesis); for a rig,
    `T_right_left` is (rvec, tvec) with x_right = R x_left + T. `poses` (n, 6) T_left_board: these views instead
    (e.g. `poses.wide_board_poses` for a lens whose pinhole-minded pose set would not fit).
    """
    if (cam_right is None) != (T_right_left is None):
        raise DstereoError("calibration_set: give both cam_right and T_right_left for a rig, or neither")
    board = Board(tuple(pattern), float(square), float(square if border is None else border))
    cameras = [cam_left] + ([cam_right] if cam_right is not None else [])
    rig = [np.zeros(6)] + ([np.asarray(T_right_left, float).reshape(6)] if cam_right is not None else [])
    if poses is None:
        poses = board_pose_set(cameras, rig, board, n_views, seed, max_tilt_deg=max_tilt_deg, fill=fill)
    poses = np.asarray(poses, float).reshape(-1, 6)
    images, views = [], []
    for c, (cam, t_cam_left) in enumerate(zip(cameras, rig)):
        blank = options.blank_beyond_field
        rays, centre = camera_rays(cam, options.supersample, blank), camera_rays(cam, 1, blank)
        rendered = [render_board(cam, compose(t_cam_left, p), board, options, seed=[seed, c, i], rays=rays,
                                 centre_rays=centre) for i, p in enumerate(poses)]
        images.append([img for img, _ in rendered])
        views.append([t for _, t in rendered])
    truth = {
        "kind": "calibration_set",
        "board": {"pattern": list(board.pattern), "square": board.square, "border": board.border},
        "left": views[0][0]["camera"],
        "poses_left": poses,
        "object_points": board.geometry.object_points(),
        "corners_left": np.stack([v["corners"] for v in views[0]]),
        "render": options.to_truth(),
        "seed": seed,
    }
    if cam_right is not None:
        m = pose_matrix(rig[1])
        truth |= {"right": views[1][0]["camera"], "T_right_left": rig[1].tolist(), "R": m[:3, :3].tolist(),
                  "T": m[:3, 3].tolist(), "corners_right": np.stack([v["corners"] for v in views[1]])}
    right = images[1] if cam_right is not None else None
    return CalibrationSet(images[0], right, views[0], views[1] if cam_right is not None else None, truth)


@dataclass
class StereoRender:
    """One stereo pair of an object and its truths (per camera: camera, pose, depth map, surface)."""

    left: np.ndarray
    right: np.ndarray
    truth_left: dict
    truth_right: dict


def _object_pair(rig: StereoRig, surface, texture: Speckle, T_world_object, light_world, options, seed: list[int],
                 rays: dict, extra: dict) -> StereoRender:
    """Render both cameras; `seed` (a list) is extended by the camera index for the sensor noise."""
    t_left_obj = compose(rig.T_left_world, T_world_object)
    t_right_obj = compose(rig.T_right_left, t_left_obj)
    light_obj = pose_matrix(T_world_object)[:3, :3].T @ np.asarray(light_world, float)
    out = []
    for c, (cam, pose) in enumerate(((rig.left, t_left_obj), (rig.right, t_right_obj))):
        image, truth = render_object(cam, pose, surface, texture, light_obj, options=options, seed=[*seed, c],
                                     rays=rays[c][0], centre_rays=rays[c][1])
        truth |= {"rig": rig.to_truth(), "T_world_object": np.asarray(T_world_object).tolist(), **extra}
        out.append((image, truth))
    return StereoRender(out[0][0], out[1][0], out[0][1], out[1][1])


def _rays_for(rig: StereoRig, options: RenderOptions) -> dict:
    cams = (rig.left, rig.right)
    blank = options.blank_beyond_field
    return {c: (camera_rays(cam, options.supersample, blank), camera_rays(cam, 1, blank)) for c, cam in enumerate(cams)}


def object_pair(rig: StereoRig, surface, T_world_object, seed: int = 0, speckle_mm: float = 0.6,
                light_world=LIGHT_WORLD, options: RenderOptions = OBJECT_OPTIONS) -> StereoRender:
    """Both cameras of `rig` viewing any analytic `surface` (Plane, Sphere, Sample) placed at `T_world_object`."""
    texture = Speckle.create(seed, speckle_mm)
    return _object_pair(rig, surface, texture, T_world_object, light_world, options, [seed], _rays_for(rig, options),
                        {})


def sample_pair(
    rig: StereoRig | None = None,
    sample: Sample | None = None,
    T_world_sample=None,
    seed: int = 0,
    speckle_mm: float = 0.6,
    light_world=LIGHT_WORLD,
    options: RenderOptions = OBJECT_OPTIONS,
) -> StereoRender:
    """The cork sample (domed unless `sample` says otherwise, e.g. `Sample.flat()`) seen by the reduced
    Plasmatron rig (`rig.plasmatron_rig`), its head 600 mm from both cameras, its axis pointing back at the rig."""
    rig = plasmatron_rig() if rig is None else rig
    sample = Sample() if sample is None else sample
    T_world_sample = sample_pose(sample.length) if T_world_sample is None else T_world_sample
    return object_pair(rig, sample, T_world_sample, seed, speckle_mm, light_world, options)


def recession_sequence(
    rig: StereoRig | None = None,
    sample: Sample | None = None,
    profile: RecessionProfile | None = None,
    n_frames: int = 10,
    duration_s: float = 40.0,
    T_world_sample=None,
    seed: int = 0,
    speckle_mm: float = 0.6,
    options: RenderOptions = OBJECT_OPTIONS,
) -> list[StereoRender]:
    """One stereo pair per timestamp while the front face recedes by `profile` (default: 2 mm at the stagnation
    point after `duration_s`). Each truth carries `time_s`, `recession_stagnation_mm` and the profile."""
    rig = plasmatron_rig() if rig is None else rig
    sample = Sample() if sample is None else sample
    profile = profile_for_total(2.0, duration_s) if profile is None else profile
    T_world_sample = sample_pose(sample.length) if T_world_sample is None else T_world_sample
    texture = Speckle.create(seed, speckle_mm)
    rays = _rays_for(rig, options)
    frames = []
    for i, t in enumerate(frame_times(n_frames, duration_s)):
        extra = {"frame": i, "time_s": float(t), "recession_stagnation_mm": profile.at_stagnation(t),
                 "profile": profile.to_truth()}
        frames.append(_object_pair(rig, receded(sample, profile, t), texture, T_world_sample, LIGHT_WORLD,
                                   options, [seed, i], rays, extra))
    return frames

