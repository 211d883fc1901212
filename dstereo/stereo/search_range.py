"""The SGBM disparity search range: where it comes from, and whether the scene stayed inside it.

Disparities here are *sign-normalised*: d_s = sign(Q[3,2]) (u_left - u_right), the disparity SGBM is run on (a
rig whose right camera sits on the left is matched mirrored). Depth Z = Q[2,3] / (|Q[3,2]| d_s + Q[3,3]); a
converging rig rectified with each view on its own centre has negative d_s behind its zero-disparity plane, and
those are part of the range (SGBM's min_disparity may be negative).

Sources, first that applies wins (`choose_range`):
1. the user's depth range (--z-min/--z-max) or SGBM range (--sgbm min_disparity/num_disparities, a preset);
2. a Middlebury calib.txt's `ndisp` (the conservative bound the benchmark allows algorithms to use: 0..ndisp-1;
   its vmin/vmax are for visualisation only and are used only when ndisp is missing);
3. sparse SIFT matches on the rectified pair: matches on the same row (|dy| <= 1.5 px) whose disparity agrees with
   their image neighbours' give d_s; the range is
   their 0.5..99.5th percentile widened by a margin (30 % of that span, at least 16 px: sparse features miss
   textureless parts; measured on Middlebury upscaled 2x, the nearest 1 % of Adirondack lies 20 px beyond them);
4. with fewer sparse matches, the calibration's board distances (`dstereo calibrate` writes the nearest and
   farthest board corner depth as `board_depth_min`/`board_depth_max` into stereo.yml): the depth range the rig
   was calibrated over, widened by BOARD_MARGIN (a prior: the scene need not lie there; saturation still widens);
5. otherwise the default 0..63 px, with a warning.
After matching (`saturation`), the share of valid pixels within one px of either end is checked; a range the tool
chose itself is widened on the saturated side and matched again (`MAX_WIDENINGS` times at most); a user's range is
kept and the result carries a warning with the figures and the fix; a user's range is also checked against the
sparse matches (over SPARSE_OUTSIDE_SHARE of them outside: a warning), since SGBM does not always pile up at a
range end when the scene runs past it.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from dstereo.stereo.range_bounds import DisparityBounds

DEFAULT_RANGE = (0, 64)
EDGE_SHARE = 0.01  # share of valid pixels within 1 px of a range end above which the scene runs off it
MAX_WIDENINGS = 2
MIN_MATCHES = 20
SPARSE_OUTSIDE_SHARE = 0.02  # a user's range that leaves out more of the sparse matches than this gets a warning
ROW_TOLERANCE_PX = 1.5  # |y_left - y_right| of a sparse match on a rectified pair (calibration-limited)
SPARSE_MAX_PIXELS = 1_500_000  # larger pairs are downscaled for the sparse estimate (SIFT time)


@dataclass(frozen=True)
class SearchRange:
    """min_disparity .. min_disparity + num_disparities - 1 (px, sign-normalised), where it came from, and the
    figures behind it (`detail`)."""

    min_disparity: int
    num_disparities: int
    source: str
    detail: str = ""
    user: bool = False
    widened: int = 0

    @property
    def max_disparity(self) -> int:
        return self.min_disparity + self.num_disparities - 1

    def depth_range(self, Q: np.ndarray) -> tuple[float, float]:
        """(nearest, farthest) depth the range covers, in Q's unit (inf: the range reaches past infinity)."""
        return depth_for(Q, self.max_disparity), depth_for(Q, self.min_disparity)

    def as_dict(self, Q: np.ndarray | None = None) -> dict:
        out = asdict(self) | {"max_disparity": self.max_disparity}
        if Q is not None:
            near, far = self.depth_range(Q)
            out["depth_range_mm"] = {"near": near, "far": far if math.isfinite(far) else None,
                                     "note": "far None: the range includes disparities at or behind infinity"}
        return out


def depth_for(Q: np.ndarray, d_s: float) -> float:
    """Depth of sign-normalised disparity d_s (inf at or beyond infinity)."""
    w = abs(Q[3, 2]) * d_s + Q[3, 3]
    return float(Q[2, 3] / w) if w > 0 else math.inf


def ceil16(n: float) -> int:
    return max(16, 16 * math.ceil(n / 16))


def from_bounds(lo: float, hi: float, source: str, detail: str = "", user: bool = False) -> SearchRange:
    """Smallest SGBM range holding every disparity in [lo, hi]: floor(lo) .. at least ceil(hi)."""
    start = math.floor(lo)
    return SearchRange(start, ceil16(math.ceil(hi) - start + 1), source, detail, user)


