"""The front face in sample coordinates: its axis, a grid over it, and the face height per grid cell.

Sample frame: origin at the stagnation point `s`, unit axis `n` pointing away from the cameras (into the
sample), `e1`, `e2` completing a right-handed frame. A point p has face coordinates u = (p - s).e1,
v = (p - s).e2 and height h = (p - s).n; as the face recedes its height grows, so recession = h(t) - h(t0).

Auto axis (`estimate_axis`, `fit_face`): start from the points near the plane most of them lie near (RANSAC,
in their largest connected region); then, until the axis settles (moves by less than AXIS_TOLERANCE_DEG between
passes with the same face points; MAX_PASSES at most, else an error), fit a least-squares plane to the face
points and keep the points within k robust sigma of a quadric h(u, v) in that plane's coordinates, fitted to the
face found so far (a domed face is not trimmed at its top or rim; a side wall does not widen the tolerance that
is to reject it), that form the largest connected region of grid cells in (u, v) once the cells are opened by
OPENING_CELLS (background and stray matches apart from the face, and ragged fields joined to it, are cut off), and
that lie within the circle through that region's outline (`within_outline`: a solid field joined beside it is
cut at the rim). After FREE_PASSES passes a dropped point stays dropped (points at the threshold
could otherwise make the fit cycle). The plane's normal is the axis; `axis_sigma_deg` is the RMS angle error it
expects, the quadrature sum of `axis_sigma_parts`: noise by a block jackknife (neighbouring points'
errors are correlated), the apex's consistency, the axis's dependence on the face's support, and a matching bias
of one pixel's footprint across the face (the largest part; measured against rendered truth in
experiments/results/range_axis_sigma.md: z = error / sigma 0.1-1.0 over 18 cases). The stagnation point is
the centre of the face: the centre of the largest disc inside the face's grid cells (`face_centre`), moved onto
the quadric. This assumes the face is
seen whole and the axis is roughly normal to the face's outline (true for the flat and the domed samples of the
thesis, also turned 10-15 deg off the rig axis with the side wall in view); give the axis and the point otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dstereo.errors import DstereoError

MAD_SCALE = 1.4826  # MAD -> standard deviation for Gaussian noise


@dataclass(frozen=True)
class SampleFrame:
    """Stagnation point (mm) and orthonormal axes (rows e1, e2, n) in the left camera frame."""

    point: np.ndarray
    axes: np.ndarray
    source: str = "auto"
    axis_sigma_deg: float | None = None  # auto axis: RMS angle error it expects (`axis_sigma_parts`, as_dict)
    passes: int | None = None  # plane fits the auto axis took to settle
    axis_sigma_parts: dict | None = None  # its parts (deg), combined in quadrature

    @property
    def axis(self) -> np.ndarray:
        return self.axes[2]

    def coordinates(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) left-camera points -> (n, 3) face coordinates (u, v, h) in mm."""
        return (points - self.point) @ self.axes.T

    def to_camera(self, uvh: np.ndarray) -> np.ndarray:
        return uvh @ self.axes + self.point

    def as_dict(self) -> dict:
        return {"stagnation_point_mm": self.point.tolist(), "axis": self.axis.tolist(), "e1": self.axes[0].tolist(),
                "e2": self.axes[1].tolist(), "source": self.source,
                "axis_sigma_deg": self.axis_sigma_deg, "axis_passes": self.passes,
                "axis_sigma_parts_deg": self.axis_sigma_parts,
                "axis_sigma_note": "auto axis: expected RMS angle error, quadrature sum of its parts (noise by block "
                                   "jackknife, apex consistency, dependence on the face's support, one pixel's "
                                   "footprint of depth bias across the face); checked against rendered truth: error "
                                   "/ sigma 0.1-1.0 over 18 renders",
                "frame": "left camera (x right, y down, z forward), mm; axis points away from the cameras"}


