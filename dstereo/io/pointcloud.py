"""Point clouds and meshes out: coloured PLY points, a triangle mesh over the pixel grid.

Organised clouds are (h, w, 3) arrays with NaN where a pixel has no point; colours are (h, w, 3) uint8 RGB.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dstereo.errors import DstereoError


def _flat(points: np.ndarray, colors: np.ndarray | None):
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    ok = np.all(np.isfinite(pts), axis=1)
    cols = None if colors is None else np.asarray(colors, dtype=np.uint8).reshape(-1, 3)[ok]
    return pts[ok], cols


def write_ply_points(path: str | Path, points: np.ndarray, colors: np.ndarray | None = None,
                     scalars: dict[str, np.ndarray] | None = None) -> int:
    """Binary little-endian PLY of the finite points (float32 x y z, uint8 r g b, then one float32 property per
    entry of `scalars`, each shaped like the cloud without its last axis, e.g. sigma_z); returns the point count."""
    pts, cols = _flat(points, colors)
    ok = np.all(np.isfinite(np.asarray(points, dtype=np.float64).reshape(-1, 3)), axis=1)
    extra = {k: np.asarray(v, dtype=np.float32).reshape(-1)[ok] for k, v in (scalars or {}).items()}
    props = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")] + ([] if cols is None else [("red", "u1"), ("green", "u1"),
                                                                                ("blue", "u1")])
    props += [(k, "<f4") for k in extra]
    rec = np.empty(len(pts), dtype=props)
    rec["x"], rec["y"], rec["z"] = pts.T
    if cols is not None:
        rec["red"], rec["green"], rec["blue"] = cols.T
    for k, v in extra.items():
        rec[k] = v
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(pts)}"]
    header += [f"property {'float' if t == '<f4' else 'uchar'} {n}" for n, t in props] + ["end_header"]
    with Path(path).open("wb") as f:
        f.write(("\n".join(header) + "\n").encode())
        f.write(rec.tobytes())
    return len(pts)


def grid_faces(points: np.ndarray, max_jump: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Triangles over the pixel grid of an organised cloud: two per 2 x 2 pixel cell whose corners are valid.

    A triangle is dropped when two of its corners differ in depth by more than `max_jump` x the nearer depth
    (a depth jump, e.g. an occluding edge). Returns (vertex index per valid pixel (h, w), faces (m, 3)), vertex
    indices counting the valid pixels row by row.
    """
    h, w, _ = points.shape
    valid = np.all(np.isfinite(points), axis=2)
    index = np.full((h, w), -1, dtype=np.int64)
    index[valid] = np.arange(int(valid.sum()))
    z = np.where(valid, points[..., 2], np.nan)
    corners = [(slice(0, -1), slice(0, -1)), (slice(0, -1), slice(1, None)),
               (slice(1, None), slice(0, -1)), (slice(1, None), slice(1, None))]
    ids = [index[c] for c in corners]  # top-left, top-right, bottom-left, bottom-right
    zs = [z[c] for c in corners]
    faces = []
    for a, b, c in ((0, 2, 1), (1, 2, 3)):  # counter-clockwise seen from the camera (y down, z forward)
        za, zb, zc = zs[a], zs[b], zs[c]
        with np.errstate(invalid="ignore"):
            near = np.fmin(np.fmin(za, zb), zc)
            far = np.fmax(np.fmax(za, zb), zc)
            ok = (ids[a] >= 0) & (ids[b] >= 0) & (ids[c] >= 0) & (far - near <= max_jump * np.abs(near))
        faces.append(np.stack([ids[a][ok], ids[b][ok], ids[c][ok]], axis=1))
    return index, np.concatenate(faces, axis=0)


def grid_mesh(points: np.ndarray, colors: np.ndarray | None = None, max_jump: float = 0.05):
    """trimesh.Trimesh over the pixel grid (see `grid_faces`), vertex colours from the image."""
    import trimesh

    index, faces = grid_faces(points, max_jump)
    valid = index >= 0
    kwargs = {}
    if colors is not None:
        rgb = np.asarray(colors, dtype=np.uint8)[valid]
        kwargs["vertex_colors"] = np.c_[rgb, np.full(len(rgb), 255, np.uint8)]
    return trimesh.Trimesh(vertices=points[valid], faces=faces, process=False, **kwargs)


def write_mesh_ply(path: str | Path, points: np.ndarray, colors: np.ndarray | None = None,
                   max_jump: float = 0.05) -> tuple[int, int]:
    """Grid mesh as binary PLY via trimesh; returns (vertices, faces). A cloud without a finite point is written
    as a valid PLY with no vertex and no face (trimesh's exporter fails on it); the caller warns."""
    if not np.all(np.isfinite(np.asarray(points, dtype=np.float64)), axis=-1).any():
        _write_empty_mesh(path, colors is not None)
        return 0, 0
    mesh = grid_mesh(points, colors, max_jump)
    Path(path).write_bytes(mesh.export(file_type="ply"))
    return len(mesh.vertices), len(mesh.faces)


def _write_empty_mesh(path: str | Path, colors: bool) -> None:
    """mesh.ply with 0 vertices and 0 faces, the properties the non-empty file has (readers take it as empty)."""
    header = ["ply", "format binary_little_endian 1.0", "element vertex 0", "property float x", "property float y",
              "property float z"]
    header += [f"property uchar {c}" for c in ("red", "green", "blue", "alpha")] if colors else []
    header += ["element face 0", "property list uchar int vertex_indices", "end_header"]
    Path(path).write_bytes(("\n".join(header) + "\n").encode())
