"""CLI options shared by the commands that match a stereo pair (`reconstruct`, `recession`): SGBM preset and
overrides, depth range, region of interest. Parsed once here so both give the same errors. The SGBM fields the
user names are recorded (`sgbm_user`): those stay as given, the others follow the images."""

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


def _field_names(overrides: dict) -> tuple[str, ...]:
    from dstereo.disparity import CV_NAMES

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