def frame_from_axis(axis, point) -> SampleFrame:
    """Orthonormal frame around a given axis (turned to point away from the cameras, i.e. axis.z > 0 side)."""
    n = np.asarray(axis, float).reshape(3)
    if not np.linalg.norm(n) > 0:
        raise DstereoError(f"axis {n.tolist()}: give a non-zero direction x,y,z")
    n = n / np.linalg.norm(n)
    point = np.asarray(point, float).reshape(3)
    if n @ point < 0:
        n = -n  # away from the cameras: the camera centre (origin) lies on the side the face looks at
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = helper - (helper @ n) * n
    e1 /= np.linalg.norm(e1)
    return SampleFrame(point, np.stack([e1, np.cross(n, e1), n]))


def valid_points(points: np.ndarray) -> np.ndarray:
    p = np.asarray(points, float).reshape(-1, 3)
    return p[np.all(np.isfinite(p), axis=1)]


def _quadric_design(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=1)


def _trim(uvh: np.ndarray, k: float, start: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Inlier mask and quadric coefficients: points within k robust sigma of a quadric h(u, v), refitted three
    times, starting from the `start` points (default all)."""
    keep = np.ones(len(uvh), bool) if start is None else start.copy()
    coef = np.zeros(6)
    for _ in range(3):
        a = _quadric_design(uvh[keep, 0], uvh[keep, 1])
        coef = np.linalg.lstsq(a, uvh[keep, 2], rcond=None)[0]
        res = uvh[:, 2] - _quadric_design(uvh[:, 0], uvh[:, 1]) @ coef
        scale = MAD_SCALE * np.median(np.abs(res[keep] - np.median(res[keep])))
        keep = np.abs(res) <= k * max(scale, 1e-6)
    return keep, coef


AXIS_TOLERANCE_DEG = 0.01
MAX_PASSES = 30
FREE_PASSES = 5  # passes that may also take points back (measured: 320 x 240 renders settle in 4-6, or cycle)


OPENING_CELLS = 2  # the face's region is opened by this many cells before its largest part is taken


def largest_region(uv: np.ndarray, keep: np.ndarray, grid_mm: float) -> np.ndarray:
    """`keep` restricted to the points in the largest 8-connected region of occupied grid cells (grid_mm), the
    occupied cells first opened (eroded, then dilated back) by OPENING_CELLS cells.

    The opening cuts what is thinner than 2 OPENING_CELLS + 1 cells: a side wall or background seen at a grazing
    angle leaves a ragged field of cells, every other one on the face's quadric by chance, that joins the face and
    passes as part of it. Measured on a render tilted 11.8 deg (640 x 480, experiments/recession_coverage.py seed
    11): such a field 15 mm wide beside the face took the axis 2.8 deg and the face centre 9 mm off, the rate 29 %;
    a solid face (even one with a few empty cells) comes back from the opening whole but for its outline's corners."""
    from scipy import ndimage

    if not keep.any():
        return keep
    cells = np.round(uv / grid_mm).astype(np.int64)
    lo = cells[keep].min(axis=0) - OPENING_CELLS  # a margin: the erosion sees empty cells beyond the outermost
    idx = cells - lo
    shape = idx[keep].max(axis=0) + 1 + OPENING_CELLS
    occupied = np.zeros(shape[::-1], bool)
    occupied[idx[keep, 1], idx[keep, 0]] = True
    solid = ndimage.binary_opening(occupied, structure=np.ones((3, 3)), iterations=OPENING_CELLS)
    if solid.any():  # a region too thin for the opening (a test's strip of points) is kept as it is
        occupied = solid
    labels, n = ndimage.label(occupied, structure=np.ones((3, 3)))
    biggest = 1 + int(np.argmax(ndimage.sum(occupied, labels, range(1, n + 1))))
    inside = np.all((idx >= 0) & (idx < shape), axis=1)
    out = np.zeros_like(keep)
    out[inside] = labels[idx[inside, 1], idx[inside, 0]] == biggest
    return keep & out


def face_points(uvh: np.ndarray, grid_mm: float, k: float = 4.0,
                start: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(mask, quadric coefficients) of the front face's points in face coordinates: on the quadric within k
    robust sigma (the quadric and its sigma first fitted to the `start` points: the face found so far, so a
    side wall or background does not widen the tolerance that is to reject them) and in the largest connected
    region of grid cells."""
    keep, coef = _trim(uvh, k, start)
    keep = largest_region(uvh[:, :2], keep, grid_mm)
    return within_outline(uvh[:, :2], keep, grid_mm), coef


def within_outline(uv: np.ndarray, keep: np.ndarray, grid_mm: float) -> np.ndarray:
    """`keep` restricted to the points within OUTLINE_TOLERANCE_CELLS of the face's `outline_circle`: what joins
    the face beyond its rim and survived the opening (SGBM carrying the face's disparity along the rows into the
    untextured background beside it: a field 15 mm wide beside a render tilted 10.5 deg, seed 14 of
    experiments/recession_coverage.py, that took the axis 2 deg off). A prismatic face loses its corners here."""
    if keep.sum() < 3:
        return keep
    cells = np.unique(np.round(uv[keep] / grid_mm).astype(np.int64), axis=0) * grid_mm
    centre, radius = outline_circle(cells, grid_mm)
    return keep & (np.hypot(uv[:, 0] - centre[0], uv[:, 1] - centre[1]) <= radius + OUTLINE_TOLERANCE_CELLS * grid_mm)


JACKKNIFE_BLOCKS = 6  # blocks across the face's larger extent (~28 over a round face)
SUPPORT_SHARES = (0.95, 0.9, 0.8)  # inner shares of the face (by distance from its centre) refitted


def block_jackknife_axis_deg(uvh: np.ndarray, blocks: int = JACKKNIFE_BLOCKS) -> float:
    """RMS angle error (deg) of the face's tilt from its noise: a delete-one-block jackknife of the quadric's
    slope at the origin, the face cut into square blocks in (u, v), `blocks` across its larger extent.
    Neighbouring points share SGBM's window and the refinement's kernel, so their errors are correlated: a
    per-point covariance or bootstrap counts them as independent and understates the spread (tenfold
    on a synthetic face with noise correlated over ~1 mm, tests/recession/test_axis.py); blocks many matching
    windows wide are close to independent. The quadric, not the plane, is refitted: without a block a plane
    through a domed face tilts with the dome's slope, which is not an error; on a face symmetric about the origin
    the quadric's slope and the plane's coincide. Measured on that synthetic face: error / this sigma has an RMS
    of 1.2-1.4 over 12 draws (blocks still share errors at their edges), hence few, large blocks."""
    uv = uvh[:, :2]
    size = max(float((uv.max(axis=0) - uv.min(axis=0)).max()) / blocks, 1e-9)
    ids = np.unique(np.floor((uv - uv.min(axis=0)) / size).astype(np.int64), axis=0, return_inverse=True)[1]
    ids = ids.ravel()
    nb = int(ids.max()) + 1
    if nb < 4:
        return float("nan")
    a = _quadric_design(uv[:, 0], uv[:, 1])
    ata = np.zeros((nb, 6, 6))
    np.add.at(ata, ids, a[:, :, None] * a[:, None, :])
    ath = np.zeros((nb, 6))
    np.add.at(ath, ids, a * uvh[:, 2:3])
    without = np.linalg.solve(ata.sum(axis=0)[None] - ata, (ath.sum(axis=0)[None] - ath)[..., None])[..., 0]
    slopes = without[:, 1:3]
    spread = slopes - slopes.mean(axis=0)
    return float(np.degrees(np.sqrt((nb - 1) / nb * np.sum(spread**2))))


def support_axis_deg(face: np.ndarray, frame: "SampleFrame", centre_uv) -> float:
    """RMS angle (deg) between the axis and the plane normals of the face's inner SUPPORT_SHARES (points
    nearest the face centre): how much the axis depends on which part of the face is kept (the rim's matches,
    the face's trimmed edge, a dome seen unevenly)."""
    uv = frame.coordinates(face)[:, :2] - np.asarray(centre_uv)
    r = np.hypot(uv[:, 0], uv[:, 1])
    angles = []
    for share in SUPPORT_SHARES:
        inner = _plane_frame(face[r <= np.quantile(r, share)])
        angles.append(np.degrees(np.arccos(min(1.0, abs(float(inner.axis @ frame.axis))))))
    return float(np.sqrt(np.mean(np.square(angles))))


def footprint_axis_deg(n_points: int, area_mm2: float) -> float:
    """The tilt (deg) of a depth bias that differs by one pixel's footprint (sqrt(area / points) mm) across the
    face's diameter. Not seen by any resampling: it is the matching's systematic share. Measured on renders of
    a domed sample turned 12 deg (experiments/results/range_axis_sigma.md): axis errors of 0.11-0.13 deg at
    640x480 (footprint 0.13 mm) and 0.20-0.28 deg at 320x240 (0.25 mm), 0.8-1.0 such footprints over the face,
    the same on every noise seed; the resampled noise was 0.005-0.016 deg."""
    footprint = np.sqrt(area_mm2 / max(n_points, 1))
    diameter = 2.0 * np.sqrt(area_mm2 / np.pi)
    return float(np.degrees(np.arctan(footprint / max(diameter, 1e-9))))


def axis_sigma_parts(face: np.ndarray, frame: "SampleFrame", coef: np.ndarray, centre_uv, area_mm2: float) -> dict:
    """The auto axis's expected RMS angle error (deg) in parts, combined in quadrature by `fit_face`:
    `noise` (block jackknife), `apex` (the angle between the plane's normal and the quadric's
    normal at the face centre: the apex of a symmetric face lies on the axis, so they differ when the face is
    seen unevenly), `support` (refits on the inner face) and `matching_bias` (one pixel footprint of depth bias
    across the face)."""
    u0, v0 = centre_uv
    slope = np.array([coef[1] + 2 * coef[3] * u0 + coef[4] * v0, coef[2] + coef[4] * u0 + 2 * coef[5] * v0])
    return {"noise": block_jackknife_axis_deg(frame.coordinates(face)),
            "apex": float(np.degrees(np.arctan(np.linalg.norm(slope)))),
            "support": support_axis_deg(face, frame, centre_uv),
            "matching_bias": footprint_axis_deg(len(face), area_mm2)}


def _ransac_start(p: np.ndarray, grid_mm: float, tries: int = 256, seed: int = 0) -> np.ndarray:
    """Start of the face fit: the points near the plane (within 3 % of the cloud's extent) that most points lie
    near, in their largest connected region. A plane through all points would lean towards the side wall and the
    background (measured 22 deg off on a cloud with a side wall in view); a band around the face's best plane
    holds most of the face and little of anything else."""
    rng = np.random.default_rng(seed)
    spread = np.percentile(p, 90, axis=0) - np.percentile(p, 10, axis=0)
    band = 0.03 * float(np.sort(spread)[1:].mean())  # the two larger extents: across the face
    sample = p[rng.choice(len(p), min(len(p), 5000), replace=False)]
    best, best_count = None, -1
    for _ in range(tries):
        a, b, c = sample[rng.choice(len(sample), 3, replace=False)]
        n = np.cross(b - a, c - a)
        if np.linalg.norm(n) < 1e-9:
            continue
        n = n / np.linalg.norm(n)
        count = int(np.sum(np.abs((sample - a) @ n) <= band))
        if count > best_count:
            best, best_count = (n, a), count
    if best is None:
        return np.ones(len(p), bool)
    n, a = best
    near = np.abs((p - a) @ n) <= band
    frame = frame_from_axis(n, a)
    return largest_region(frame.coordinates(p)[:, :2], near, grid_mm)


def _plane_frame(p: np.ndarray) -> "SampleFrame":
    """Least-squares plane through the points (equal weights: one mean point per grid cell instead was measured
    no better, 0.30 vs 0.28 deg at 12 deg yaw, 320 x 240, and its binning made the fit jitter by 0.03 deg)."""
    centre = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - centre, full_matrices=False)
    return frame_from_axis(vt[2], centre)


OUTLINE_TOLERANCE_CELLS = 1.0  # outline cells this far outside the fitted circle are not the rim


def face_centre(cells: np.ndarray, grid_mm: float) -> np.ndarray:
    """(u, v) mm: the centre of `outline_circle`."""
    return outline_circle(cells, grid_mm)[0]


def outline_circle(cells: np.ndarray, grid_mm: float) -> tuple[np.ndarray, float]:
    """(centre (u, v), radius) mm of the circle through the face's outline (`cells` (n, 2), the face's grid cells'
    centres, holes filled), fitted by least squares (Kasa's algebraic fit) and refitted without the outline cells
    more than OUTLINE_TOLERANCE_CELLS outside it until the kept cells stop changing.

    Not the cells' centroid: stray matches beyond the rim that join the face (the background next to the face's
    far edge taking its disparity, the first millimetres of a side wall in view) sit on one side of a tilted face
    and pull a centroid towards it; outside the rim's circle, they leave its fit. Measured on renders tilted
    10-18 deg with the side wall in view (640 x 480; experiments/recession_coverage.py's seeds 0-10): the face's
    cells reached 26-29 mm from the true axis on some sides (rim 24.5 mm); the centroid was 0.71 mm RMS off the true
    stagnation point (a rate 0.1-0.5 % low on the rendered profile, the same in every frame). This centre, with the
    face's region opened and cut at this circle (`largest_region`, `within_outline`): 0.23 mm RMS, 0.30 mm at most,
    over the 20 seeds of experiments/results/recession_coverage.md (11 frames, 10000 electrons). A prismatic
    face's outline gives its centre too (the fit is symmetric); a face seen in part does not (give the point)."""
    from scipy import ndimage

    idx = np.round(cells / grid_mm).astype(np.int64)
    lo = idx.min(axis=0) - 1  # a cell of margin: the outline is where the erosion sees the empty cells beyond
    shape = idx.max(axis=0) - lo + 2
    mask = np.zeros(shape[::-1], bool)
    mask[idx[:, 1] - lo[1], idx[:, 0] - lo[0]] = True
    mask = ndimage.binary_fill_holes(mask)
    iy, ix = np.nonzero(mask & ~ndimage.binary_erosion(mask))
    x, y = (ix + lo[0]) * grid_mm, (iy + lo[1]) * grid_mm
    keep = np.ones(len(x), bool)
    centre = np.array([x.mean(), y.mean()])
    radius = float(np.hypot(x - centre[0], y - centre[1]).max())  # too few outline cells for a fit: all of them
    for _ in range(10):
        if keep.sum() < 3:
            break
        a = np.stack([2 * x[keep], 2 * y[keep], np.ones(int(keep.sum()))], axis=1)
        sol = np.linalg.lstsq(a, (x * x + y * y)[keep], rcond=None)[0]
        centre = sol[:2]
        radius = float(np.sqrt(max(sol[2] + centre @ centre, 0.0)))
        new = np.hypot(x - centre[0], y - centre[1]) - radius <= OUTLINE_TOLERANCE_CELLS * grid_mm
        if np.array_equal(new, keep):
            break
        keep = new
    return centre, radius


@dataclass(frozen=True)
class FaceFit:
    """The auto axis's frame and the first frame's face points (mask over the valid points)."""

    frame: "SampleFrame"
    keep: np.ndarray


def fit_face(points: np.ndarray, grid_mm: float, min_points: int = 500, k: float = 4.0) -> FaceFit:
    """Sample frame and face points from the first frame's points (module docstring); an error when the axis
    does not settle within MAX_PASSES plane fits."""
    p = valid_points(points)
    if len(p) < min_points:
        raise DstereoError(f"only {len(p)} points in the first frame; need at least {min_points} to find the "
                           "sample axis (check the calibration and the depth range, or give `axis` and `point`)")
    keep = _ransac_start(p, grid_mm)
    previous, change = None, float("nan")
    for passes in range(1, MAX_PASSES + 1):
        if keep.sum() < min_points:
            raise DstereoError(f"the automatic sample axis kept only {int(keep.sum())} face points after {passes - 1} "
                               "plane fits; the front face is not seen clearly: give `axis` and `point`")
        frame = _plane_frame(p[keep])
        new_keep, coef = face_points(frame.coordinates(p), grid_mm, k, keep)
        if passes > FREE_PASSES:
            new_keep &= keep  # a point once dropped stays dropped: the fit cannot cycle between two point sets
        if previous is not None:
            change = float(np.degrees(np.arccos(np.clip(abs(previous @ frame.axis), -1.0, 1.0))))
            if change < AXIS_TOLERANCE_DEG and np.mean(new_keep != keep) < 1e-3:
                break
        previous, keep = frame.axis, new_keep
    else:
        raise DstereoError(f"the automatic sample axis did not settle: after {MAX_PASSES} plane fits it still moved "
                           f"{change:.3f} deg per fit (tolerance {AXIS_TOLERANCE_DEG} deg); the face may be hidden in "
                           "part or not roughly symmetric: give `axis` and `point`")
    uvh = frame.coordinates(p[new_keep])
    _, coef = _trim(uvh, k, np.ones(len(uvh), bool))
    cells = np.unique(np.round(uvh[:, :2] / grid_mm).astype(np.int64), axis=0) * grid_mm
    u0, v0 = face_centre(cells, grid_mm)
    h0 = float((_quadric_design(np.array([u0]), np.array([v0])) @ coef)[0])
    centre = frame.to_camera(np.array([u0, v0, h0]))
    parts = axis_sigma_parts(p[new_keep], frame, coef, (u0, v0), len(cells) * grid_mm**2)
    sigma = float(np.sqrt(sum(v * v for v in parts.values())))
    sample = SampleFrame(centre, frame.axes, f"auto: robust plane fit of the first frame's face ({passes} fits, "
                         f"settled to {AXIS_TOLERANCE_DEG} deg), face centre", sigma, passes, parts)
    return FaceFit(sample, new_keep)


def estimate_axis(points: np.ndarray, grid_mm: float, min_points: int = 500, k: float = 4.0) -> SampleFrame:
    """Sample frame from the first frame's points (module docstring, `fit_face`)."""
    return fit_face(points, grid_mm, min_points, k).frame


@dataclass(frozen=True)
class Grid:
    """Cell centres at integer multiples of `spacing` (mm) in (u, v): index (iy, ix) <-> (v, u)."""

    spacing: float
    u: np.ndarray  # (nx,) cell centres
    v: np.ndarray  # (ny,)

    @property
    def shape(self) -> tuple[int, int]:
        return len(self.v), len(self.u)

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(ny, nx) arrays U, V of cell centres."""
        return np.meshgrid(self.u, self.v)

    def cell_index(self, uv: np.ndarray) -> np.ndarray:
        """Flat cell index per point, -1 outside the grid."""
        ix = np.round((uv[:, 0] - self.u[0]) / self.spacing).astype(np.int64)
        iy = np.round((uv[:, 1] - self.v[0]) / self.spacing).astype(np.int64)
        inside = (ix >= 0) & (ix < len(self.u)) & (iy >= 0) & (iy < len(self.v))
        return np.where(inside, iy * len(self.u) + ix, -1)


def grid_over(uv: np.ndarray, spacing: float) -> Grid:
    """Grid covering the given face coordinates (first frame) with a cell centre on the stagnation point."""
    if not spacing > 0:
        raise DstereoError(f"`grid` {spacing}: need a positive cell size in mm")
    lo = np.floor(uv.min(axis=0) / spacing).astype(int)
    hi = np.ceil(uv.max(axis=0) / spacing).astype(int)
    if np.prod(hi - lo + 1) > 4_000_000:
        raise DstereoError(f"`grid` {spacing} mm gives {np.prod(hi - lo + 1)} cells over the face; use a coarser grid")
    return Grid(float(spacing), np.arange(lo[0], hi[0] + 1) * spacing, np.arange(lo[1], hi[1] + 1) * spacing)


def _cell_plane_fit(cell, du, dv, h, w, n_cells):
    """Per-cell weighted least-squares plane h = a + b du + c dv; returns a, its SE, count, residuals."""
    def s(x):
        return np.bincount(cell, weights=w * x, minlength=n_cells)

    one = np.ones_like(du)
    m = np.stack([np.stack([s(one), s(du), s(dv)], -1), np.stack([s(du), s(du * du), s(du * dv)], -1),
                  np.stack([s(dv), s(du * dv), s(dv * dv)], -1)], -2)
    rhs = np.stack([s(h), s(h * du), s(h * dv)], -1)
    count = np.bincount(cell, weights=w, minlength=n_cells)
    det = np.linalg.det(m)
    ok = (count >= 4) & (np.abs(det) > 1e-12 * np.maximum(count, 1) ** 3)
    coef = np.full((n_cells, 3), np.nan)
    inv = np.full((n_cells, 3, 3), np.nan)
    if ok.any():
        inv[ok] = np.linalg.inv(m[ok])
        coef[ok] = np.einsum("cij,cj->ci", inv[ok], rhs[ok])
    res = h - (coef[cell, 0] + coef[cell, 1] * du + coef[cell, 2] * dv)
    rss = np.bincount(cell, weights=w * np.nan_to_num(res) ** 2, minlength=n_cells)
    dof = np.maximum(count - 3, 1)
    se = np.sqrt(rss / dof * inv[:, 0, 0])
    return coef[:, 0], np.where(ok, se, np.nan), count, res


def _per_cell_median(cell: np.ndarray, values: np.ndarray, n_cells: int) -> np.ndarray:
    if n_cells <= 1 << 16:
        # lexsort((values, cell))'s arrangement (cells ascending, values ascending within each; equal values are
        # interchangeable) in two passes, 5x faster at 280k points: values by quicksort, then the cells by a
        # stable sort of 16-bit keys (numpy's radix sort)
        by_value = np.argsort(values)
        order = by_value[np.argsort(cell[by_value].astype(np.uint16), kind="stable")]
    else:
        order = np.lexsort((values, cell))
    c, x = cell[order], values[order]
    starts = np.searchsorted(c, np.arange(n_cells))
    counts = np.bincount(c, minlength=n_cells)
    mid = np.clip(starts + (counts - 1) // 2, 0, max(len(x) - 1, 0))
    return np.where(counts > 0, x[mid] if len(x) else np.nan, np.nan)


def cell_heights(uvh: np.ndarray, grid: Grid, min_points: int = 8, k: float = 3.0) -> tuple[np.ndarray, ...]:
    """Face height per grid cell: a local plane through the cell's points, evaluated at the cell centre, refitted
    once without the points beyond k robust sigma (the cell's MAD) of the first fit. Returns (height, its
    standard error, points used), each (ny, nx); cells with fewer than `min_points` are NaN, never filled."""
    n_cells = grid.shape[0] * grid.shape[1]
    idx = grid.cell_index(uvh[:, :2])
    inside = idx >= 0
    cell, u, v, h = idx[inside], uvh[inside, 0], uvh[inside, 1], uvh[inside, 2]
    uc, vc = grid.centres()
    du, dv = u - uc.ravel()[cell], v - vc.ravel()[cell]
    w = np.ones_like(h)
    _, _, _, res = _cell_plane_fit(cell, du, dv, h, w, n_cells)
    absdev = np.where(np.isfinite(res), np.abs(res), np.inf)
    mad = MAD_SCALE * _per_cell_median(cell, absdev, n_cells)
    floor = 1e-3  # mm: a cell of identical heights keeps its points
    limit = k * np.maximum(np.where(np.isfinite(mad), mad, 0.0), floor)
    w = (absdev <= limit[cell]).astype(float)
    height, se, count, _ = _cell_plane_fit(cell, du, dv, h, w, n_cells)
    few = count < min_points
    height[few], se[few] = np.nan, np.nan
    return height.reshape(grid.shape), se.reshape(grid.shape), count.reshape(grid.shape).astype(int)
