"""Every estimate of the demo against its truth, with the bound it is held to (`settings.BOUNDS`)."""

from __future__ import annotations

import numpy as np

from dstereo.demo.report import number_text
from dstereo.demo.settings import BOUNDS, DISPARITY_NOISE_PX, DemoSettings


def rotation_error_deg(r_est: np.ndarray, r_true: np.ndarray) -> float:
    """Angle of R_est R_true^T, degrees (through the one rotation log: arccos of the trace loses half the digits
    at the small angles compared here)."""
    from dstereo.models.pose import rotation_vector

    return float(np.degrees(np.linalg.norm(rotation_vector(np.asarray(r_est) @ np.asarray(r_true).T))))


def _norm_sigma(v: np.ndarray, cov: np.ndarray) -> float:
    """Standard deviation of |v| for v with covariance `cov` (first order)."""
    grad = v / np.linalg.norm(v)
    return float(np.sqrt(grad @ cov @ grad))


def surface_bound(s, cov: np.ndarray, settings: DemoSettings, slope: float) -> dict:
    """Surface RMS bounds (mm). Matching alone (the true calibration, or the shape after a rigid fit) is held
    to the depth noise of DISPARITY_NOISE_PX at the sample, Z^2 / (f B) sigma_d. The joint calibration adds, in
    quadrature, what 3 sigma of it can do: a depth scale error (left focal length, baseline), Z sigma_scale,
    and a turn of the whole cloud with the left camera's pointing (principal point / f), which slides the
    domed face sideways by Z sigma_pointing and shows as depth error `slope` (RMS over the face) times that."""
    z, f, b = settings.distance_mm, settings.focal_px, settings.baseline_mm
    matching = z * z / (f * b) * DISPARITY_NOISE_PX
    std = dict(zip(s.names, np.sqrt(np.diag(cov))))
    k = BOUNDS["sigmas"]
    scale = k * z * np.hypot(std["left.fx"] / float(s.left.k[0]), _norm_sigma(s.T, cov[3:6, 3:6]) / s.baseline)
    pointing = k * z * slope * np.hypot(std["left.cx"], std["left.cy"]) / float(s.left.k[0])
    return {"matching_mm": matching, "scale_mm": float(scale), "pointing_mm": float(pointing),
            "joint_mm": float(np.linalg.norm([matching, scale, pointing]))}


def _row(parameter: str, unit: str, truth, joint, error, bound, sigma=None, thesis=None, thesis_error=None,
         error_unit: str | None = None) -> dict:
    return {"parameter": parameter, "unit": unit, "error_unit": error_unit or unit, "truth": truth,
            "thesis": thesis, "thesis_error": thesis_error, "estimate": joint, "error": error, "sigma": sigma,
            "bound": bound, "ok": bool(np.isfinite(error) and abs(error) <= bound)}


