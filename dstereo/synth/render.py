"""Render a chessboard or an analytic object seen by one camera, with the truth of the render.

Every pixel sample is traced along the ray through the exact inverse of the camera's distortion
(`rays.camera_rays`), intersected with the board plane or the object, and shaded; samples are averaged per pixel
(box-filter anti-aliasing), then `sensor.expose` turns radiance into an 8-bit image. Ray grids depend only on
the camera, so callers rendering many views with one camera compute them once and pass them in.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dstereo.models.camera import Camera
from dstereo.models.pose import rodrigues
from dstereo.synth.board import Board, board_reflectance, true_corners
from dstereo.synth.objects import MISS
from dstereo.synth.rays import camera_rays, map_chunked
from dstereo.synth.sensor import RenderOptions, expose
from dstereo.synth.texture import Speckle, albedo, lambert
from dstereo.synth.truth import camera_truth


def _ray_frame(pose: Float[Array, "6"]) -> tuple[Float[Array, "3"], Float[Array, "3 3"]]:
    """Camera centre in the object frame and the camera-to-object rotation, for T_cam_object `pose`."""
    r = rodrigues(pose[:3])
    return -r.T @ pose[3:6], r.T


# --- chessboard -------------------------------------------------------------------------------------------
@partial(jax.jit, static_argnames=("board",))
def board_radiance(rays: Float[Array, "h w s2 2"], pose: Float[Array, "6"], board: Board) -> Float[Array, "h w"]:
    """Pixel-averaged board reflectance for rays (h, w, s*s, 2) and T_cam_board `pose`."""
    h, w, s2, _ = rays.shape
    s = int(round(s2**0.5))
    o, r_t = _ray_frame(pose)
    seen = jnp.all(jnp.isfinite(rays), axis=-1)  # NaN: a sample with no ray in front (`camera_rays(blank=True)`)
    rays = jnp.where(seen[..., None], rays, 0.0)
    d = jnp.einsum("ij,hwsj->hwsi", r_t, jnp.concatenate([rays, jnp.ones(rays.shape[:-1] + (1,))], axis=-1))
    dz = jnp.where(jnp.abs(d[..., 2]) > 1e-15, d[..., 2], 1e-15)
    t = -o[2] / dz
    xy = o[:2] + t[..., None] * d[..., :2]
    # Footprint of one sample on the board: the pixel-to-board Jacobian (finite differences across pixels).
    centre = jnp.mean(xy, axis=2)
    d_du = jnp.gradient(centre, axis=1)
    d_dv = jnp.gradient(centre, axis=0)
    width = jnp.clip((jnp.abs(d_du) + jnp.abs(d_dv)) / s, 0.0, 10.0 * board.square)
    width = jnp.broadcast_to(width[:, :, None, :], xy.shape)
    refl = jax.vmap(board_reflectance, in_axes=(None, 0, 0))(board, xy.reshape(-1, 2), width.reshape(-1, 2))
    refl = jnp.where((t > 0).reshape(-1) & seen.reshape(-1), refl, board.background)
    return jnp.mean(refl.reshape(h, w, s2), axis=2)


@partial(jax.jit, static_argnames=("board",))
def board_depth(centre_rays: Float[Array, "h w 1 2"], pose: Float[Array, "6"], board: Board) -> Float[Array, "h w"]:
    """Depth Z (camera frame, mm) of the printed board through each pixel centre; NaN off the board."""
    o, r_t = _ray_frame(pose)
    xy1 = jnp.concatenate([centre_rays[:, :, 0], jnp.ones(centre_rays.shape[:2] + (1,))], axis=-1)
    d = jnp.einsum("ij,hwj->hwi", r_t, xy1)
    t = -o[2] / jnp.where(jnp.abs(d[..., 2]) > 1e-15, d[..., 2], 1e-15)
    xy = o[:2] + t[..., None] * d[..., :2]
    x0, y0, x1, y1 = board.squares_extent()
    b = board.border
    inside_x = (xy[..., 0] >= x0 - b) & (xy[..., 0] <= x1 + b)
    inside_y = (xy[..., 1] >= y0 - b) & (xy[..., 1] <= y1 + b)
    return jnp.where((t > 0) & inside_x & inside_y, t, jnp.nan)


def render_board(
    camera: Camera, pose, board: Board, options: RenderOptions = RenderOptions(), seed=0, rays=None,
    centre_rays=None,
) -> tuple[np.ndarray, dict]:
    """8-bit image of `board` at T_cam_board `pose` (rvec, tvec), and its truth: camera, pose, true corners
    (`corners`, (n, 2) px, OpenCV's object-point order; `corners_in_image` flags those inside the frame) and the
    board's depth map (`depth`, NaN off the board).

    `rays` / `centre_rays`: `camera_rays(camera, options.supersample)` / `camera_rays(camera, 1)` if already
    computed; `seed` (an int or a list of ints) feeds the sensor noise.
    """
    blank = options.blank_beyond_field
    rays = camera_rays(camera, options.supersample, blank) if rays is None else rays
    if centre_rays is None:
        centre_rays = rays if options.supersample == 1 else camera_rays(camera, 1, blank)
    pose = np.asarray(pose, float).reshape(6)
    radiance = np.asarray(board_radiance(rays, jnp.asarray(pose), board))
    image = expose(radiance, np.asarray(camera.k[2:4]), options, np.random.default_rng(seed))
    corners = true_corners(camera, pose, board.pattern, board.square)
    w, h = camera.image_size
    truth = {
        "kind": "board",
        "camera": camera_truth(camera),
        "pose_cam_board": pose.tolist(),
        "board": {"pattern": list(board.pattern), "square": board.square, "border": board.border},
        "render": options.to_truth(),
        "seed": np.asarray(seed).tolist(),
        "corners": corners,
        "corners_in_image": np.all((corners >= -0.5) & (corners <= np.array([w, h]) - 0.5), axis=1),
        "depth": np.asarray(board_depth(centre_rays, jnp.asarray(pose), board)),
    }
    return image, truth


# --- analytic objects -------------------------------------------------------------------------------------
def _trace(surface, o, r_t, xy):
    seen = jnp.all(jnp.isfinite(xy))  # NaN: a sample with no ray in front (`camera_rays(blank=True)`): a miss
    xy = jnp.where(seen, xy, 0.0)
    d = r_t @ jnp.array([xy[0], xy[1], 1.0])
    t, part = surface.hit(o, d)
    return t, jnp.where(seen, part, MISS), d


def _shade(surface, texture, light, ambient, background, o, r_t, xy):
    t, part, d = _trace(surface, o, r_t, xy)
    p = o + jnp.where(part == MISS, 0.0, t) * d
    radiance = lambert(albedo(texture, surface.texture_point(p, part)), surface.normal(p, part), d, light, ambient)
    return jnp.where(part == MISS, background, radiance)


@jax.jit
def object_images(
    rays: Float[Array, "h w s2 2"], centre_rays: Float[Array, "h w 1 2"], pose: Float[Array, "6"], surface,
    texture: Speckle, light: Float[Array, "3"], ambient: float, background: float,
) -> tuple[Float[Array, "h w"], Float[Array, "h w"], Array]:
    """Pixel-averaged Lambertian radiance of `surface` at T_cam_object `pose` (`light`: unit, object frame),
    the depth Z (camera frame, mm) of the first hit through each pixel centre (NaN on background), and the
    part hit there (-1 on background)."""
    h, w, s2, _ = rays.shape
    o, r_t = _ray_frame(pose)
    radiance = map_chunked(partial(_shade, surface, texture, light, ambient, background, o, r_t), rays.reshape(-1, 2))
    t, part, _ = map_chunked(lambda xy: _trace(surface, o, r_t, xy), centre_rays.reshape(-1, 2))
    # Rays are (x, y, 1) in the camera frame, so the ray parameter is the depth.
    depth = jnp.where(part == MISS, jnp.nan, t)
    return jnp.mean(radiance.reshape(h, w, s2), axis=2), depth.reshape(h, w), part.reshape(h, w)


def render_object(
    camera: Camera, pose, surface, texture: Speckle, light=None, ambient: float = 0.25,
    background: float = 0.04, options: RenderOptions = RenderOptions(supersample=2), seed=0, rays=None,
    centre_rays=None,
) -> tuple[np.ndarray, dict]:
    """8-bit image of `surface` at T_cam_object `pose`, and its truth (camera, pose, depth map, surface).

    `light` is the direction towards the light in the object frame (normalised here); None puts the light at
    the camera (a head lamp: the direction from the object-frame origin to the camera centre). `rays` /
    `centre_rays`: `camera_rays(camera, options.supersample)` / `camera_rays(camera, 1)` if already computed.
    """
    rays = camera_rays(camera, options.supersample, options.blank_beyond_field) if rays is None else rays
    centre_rays = camera_rays(camera, 1, options.blank_beyond_field) if centre_rays is None else centre_rays
    pose = np.asarray(pose, float).reshape(6)
    if light is None:
        light = np.asarray(_ray_frame(jnp.asarray(pose))[0])
    light = np.asarray(light, float) / np.linalg.norm(light)
    radiance, depth, part = object_images(rays, centre_rays, jnp.asarray(pose), surface, texture, jnp.asarray(light),
                                          ambient, background)
    image = expose(np.asarray(radiance), np.asarray(camera.k[2:4]), options, np.random.default_rng(seed))
    truth = {
        "kind": "object",
        "camera": camera_truth(camera),
        "pose_cam_object": pose.tolist(),
        "surface": surface.truth(),
        "texture": texture.to_truth(),
        "light_object": light.tolist(),
        "ambient": ambient,
        "background": background,
        "render": options.to_truth(),
        "seed": np.asarray(seed).tolist(),
        "depth": np.asarray(depth),
        "part": np.asarray(part, dtype=np.int8),
    }
    return image, truth
