"""CLI options shared by the commands that match a stereo pair (`reconstruct`, `recession`): SGBM preset and
overrides, depth range, region of interest. Parsed once here so both give the same errors."""

from __future__ import annotations


def matching_changes(base_sgbm, preset: str | None, sgbm: list[str] | None, z_min: float | None,
                     z_max: float | None, roi: str | None) -> dict:
    """ReconstructionConfig fields set by these options (only those given), validated with one-line errors."""
    from dstereo.disparity import PRESETS, parse_overrides
    from dstereo.errors import DstereoError

    params = base_sgbm
    if preset is not None:
        if preset not in PRESETS:
            raise DstereoError(f"--preset {preset!r}: use one of {sorted(PRESETS)}")
        params = PRESETS[preset]
    changes = {"sgbm": params.with_overrides(parse_overrides(sgbm or []))}
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
