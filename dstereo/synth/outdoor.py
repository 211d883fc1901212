"""Outdoor-like stereo scenes with known depth (issue 30's ETH3D-style check on renders): a parallel rig of two
identical distortion-free cameras 1.5 m above a slanted ground plane, looking ahead and slightly down.

The scene, in the left camera's frame (x right, y down, z forward), from `outdoor_layers(seed)`:
- the ground: a plane running from under the cameras to 50 m, multi-scale (fractal) texture, seen at a grazing
  angle, so its disparity falls steadily up the image;
- a road: a low-texture strip on the ground (asphalt: a tenth of the ground's contrast);
- a backdrop at 45 m, 5 m high (hills, trees far away): large, soft texture, nearly at infinity (~1.7 px);
- a wall of a building at an angle, low texture (concrete);
- a few spheres standing on the ground (rocks, bushes) at 5-15 m, fractal texture;
- above the backdrop nothing: the renderer's dark background (a textureless sky, with no depth).
Positions and textures are drawn from the seed. Light from the side and above (Lambert shading: brightness
differences between surfaces facing the light or not). A difference of exposure between the two views is the
caller's to apply (`exposed`), as a camera pair with its own auto-exposure would show.

`visible_in_right` says which left pixels the right camera also sees (the rest are occluded, as Middlebury's
mask0nocc marks them): the scoring mask for density.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dstereo.synth.layered import Layer, layered_pair
from dstereo.synth.objects import Plane, Sphere
from dstereo.synth.poses import pose_from_rt
from dstereo.synth.rig import stereo_rig
from dstereo.synth.scenes import OBJECT_OPTIONS, StereoRender
from dstereo.synth.sensor import RenderOptions

HEIGHT_MM = 1500.0  # the cameras above the ground
PITCH_DEG = 8.0  # looking down by this much
FRACTAL_OCTAVES = 5  # octave k at size / 2^k: 400 mm blobs down to 25 mm on the ground


@dataclass(frozen=True)
class OutdoorRig:
    """The parallel rig: image size (w, h), focal length px, baseline mm."""

    size: tuple[int, int] = (480, 320)
    focal_px: float = 500.0
    baseline_mm: float = 150.0

    def camera(self):
        from dstereo.models.camera import Camera

        w, h = self.size
        return Camera.create(self.focal_px, self.focal_px, (w - 1) / 2, (h - 1) / 2, image_size=self.size)

    def calibration(self):
        """The rig's `StereoCalibration` (identical cameras side by side: rectification is the identity)."""
        from dstereo.io.calib_files import StereoCalibration

        k = np.asarray(self.camera().matrix())
        return StereoCalibration(k, np.zeros(8), k, np.zeros(8), np.eye(3), np.array([-self.baseline_mm, 0.0, 0.0]),
                                 self.size, source="rendered outdoor rig")


def _rx(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), -np.sin(a)], [0.0, np.sin(a), np.cos(a)]])


def _ry(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])


def outdoor_layers(seed: int = 0) -> list[Layer]:
    """The scene's surfaces in the left camera's frame (module docstring)."""
    rng = np.random.default_rng(seed)
    world_to_cam = _rx(PITCH_DEG)  # the cameras pitched down: a point ahead moves down their image

    def place(r_world: np.ndarray, t_world) -> np.ndarray:
        return pose_from_rt(world_to_cam @ r_world, world_to_cam @ np.asarray(t_world, float))

    flat = _rx(90.0)  # a Plane's z = 0 laid on the ground: its normal up (-y), its y axis forward
    layers = [
        Layer(Plane(15000.0, 25000.0), place(flat, [0.0, HEIGHT_MM, 25000.0]), 400.0, 0.6, FRACTAL_OCTAVES),
        # the road 5 mm above the ground (the nearer surface wins), 3 m wide, off to one side
        Layer(Plane(1500.0, 25000.0), place(flat, [rng.uniform(-2500.0, 2500.0), HEIGHT_MM - 5.0, 25000.0]),
              300.0, 0.1, FRACTAL_OCTAVES),
        Layer(Plane(60000.0, 2500.0), place(np.eye(3), [0.0, HEIGHT_MM - 2500.0, 45000.0]), 2500.0, 0.5, 3),
    ]
    side = rng.choice([-1.0, 1.0])
    wall_z = rng.uniform(11000.0, 14000.0)
    layers.append(Layer(Plane(2500.0, 1800.0), place(_ry(side * 35.0), [side * 4500.0, HEIGHT_MM - 1800.0, wall_z]),
                        500.0, 0.2, 3))
    for _ in range(3):
        radius = rng.uniform(400.0, 1100.0)
        z = rng.uniform(5000.0, 15000.0)
        x = rng.uniform(-0.3, 0.3) * z
        layers.append(Layer(Sphere(radius), place(np.eye(3), [x, HEIGHT_MM - radius, z]), 150.0, 0.7, FRACTAL_OCTAVES))
    return layers


def outdoor_pair(rig: OutdoorRig = OutdoorRig(), seed: int = 0,
                 options: RenderOptions = OBJECT_OPTIONS) -> StereoRender:
    """Both views of `outdoor_layers(seed)` (module docstring), with their truth (`depth` mm, `layer`)."""
    cam = rig.camera()
    srig = stereo_rig(cam, cam, np.array([0.0, 0.0, 0.0, -rig.baseline_mm, 0.0, 0.0]))
    return layered_pair(srig, outdoor_layers(seed), seed=seed, options=options)


def exposed(image: np.ndarray, gain: float, gamma: float = 1.0) -> np.ndarray:
    """The image's levels through 255 gain (I / 255)^gamma, rounded to 8 bits (another exposure and response)."""
    x = image.astype(np.float64) / 255.0
    return np.clip(np.rint(255.0 * gain * x ** gamma), 0, 255).astype(np.uint8)


def true_disparity(render: StereoRender, rig: OutdoorRig = OutdoorRig()) -> np.ndarray:
    """The left view's true disparity px (f b / Z: the rectification is the identity), NaN where no surface."""
    return rig.focal_px * rig.baseline_mm / render.truth_left["depth"]


def visible_in_right(render: StereoRender, rig: OutdoorRig = OutdoorRig(), tol: float = 0.01) -> np.ndarray:
    """(h, w) bool: left pixels with a surface whose point the right camera sees too (its depth there, on the same
    row at x - d, within `tol` of the point's: not hidden behind a nearer surface, not off the right image)."""
    z_left, z_right = render.truth_left["depth"], render.truth_right["depth"]
    h, w = z_left.shape
    d = true_disparity(render, rig)
    x = np.arange(w)[None, :] - np.nan_to_num(d, nan=-1e9)
    seen = np.zeros((h, w), bool)
    for col in (np.floor(x), np.ceil(x)):
        inside = (col >= 0) & (col <= w - 1)
        c = np.clip(col, 0, w - 1).astype(int)
        zr = np.take_along_axis(z_right, c, axis=1)
        seen |= inside & (np.abs(zr - z_left) <= tol * z_left)
    return seen & np.isfinite(z_left)
