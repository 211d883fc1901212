"""The summary at the top of each report.html (`io.report_html.Headline`): what was measured with its +- and the
verdicts of the self-checks, picked from the summary a writer has just written (summary.json, refine.json, the
optics results). Formatting only: every number and verdict here was computed before the writer ran."""

from __future__ import annotations

import math

from dstereo.io.report_html import Check, Headline


def pm(value, std=None, unit: str = "") -> str:
    """`value +- std unit`, the value to the std's second significant digit (no std: 6 significant digits)."""
    tail = f" {unit}" if unit else ""
    if value is None or not math.isfinite(float(value)):
        return "-"
    if std is None or not math.isfinite(float(std)) or std <= 0:
        return f"{value:.6g}{tail}"
    decimals = max(0, 1 - int(math.floor(math.log10(abs(std)))))
    return f"{value:.{decimals}f} +- {std:.{decimals}f}{tail}"


def camera_headline(summary: dict) -> Headline:
    """One camera's calibration (`io.results.summary_dict` and what `fill_camera_folder` adds)."""
    final, std = summary["final"], {r["parameter"]: r["full_set_std"] for r in summary["comparison"]}
    unit = (summary.get("pattern") or {}).get("unit", "")
    measured = [(name, pm(final[name], std.get(name), "px")) for name in ("fx", "fy", "cx", "cy") if name in final]
    lens = [n for n in summary["model"] if n in final]
    if lens:
        measured.append(("distortion", ", ".join(f"{n} {pm(final[n], std.get(n))}" for n in lens)))
    full = summary["full_set"]
    measured.append(("reprojection RMS", f"{full['rms']:.4f} px (full set, {len(summary['images']['used'])} images)"))
    pu = summary.get("projection_uncertainty")
    if pu and pu.get("std_px", {}).get("median") is not None:
        measured.append(("projection uncertainty", f"median {pu['std_px']['median']:.3g} px, max "
                                                   f"{pu['std_px']['max']:.3g} px at {pu['range']:.4g} {unit}"))
    cond = full["conditioning"]
    checks = [Check("identifiability", bool(cond["identifiable"]) and not cond.get("wild_parameters"),
                    cond["message"])]
    out = summary.get("outliers")
    if out and out.get("enabled", True):
        n = len(out.get("corners") or [])
        checks.append(Check("outlier corners", None, f"{n} of {out.get('corners_tested', '?')} rejected (|r| > "
                                                     f"{out['k_sigma']:.3g} sigma); RMS {out['rms_before_px']:.4g} -> "
                                                     f"{out['rms_after_px']:.4g} px"))
    pattern = summary.get("residual_pattern")
    if pattern:
        checks.append(Check("residual pattern", not pattern["significant"],
                            f"systematic {pattern['systematic_px']:.3f} px of RMS {pattern['rms_px']:.3f} px, p = "
                            f"{pattern['p_value']:.2g}" + (": the model is too simple" if pattern["significant"] else "")))
    if summary.get("model_advice"):
        checks.append(Check("model", False, summary["model_advice"]))
    mean = (summary.get("final_check") or {}).get("mean_check")
    if mean:
        checks.append(Check("subset mean", not mean["mean_worse"], f"fits the surviving views at "
                                                                   f"{mean['ratio']:.3f}x the solve's RMS"))
    xv = summary.get("cross_validation")
    if xv:
        checks.append(Check("cross-validation", xv.get("trusted"), xv.get("verdict", "")))
    return Headline(measured, checks, "+-: one standard deviation of the full-set solve (with the views' effects "
                                      "where they were fitted); the values are the file's (camera.yml).")


