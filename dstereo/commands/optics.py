"""`dstereo optics`: depth of field, diffraction and stereo resolution for a planned capture (thesis 5.1)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer

from dstereo.config.options import OPTICS  # flags and help declared once, with the file keys

# (results key, label) in the order the console table shows them; rows whose value is None are skipped.
ROWS = (
    ("focus_distance_mm", "focus distance (mm)"),
    ("focal_length_mm", "lens focal length (mm)"),
    ("f_number", "f-number"),
    ("sensor_width_mm", "sensor width (mm)"),
    ("sensor_height_mm", "sensor height (mm)"),
    ("sensor_diagonal_mm", "sensor diagonal (mm)"),
    ("crop_factor", "crop factor"),
    ("effective_focal_length_mm", "effective focal length (mm)"),
    ("dof_focal_length_mm", "focal length used for DoF (mm)"),
    ("coc_mm", "circle of confusion (mm)"),
    ("hyperfocal_mm", "hyperfocal distance (mm)"),
    ("near_mm", "near limit (mm)"),
    ("far_mm", "far limit (mm)"),
    ("total_dof_mm", "total depth of field (mm)"),
    ("front_mm", "in front of subject (mm)"),
    ("front_percent", "in front of subject (%)"),
    ("behind_mm", "behind subject (mm)"),
    ("behind_percent", "behind subject (%)"),
    ("wavelength_mm", "wavelength (mm)"),
    ("airy_disk_mm", "Airy disk diameter (mm)"),
    ("pixel_size_mm", "pixel size (mm)"),
    ("three_pixels_mm", "3 x pixel size (mm)"),
    ("airy_over_pixel", "Airy disk / pixel"),
    ("diffraction_limited", "diffraction limited"),
    ("fov_horizontal_deg", "horizontal field of view (deg)"),
    ("fov_vertical_deg", "vertical field of view (deg)"),
    ("fov_diagonal_deg", "diagonal field of view (deg)"),
    ("footprint_width_mm", "footprint width at focus (mm)"),
    ("footprint_height_mm", "footprint height at focus (mm)"),
    ("baseline_mm", "stereo baseline (mm)"),
    ("disparity_at_focus_px", "disparity at focus (px)"),
    ("depth_per_pixel_mm", "depth per pixel of disparity (mm)"),
    ("disparity_precision_px", "matcher precision (px)"),
    ("depth_resolution_mm", "depth resolution at that precision (mm)"),
)


def _fmt(value: Any) -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    if value == float("inf"):
        return "infinity"
    return f"{value:.2f}" if abs(value) >= 10 else f"{value:.4g}"


def table_rows(results: dict[str, Any]) -> list[tuple[str, str]]:
    """(label, value) of each result that has a value, in the order of ROWS."""
    return [(label, _fmt(results[key])) for key, label in ROWS if results.get(key) is not None]


def render_table(results: dict[str, Any]) -> str:
    """Plain two-column text table of the results, then the notes."""
    rows = table_rows(results)
    width = max(len(label) for label, _ in rows)
    lines = [f"{label:<{width}}  {value}" for label, value in rows]
    lines += [f"note: {note}" for note in results["notes"]]
    return "\n".join(lines)


def to_json(results: dict[str, Any]) -> str:
    """JSON text of the results; an infinite length (far limit beyond the hyperfocal) becomes null."""
    import json
    import math

    clean = {k: (None if isinstance(v, float) and math.isinf(v) else v) for k, v in results.items()}
    return json.dumps(clean, indent=2)


def optics(
    focus_distance: Optional[float] = OPTICS.option("focus_distance"),
    focal_length: Optional[float] = OPTICS.option("focal_length"),
    sensor: Optional[str] = OPTICS.option("sensor"),
    crop_factor: Optional[float] = OPTICS.option("crop_factor"),
    f_number: Optional[float] = OPTICS.option("f_number"),
    coc: Optional[float] = OPTICS.option("coc"),
    pixel_size: Optional[float] = OPTICS.option("pixel_size"),
    wavelength: Optional[float] = OPTICS.option("wavelength"),
    baseline: Optional[float] = OPTICS.option("baseline"),
    disparity_precision: Optional[float] = OPTICS.option("disparity_precision"),
    dof_focal_length: Optional[str] = OPTICS.option("dof_focal_length"),
    config: Optional[Path] = OPTICS.option("config"),
    plots: Optional[Path] = OPTICS.option("plots"),
    json_output: bool = typer.Option(False, "--json", help="Print only JSON (lengths in mm)."),
) -> None:
    """Depth of field, hyperfocal distance, diffraction check and stereo depth resolution for a capture set-up."""
    from dstereo.optics import calculator as lib
    from dstereo.io.output_location import check_creatable

    if plots is not None:
        check_creatable(plots, "--plots")  # before any work: the figures come last
    flags = {
        "focus_distance": focus_distance, "focal_length": focal_length, "sensor": sensor,
        "crop_factor": crop_factor, "f_number": f_number, "coc": coc, "pixel_size": pixel_size,
        "wavelength": wavelength, "baseline": baseline, "disparity_precision": disparity_precision,
        "dof_focal_length": dof_focal_length,
    }
    from dstereo.config import optics as settings

    file_layer = settings.file_layer(config) if config is not None else {}
    setup = lib.make_config(settings.settings(file_layer, flags))
    results = lib.compute_optics(setup)
    if plots is not None:
        from dstereo.io.optics_figures import write_plots, write_report

        results["plots"] = [str(p) for p in write_plots(setup, lib.dof_curves(setup), plots)]
        results["plots"] += [str(p) for p in write_report(plots, table_rows(results), results)]
    if json_output:
        typer.echo(to_json(results))
        return
    typer.echo(render_table(results))
    for path in results.get("plots", []):
        typer.echo(f"wrote {path}")