def compare(rig, job, s, cov: np.ndarray, surface: dict, settings: DemoSettings) -> dict:
    """One row per parameter: truth, the thesis's path (estimate, error), the joint refinement (estimate, error,
    sigma), the bound and whether the joint error is within it; then the subset and surface summaries. Rotation:
    truth and estimates are rotation angles, errors the angle of R_est R_true^T. Focal lengths and the baseline
    have errors in %, and their sigma too."""
    k_sig = BOUNDS["sigmas"]
    std = dict(zip(s.names, np.sqrt(np.diag(cov))))
    rows = []
    thesis_R, thesis_T = thesis_rig(job)
    for side, true_cam, thesis_cal, cam in (("left", rig.left, job.cameras[0], s.left),
                                            ("right", rig.right, job.cameras[1], s.right)):
        kt, ke = (np.asarray(c.k, float) for c in (true_cam, cam))
        kh = np.array([thesis_cal.final[n] for n in ("fx", "fy", "cx", "cy")])
        for j, name in enumerate(("fx", "fy", "cx", "cy")):
            sig = std[f"{side}.{name}"]
            if j < 2:
                pct = lambda v: 100 * (v / kt[j] - 1)  # noqa: E731
                rows.append(_row(f"{side} {name}", "px", kt[j], ke[j], pct(ke[j]), BOUNDS["focal_percent"],
                                 100 * sig / kt[j], kh[j], pct(kh[j]), "%"))
            else:
                rows.append(_row(f"{side} {name}", "px", kt[j], ke[j], ke[j] - kt[j],
                                 max(BOUNDS["principal_px"], k_sig * sig), sig, kh[j], kh[j] - kt[j]))
    r_true, t_true = rig.rotation_translation()
    b_true, b_thesis = float(np.linalg.norm(t_true)), thesis_T
    rows.append(_row("baseline |T|", "mm", b_true, s.baseline, 100 * (s.baseline / b_true - 1),
                     BOUNDS["baseline_percent"], 100 * _norm_sigma(s.T, cov[3:6, 3:6]) / s.baseline, b_thesis,
                     100 * (b_thesis / b_true - 1), "%"))
    rot_sigma = float(np.degrees(np.sqrt(np.trace(cov[0:3, 0:3]))))
    from dstereo.models.pose import rotation_vector

    angle = lambda r: float(np.degrees(np.linalg.norm(rotation_vector(r))))  # noqa: E731
    rows.append(_row("rotation R", "deg", angle(r_true), angle(s.R), rotation_error_deg(s.R, r_true),
                     max(BOUNDS["rotation_deg"], k_sig * rot_sigma), rot_sigma, angle(thesis_R),
                     rotation_error_deg(thesis_R, r_true)))
    bound = surface_bound(s, cov, settings, surface["rms_slope"])
    joint, thesis, ref = surface["joint"], surface["thesis"], surface["true_calibration"]
    rows.append(_row("surface RMS", "mm", 0.0, joint["rms_mm"], joint["rms_mm"], bound["joint_mm"],
                     thesis=thesis["rms_mm"], thesis_error=thesis["rms_mm"]))
    rows.append(_row("surface RMS, rigid fit", "mm", 0.0, joint["shape_rms_mm"], joint["shape_rms_mm"],
                     bound["matching_mm"], thesis=thesis["shape_rms_mm"], thesis_error=thesis["shape_rms_mm"]))
    rows.append(_row("surface RMS, true calibration", "mm", 0.0, ref["rms_mm"], ref["rms_mm"], bound["matching_mm"]))
    sub = job.subsets
    f, stats = sub.filtering, sub.stats()
    subsets = {
        "plan": sub.plan.describe(), "per_set": int(sub.plan.per_set), "solved": int(len(f.table)),
        "converged": int(f.usable.sum()), "survivors": int(f.survivors.sum()),
        "steps": [o.message for o in f.steps],
        "after_steps": {c: {"mean": stats[c + PAIR]["mean"], "std": stats[c + PAIR]["std"]}
                        for c in ("stereo_re", "Tnorm", "RVnorm")},
        "individual": {side: {"plan": c.plan.describe(), "rms_px": float(c.full.rms)}
                       for side, c in zip(job.labels, job.cameras)},
    }
    both = np.asarray(job.visible, bool).all(axis=1)
    warnings = [f"{r['parameter']}: error {number_text(r['error'])} {r['error_unit']} exceeds the bound "
                f"{number_text(r['bound'])} {r['error_unit']}" for r in rows if not r["ok"]]
    return {"rows": rows, "ok": not warnings, "warnings": warnings, "calibration_warnings": list(job.warnings),
            "subsets": subsets, "surface": surface, "surface_bound": bound, "bounds": BOUNDS,
            "disparity_noise_px": DISPARITY_NOISE_PX,
            "stereo": {"pairs": int(both.sum()), "dropped": int((~both).sum()),
                       "thesis_rms_px": float(job.held.rms), "joint_rms_px": s.rms, "joint_status": s.solution.status_text}}


PAIR = "@left-right"  # the stereo job's one pair in the rig subsets' column names (calib/rig_subsets.py)


def thesis_rig(job) -> tuple[np.ndarray, float]:
    """(R, |T|) of the thesis's answer: the means over the surviving rig subsets (intrinsics held at each camera's
    own calibration) of the rotation vector and of the baseline."""
    from dstereo.models.pose import rodrigues

    stats = job.subsets.stats()
    rvec = np.array([stats[f"RV{a}{PAIR}"]["mean"] for a in "xyz"])
    return np.asarray(rodrigues(rvec)), float(stats["Tnorm" + PAIR]["mean"])
