"""CLI options shared by the commands that match a stereo pair (`reconstruct`, `recession`): SGBM preset and
overrides, depth range, region of interest. Parsed once here so both give the same errors. The SGBM fields the
user names are recorded (`sgbm_user`): those stay as given, the others follow the images."""

from __future__ import annotations


def matching_changes(base_sgbm, preset: str | None, sgbm: list[str] | None, z_min: float | None,
                     z_max: float | None, roi: str | None) -> dict:
    """ReconstructionConfig fields set by these options (only those given), validated with one-line errors."""
    from dstereo.stereo.disparity import PRESETS, parse_overrides
    from dstereo.errors import DstereoError

    params = base_sgbm
    if preset is not None:
        if preset not in PRESETS:
            raise DstereoError(f"--preset {preset!r}: use one of {sorted(PRESETS)}")
        params = PRESETS[preset]
    overrides = parse_overrides(sgbm or [])
    changes = {"sgbm": params.with_overrides(overrides)}
    # What the user set is kept as given; the rest (search range, block size, speckle window) follows the data.
    changes["sgbm_user"] = (("preset",) if preset is not None else ()) + _field_names(overrides)
    if (z_min is None) != (z_max is None):
        raise DstereoError("give both --z-min and --z-max (mm), or neither")
    if z_min is not None:
        changes["depth_range"] = (z_min, z_max)
    if roi is not None:
        try:
            x, y, w, h = (int(v) for v in roi.split(","))
        except ValueError:
            raise DstereoError(f"--roi {roi!r}: write x,y,w,h in pixels, e.g. --roi 100,50,400,300") from None
        changes["roi"] = (x, y, w, h)
    return changes


# (ReconstructionConfig field, flag, rule) for the numbers a user sets; each rule is checked after files and flags
# are merged, so a configuration file's value is held to it too.
_POSITIVE = (("outlier_std", "--outlier-std"), ("max_jump", "--max-jump"), ("focal_mm", "--focal-mm"),
             ("pixel_size_mm", "--pixel-size-mm"), ("crop_factor", "--crop-factor"), ("focal_px", "--focal-px"),
             ("baseline_mm", "--baseline-mm"))


def check_reconstruction_config(cfg, image_width: int | None = None) -> None:
    """Refuse values no reconstruction can use (one line naming the flag), before any work."""
    import math

    from dstereo.errors import DstereoError

    for name, flag in _POSITIVE:
        value = getattr(cfg, name)
        if value is not None and not (math.isfinite(value) and value > 0):
            raise DstereoError(f"{flag} {value}: must be a positive number")
    if cfg.outlier_neighbours < 0:
        raise DstereoError(f"--outliers {cfg.outlier_neighbours}: give a number of neighbours >= 0 (0 turns it off)")
    if not (cfg.alpha == -1 or 0 <= cfg.alpha <= 1):
        raise DstereoError(f"--alpha {cfg.alpha}: rectification's free scaling is -1 (OpenCV's default) or 0..1")
    lr = cfg.sgbm.lr_check
    if lr is not None and not (math.isfinite(lr) and lr >= 0):
        raise DstereoError(f"--lr-check {lr}: the left-right tolerance is a distance in px, >= 0")
    lo, n = cfg.sgbm.min_disparity, cfg.sgbm.num_disparities
    if image_width is not None and (lo <= -image_width or lo + n > 2 * image_width):
        raise DstereoError(f"--sgbm min_disparity={lo} with num_disparities={n} searches disparities "
                           f"{lo}..{lo + n - 1} "
                           f"px, far outside the {image_width} px wide image; set the range from the scene's depth "
                           "with --z-min/--z-max")


def _field_names(overrides: dict) -> tuple[str, ...]:
    from dstereo.stereo.disparity import CV_NAMES

    return tuple(CV_NAMES.get(k, k).strip().lower().replace("-", "_") for k in overrides)


def search_range_line(search: dict | None) -> str:
    """One console line for summary['search_range']: the range, its source, the depths it covers, the reruns."""
    if not search:
        return "disparity search range: not recorded"
    depth = search.get("depth_range_mm") or {}
    far = depth.get("far")
    cover = (f"; depth {depth['near']:.4g}..{far:.4g} mm" if far is not None else
             f"; depth {depth['near']:.4g} mm..infinity") if depth else ""
    grown = f", widened {search['widened']}x after saturation" if search.get("widened") else ""
    return (f"disparity search range {search['min_disparity']}..{search['max_disparity']} px "
            f"({search['source']}{grown}{cover})")