def from_middlebury(extras: dict) -> SearchRange | None:
    """0..ndisp-1 of a Middlebury calib.txt (vmin..vmax, 10 % margin, when ndisp is missing), else None."""
    if "ndisp" in extras and extras["ndisp"] > 0:
        return from_bounds(0, extras["ndisp"] - 1, "calib.txt ndisp", f"ndisp = {extras['ndisp']:g}")
    if "vmin" in extras and "vmax" in extras and extras["vmax"] > extras["vmin"]:
        pad = max(2.0, 0.1 * (extras["vmax"] - extras["vmin"]))
        return from_bounds(extras["vmin"] - pad, extras["vmax"] + pad, "calib.txt vmin/vmax",
                           f"vmin {extras['vmin']:g}, vmax {extras['vmax']:g}, margin {pad:g} px")
    return None


BOARD_MARGIN = 0.5  # the board-distance prior spans depth / (1 + m) .. depth * (1 + m): scenes near the boards


def from_board_depths(extras: dict, Q: np.ndarray, width: int) -> SearchRange | None:
    """Range from the calibration's board depths (`board_depth_min`/`board_depth_max` in the calibration's unit,
    read into StereoCalibration.extras), widened to depth / (1 + BOARD_MARGIN) .. depth * (1 + BOARD_MARGIN);
    None when the file has none. Clipped to +-(width - 1) px like the sparse estimate."""
    near, far = extras.get("board_depth_min"), extras.get("board_depth_max")
    if near is None or far is None or not 0 < near <= far:
        return None
    near_z, far_z = near / (1 + BOARD_MARGIN), far * (1 + BOARD_MARGIN)
    d_near, d_far = disparity_for(Q, near_z), disparity_for(Q, far_z)
    lo, hi = max(min(d_near, d_far), -(width - 1)), min(max(d_near, d_far), width - 1)
    return from_bounds(lo, hi, "calibration board depths",
                       f"boards at {near:.4g}..{far:.4g} (calibration unit), prior {near_z:.4g}..{far_z:.4g}: "
                       f"too few sparse matches on the rectified rows")


def disparity_for(Q: np.ndarray, z: float) -> float:
    """Sign-normalised disparity of depth z (the inverse of `depth_for`)."""
    return float((Q[2, 3] / z - Q[3, 3]) / abs(Q[3, 2]))


def sparse_disparities(left_rect: np.ndarray, right_rect: np.ndarray, sign: float) -> np.ndarray:
    """Sign-normalised disparities (px) of SIFT matches that lie on the same rectified row."""
    import cv2

    from dstereo.errors import DstereoError
    from dstereo.stereo.features import match_sift

    h, w = left_rect.shape[:2]
    scale = min(1.0, math.sqrt(SPARSE_MAX_PIXELS / (h * w)))
    if scale < 1.0:
        size = (round(w * scale), round(h * scale))
        left_rect = cv2.resize(left_rect, size, interpolation=cv2.INTER_AREA)
        right_rect = cv2.resize(right_rect, size, interpolation=cv2.INTER_AREA)
    try:
        m = match_sift(left_rect, right_rect, ratio=0.8)
    except DstereoError:
        return np.zeros(0)
    same_row = np.abs(m.left[:, 1] - m.right[:, 1]) <= ROW_TOLERANCE_PX
    d_s = sign * (m.left[same_row, 0] - m.right[same_row, 0]) / scale
    return d_s[consistent_with_neighbours(m.left[same_row], d_s)]


def consistent_with_neighbours(q: np.ndarray, d: np.ndarray, k: int = 6) -> np.ndarray:
    """Matches whose disparity agrees with the median of their k nearest matches in the image (within 3 px or
    10 %): a false match on a repeated pattern (a chessboard row) lands on the right row with a wrong disparity,
    and its neighbours say so. Fewer than k + 1 matches: all are kept."""
    if len(d) <= k:
        return np.ones(len(d), bool)
    from scipy.spatial import cKDTree

    _, idx = cKDTree(q).query(q, k + 1)
    local = np.median(d[idx[:, 1:]], axis=1)
    return np.abs(d - local) <= np.maximum(3.0, 0.1 * np.abs(local))


def from_sparse(d_s: np.ndarray, width: int) -> SearchRange | None:
    """Range from sparse disparities: 0.5..99.5th percentile, margin max(16 px, 30 % of that span); None when
    fewer than MIN_MATCHES. The range is clipped to +-(width - 1) px, the most a pair of that width can hold."""
    if len(d_s) < MIN_MATCHES:
        return None
    p1, p99 = np.percentile(d_s, [0.5, 99.5])
    margin = max(16.0, 0.3 * (p99 - p1))
    lo, hi = max(p1 - margin, -(width - 1)), min(p99 + margin, width - 1)
    return from_bounds(lo, hi, "sparse matches",
                       f"{len(d_s)} SIFT matches on the rectified rows: 0.5-99.5 % disparities {p1:.1f}..{p99:.1f} px, "
                       f"margin {margin:.1f} px")


