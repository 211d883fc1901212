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


def search_range_tries(search: dict | None) -> list[str]:
    """One console line per try when the range was widened or a widening was tried: its range, valid and
    left-right consistent shares, and whether it was kept (and why not); none for a single try."""
    tries = (search or {}).get("tries") or []
    if len(tries) < 2:
        return []
    lines = []
    for t in tries:
        lr = t.get("lr_consistent_share")
        lr_text = "" if lr is None else f", {100 * lr:.1f}% left-right consistent"
        lines.append(f"try {t['min_disparity']}..{t['max_disparity']} px: {100 * t['valid_share']:.1f}% valid{lr_text}"
                     f" ({t['verdict']})")
    return lines


def matching_cost_lines(search: dict | None) -> list[str]:
    """Console lines for summary['search_range']['matching_cost']: the cost SGBM matched and why (with its figure),
    and what the rank cost's check dropped (`dstereo.stereo.cost_check`)."""
    cost = (search or {}).get("matching_cost")
    if not cost:
        return []
    lines = [f"matching cost: {cost['cost']} ({cost['why']})"]
    check = cost.get("cross_check")
    if check:
        lines.append(f"rank check: {100 * check['disagree_share']:.1f}% of the pixels disagree by more than "
                     f"{check['agreement_px']:g} px; {100 * check['dropped_share']:.1f}% dropped in regions where most "
                     f"disagree ({check['region_px']} px windows), {100 * check['kept_share']:.1f}% kept")
    return lines


def fill_line(fill: dict | None) -> str | None:
    """One console line for summary['fill']: whether the fill ran and why, and what it filled."""
    if not fill or "why" not in fill:
        return None
    if not fill.get("enabled"):
        return f"fill: off, {fill['why']}"
    total = fill.get("filled_points", 0) + fill.get("matched_points", 0)
    sigma = fill.get("sigma_px")
    what = (f"{fill.get('filled_points', 0)} of {total} points filled (flag `filled`)" if total else
            f"{fill['filled_pixels']} pixels filled")
    return (f"fill: on, {fill['why']}: {what}" + (f", sigma_d median {sigma['median']:.3g} px" if sigma else ""))


def density_check_line(check: dict | None) -> str | None:
    """One console line for summary['density_check'] (`dstereo.stereo.density_check`): the map kept and why, with
    each try's figures; None where the check did not run (a cost or fill given, or the rank cost chosen)."""
    if not check or "why" not in check:
        return None
    return f"density check: kept the {check['kept']} cost's map ({check['why']})"
