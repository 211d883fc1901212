"""Console text shared by the commands that match a stereo pair (`reconstruct`, `recession`). Their matching
options (SGBM preset and overrides, depth range, region of interest) are parsed by `dstereo.config.reconstruction`,
one place for both."""

from __future__ import annotations


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
