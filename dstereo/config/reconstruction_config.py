"""What a reconstruction can be told: `ReconstructionConfig` (the CLI and configuration files fill it)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from dstereo.config.sgbm import PRESETS, SGBMParams


@dataclass(frozen=True)
class ReconstructionConfig:
    """Everything a reconstruction can be told (the CLI and configuration files fill it).

    depth_range (mm) sets the SGBM search range; without it (and without min/num_disparities in `sgbm_user`)
    the range comes from the data (`dstereo.stereo.search_range`, `match_in_range`; `search_range` (min, num) is a range a
    program chose, widened like an estimate when saturated), as do block size and speckle window
    unless named in `sgbm_user`; alpha / zero_disparity are stereoRectify's (the default
    zero_disparity=False keeps each rectified image centred on its own view, as converging rigs need); roi
    (x, y, w, h) on the rectified left image keeps points inside it only; outlier_neighbours > 0 turns on
    statistical outlier removal; max_jump is the relative depth step that breaks the mesh. refine: SGBM's
    pixel-locked sub-pixel disparity is refined (`dstereo.stereo.subpixel`); a pixel the refinement cannot refine
    is dropped (NaN), not kept at SGBM's value. Off by default: on rendered speckle it cuts the surface error
    2.6x, but on Middlebury 2014 (slanted, occluding, real images) it drops 4-10 % of the pixels and does not
    improve the good ones (experiments/results/middlebury.md). matching_cost: 'rank' (SGBM on the rank transform:
    survives a lighting change between the views), 'intensity' (on the grey levels, as before issue 30) or 'auto'
    (default: rank where the views' grey levels differ, `stereo.matching.LIGHTING_MISMATCH`; else the grey levels
    checked by the rank cost, `stereo.cost_check`). fill: unmatched pixels filled by an edge-aware plane fit where
    its sigma is at most fill_max_sigma px, each carrying its own sigma and the flag `filled` (`dstereo.stereo.fill`);
    False leaves them empty, None (default) fills the rank cost's maps only (`stereo.fill.fill_wanted`), including the
    one the density check keeps where the grey levels' map is under 80 % dense over the pixels whose SGBM block is
    not blank (`stereo.density_check`).
    """

    sgbm: SGBMParams = PRESETS["default"]
    sgbm_user: tuple[str, ...] = ()  # SGBM fields the user set (CLI/config), kept as given; "preset": all of them
    depth_range: tuple[float, float] | None = None
    search_range: tuple[int, int] | None = None  # (min, num) chosen by a caller (a sequence's first frame), not a user
    alpha: float = -1.0
    rectification: str = "auto"  # auto | pinhole | spherical (`dstereo.stereo.rectify_fisheye.choose_projection`)
    zero_disparity: bool = False
    undistort: str = "opencv"
    color_matching: bool = False
    matching_cost: str = "auto"  # auto | rank | intensity (`dstereo.stereo.matching.chosen_cost`)
    # fill unmatched pixels where the fit is confident (`dstereo.stereo.fill`), flagged: True / False force it; None
    # (the default) fills the rank cost's maps and not the grey levels' (`stereo.fill.fill_wanted`: the measured why)
    fill: bool | None = None
    fill_max_sigma: float = 0.7  # px: a pixel whose fill sigma would exceed this stays unmatched (`stereo.fill`: why)
    roi: tuple[int, int, int, int] | None = None
    outlier_neighbours: int = 0
    outlier_std: float = 2.0
    max_jump: float = 0.05
    refine: bool = False
    # uncalibrated path
    focal_mm: float | None = None
    pixel_size_mm: float | None = None
    crop_factor: float | None = None
    focal_px: float | None = None
    baseline_mm: float | None = None
    ratio: float = 0.75
    f_threshold: float = 1.0
    # point uncertainty (calibrated path): disparity_sigma None = estimated from a left-right check
    uncertainty: bool = True
    disparity_sigma: float | None = None
    full_covariance: bool = False

    def as_dict(self) -> dict:
        return asdict(self)


def user_sgbm_names(config: ReconstructionConfig) -> set[str]:
    """SGBM fields the user chose: named in `sgbm_user` (CLI, configuration file; "preset" = all) or set to a
    value other than the default's (library callers passing their own SGBMParams)."""
    from dataclasses import fields

    names = {f.name for f in fields(SGBMParams)}
    if "preset" in config.sgbm_user:
        return names
    default = PRESETS["default"]
    return set(config.sgbm_user) | {n for n in names if getattr(config.sgbm, n) != getattr(default, n)}
