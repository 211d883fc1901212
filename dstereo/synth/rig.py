"""Stereo rigs for synthetic scenes, including a reduced version of the thesis's Plasmatron set-up.

Reduced Plasmatron geometry (thesis 5.3.1): two cameras ~100 mm apart, both ~600 mm from the sample and aimed at
it (an isosceles triangle, d / B ~ 6). The thesis cameras (12 MP, 4000 x 3000, ~10,000 px focal length) are
reduced to 640 x 480 px with a 4,800 px focal length, so the field at 600 mm is 80 x 60 mm and the sample's 49 mm
head spans ~390 px, filling the frame as in the experiment while rendering in about a second.

The rig's world frame has its origin midway between the camera centres, x from the left to the right camera,
z towards the sample, y down.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from dstereo.models.camera import Camera
from dstereo.models.pose import rotation_vector
from dstereo.models.rig import Rig
from dstereo.synth.poses import compose, invert, look_at
from dstereo.synth.truth import camera_truth

# Two slightly different lenses (OpenCV order k1, k2, p1, p2, k3): the rig need not be symmetric.
PLASMATRON_COEFFS_LEFT = (-0.18, 0.9, 0.0004, -0.0003, 0.0)
PLASMATRON_COEFFS_RIGHT = (-0.22, 1.1, -0.0002, 0.0005, 0.0)


@dataclass
class StereoRig:
    """Two cameras, their `Rig` (T_right_left: x_right = R x_left + T, OpenCV's stereoCalibrate) and
    `T_left_world` (a 6-vector rvec, tvec)."""

    left: Camera
    right: Camera
    rig: Rig
    T_left_world: np.ndarray

    @property
    def T_right_left(self) -> np.ndarray:
        """The rig as a 6-vector (rvec, tvec), the form `dstereo.synth.poses` composes."""
        return np.array(self.rig.as_vector(), float)  # a writable copy: scipy refuses read-only views of JAX arrays

    @property
    def T_right_world(self) -> np.ndarray:
        return compose(self.T_right_left, self.T_left_world)

    def rotation_translation(self) -> tuple[np.ndarray, np.ndarray]:
        """(R, T) of T_right_left as OpenCV's stereoCalibrate returns them."""
        return np.array(self.rig.rotation(), float), np.array(self.rig.tvec, float)

    def to_truth(self) -> dict:
        r, t = self.rotation_translation()
        return {
            "left": camera_truth(self.left), "right": camera_truth(self.right),
            "T_right_left": self.T_right_left.tolist(), "R": r.tolist(), "T": t.tolist(),
            "T_left_world": np.asarray(self.T_left_world).tolist(),
        }


def stereo_rig(left: Camera, right: Camera, T_right_left) -> StereoRig:
    """Rig from two cameras and their relative pose (a `Rig` or its 6-vector); the world frame is the left camera's."""
    rig = T_right_left if isinstance(T_right_left, Rig) else Rig.from_vector(np.asarray(T_right_left, float).reshape(6))
    return StereoRig(left, right, rig, np.zeros(6))


def plasmatron_rig(
    image_size: tuple[int, int] = (640, 480),
    focal_px: float = 4800.0,
    baseline_mm: float = 100.0,
    distance_mm: float = 600.0,
    coeffs_left=PLASMATRON_COEFFS_LEFT,
    coeffs_right=PLASMATRON_COEFFS_RIGHT,
) -> StereoRig:
    """The reduced Plasmatron rig (module docstring): cameras at x = -+baseline/2 aimed at (0, 0, distance)."""
    w, h = image_size
    left = Camera.create(focal_px, focal_px * 1.0005, (w - 1) / 2 + 2.5, (h - 1) / 2 - 1.5, coeffs_left,
                         image_size=image_size)
    right = Camera.create(focal_px * 1.004, focal_px * 1.0035, (w - 1) / 2 - 3.0, (h - 1) / 2 + 2.0, coeffs_right,
                          image_size=image_size)
    target = np.array([0.0, 0.0, distance_mm])
    t_left_world = look_at([-baseline_mm / 2, 0.0, 0.0], target)
    t_right_world = look_at([baseline_mm / 2, 0.0, 0.0], target)
    return StereoRig(left, right, Rig.from_vector(compose(t_right_world, invert(t_left_world))), t_left_world)


def sample_pose(length_mm: float = 50.0, distance_mm: float = 600.0, yaw_deg: float = 0.0,
                pitch_deg: float = 0.0) -> np.ndarray:
    """T_world_sample: the sample's axis (+z of its frame) points back at the rig, turned by `yaw_deg` about the
    world y axis and `pitch_deg` about x, with the centre of the head circle (z = length) at (0, 0, distance)."""
    r_face = np.diag([1.0, -1.0, -1.0])  # sample +z -> world -z
    r_turn = Rotation.from_euler("yx", [yaw_deg, pitch_deg], degrees=True).as_matrix()
    rmat = r_turn @ r_face
    head = np.array([0.0, 0.0, distance_mm])
    tvec = head - rmat @ np.array([0.0, 0.0, length_mm])
    return np.concatenate([rotation_vector(rmat), tvec])


# A wide-angle rig for the fisheye paths (issue 16): two cv2.fisheye lenses of ~128 degrees across a 640 px width
# (corners 74 degrees off axis), 120 mm apart and converging by 4.6 degrees; the mixed rig swaps the left camera
# for a pinhole lens of 75 degrees. The two fisheye lenses differ (focal, centre, k1..k4), as real ones do.
FISHEYE_LEFT = ((285.0, 284.6, 322.4, 238.1), (0.05, -0.01, 0.003, -0.0005))
FISHEYE_RIGHT = ((290.2, 290.6, 317.5, 243.2), (0.03, 0.004, -0.002, 0.0003))
PINHOLE_LEFT = ((420.0, 420.5, 318.2, 241.7), (-0.2, 0.05, 0.0005, -0.0004, 0.0))
FISHEYE_RIG = (0.01, -0.08, 0.005, -120.0, 1.5, 3.0)  # T_right_left: rvec (rad), tvec (mm)


def fisheye_rig(mixed: bool = False, scale: float = 1.0) -> StereoRig:
    """Two fisheye cameras (or, `mixed`, a pinhole left and a fisheye right) at 640 x 480 px times `scale` (focal
    lengths and centres scaled alike: the same fields of view), in the FISHEYE_RIG pose; world = left camera."""
    from dstereo.models.distortion import PRESETS

    size = (int(round(640 * scale)), int(round(480 * scale)))

    def camera(spec, lens):
        (fx, fy, cx, cy), coeffs = spec
        c = lambda v: (v + 0.5) * scale - 0.5  # noqa: E731  (pixel centres scale about the image's corner)
        free = PRESETS["fisheye"] if lens == "fisheye" else PRESETS["default"]
        return Camera.create(fx * scale, fy * scale, c(cx), c(cy), coeffs, free, size)

    left = camera(PINHOLE_LEFT, "pinhole") if mixed else camera(FISHEYE_LEFT, "fisheye")
    return stereo_rig(left, camera(FISHEYE_RIGHT, "fisheye"), np.array(FISHEYE_RIG))


# A rig whose lenses see more than 180 degrees across the sensor (issue 30: a real one of 960 x 600 px, f ~ 227 px):
# equidistant-like cv2.fisheye lenses whose polynomials fold back at 144 / 141 degrees off the axis, 470 / 468 px
# from the centre, inside the 480 px half-width (the image's edge midpoints left and right have no ray; the
# top and bottom ones lie 76 / 75 degrees off the axis, at or past what a pinhole rectification holds). 100 mm
# apart, nearly parallel. Rendered with RenderOptions(blank_beyond_field=True): pixels past 90 degrees see nothing.
WIDE_FISHEYE_LEFT = ((227.0, 226.7, 481.3, 298.2), (0.01, -0.006, 0.0, 0.0))
WIDE_FISHEYE_RIGHT = ((229.1, 229.4, 478.6, 301.5), (0.012, -0.0066, 0.0, 0.0))
WIDE_FISHEYE_RIG = (0.004, -0.012, 0.003, -100.0, 0.8, 0.5)  # T_right_left: rvec (rad), tvec (mm)


def wide_fisheye_rig(scale: float = 1.0, lens=None) -> StereoRig:
    """Two fisheye cameras seeing more than 180 degrees across 960 x 600 px times `scale` (module constants), in the
    WIDE_FISHEYE_RIG pose; world = left camera. `lens`: one ((fx, fy, cx, cy), (k1..k4), (w, h)) for both cameras
    instead (e.g. a real camera's calibration paired with itself)."""
    from dstereo.models.distortion import PRESETS

    def camera(spec, size):
        (fx, fy, cx, cy), coeffs = spec
        c = lambda v: (v + 0.5) * scale - 0.5  # noqa: E731  (pixel centres scale about the image's corner)
        return Camera.create(fx * scale, fy * scale, c(cx), c(cy), coeffs, PRESETS["fisheye"],
                             (int(round(size[0] * scale)), int(round(size[1] * scale))))

    if lens is not None:
        (k, d, size) = lens
        return stereo_rig(camera((k, d), size), camera((k, d), size), np.array(WIDE_FISHEYE_RIG))
    size = (960, 600)
    return stereo_rig(camera(WIDE_FISHEYE_LEFT, size), camera(WIDE_FISHEYE_RIGHT, size), np.array(WIDE_FISHEYE_RIG))
