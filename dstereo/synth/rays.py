"""Per-pixel rays through the exact inverse of a camera's lens model, for supersampled rendering.

Two lens models (`Camera.lens`): OpenCV's pinhole + distortion (Newton inverse) and cv2.fisheye's Kannala-Brandt
(`models.fisheye.unproject`, its convergence checked). `lens` is a static argument of the compiled functions, so
a pinhole camera runs exactly the code it always ran (its renders are unchanged).

Pixel (u, v) covers [u - 1/2, u + 1/2] x [v - 1/2, v + 1/2] (pixel (0, 0) is centred on the origin, OpenCV's
convention). A supersample factor s places s x s samples at the centres of an s x s subdivision of that square.
A ray is returned as its normalised direction (x, y) with z = 1, so a point at ray parameter t has camera depth
Z = t exactly.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dstereo.errors import DstereoError
from dstereo.models import fisheye
from dstereo.models.camera import Camera, project
from dstereo.models.distortion import undistort

# Rays are computed in chunks of this many samples so memory stays bounded for any image size.
CHUNK = 65536


NEWTON_ITERATIONS = 12  # the renderer has always taken 12 steps (4 more than the default): renders stay unchanged


def unproject_point(k: Float[Array, "4"], coeffs: Float[Array, "8"], q: Float[Array, "2"]) -> Float[Array, "2"]:
    """Pixel -> normalised undistorted (x, y) of its ray, one point (the exact Newton inverse)."""
    return undistort(coeffs, (q - k[2:4]) / k[0:2], NEWTON_ITERATIONS)


def unproject_point_fisheye(k: Float[Array, "4"], coeffs: Float[Array, "8"], q: Float[Array, "2"]) -> Float[Array, "2"]:
    """Pixel -> (x, y) of its ray on z = 1 through the fisheye model (D in coeffs[:4]); NaN where the inverse did
    not converge or the ray is at or beyond 90 degrees (no point on z = 1)."""
    ray, ok = fisheye.unproject(k, coeffs[:4], q)
    front = ok & (ray[2] > 0)
    return jnp.where(front, ray[:2] / jnp.where(front, ray[2], 1.0), jnp.nan)


def _unproject_fn(lens: str):
    return unproject_point_fisheye if lens == "fisheye" else unproject_point


def _project_fn(lens: str):
    return (lambda k, c, p: fisheye.project(k, c[:4], p)) if lens == "fisheye" else project


@partial(jax.jit, static_argnames=("lens",))
def unproject_points(k: Float[Array, "4"], coeffs: Float[Array, "8"], q: Float[Array, "n 2"],
                     lens: str = "pinhole") -> Float[Array, "n 2"]:
    return jax.vmap(_unproject_fn(lens), in_axes=(None, None, 0))(k, coeffs, q)


@partial(jax.jit, static_argnames=("lens",))
def project_points(k: Float[Array, "4"], coeffs: Float[Array, "8"], p_cam: Float[Array, "n 3"],
                   lens: str = "pinhole") -> Float[Array, "n 2"]:
    return jax.vmap(_project_fn(lens), in_axes=(None, None, 0))(k, coeffs, p_cam)


def map_chunked(fn, xs: Float[Array, "n d"]):
    """`vmap(fn)` over the rows of `xs`, CHUNK rows at a time (memory stays bounded for any image size).

    The rows are padded to whole chunks, so the body is compiled once (`lax.map(batch_size=...)` would compile
    it a second time for the remainder).
    """
    n = xs.shape[0]
    n_chunks = -(-n // CHUNK)
    padded = jnp.concatenate([xs, jnp.broadcast_to(xs[:1], (n_chunks * CHUNK - n,) + xs.shape[1:])])
    out = jax.lax.map(jax.vmap(fn), padded.reshape((n_chunks, CHUNK) + xs.shape[1:]))
    return jax.tree.map(lambda a: a.reshape((n_chunks * CHUNK,) + a.shape[2:])[:n], out)


def subpixel_offsets(supersample: int) -> np.ndarray:
    """(s*s, 2) offsets (du, dv) of the samples inside one pixel, row-major over (v, u)."""
    c = (np.arange(supersample) + 0.5) / supersample - 0.5
    dv, du = np.meshgrid(c, c, indexing="ij")
    return np.stack([du.ravel(), dv.ravel()], axis=1)


@partial(jax.jit, static_argnames=("image_size", "supersample", "lens"))
def _rays(k, coeffs, image_size: tuple[int, int], supersample: int, lens: str = "pinhole"):
    w, h = image_size
    v, u = jnp.meshgrid(jnp.arange(h, dtype=float), jnp.arange(w, dtype=float), indexing="ij")
    centres = jnp.stack([u, v], axis=-1)[:, :, None, :]
    q = (centres + jnp.asarray(subpixel_offsets(supersample))[None, None]).reshape(-1, 2)
    inverse = _unproject_fn(lens)
    xy = map_chunked(lambda qi: inverse(k, coeffs, qi), q)
    return xy.reshape(h, w, supersample * supersample, 2)


def camera_rays(camera: Camera, supersample: int = 1, blank: bool = False) -> Float[Array, "h w s2 2"]:
    """Normalised ray directions (x, y) for every sample of every pixel, shape (height, width, s*s, 2).

    Raises `DstereoError` where the distortion is not invertible over the image (the Newton inverse would not
    reproduce the pixel), because the render would then disagree with the model it is meant to test; for a
    fisheye also where a pixel sees 90 degrees or more off the axis (a ray (x, y, 1) cannot hold it), unless
    `blank`: those samples are then NaN (the renderers draw them as background) and the rest are checked.
    """
    w, h = camera.image_size
    if w <= 0 or h <= 0:
        raise DstereoError(f"camera image_size {camera.image_size}: give the camera a (width, height) to render")
    if supersample < 1:
        raise DstereoError(f"supersample={supersample}: need an integer >= 1")
    xy = _rays(camera.k, camera.dist.coeffs, (int(w), int(h)), int(supersample), camera.lens)
    if camera.lens == "fisheye" and not blank and not bool(jnp.all(jnp.isfinite(xy))):
        raise DstereoError(f"fisheye camera f = {np.asarray(camera.k[:2]).round(2).tolist()} px: some of its {w}x{h} "
                           "pixels see 90 degrees or more off the axis (or the lens model folds back there); the "
                           "renderer needs every ray in front of the camera: lengthen the focal or shrink the image")
    check_invertible(camera, xy, blank and camera.lens == "fisheye")
    return xy


def check_invertible(camera: Camera, xy: Float[Array, "h w s2 2"], blank: bool = False) -> None:
    """Re-project a sparse subset of the rays and demand the pixel comes back (to 1e-6 px); `blank`: only the
    rays that are there (not NaN)."""
    h, w, s2, _ = xy.shape
    s = int(round(np.sqrt(s2)))
    rows = np.linspace(0, h - 1, 9).astype(int)
    cols = np.linspace(0, w - 1, 9).astype(int)
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    sub = np.asarray(xy)[rr.ravel(), cc.ravel()]  # (81, s2, 2)
    q_expected = np.stack([cc.ravel(), rr.ravel()], axis=1)[:, None, :] + subpixel_offsets(s)[None]
    p = np.concatenate([sub, np.ones(sub.shape[:2] + (1,))], axis=-1).reshape(-1, 3)
    q = np.asarray(project_points(camera.k, camera.dist.coeffs, jnp.asarray(p), camera.lens)).reshape(q_expected.shape)
    if blank:
        there = np.isfinite(sub).all(axis=-1).reshape(q_expected.shape[:2])
        q, q_expected = q[there], q_expected[there]
    err = np.max(np.abs(q - q_expected)) if q.size and np.all(np.isfinite(q)) else np.inf
    if not err <= 1e-6:
        raise DstereoError(
            f"camera distortion {np.asarray(camera.dist.coeffs).round(4).tolist()} is not invertible over the "
            f"{w}x{h} image (round-trip error {err:.3g} px); weaken the coefficients or shrink the image"
        )
