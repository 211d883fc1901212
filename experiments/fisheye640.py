"""Fisheye model on the real fisheye640 camera (15 views, 9x6 board): dstereo vs OpenCV on the same corners.

- Full set: RMS of dstereo's fisheye (cv2.fisheye model, structured LM from the equidistant start), dstereo's
  5-coefficient default and rational pinhole models, and OpenCV's cv2.fisheye.calibrate / cv2.calibrateCamera
  (rational and 5-coefficient) with tight criteria; parameter agreement dstereo fisheye vs cv2.fisheye.
- Held-out views (leave one view out): the left-out view's pose solved with the fold's intrinsics fixed
  (OpenCV's solvePnP / fisheye.solvePnP + LM refinement), RMS over the held-out corners.
- A synthetic ~240-degree lens where cv2.fisheye.calibrate fails: dstereo against the truth.
- Subsets of 6 views (random sample): how often cv2.fisheye.calibrate fails (exception) with CALIB_CHECK_COND
  and without, and what dstereo does on those subsets (from scratch: equidistant start, no help from the
  full set).
- Inverse: dstereo's Newton undistortion of every detected corner (count of non-converged points).

`python -m experiments.fisheye640`; writes experiments/results/fisheye640.{md,json}. ~1 min on one core.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "fisheye640"
OUT = Path(__file__).resolve().parent / "results"
N_SUBSETS, PER_SET = 60, 6


def _corners():
    from dstereo.io.corners import detect_folder

    det = detect_folder(DATA, (9, 6), 1.0)
    used = [n for n in det.names if n in det.corners]
    return det.object_points, np.stack([det.corners[n] for n in used]), det.image_size, used


def _cv_fisheye(obj, obs, size, check_cond=False):
    import cv2

    flags = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW | (cv2.CALIB_CHECK_COND if check_cond else 0)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 1000, 1e-15)
    try:
        rms, k, d, _, _ = cv2.fisheye.calibrate([obj[None]] * len(obs), [o[None] for o in obs], size, None, None,
                                                flags=flags, criteria=crit)
    except cv2.error as exc:
        return {"ok": False, "error": " ".join(str(exc).split())[-160:]}
    return {"ok": True, "rms": float(rms), "k": [k[0, 0], k[1, 1], k[0, 2], k[1, 2]], "d": d.ravel().tolist()}


def _cv_pinhole(obj, obs, size, rational):
    import cv2

    flags = cv2.CALIB_RATIONAL_MODEL if rational else 0
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 1000, 1e-15)
    rms, k, d, _, _ = cv2.calibrateCamera([obj.astype(np.float32)] * len(obs), [o.astype(np.float32) for o in obs],
                                          size, None, None, flags=flags, criteria=crit)
    return {"ok": True, "rms": float(rms), "K": k, "d": d.ravel()}


def _pose_refine(project, obj, q, rvec, tvec):
    """Held-out view's pose with the intrinsics fixed: least squares in pixels from a PnP start."""
    from scipy.optimize import least_squares

    fit = least_squares(lambda x: (project(x[:3], x[3:]) - q).ravel(), np.concatenate([rvec.ravel(), tvec.ravel()]),
                        method="lm", xtol=1e-14, ftol=1e-14)
    return project(fit.x[:3], fit.x[3:])


def _held_out(obj, obs, size, kind):
    """Leave-one-view-out held-out RMS (px per corner) with OpenCV's calibrations (dstereo's equal them)."""
    import cv2

    errs = []
    for v in range(len(obs)):
        train = np.delete(obs, v, axis=0)
        if kind == "fisheye":
            fit = _cv_fisheye(obj, train, size)
            if not fit["ok"]:
                return None
            k, d = fit["k"], np.array(fit["d"])
            kmat = np.array([[k[0], 0, k[2]], [0, k[1], k[3]], [0, 0, 1.0]])
            # start: PnP on the undistorted normalised corners (a pinhole with K = I)
            und = cv2.fisheye.undistortPoints(obs[v][None], kmat, d)[0]
            _, rvec, tvec = cv2.solvePnP(obj, und, np.eye(3), np.zeros(5))
            project = lambda r, t: cv2.fisheye.projectPoints(obj[None], r, t, kmat, d)[0][0]  # noqa: E731
        else:
            fit = _cv_pinhole(obj, train, size, rational=kind == "rational")
            kmat, d = fit["K"], fit["d"]
            _, rvec, tvec = cv2.solvePnP(obj, obs[v], kmat, d)
            project = lambda r, t: cv2.projectPoints(obj, r, t, kmat, d)[0][:, 0]  # noqa: E731
        q = _pose_refine(project, obj, obs[v], rvec, tvec)
        errs.append(np.sum((q - obs[v]) ** 2, axis=1))
    return float(np.sqrt(np.mean(np.concatenate(errs))))