def rig_headline(summary: dict) -> Headline:
    """A rig's calibration (`io.cameras_files.cameras_summary` and what `write_multiview_results` adds)."""
    unit = summary.get("unit", "")
    measured = []
    for pair in summary.get("pairs", []):
        cols = pair["columns"]
        name = f"{pair['left']}-{pair['right']}"
        measured.append((f"baseline |T| {name}", pm(cols["Tnorm"]["value"], cols["Tnorm"]["std"], unit)))
        measured.append((f"rotation |RV| {name}", pm(math.degrees(cols["RVnorm"]["value"]),
                                                     math.degrees(cols["RVnorm"]["std"]), "deg")))
    for c in summary["cameras"]:
        k = c["camera_matrix"]
        measured.append((f"{c['name']} fx, fy", f"{k[0][0]:.2f}, {k[1][1]:.2f} px ({c['views']} views, RMS "
                                                f"{c['rms_joint']:.4f} px)"))
    joint = summary["joint"]
    measured.append(("joint RMS", f"{joint['rms']:.4f} px ({joint['status']})"))
    checks = []
    rc = summary.get("rig_consistency")
    if rc:
        checks.append(Check("rig consistency", bool(rc["consistent"]),
                            f"T/c = {rc['ratio']:.2f} (1 expected), p = {rc['p_value']:.2g}"))
    cv = summary.get("rig_cross_validation")
    if cv:
        checks.append(Check("rig cross-validation", bool(cv["trusted"]),
                            f"placements {cv['rig_ratio']:.2f}, intrinsics {cv['intrinsics_ratio']:.2f} (1 when the "
                            "+- is right)"))
    rs = summary.get("rig_subsets")
    if rs:
        left = rs.get("left_out_frames") or []
        checks.append(Check("frame subsets", None, f"{rs['surviving']} of {rs['subsets']} subsets survive the steps"
                                                   + (f"; left out: {', '.join(left)}" if left else "")))
    if summary.get("rejected_frames"):
        checks.append(Check("frames the rig cannot explain", False,
                            ", ".join(r["frame"] for r in summary["rejected_frames"])))
    reports = ", ".join(f"[{c['name']}]({c['name']}/report.html)" for c in summary["cameras"])
    return Headline(measured, checks, "+-: one standard deviation from the pair's covariance in its stereo file. "
                                      f"Each camera's own report: {reports}.")


def reconstruction_headline(summary: dict) -> Headline:
    """One reconstructed pair (its summary.json)."""
    depth, unc = summary.get("depth_mm") or {}, summary.get("uncertainty") or {}
    w, h = summary.get("image_size") or ("?", "?")
    measured = [("valid points", f"{summary['valid_points']} ({100 * summary['valid_fraction']:.1f} % of "
                                 f"{w} x {h} px)")]
    if depth:
        measured.append(("depth", f"median {depth['median']:.4g} mm (5-95 %: {depth['p05']:.4g} .. "
                                  f"{depth['p95']:.4g} mm)"))
    if unc.get("sigma_z_mm"):
        part = unc["median_point"]
        measured.append(("depth std sigma_z", f"median {unc['sigma_z_mm']['median']:.3g} mm, p95 "
                                              f"{unc['sigma_z_mm']['p95']:.3g} mm (at the median point: calibration "
                                              f"{part['calibration_mm']:.3g} mm, disparity {part['disparity_mm']:.3g} mm)"))
    sr = summary.get("search_range") or {}
    checks = []
    if sr:
        sat = sr.get("saturation") or {}
        edge = bool(sat.get("saturated_low") or sat.get("saturated_high"))
        checks.append(Check("disparity search range", not edge,
                            f"{sr['min_disparity']}..{sr.get('max_disparity', '?')} px ({sr.get('source', '')})"
                            + ("; matches pile up at an end of the range" if edge else "")))
    check = (summary.get("disparity_noise") or {}).get("plane_check") or {}
    if check.get("ratio") is not None:
        lo, hi = check.get("band", [0.67, 1.5])
        checks.append(Check("disparity noise", lo <= check["ratio"] <= hi,
                            f"scatter about local surface fits {check['ratio']:.2f}x the predicted sigma_d "
                            f"({check['tiles']} tiles; {lo:g}-{hi:g} expected)"))
    if unc:
        checks.append(Check("calibration uncertainty", bool(unc.get("calibration_included")),
                            "included in every point's sigma" if unc.get("calibration_included") else
                            "not included: the calibration file has no covariance"))
    return Headline(measured, checks)


