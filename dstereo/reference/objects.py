"""Reference objects of known geometry: a chessboard, a sphere, marked points with known distances, a mesh.

Each is a small immutable pytree holding only what is known about the object (lengths in mm). Which
observations go with which object: a Board (`dstereo.models.board.Board`, the calibration's board) with its inner
corners in both images, a Sphere or Mesh with dense matched pixel pairs, Distances with the marked points' pixels
in both images (in the order of `points`).
"""

from __future__ import annotations

import csv
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from dstereo.errors import DstereoError
from dstereo.models.board import Board

__all__ = ["Board", "Distances", "Mesh", "Sphere", "read_marks"]


class Sphere(eqx.Module):
    """Sphere of known `diameter` (mm); its centre is a nuisance parameter."""

    diameter: float = eqx.field(static=True)

    def __check_init__(self):
        if not self.diameter > 0:
            raise DstereoError(f"sphere diameter {self.diameter}: give a positive diameter in mm")

    @property
    def radius(self) -> float:
        return 0.5 * float(self.diameter)


class Distances(eqx.Module):
    """Known distances between marked points: `pairs` (k, 2) point indices, `lengths` (k,) mm.

    `sigma_px` is the marking accuracy in the images and `sigma_mm` that of the known distances; they weight
    the two kinds of residual against each other (both are whitened by them).
    """

    pairs: Int[Array, "k 2"]
    lengths: Float[Array, " k"]
    sigma_px: float = eqx.field(static=True, default=0.3)
    sigma_mm: float = eqx.field(static=True, default=0.01)

    @property
    def n_points(self) -> int:
        return int(np.max(np.asarray(self.pairs))) + 1


class Mesh(eqx.Module):
    """A known surface as a triangle mesh (vertices (v, 3) mm, faces (f, 3)) in its own frame, and a start for
    its pose in the left camera frame (`pose0`: rvec, tvec of T_left_mesh); the pose is a nuisance parameter."""

    vertices: Float[Array, "v 3"]
    faces: Int[Array, "f 3"]
    pose0: Float[Array, "6"]

    @classmethod
    def from_trimesh(cls, mesh, pose0) -> "Mesh":
        return cls(jnp.asarray(mesh.vertices, float), jnp.asarray(mesh.faces, int), jnp.asarray(pose0, float))


def read_marks(path: str | Path) -> tuple[np.ndarray, np.ndarray, Distances]:
    """Marked points and known distances from one CSV file.

    Rows `point,NAME,xl,yl,xr,yr` give a marked point's pixels (left, right image; pixel (0, 0) is the centre of
    the top-left pixel); rows `distance,NAME_A,NAME_B,MM` give a known distance. Lines starting with '#' are
    comments. Returns (q_left (m, 2), q_right (m, 2), Distances).
    """
    path = Path(path)
    if not path.is_file():
        raise DstereoError(f"marks file {path} does not exist")
    names, q_l, q_r, dist = [], [], [], []
    with path.open(newline="") as f:
        for i, row in enumerate(csv.reader(f), start=1):
            row = [c.strip() for c in row]
            if not row or not row[0] or row[0].startswith("#"):
                continue
            try:
                if row[0] == "point" and len(row) == 6:
                    names.append(row[1])
                    q_l.append([float(row[2]), float(row[3])])
                    q_r.append([float(row[4]), float(row[5])])
                    continue
                if row[0] == "distance" and len(row) == 4:
                    dist.append((row[1], row[2], float(row[3])))
                    continue
            except ValueError:
                pass
            raise DstereoError(f"{path}:{i}: write 'point,NAME,xl,yl,xr,yr' or 'distance,NAME_A,NAME_B,MM', got {row}")
    unknown = sorted({n for a, b, _ in dist for n in (a, b)} - set(names))
    if unknown or not dist:
        problem = f"distances name unknown points {unknown}" if unknown else "no distance rows"
        raise DstereoError(f"{path}: {problem}; every distance needs two 'point' rows naming its ends")
    if any(d <= 0 for *_, d in dist):
        raise DstereoError(f"{path}: distances must be positive (mm)")
    index = {n: j for j, n in enumerate(names)}
    pairs = np.array([[index[a], index[b]] for a, b, _ in dist])
    return np.array(q_l), np.array(q_r), Distances(jnp.asarray(pairs), jnp.asarray([d for *_, d in dist]))