def _wide_synthetic(n_seeds: int = 10) -> dict:
    """A ~240-degree lens (f = 150 px, 640 px image), 14 boards up to ~80 degrees off axis, 0.05 px noise: how
    often cv2.fisheye.calibrate fails, and dstereo's error against the truth (in its own standard deviations)."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    import test_fisheye_calib as t  # the unit test's synthetic views (cv2.fisheye.projectPoints + noise)

    from dstereo.calib.mono import calibrate_full

    obj, k = t._board(), np.array([150.0, 150.0, 319.5, 319.5])
    rows = []
    for seed in range(n_seeds):
        obs = t._views(obj, seed=seed, k=k, theta_max=1.4)
        obs = obs + np.random.default_rng(5).normal(0, t.SIGMA / 2, obs.shape)
        cv = _cv_fisheye(obj, obs, t.SIZE)
        s = calibrate_full(obj, obs, t.SIZE, free=t.FISHEYE)
        rows.append({"seed": seed, "opencv_ok": cv["ok"], "opencv_error": cv.get("error", ""),
                     "dstereo_converged": bool(s.converged), "dstereo_rms": s.rms,
                     "focal_rel_err": float(np.max(np.abs(s.values[:2] / k[:2] - 1))),
                     "max_err_in_std": float(np.max(np.abs(s.values[:4] - k) / s.std[:4]))})
    return {"seeds": n_seeds, "opencv_failures": sum(not r["opencv_ok"] for r in rows),
            "dstereo_converged": sum(r["dstereo_converged"] for r in rows),
            "focal_rel_err_max": max(r["focal_rel_err"] for r in rows),
            "max_err_in_std": max(r["max_err_in_std"] for r in rows), "rows": rows}


def main() -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from dstereo.calib.mono import calibrate_full
    from dstereo.calib.subsets import plan_subsets
    from dstereo.models import fisheye
    from dstereo.models.distortion import PRESETS

    obj, obs, size, used = _corners()
    res: dict = {"views": len(used), "corners_per_view": int(obs.shape[1]), "image_size": list(size)}
    t0 = time.perf_counter()
    fe = calibrate_full(obj, obs, size, free=PRESETS["fisheye"])
    res["dstereo_fisheye"] = {"rms": fe.rms, "status": fe.status_text, "iterations": fe.iterations,
                              "solve_s": time.perf_counter() - t0, "values": dict(zip(fe.names, map(float, fe.values))),
                              "std": dict(zip(fe.names, map(float, fe.std))),
                              "identifiable": bool(fe.conditioning.identifiable)}
    for name in ("default", "rational"):
        s = calibrate_full(obj, obs, size, free=PRESETS[name])
        res[f"dstereo_{name}"] = {"rms": s.rms, "status": s.status_text}
    cvf = _cv_fisheye(obj, obs, size)
    res["opencv_fisheye"] = cvf
    res["opencv_fisheye_check_cond"] = _cv_fisheye(obj, obs, size, check_cond=True)
    res["opencv_rational"] = {"rms": _cv_pinhole(obj, obs, size, True)["rms"]}
    res["opencv_default"] = {"rms": _cv_pinhole(obj, obs, size, False)["rms"]}
    if cvf["ok"]:
        ref = np.array(cvf["k"] + cvf["d"])
        res["dstereo_vs_opencv_fisheye"] = {"max_rel_k": float(np.max(np.abs(fe.values[:4] / ref[:4] - 1))),
                                            "max_abs_d": float(np.max(np.abs(fe.values[4:] - ref[4:]))),
                                            "rms_rel": float(abs(fe.rms / cvf["rms"] - 1))}
    res["held_out_rms"] = {kind: _held_out(obj, obs, size, kind) for kind in ("fisheye", "rational", "default")}
    xy, n_bad = fisheye.undistort_points(jnp.asarray(fe.values[:4]), jnp.asarray(fe.values[4:]),
                                         jnp.asarray(obs.reshape(-1, 2)))
    res["undistort_non_converged"] = {"count": int(n_bad), "of": int(obs.shape[0] * obs.shape[1])}

    plan = plan_subsets(len(obs), PER_SET, cap=N_SUBSETS, seed=1)
    rows = []
    for idx in np.asarray(plan.index):
        sub = obs[idx]
        a, b = _cv_fisheye(obj, sub, size, check_cond=True), _cv_fisheye(obj, sub, size)
        row = {"views": [used[i] for i in idx], "opencv_check_cond": a, "opencv": b}
        if not (a["ok"] and b["ok"]):
            s = calibrate_full(obj, sub, size, free=PRESETS["fisheye"])
            row["dstereo"] = {"rms": s.rms, "converged": bool(s.converged), "status": s.status_text,
                              "identifiable": bool(s.conditioning.identifiable),
                              "weak": list(s.conditioning.weak_parameters),
                              "f": float(s.values[0]), "f_std": float(s.std[0])}
        rows.append(row)
    fails_cc = [r for r in rows if not r["opencv_check_cond"]["ok"]]
    fails = [r for r in rows if not r["opencv"]["ok"]]
    tried = [r for r in rows if "dstereo" in r]
    res["subsets"] = {
        "per_set": PER_SET, "count": len(rows),
        "opencv_check_cond_failures": len(fails_cc), "opencv_failures": len(fails),
        "opencv_messages": sorted({r["opencv_check_cond"].get("error", "")[-90:] for r in fails_cc}
                                  | {r["opencv"].get("error", "")[-90:] for r in fails}),
        "dstereo_on_failed": {"count": len(tried), "converged": sum(r["dstereo"]["converged"] for r in tried),
                              "identifiable": sum(r["dstereo"]["identifiable"] for r in tried),
                              "rms_max": max((r["dstereo"]["rms"] for r in tried), default=None),
                              "f_range": [min((r["dstereo"]["f"] for r in tried), default=None),
                                          max((r["dstereo"]["f"] for r in tried), default=None)]},
        "rows": rows,
    }
    res["wide_synthetic"] = _wide_synthetic()
    OUT.mkdir(exist_ok=True)
    (OUT / "fisheye640.json").write_text(json.dumps(res, indent=1, default=float))
    (OUT / "fisheye640.md").write_text(_markdown(res))
    return res


def _markdown(r: dict) -> str:
    f = lambda v: "fails" if v is None else f"{v:.4f}"  # noqa: E731
    cvf, cvc = r["opencv_fisheye"], r["opencv_fisheye_check_cond"]
    ho = r["held_out_rms"]
    sub = r["subsets"]
    lines = [
        "# Fisheye model on fisheye640 (15 views, 9x6 board, 640x640, dstereo's corners)", "",
        "| model | dstereo RMS (px) | OpenCV RMS (px) | held-out RMS (px, leave one view out, OpenCV fits) |",
        "|---|---|---|---|",
        f"| fisheye (Kannala-Brandt k1..k4) | {f(r['dstereo_fisheye']['rms'])} | "
        f"{f(cvf.get('rms'))} (CHECK_COND: {f(cvc.get('rms'))}) | {f(ho['fisheye'])} |",
        f"| rational (k1..k6, p1, p2) | {f(r['dstereo_rational']['rms'])} | {f(r['opencv_rational']['rms'])} | "
        f"{f(ho['rational'])} |",
        f"| 5-coefficient default | {f(r['dstereo_default']['rms'])} | {f(r['opencv_default']['rms'])} | "
        f"{f(ho['default'])} |", "",
        f"dstereo fisheye: {r['dstereo_fisheye']['status']}, {r['dstereo_fisheye']['iterations']} iterations, "
        f"identifiable: {r['dstereo_fisheye']['identifiable']}.",
    ]
    if "dstereo_vs_opencv_fisheye" in r:
        c = r["dstereo_vs_opencv_fisheye"]
        lines.append(f"dstereo vs cv2.fisheye.calibrate: K max relative difference {c['max_rel_k']:.2e}, "
                     f"D max absolute difference {c['max_abs_d']:.2e}, RMS relative {c['rms_rel']:.2e}.")
    u = r["undistort_non_converged"]
    lines += [f"Newton undistortion of all {u['of']} corners: {u['count']} did not converge.", "",
              f"## Subsets of {sub['per_set']} views ({sub['count']} random)", "",
              f"cv2.fisheye.calibrate failed on {sub['opencv_check_cond_failures']} with CALIB_CHECK_COND and on "
              f"{sub['opencv_failures']} without it. Messages: " + "; ".join(f"`{m}`" for m in sub["opencv_messages"] if m),
              "", f"dstereo on those {sub['dstereo_on_failed']['count']} subsets (from scratch): "
              f"{sub['dstereo_on_failed']['converged']} converged, {sub['dstereo_on_failed']['identifiable']} "
              f"identifiable, max RMS {f(sub['dstereo_on_failed']['rms_max'])} px, focal range "
              f"{sub['dstereo_on_failed']['f_range']}.", ""]
    w = r["wide_synthetic"]
    lines += ["## Synthetic 240-degree lens (f = 150 px on 640 px, boards to ~80 degrees, 0.05 px noise)", "",
              f"cv2.fisheye.calibrate failed on {w['opencv_failures']} of {w['seeds']} view sets ("
              + "; ".join(sorted({f"`{x['opencv_error'][-60:]}`" for x in w["rows"] if x["opencv_error"]})) + "); "
              f"dstereo converged on {w['dstereo_converged']}: focal error at most {100 * w['focal_rel_err_max']:.3f} %, "
              f"fx fy cx cy within {w['max_err_in_std']:.2f} of their standard deviations.", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    out = main()
    print((OUT / "fisheye640.md").read_text())