def recession_headline(summary: dict) -> Headline:
    """A recession run (`io.recession_files.write_results`' summary)."""
    rate = summary["rate"]
    lo, hi = rate["ci95"]
    measured = [("recession rate at the stagnation point",
                 f"{1000 * rate['rate']:.4g} um/s (95 % interval {1000 * lo:.4g} .. {1000 * hi:.4g} um/s)"),
                ("frames", f"{summary['frames_used']} used of {summary['frames']}")]
    if summary.get("final_recession_mm") is not None:
        measured.append(("final recession", f"{summary['final_recession_mm']:.4g} mm"))
    weighted = summary.get("rate_weighted")
    if weighted:
        wlo, whi = weighted["ci95"]
        measured.append(("weighted rate", f"{1000 * weighted['rate']:.4g} um/s ({1000 * wlo:.4g} .. "
                                          f"{1000 * whi:.4g} um/s)"))
    checks = [Check("frames", not summary["skipped"], "every frame used" if not summary["skipped"] else
                    f"{len(summary['skipped'])} skipped: " + "; ".join(f"{k['name']}: {k['reason']}"
                                                                      for k in summary["skipped"][:3]))]
    checks.append(Check("line fit", None, f"residual RMS {rate['residual_rms']:.3g} mm over {rate['n']} frames"))
    return Headline(measured, checks)


def refine_headline(report: dict) -> Headline:
    """A rig refinement (`refine.json`)."""
    b, res = report["baseline"], report["residual_rms"]
    measured = [("baseline", f"{b['before_mm']:.4f} -> {b['after_mm']:.4f} mm ({b['percent']:+.4f} %"
                             + (f" +- {b['std_percent']:.2g} %" if b.get("std_percent") is not None else "") + ")")]
    for ax, r in report["rotation_right_camera_deg"].items():
        measured.append((f"rotation of the right camera about {ax}", pm(r["value"], r["std"], "deg")))
    measured.append((f"residual RMS ({res['unit']})", f"{res['before']:.4g} before, {res['after']:.4g} after"))
    checks = [Check("converged", bool(report["converged"]), f"{report['iterations']} iterations"),
              Check("determined by the reference", not report["poorly_determined"],
                    "every free parameter" if not report["poorly_determined"] else
                    "not: " + ", ".join(report["poorly_determined"])),
              Check("conditioning", None, report["conditioning"]["message"])]
    return Headline(measured, checks)


def optics_headline(results: dict) -> Headline:
    """`dstereo optics --plots` (`optics.calculator.compute_optics`' results)."""
    def mm(key):
        v = results.get(key)
        return "infinity" if v is None or v == float("inf") else f"{v:.5g} mm"

    measured = [("total depth of field", mm("total_dof_mm")), ("near .. far limit", f"{mm('near_mm')} .. "
                                                                                     f"{mm('far_mm')}"),
                ("hyperfocal distance", mm("hyperfocal_mm"))]
    if results.get("depth_resolution_mm") is not None:
        measured.append(("stereo depth resolution", mm("depth_resolution_mm")))
    checks = []
    if results.get("diffraction_limited") is not None:
        ratio = results.get("airy_over_pixel")
        checks.append(Check("diffraction", not results["diffraction_limited"],
                            f"Airy disk {results['airy_disk_mm']:.3g} mm"
                            + (f" = {ratio:.3g} x the pixel" if ratio is not None else "")
                            + ("; diffraction limited" if results["diffraction_limited"] else "; not diffraction "
                               "limited")))
    return Headline(measured, checks)