@dataclass(frozen=True)
class Saturation:
    """Shares of the valid pixels within 1 px of the low / high range end, and of invalid pixels.
    `low_at_infinity`: the range's low end already holds infinity (`DisparityBounds.low_reaches_infinity`), so
    pixels piled there lie at or beyond infinity (far background): normal, not a saturation."""

    low_share: float
    high_share: float
    invalid_share: float
    low_at_infinity: bool = False

    @property
    def low(self) -> bool:
        return self.low_share > EDGE_SHARE and not self.low_at_infinity

    @property
    def high(self) -> bool:
        return self.high_share > EDGE_SHARE

    @property
    def saturated(self) -> bool:
        return self.low or self.high

    def as_dict(self) -> dict:
        return asdict(self) | {"saturated_low": self.low, "saturated_high": self.high, "edge_share_limit": EDGE_SHARE}


def saturation(d_s: np.ndarray, rng: SearchRange, usable: np.ndarray | None = None,
               bounds: DisparityBounds | None = None) -> Saturation:
    """Saturation figures of a sign-normalised disparity map (NaN = invalid) over the `usable` pixels; with the
    rig's `bounds`, a pile-up at a low end that holds infinity is background (`Saturation.low_at_infinity`)."""
    d = d_s if usable is None else d_s[usable]
    valid = np.isfinite(d)
    n = max(int(valid.sum()), 1)
    dv = d[valid]
    at_infinity = bounds is not None and bounds.low_reaches_infinity(rng.min_disparity)
    return Saturation(float(np.sum(dv < rng.min_disparity + 1) / n), float(np.sum(dv > rng.max_disparity - 1) / n),
                      float(1.0 - valid.mean()) if d.size else 1.0, at_infinity)


def within(rng: SearchRange, bounds: DisparityBounds) -> SearchRange:
    """`rng` cut to the bounds; num_disparities' rounding up to 16 is taken from the low side where it would
    pass the high bound (the bounds hold whole blocks of 16, `range_bounds.whole_blocks`, so it always fits)."""
    lo, hi = max(rng.min_disparity, bounds.low), min(rng.max_disparity, bounds.high)
    if (lo, hi) == (rng.min_disparity, rng.max_disparity):
        return rng
    num = ceil16(hi - lo + 1)
    lo = max(bounds.low, min(lo, bounds.high - num + 1))
    detail = f"{rng.detail}; cut to the rig's disparity bounds {bounds.low}..{bounds.high} px".lstrip("; ")
    return SearchRange(lo, num, rng.source, detail, rng.user, rng.widened)


def widened(rng: SearchRange, sat: Saturation, bounds: DisparityBounds) -> SearchRange | None:
    """The range grown by its own width on each saturated side, within the rig's bounds (None when neither
    saturated side can grow: at a bound, or a low end that already holds infinity). A low end that would stop
    less than one more such step short of a known infinity goes to it: between a far depth Z and infinity lie
    only f B / Z px, so that is where a far background is, and stopping just short of it leaves all of it out."""
    grow = max(16, rng.num_disparities)
    lo = rng.min_disparity - (grow if sat.low else 0)
    if sat.low and bounds.infinity is not None and lo - bounds.low <= grow:
        lo = bounds.low
    hi = rng.max_disparity + (grow if sat.high else 0)
    lo, hi = max(lo, bounds.low), min(hi, bounds.high)
    if lo >= rng.min_disparity and hi <= rng.max_disparity:
        return None
    out = within(from_bounds(lo, hi, rng.source, rng.detail, rng.user), bounds)
    return SearchRange(out.min_disparity, out.num_disparities, rng.source, out.detail, rng.user, rng.widened + 1)


def saturation_warning(name: str, rng: SearchRange, sat: Saturation, Q: np.ndarray) -> str:
    sides = [s for s, on in (("low (far)", sat.low), ("high (near)", sat.high)) if on]
    near, far = rng.depth_range(Q)
    fix = ("widen --z-min/--z-max (or --sgbm min_disparity/num_disparities) to the scene's depth" if rng.user else
           "set --z-min/--z-max to the scene's depth range")
    return (f"{name}: the scene runs off the disparity search range {rng.min_disparity}..{rng.max_disparity} px "
            f"({rng.source}; depth {near:.0f}..{far:.0f} mm) at its {' and '.join(sides)} end: "
            f"{100 * sat.low_share:.1f}% / {100 * sat.high_share:.1f}% of valid pixels sit within 1 px of the "
            f"low / high end, {100 * sat.invalid_share:.0f}% invalid; depths there are wrong; {fix}")
