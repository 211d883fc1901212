"""Views that disagree with the rest: an RMS far above the others, corners in another order than the others.

A wrong `--pattern` (6x9 given for a 9x6 board, a square board whose corners OpenCV may number from any of its
four corners), a mirrored image or a mis-detected board all look like a few views that do not fit. These checks
name such views with figures; the caller prints them as warnings and keeps them in summary.json.

- `outlying_views`: per-view RMS reprojection error above `FACTOR` times the median of the views and above the
  median plus `ROBUST_SIGMAS` robust standard deviations (1.4826 x MAD): far above the rest, not merely the worst.
- `stray_corners`: a view with a corner whose residual exceeds `CORNER_FACTOR` times the set's RMS (and 1 px).
- `mirrored_views`: the detected grid's handedness (image-plane cross product of its column and row directions);
  every view of one physical board seen from its front has the same one, so a view of the other is mirrored.
- `grid_angle` / `align_order`: the direction in which a view's first corner row runs; the right image of a
  stereo pair whose grid runs the opposite way (OpenCV numbered the board from the opposite corner) is renumbered
  to match the left, the grid's symmetries being the only renumberings that keep its shape.
"""

from __future__ import annotations

import numpy as np

FACTOR = 3.0
ROBUST_SIGMAS = 6.0
CORNER_FACTOR = 10.0


def _pattern_hint(pattern: tuple[int, int]) -> str:
    cols, rows = pattern
    if cols < rows:
        return (f"; the pattern is {cols}x{rows} (COLSxROWS inner corners): did you mean {rows}x{cols}? OpenCV's "
                "convention and the thesis's give the longer side first")
    return f"; check --pattern {cols}x{rows} (inner corners, COLSxROWS) against the board"


def outlying_views(names: list[str], rms: np.ndarray, what: str = "view") -> list[str]:
    """One warning per view whose RMS (px) is far above the rest (module docstring)."""
    rms = np.asarray(rms, dtype=float)
    if rms.size < 4:
        return []  # too few views to tell one from the rest
    med = float(np.median(rms))
    mad = 1.4826 * float(np.median(np.abs(rms - med)))
    limit = max(FACTOR * med, med + ROBUST_SIGMAS * mad)
    return [f"{what} {name}: RMS {r:.3g} px, {r / med:.1f} x the median {med:.3g} px of {rms.size} {what}s; look "
            "at its corners (the residual plots) and remove it if the board is mis-detected or blurred"
            for name, r in zip(names, rms) if r > limit]


def stray_corners(names: list[str], residuals: np.ndarray, pattern: tuple[int, int]) -> list[str]:
    """Views with a corner far off: residual norm above CORNER_FACTOR x the set's RMS and above 1 px."""
    res = np.asarray(residuals, dtype=float)  # (V, n, 2)
    norms = np.linalg.norm(res, axis=-1)
    rms = float(np.sqrt(np.mean(np.sum(res ** 2, axis=-1))))
    limit = max(CORNER_FACTOR * rms, 1.0)
    out = []
    for name, row in zip(names, norms):
        k = int(np.argmax(row))
        if row[k] > limit:
            out.append(f"view {name}: corner {k} (row {k // pattern[0]}, column {k % pattern[0]}) is {row[k]:.3g} px "
                       f"off, {row[k] / rms:.0f} x the RMS {rms:.3g} px of all corners: a mis-detected or "
                       f"mis-numbered corner{_pattern_hint(pattern)}")
    return out


def _directions(q: np.ndarray, pattern: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    grid = np.asarray(q, dtype=float).reshape(pattern[1], pattern[0], 2)
    return (grid[:, -1] - grid[:, 0]).mean(axis=0), (grid[-1, :] - grid[0, :]).mean(axis=0)


def handedness(q: np.ndarray, pattern: tuple[int, int]) -> int:
    """+1 or -1: the sign of (column direction x row direction) in the image."""
    ex, ey = _directions(q, pattern)
    return 1 if ex[0] * ey[1] - ex[1] * ey[0] > 0 else -1


def mirrored_views(corners: dict[str, np.ndarray], pattern: tuple[int, int]) -> list[str]:
    """Views whose grid handedness differs from the majority's (module docstring)."""
    signs = {name: handedness(q, pattern) for name, q in corners.items()}
    majority = 1 if sum(signs.values()) >= 0 else -1
    odd = sorted(n for n, s in signs.items() if s != majority)
    if not odd or 2 * len(odd) >= len(signs):
        return []
    return [f"{len(odd)} of {len(signs)} views have their corners in mirrored order ({', '.join(odd[:6])}"
            f"{' ...' if len(odd) > 6 else ''}): a mirrored image or a different board in them; such a view "
            f"cannot fit the same board{_pattern_hint(pattern)}"]


def grid_angle(q: np.ndarray, pattern: tuple[int, int]) -> float:
    """Image angle (deg) of the direction along the first index (the board's columns) of a view's grid."""
    ex, _ = _directions(q, pattern)
    return float(np.degrees(np.arctan2(ex[1], ex[0])))


def _renumberings(pattern: tuple[int, int]) -> list[tuple[int, callable]]:
    """(rotation in deg, function of a (rows, cols, 2) grid) for the grid symmetries that keep its shape."""
    out = [(0, lambda g: g), (180, lambda g: g[::-1, ::-1])]
    if pattern[0] == pattern[1]:
        out += [(90, lambda g: np.rot90(g, 1)), (270, lambda g: np.rot90(g, -1))]
    return out


def align_order(q_ref: np.ndarray, q: np.ndarray, pattern: tuple[int, int]) -> tuple[np.ndarray, int]:
    """`q` renumbered by the grid symmetry whose column direction is closest to `q_ref`'s, and that rotation (deg;
    0 when `q` already runs like `q_ref`)."""
    target = grid_angle(q_ref, pattern)
    grid = np.asarray(q).reshape(pattern[1], pattern[0], 2)
    best = None
    for turn, renumber in _renumberings(pattern):
        cand = renumber(grid).reshape(-1, 2)
        gap = abs((grid_angle(cand, pattern) - target + 180.0) % 360.0 - 180.0)
        if best is None or gap < best[0]:
            best = (gap, cand, turn)
    return np.ascontiguousarray(best[1]), best[2]


def view_warnings(used: list[str], full, corners: dict, pattern) -> list[str]:
    """A calibration's view warnings from its full-set solve: views far off the rest, stray corners (the rejected
    ones too: a corner far off may mean a wrong --pattern, whose hint this warning carries), and views in another
    corner order."""
    return (outlying_views(used, full.per_view_rms[:, 0]) + stray_corners(used, full.residuals[:, 0], pattern)
            + mirrored_views(corners, pattern))
