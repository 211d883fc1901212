"""report.md and report.html of a `dstereo reconstruct` results folder, from the pair's finished summary.json:
what was matched and how, the depth and its standard deviation, the self-checks, the figures, the warnings; the
html adds the cloud in 3D (`io.view3d`). With several pairs, the top folder's report lists them (`write_index`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

FILES = ("points.ply", "mesh.ply", "points.npy", "depth.npy", "disparity.npy", "sigma_z.npy", "sigma_xyz.npy",
         "matrices.npz", "summary.json")


def _search_range(sr: dict) -> str:
    text = f"{sr['min_disparity']}..{sr.get('max_disparity', sr['min_disparity'] + sr['num_disparities'] - 1)} px"
    if sr.get("source"):
        text += f" ({sr['source']}" + (f": {sr['detail']}" if sr.get("detail") else "") + ")"
    if sr.get("widened"):
        text += f", widened {sr['widened']}x after the matches piled up at an end"
    return text


def report_markdown(summary: dict, files: list[str]) -> str:
    """report.md of one pair's folder; `files`: the folder's files (the figures shown are those among them)."""
    s, depth, unc = summary, summary.get("depth_mm") or {}, summary.get("uncertainty") or {}
    w, h = s.get("image_size") or ("?", "?")
    lines = [f"# Reconstruction: {s.get('name', 'pair')}", "",
             f"- {s.get('mode', 'a')} pair, {w} x {h} px"
             + (f", calibration {s['calibration']}" if s.get("calibration") else "")
             + (f" ({s['calibration_unit']})" if s.get("calibration_unit") else ""),
             f"- points with a depth: {s['valid_points']} ({100 * s['valid_fraction']:.1f} % of the pixels), in "
             f"{s.get('units', 'mm')}" + (f"; frame: {s['frame']}" if s.get("frame") else "")]
    if s.get("rectification"):
        lines.append(f"- rectification: {s['rectification']['projection']} ({s['rectification']['why']})")
    lines.append("")
    if depth:
        lines += ["## Depth", "", f"Depth {depth['min']:.5g} .. {depth['max']:.5g} {s.get('units', 'mm')}, median "
                  f"{depth['median']:.5g} (5-95 %: {depth['p05']:.5g} .. {depth['p95']:.5g}).", ""]
    lines += ["## Disparity", ""]
    if s.get("search_range"):
        lines += [f"Search range {_search_range(s['search_range'])}.", ""]
    if (s.get("refine") or {}).get("enabled"):
        lines += [f"Sub-pixel refinement: {100 * s['refine']['dropped_fraction']:.2f} % of SGBM's pixels dropped "
                  f"({s['refine'].get('method', '')}).", ""]
    density = s.get("density_check") or {}
    if density.get("why"):  # the default's density check (`dstereo.stereo.density_check`): what it kept and why
        lines += [f"Density check: kept the {density['kept']} cost's map ({density['why']}).", ""]
    fill = s.get("fill") or {}
    if fill.get("filled_points"):
        lines += [f"Filled (not matched, flag `filled` in points.ply): {fill['filled_points']} points.", ""]
    lines += [f"![disparity]({n})" for n in ("disparity.png",) if n in files] + [""]
    if unc:
        lines += ["## Uncertainty", ""]
        if unc.get("sigma_z_mm"):
            part = unc["median_point"]
            lines += [f"Depth standard deviation sigma_z: median {unc['sigma_z_mm']['median']:.3g} mm, p95 "
                      f"{unc['sigma_z_mm']['p95']:.3g} mm, max {unc['sigma_z_mm']['max']:.3g} mm; disparity noise "
                      f"sigma_d median {unc['sigma_d_px']:.3g} px ({unc.get('sigma_d_source', '')}). At the median "
                      f"point: calibration {part['calibration_mm']:.3g} mm, disparity {part['disparity_mm']:.3g} mm"
                      + ("." if unc.get("calibration_included") else "; **calibration uncertainty not included**."),
                      ""]
        check = (s.get("disparity_noise") or {}).get("plane_check") or {}
        if check.get("ratio") is not None:
            lines += [f"Noise check: the disparity's scatter about local surface fits is {check['observed_px']:.3g} "
                      f"px, {check['ratio']:.2f}x the predicted sigma_d over {check['tiles']} smooth tiles"
                      + (f"; the sigmas were scaled by {s['disparity_noise']['scaled_by']:.2f}"
                         if s["disparity_noise"].get("scaled_by", 1.0) != 1.0 else "") + ".", ""]
        lines += [f"![depth std]({n})" for n in ("sigma_z.png",) if n in files] + [""]
    lines += ["## Rectification", ""]
    lines += [f"![epipolar lines]({n})" for n in ("epipolar.png",) if n in files]
    lines += ["", "The rectified images: " + ", ".join(f"[{n}]({n})" for n in ("rectified_left.png",
                                                                               "rectified_right.png") if n in files),
              "", "## Files", "", ", ".join(f"[{n}]({n})" for n in FILES if n in files) + "; every setting used "
              "is in summary.json (`config`).", ""]
    if s.get("warnings"):
        lines += ["## Warnings", ""] + [f"- {x}" for x in s["warnings"]] + [""]
    return "\n".join(lines)


def write_report(folder: Path, summary: dict, points: np.ndarray, sigma_z: np.ndarray | None) -> None:
    """report.md and report.html (with the cloud in 3D) of one pair's folder, once every other file is there."""
    from dstereo.io.report_headlines import reconstruction_headline
    from dstereo.io.report_html import write_report_html
    from dstereo.io.view3d import cloud_view

    files = sorted(p.name for p in Path(folder).iterdir() if p.is_file())
    (folder / "report.md").write_text(report_markdown(summary, files))
    write_report_html(folder, reconstruction_headline(summary), cloud_view(points, sigma_z, summary.get("units", "mm")))


def write_index(folder: Path, summaries: list[dict], names: list[str]) -> None:
    """report.md and report.html of a results folder of several pairs: one row per pair, linking its report."""
    from dstereo.io.report_html import write_report_html

    lines = [f"# Reconstruction: {len(summaries)} pairs", "",
             "| pair | points with a depth | depth median (mm) | sigma_z median (mm) | warnings | report |",
             "|---|---|---|---|---|---|"]
    for name, s in zip(names, summaries):
        unc = (s.get("uncertainty") or {}).get("sigma_z_mm") or {}
        lines.append(f"| {name} | {100 * s['valid_fraction']:.1f} % | {(s.get('depth_mm') or {}).get('median', float('nan')):.5g} | "
                     f"{unc.get('median', float('nan')):.3g} | {len(s.get('warnings') or [])} | "
                     f"[{name}/report.html]({name}/report.html) |")
    (folder / "report.md").write_text("\n".join(lines) + "\n")
    write_report_html(folder)
