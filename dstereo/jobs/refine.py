"""The file edge of rig refinement: read a calibration and a pair, observe the reference, write the results.

`run_refinement` writes, atomically (a temporary folder renamed at the end):
    stereo.yml    the corrected calibration (M1 D1 M2 D2 R T E F imageSize), readable wherever stereo.yml is
    refine.json   the correction with standard deviations, residual RMS before/after, conditioning, checks
    report.md     the same for a reader
    report.html   the same in one page a browser opens (`io.report_html`)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dstereo.errors import DstereoError
from dstereo.models.stereo_calibration import StereoCalibration
from dstereo.reference.objects import Board, Distances, Sphere
from dstereo.reference.refinement import Refinement


def board_corners(image: np.ndarray, board: Board, name: str) -> np.ndarray:
    """(n, 2) sub-pixel inner corners of `board` in one image, or a DstereoError naming the image."""
    import cv2

    from dstereo.io.corners import _detect_one  # the project's detector and sub-pixel refinement, uncached

    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    corners, reason = _detect_one(grey, tuple(board.pattern))
    if corners is None:
        raise DstereoError(f"{name}: {reason}; check `board` (inner corners, COLSxROWS, e.g. 9x6) and that the whole "
                           "board is in view")
    return corners


def observe_and_refine(calib: StereoCalibration, left: np.ndarray, right: np.ndarray, reference,
                       names=("left", "right"), focal: bool = False, fixed: tuple[str, ...] = (), marks=None,
                       config=None) -> Refinement:
    """Observations of `reference` in the pair (corners, dense matches or the given marks), then the refinement."""
    from dstereo.reference.dense import refine_dense
    from dstereo.reference.refine import refine_rig

    if isinstance(reference, Board):
        q_l, q_r = board_corners(left, reference, names[0]), board_corners(right, reference, names[1])
        return refine_rig(calib, reference, q_l, q_r, focal=focal, fixed=fixed)
    if isinstance(reference, Sphere):
        return refine_dense(calib, left, right, reference, focal=focal, fixed=fixed, config=config)
    if isinstance(reference, Distances):
        q_l, q_r = marks
        h, w = left.shape[:2]
        for side, q in (("left", q_l), ("right", q_r)):
            if np.any(q < -0.5) or np.any(q[:, 0] > w - 0.5) or np.any(q[:, 1] > h - 0.5):
                raise DstereoError(f"marks: a {side} mark lies outside the {w}x{h} image; check the pixel columns")
        return refine_rig(calib, reference, q_l, q_r, focal=focal, fixed=fixed)
    raise DstereoError(f"reference {type(reference).__name__}: the image path handles a board, a sphere or distances")


def run_refinement(calib_path, left_path, right_path, reference, out, focal: bool = False,
                   fixed: tuple[str, ...] = (), marks=None, force: bool = False, config=None) -> Refinement:
    """Read, refine and write the results folder `out` (see the module docstring)."""
    from dstereo.io.calib_files import read_stereo_calibration
    from dstereo.io.report_headlines import refine_headline
    from dstereo.io.report_html import write_report_html
    from dstereo.io.results import atomic_folder, check_output, write_json
    from dstereo.stereo.reconstruct import check_pair
    from dstereo.io.images import read_image

    check_output(out, force)
    calib = read_stereo_calibration(calib_path, unscaled=True)  # a rig in board squares: the reference scales it
    if calib.rectified:
        raise DstereoError(f"calibration {calib_path}: an already rectified (Middlebury) pair has no rig to refine")
    left, right = read_image(left_path), read_image(right_path)
    check_pair(left, right, calib, names=(str(left_path), str(right_path)))
    result = observe_and_refine(calib, left, right, reference, (str(left_path), str(right_path)), focal, fixed,
                                marks, config)
    report = result.report()
    report["inputs"] = {"calibration": str(calib_path), "left": str(left_path), "right": str(right_path),
                        "calibration_unit": calib.unit_note}  # converted to mm, or mm assumed
    with atomic_folder(out, force) as tmp:
        write_calibration(tmp / "stereo.yml", result.calibration, (left.shape[1], left.shape[0]))
        write_json(tmp / "refine.json", report)
        (tmp / "report.md").write_text(report_markdown(report))
        write_report_html(tmp, refine_headline(report))
    return result


def write_calibration(path: Path, calib: StereoCalibration, image_size: tuple[int, int]) -> None:
    from dstereo.io.stereo_files import write_stereo_yml

    rig = calib.rig
    E, F = np.array(rig.essential(), float), np.array(rig.fundamental(calib.k1, calib.k2), float)
    write_stereo_yml(path, calib.K1, calib.D1, calib.K2, calib.D2, calib.R, np.asarray(calib.T).reshape(3), E, F,
                     calib.image_size or image_size, unit="mm")  # a StereoCalibration is in mm (its readers convert)


def _std(value, fmt: str, unit: str) -> str:
    return "held" if value is None or not np.isfinite(value) else f"{format(value, fmt)} {unit}"


def report_markdown(r: dict) -> str:
    rot, b = r["rotation_right_camera_deg"], r["baseline"]
    res = r["residual_rms"]
    lines = [
        f"# Rig refinement from a {r['reference']}", "",
        f"Free parameters: {', '.join(r['free_parameters'])}. Corrections with one standard deviation "
        "(from the Jacobian at the solution).", "",
        "| correction | value | std |", "|---|---|---|",  # "held": not estimated, kept as calibrated
        *(f"| rotation of the right camera about its {ax} axis | {rot[ax]['value']:.5f} deg "
          f"| {_std(rot[ax]['std'], '.5f', 'deg')} |" for ax in "xyz"),
        f"| baseline | {b['percent']:+.4f} % ({b['mm']:+.4f} mm) | {_std(b['std_percent'], '.4f', '%')} "
        f"({_std(b['std_mm'], '.4f', 'mm')}) |",
        *(f"| baseline direction {n} | {d['value']:.5f} deg | {_std(d['std'], '.5f', 'deg')} |"
          for n, d in r["baseline_direction_deg"].items()),
        *(f"| focal length {side} | {f['percent']:+.4f} % ({f['px']:+.3f} px) | {f['std_percent']:.4f} % |"
          for side, f in r.get("focal", {}).items()),
        "",
        f"Baseline {b['before_mm']:.4f} mm -> {b['after_mm']:.4f} mm.",
        f"Residual RMS ({res['unit']}): {res['before']:.4g} before, {res['after']:.4g} after; {r['residuals']} "
        f"residuals, {r['dof']} degrees of freedom, {r['iterations']} iterations, "
        f"{'converged' if r['converged'] else 'NOT converged'}.",
        f"Conditioning: {r['conditioning']['message']}.",
    ]
    if r["poorly_determined"]:
        lines.append("**Not determined by this reference** (std > 0.1 deg or 0.5 %): "
                     f"{', '.join(r['poorly_determined'])}; hold them fixed (`--scale-only`) or add observations.")
    if "board_metric" in r["checks"]:
        m = r["checks"]["board_metric"]
        before, after = m["before"], m["after"]
        lines.append("Triangulated board, neighbour spacing vs square size: "
                     f"{before['spacing_error_mean_percent']:+.4f} % before, "
                     f"{after['spacing_error_mean_percent']:+.4f} % after (spread "
                     f"{after['spacing_error_std_percent']:.4f} %); planarity RMS {after['planarity_rms_mm']:.4f} mm.")
    if "sphere" in r["checks"]:
        s = r["checks"]["sphere"]
        lines.append(f"Sphere: {s['inliers']} of {s['matches']} matches used; free-fit diameter "
                     f"{s['free_fit_diameter_before_mm']:.3f} mm before, "
                     f"{s['free_fit_diameter_after_mm']:.3f} mm after (known {s['known_diameter_mm']:.3f} mm).")
    return "\n".join(lines) + "\n"
