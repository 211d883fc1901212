"""The recession results folder, written atomically (`io.results.atomic_folder`):

    report.md             the run in a page, with the figures
    report.html           the same in one page a browser opens, with the face in 3D (`io.report_html`)
    summary.json          rate (with its 95 % interval), weighted rate, axis, stagnation point, grid, skipped
                          frames with reasons, configuration, units
    recession.csv         one row per frame: time, stagnation-point recession and its standard error, cells, status
    recession_maps.npz    grid coordinates u, v (mm), per-frame heights / recession maps (frames, ny, nx), rate map,
                          random_sigma_mm: per cell the RMS random height std of its points (disparity noise)
    plots/recession_vs_time.png, recession_maps.png, rate_map.png, radial_profiles.png
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from dstereo.io.results import atomic_folder, write_json

CSV_COLUMNS = ("frame", "name", "time_s", "recession_mm", "recession_se_mm", "stagnation_cells", "valid_cells",
               "valid_fraction", "status", "reason")


def write_csv(path: Path, result) -> None:
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(CSV_COLUMNS)
        for f in result.frames:
            writer.writerow([f.index, f.name, f"{f.time_s:.6g}", _num(f.recession.value), _num(f.recession.se),
                             f.recession.cells, f.valid_cells, _num(f.valid_fraction), f.status, f.reason])


def _num(value: float) -> str:
    return f"{value:.6f}" if np.isfinite(value) else ""


def write_npz(path: Path, result) -> None:
    np.savez_compressed(
        path, u_mm=result.grid.u, v_mm=result.grid.v, time_s=result.times,
        names=np.array([f.name for f in result.frames]), ok=result.ok, heights_mm=result.heights,
        height_se_mm=result.height_se, recession_mm=result.recession, rate_mm_s=result.rates["rate"],
        rate_se_mm_s=result.rates["rate_se"], rate_ci95_half_mm_s=result.rates["ci95_half"],
        rate_frames=result.rates["frames"], axis=result.sample.axis, stagnation_point_mm=result.sample.point,
        axes=result.sample.axes,
        **({} if result.random_sigma is None else {"random_sigma_mm": result.random_sigma,
                                                   "random_se_mm": result.random_se}))


def write_results(out, result, calibration: str, sequence: str, force: bool = False, extra: dict | None = None) -> dict:
    """Fill the results folder (module docstring); returns the summary written to summary.json."""
    from dstereo.io import recession_figures as plots

    from dstereo.io.calib_files import calibration_unit_note

    summary = {"sequence": str(sequence), "calibration": str(calibration),
               "calibration_unit": calibration_unit_note(calibration),  # converted to mm, or mm assumed
               **result.summary(), **(extra or {})}
    with atomic_folder(out, force) as tmp:
        write_csv(tmp / "recession.csv", result)
        write_npz(tmp / "recession_maps.npz", result)
        (tmp / "plots").mkdir()
        plots.recession_vs_time(result, tmp / "plots" / "recession_vs_time.png")
        plots.recession_maps(result, tmp / "plots" / "recession_maps.png")
        plots.rate_map(result, tmp / "plots" / "rate_map.png")
        plots.radial_profiles(result, tmp / "plots" / "radial_profiles.png")
        summary["files"] = sorted(str(p.relative_to(tmp)) for p in tmp.rglob("*") if p.is_file()) + \
            ["summary.json", "report.md", "report.html"]
        write_json(tmp / "summary.json", summary)
        (tmp / "report.md").write_text(report_markdown(result, summary))
        write_html(tmp, result, summary)
    return summary


def write_html(folder: Path, result, summary: dict) -> None:
    """report.html: report.md with the summary at the top and the face of the last frame used in 3D, coloured by
    its recession since the reference frame."""
    from dstereo.io.report_headlines import recession_headline
    from dstereo.io.report_html import write_report_html
    from dstereo.io.view3d import surface_view

    used = np.flatnonzero(result.ok)
    view = None
    if len(used):
        last = int(used[-1])
        f = result.frames[last]
        view = surface_view(result.grid.u, result.grid.v, result.heights[last], result.recession[last],
                            "recession (mm)", f"The face in frame {f.name} (t = {f.time_s:g} s, the last frame used) "
                            "on the analysis grid: height along the sample axis over (u, v), coloured by its "
                            "recession since the reference frame. Drag to rotate, scroll to zoom.")
    write_report_html(folder, recession_headline(summary), view)


def _rate(fit) -> str:
    return (f"{1000 * fit.rate:.4g} um/s (95 % interval {1000 * fit.ci95[0]:.4g} .. {1000 * fit.ci95[1]:.4g} um/s, "
            f"standard error {1000 * fit.rate_se:.2g} um/s, {fit.n} frames, residual RMS {fit.residual_rms:.3g} mm)")


def report_markdown(result, summary: dict) -> str:
    s = result.sample
    lines = [f"# Surface recession: {summary['sequence']}", "",
             f"- calibration: {summary['calibration']}",
             f"- frames: {summary['frames']}, used {summary['frames_used']}, reference {summary['reference_frame']}",
             f"- sample axis (left camera frame, away from the cameras): {np.round(s.axis, 5).tolist()} ({s.source})",
             f"- stagnation point: {np.round(s.point, 3).tolist()} mm",
             f"- grid: {result.grid.spacing:g} mm cells, {len(result.grid.u)} x {len(result.grid.v)}; stagnation "
             f"value: {result.config.stagnation_model} fit within {result.config.stagnation_radius_mm:g} mm", "",
             "## Rate at the stagnation point", "",
             f"**{_rate(result.fit)}**", "",
             "Least-squares line through (time, stagnation-point recession), the thesis's HSC analysis (3.2.1) in "
             "3D. The interval holds the frames' scatter about the line (Student's t, n - 2 degrees of freedom) "
             "and the part of the error common to all frames that no frame's scatter shows: the stagnation "
             "disc's cells' own rate errors beyond their frames' noise (summary.json rate_common_part)"
             + (f"; standard errors {1000 * result.fit.rate_se_frames:.2g} and {1000 * result.fit.rate_se_common:.2g} "
                "um/s, added in quadrature" if result.fit.rate_se_common is not None else "") + "."]
    if result.weighted_fit is not None:
        lines += ["", f"Weighted by each frame's standard error: {_rate(result.weighted_fit)}."]
    lines += ["", "![recession vs time](plots/recession_vs_time.png)", "",
              "| frame | time [s] | recession [mm] | +- se [mm] | cells | status |", "|---|---|---|---|---|---|"]
    for f in result.frames:
        status = f.status + (f": {f.reason}" if f.reason else "")
        lines.append(f"| {f.name} | {f.time_s:g} | {_num(f.recession.value)} | {_num(f.recession.se)} | "
                     f"{f.valid_cells} | {status} |")
    rnd = summary.get("random_uncertainty")
    if rnd:
        lines += ["", f"Random height std per point (per-pixel disparity noise, level checked on each frame): median "
                      f"{rnd['per_point_height_sigma_mm_median']:.3g} mm; per cell in recession_maps.npz "
                      "(random_sigma_mm)."]
    lines += ["", "Standard errors treat grid cells as independent (neighbours share the matching window), so "
              "they are lower bounds; the rate's interval does not rely on them.", "",
              "## Maps", "", "![maps](plots/recession_maps.png)", "", "![rate map](plots/rate_map.png)", "",
              "![profiles](plots/radial_profiles.png)", "",
              "Data: [recession.csv](recession.csv), [recession_maps.npz](recession_maps.npz), "
              "[summary.json](summary.json).", ""]
    if result.warnings or summary["skipped"]:
        lines += ["## Warnings", ""] + [f"- {w}" for w in result.warnings]
        lines += [f"- frame {k['name']} skipped: {k['reason']}" for k in summary["skipped"]] + [""]
    return "\n".join(lines)
