"""Scenes of several analytic surfaces in depth (issue 30): a near board in front of a far wall, each with its own
speckle, composited per pixel by the nearest hit.

Each layer is rendered alone (`render_object`, same camera rays); a pixel shows the layer whose centre ray hits
nearest. Pixels on a layer's silhouette average that layer with the renderer's black background over the
pixel's samples instead of with the layer behind: a one-pixel seam, as a defocused real edge also has.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dstereo.synth.poses import compose, pose_matrix
from dstereo.synth.rays import camera_rays
from dstereo.synth.render import render_object
from dstereo.synth.rig import StereoRig
from dstereo.synth.scenes import LIGHT_WORLD, OBJECT_OPTIONS, StereoRender
from dstereo.synth.sensor import RenderOptions
from dstereo.synth.texture import Speckle


@dataclass(frozen=True)
class Layer:
    """One surface of a layered scene: the surface (Plane, Sphere, Sample), T_world_object, its speckle size, the
    speckle's contrast and octaves (`Speckle.create`)."""

    surface: object
    T_world_object: np.ndarray
    speckle_mm: float
    contrast: float = 2.0
    octaves: int = 2


def layered_pair(rig: StereoRig, layers: list[Layer], seed: int = 0,
                 options: RenderOptions = OBJECT_OPTIONS) -> StereoRender:
    """Both cameras of `rig` viewing every layer; truth per camera: `depth` (the nearest layer's, NaN where none)
    and `layer` (its index, -1 where none)."""
    poses = [(rig.left, rig.T_left_world), (rig.right, rig.T_right_world)]
    images, truths = [], []
    for c, (camera, T_cam_world) in enumerate(poses):
        rays, centre_rays = camera_rays(camera, options.supersample), camera_rays(camera, 1)
        image, depth, which = None, None, None
        for i, layer in enumerate(layers):
            img, truth = render_object(camera, compose(T_cam_world, layer.T_world_object), layer.surface,
                                       Speckle.create(seed + 101 * i, layer.speckle_mm, layer.contrast, layer.octaves),
                                       _light(layer),
                                       options=options, seed=[seed, c, i], rays=rays, centre_rays=centre_rays)
            z = np.where(np.isfinite(truth["depth"]), truth["depth"], np.inf)
            if image is None:
                image, depth, which = img.copy(), z, np.where(np.isfinite(z), i, -1)
                continue
            nearer = z < depth
            image[nearer], depth[nearer], which[nearer] = img[nearer], z[nearer], i
        images.append(image)
        truths.append({"kind": "layered", "rig": rig.to_truth(), "depth": np.where(np.isfinite(depth), depth, np.nan),
                       "layer": which.astype(np.int8), "camera": truth["camera"]})
    return StereoRender(images[0], images[1], truths[0], truths[1])


def _light(layer: Layer) -> np.ndarray:
    """The scenes' light (from the cameras' side, above) in the layer's object frame."""
    return pose_matrix(layer.T_world_object)[:3, :3].T @ np.asarray(LIGHT_WORLD, float)
