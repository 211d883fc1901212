"""Epipolar-rectified spherical rectification, for a pair whose field is too wide for a pinhole image (fisheyes
seeing more than 2 x MAX_HALF_FIELD_DEG of `rectify_fisheye`).

The rotations are Bouguet's (`rectify.rectifying_rotations`): in both rectified frames the baseline is the x axis.
A direction (x, y, z) there has two angles: phi = atan2(y, z), the tilt about the baseline of the plane through
the baseline that holds it (the same plane for both cameras: an epipolar plane), and psi = atan2(x, hypot(y, z)),
its angle within that plane from the plane's normal to the baseline. Rows are phi, columns psi, linear:
u = cx + fx psi, v = cy + fy phi (P = [[fx, 0, cx, 0], [0, fy, cy, 0], [0, 0, 1, 0]], P2[0, 3] = Tx fx as a pinhole
pair's), so a scene point lies on the same row in both images and its disparity is fx (psi_L - psi_R), the angle
the baseline subtends at it; points follow from the two angles (`triangulate.reproject_spherical`), not from Q.

The field: each camera's image sampled on a FIELD_GRID x FIELD_GRID grid of pixels with a ray (fisheye: below the
fold angle and the corners' reach when known, `rectify_fisheye.ray_limit`), turned into its rectified frame; the
front half-space (z > 0: |phi| <= 90 deg) and |psi| <= MAX_PSI_DEG kept; the box of its (psi, phi). The pair's box
is the two boxes' intersection at balance 0 (pixels both cameras see), their union at 1, linear between. fx and fy
make the box fill the image (one px per radian scale per axis). Both images share cx, cy: disparity 0 at infinity.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dstereo.errors import DstereoError

# Within 5 degrees of the baseline's direction a point's disparity is cos(85 deg) = 9 % of what it is straight
# ahead (depth resolution 11x worse) and both rays nearly coincide: not worth rectified columns.
MAX_PSI_DEG = 85.0
FIELD_GRID = 65  # pixels per side sampled for the field seen (a grid step: 1/64 of the image)


def rectified_rays(P: Float[Array, "3 4"], u, v) -> Float[Array, "... 3"]:
    """Unit rays (rectified frame) of rectified pixels (u, v) of a spherical rectification."""
    psi = (u - P[0, 2]) / P[0, 0]
    phi = (v - P[1, 2]) / P[1, 1]
    return jnp.stack([jnp.sin(psi), jnp.cos(psi) * jnp.sin(phi), jnp.cos(psi) * jnp.cos(phi)], axis=-1)


def ray_angles(rays: Float[Array, "... 3"]) -> tuple[Float[Array, "..."], Float[Array, "..."]]:
    """(psi, phi) of rays in a rectified frame (module docstring)."""
    return jnp.arctan2(rays[..., 0], jnp.hypot(rays[..., 1], rays[..., 2])), jnp.arctan2(rays[..., 1], rays[..., 2])


def seen_box(rays: np.ndarray, ok: np.ndarray, R: np.ndarray) -> np.ndarray | None:
    """(psi_lo, psi_hi, phi_lo, phi_hi) rad of the rays (n, 3) that a camera has (`ok`), in its rectified frame R,
    front half-space and |psi| <= MAX_PSI_DEG only (module docstring); None when none is left."""
    rect = np.asarray(rays, float) @ np.asarray(R, float).T
    psi, phi = (np.asarray(a) for a in ray_angles(jnp.asarray(rect)))
    keep = np.asarray(ok, bool) & (rect[:, 2] > 0) & (np.abs(psi) <= np.radians(MAX_PSI_DEG))
    if not keep.any():
        return None
    return np.array([psi[keep].min(), psi[keep].max(), phi[keep].min(), phi[keep].max()])


def pair_box(box1: np.ndarray, box2: np.ndarray, balance: float) -> np.ndarray:
    """The pair's field: the boxes' intersection (balance 0) to their union (1), linear between."""
    b = float(np.clip(balance, 0.0, 1.0))
    inner = np.r_[max(box1[0], box2[0]), min(box1[1], box2[1]), max(box1[2], box2[2]), min(box1[3], box2[3])]
    outer = np.r_[min(box1[0], box2[0]), max(box1[1], box2[1]), min(box1[2], box2[2]), max(box1[3], box2[3])]
    return (1.0 - b) * inner + b * outer


def spherical_projections(box: np.ndarray, new_size: tuple[int, int], tx: float) -> tuple[np.ndarray, np.ndarray]:
    """P1, P2 whose columns span psi in box[0:2] and rows phi in box[2:4] over the image's pixel edges
    ([-0.5, w - 0.5]); P2[0, 3] = tx fx (tx: the rectified baseline, (R2 T)[0])."""
    w, h = new_size
    fx, fy = w / (box[1] - box[0]), h / (box[3] - box[2])
    P1 = np.array([[fx, 0.0, -0.5 - fx * box[0], 0.0], [0.0, fy, -0.5 - fy * box[2], 0.0], [0.0, 0.0, 1.0, 0.0]])
    P2 = P1.copy()
    P2[0, 3] = tx * fx
    return P1, P2


def check_box(box: np.ndarray, where: str) -> None:
    if not (box[1] > box[0] and box[3] > box[2]):
        raise DstereoError(f"{where}: the two cameras see no common field in front of the rig (in the planes through "
                           "the baseline); check R, T and the lens coefficients")


def field_of_view(P: np.ndarray, size: tuple[int, int]) -> dict[str, float]:
    """Horizontal (psi) and vertical (phi) span of a spherical rectified image, degrees, from its pixel edges."""
    w, h = size
    return {"horizontal_deg": float(np.degrees(w / P[0, 0])), "vertical_deg": float(np.degrees(h / P[1, 1]))}
