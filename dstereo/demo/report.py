"""The demo's comparison as text: the console table, its notes and comparison.md."""

from __future__ import annotations

import numpy as np


def number_text(value, digits: int = 4) -> str:
    if value is None or not np.isfinite(value):
        return "-"
    return f"{value:.{digits}g}" if abs(value) < 1e4 else f"{value:.1f}"


TABLE_HEADER = ("parameter", "truth", "thesis path", "error", "joint", "error", "sigma", "bound", "check")


def table_rows(comparison: dict) -> list[tuple[str, ...]]:
    """One tuple of strings per row, in the columns of `TABLE_HEADER`."""
    out = []
    for r in comparison["rows"]:
        eu = " " + r["error_unit"]
        digits = 6 if r["unit"] == "px" and r["error_unit"] == "%" else 4

        def value(v):
            return "-" if v is None else (f"{v:.{digits}g}" if r["unit"] != "mm" or v > 10 else f"{v:.4f}")

        truth = "-" if r["parameter"].startswith("surface") else value(r["truth"])
        thesis_error = "" if r["thesis_error"] is None else number_text(r["thesis_error"], 3) + eu
        out.append((f"{r['parameter']} [{r['unit']}]", truth, value(r["thesis"]), thesis_error, value(r["estimate"]),
                    number_text(r["error"], 3) + eu, "" if r["sigma"] is None else number_text(r["sigma"], 2) + eu,
                    number_text(r["bound"], 3) + eu, "ok" if r["ok"] else "WARNING"))
    return out


def notes(comparison: dict) -> list[str]:
    """How to read the table, one sentence a line."""
    b, sb = comparison["bounds"], comparison["surface_bound"]
    return [
        "thesis path: each camera alone, then the rig with those intrinsics fixed (mean over the subsets surviving "
        "the stereo steps); joint: both cameras and the rig refined together. The check applies to the joint.",
        "sigma: the joint solve's standard deviation (Jacobian with scaled columns; corner noise from the fit).",
        f"bounds: fx, fy within {b['focal_percent']:g} %, baseline within {b['baseline_percent']:g} %; principal "
        f"points and rotation within max({b['principal_px']:g} px / {b['rotation_deg']:g} deg, {b['sigmas']:g} "
        "sigma), since a 7.6 deg field barely shows perspective on the board.",
        "rotation: truth and estimates are rotation angles; errors the angle of R_est R_true^T.",
        "surface: distance from the true surface along the true left camera's rays; 'rigid fit' after the best "
        "rigid motion of the cloud (its shape alone).",
        f"surface bounds: disparity noise {comparison['disparity_noise_px']:g} px -> {sb['matching_mm']:.3f} mm; "
        f"the joint calibration adds {b['sigmas']:g} sigma of depth scale ({sb['scale_mm']:.3f} mm) and of "
        f"pointing ({sb['pointing_mm']:.3f} mm) in quadrature.",
    ]


def surface_lines(comparison: dict) -> list[str]:
    """Surface RMS before/after the sub-pixel refinement, and the predicted depth std beside the measured error."""
    s = comparison["surface"]
    sz = s["sigma_z_mm"]
    return [
        f"surface RMS vs truth, SGBM -> refined: joint calibration {s['joint_sgbm']['rms_mm']:.4f} -> "
        f"{s['joint']['rms_mm']:.4f} mm, true calibration {s['true_calibration_sgbm']['rms_mm']:.4f} -> "
        f"{s['true_calibration']['rms_mm']:.4f} mm (mean {s['true_calibration_sgbm']['mean_mm']:+.4f} -> "
        f"{s['true_calibration']['mean_mm']:+.4f} mm); the refinement dropped "
        f"{100 * s['refine_dropped_fraction']:.2f} % of SGBM's pixels.",
        f"predicted depth std (joint covariance + per-pixel disparity noise, median {sz['sigma_d_px']:.3g} px): median "
        f"sigma_z {sz['median']:.4f} mm (calibration {sz['calibration_at_median_mm']:.4f}, disparity "
        f"{sz['disparity_at_median_mm']:.4f} mm at the median point) against the measured surface RMS "
        f"{s['joint']['rms_mm']:.4f} mm (true calibration, matching alone: {s['true_calibration']['rms_mm']:.4f} mm)."
        + ("" if sz["calibration_included"] else " Calibration uncertainty NOT included."),
    ]


def markdown(comparison: dict) -> str:
    """comparison.md: the table, the subset steps, the surface statistics and where everything is."""
    lines = ["# dstereo demo: estimates against the truth", "",
             "| " + " | ".join(TABLE_HEADER) + " |", "|" + "---|" * len(TABLE_HEADER)]
    lines += ["| " + " | ".join(c.replace("|", "\\|") for c in row) + " |" for row in table_rows(comparison)]
    sub = comparison["subsets"]
    lines += [""] + [f"- {n}" for n in notes(comparison)]
    lines += ["", f"## Stereo subsets, thesis path ({sub['plan']}, m = {sub['per_set']})", ""]
    lines += [f"- {m}" for m in sub["steps"]]
    lines += [f"- after the steps: {k} = {v['mean']:.6g} +- {v['std']:.3g}" for k, v in sub["after_steps"].items()]
    lines += ["", "## Sub-pixel refinement and predicted error", ""] + [f"- {n}" for n in surface_lines(comparison)]
    for key in ("joint", "thesis", "true_calibration", "joint_sgbm", "true_calibration_sgbm"):
        title = key.replace('_', ' ').replace('sgbm', 'SGBM only, no refinement')
        if key == "thesis":
            title = "calibration/stereo.yml, dstereo calibrate's joint rig solve on the surviving frames"
        lines += ["", f"## Surface ({title})", ""]
        lines += [f"- {k}: {number_text(v) if isinstance(v, float) else v}" for k, v in comparison["surface"][key].items()]
    lines += ["", "## Files", "", "Reports: [calibration](calibration/report.html) (each camera's in its folder), "
              "[reconstruction](reconstruction/report.html), with the cloud in 3D.", ""]
    lines += [f"- {k}: `{v}`" for k, v in comparison["paths"].items()]
    if comparison["warnings"] or comparison["calibration_warnings"]:
        lines += ["", "## Warnings", ""]
        lines += [f"- {w}" for w in comparison["warnings"] + comparison["calibration_warnings"]]
    return "\n".join(lines) + "\n"
