"""Stereo rigs with fisheye cameras, end to end on renders with known truth (issue 16, item 1).

Two rigs (`dstereo.synth.fisheye_rig`): two cv2.fisheye lenses (~128 degrees across 640 px), and a mixed rig of a
pinhole left (75 degrees) and the same fisheye right; 120 mm baseline, converging by 4.6 degrees.
1. Rectification against OpenCV: dstereo's R1 R2 P1 P2 Q against cv2.fisheye.stereoRectify (balance 0, 0.5, 1),
   the maps against cv2.fisheye.initUndistortRectifyMap where both are defined; the field of view kept.
2. Calibration: N_VIEWS board views rendered in both cameras, written as image folders, calibrated by the CLI
   (`dstereo calibrate --left --right --model fisheye`, the mixed rig with `--model default --model-right
   fisheye`); each camera's fx, fy, cx, cy against the truth (relative error of the focal lengths; principal
   point in units of its reported sigma), the baseline and rotation against the truth. The fisheye pair's images
   also go through `dstereo calibrate --cameras DIR --model fisheye` (its stereo file against the truth).
3. Reconstruction: a speckled plane, tilted 20 degrees, 450 mm in front of the rig, rendered in both cameras and
   reconstructed by the CLI (`dstereo reconstruct --calib stereo.yml`) with the calibrated file and with the true
   one. Against the rendered truth: the rectified left pixels whose source pixel shows the plane; surface RMS =
   RMS distance of their points to the true plane (mm), the robust spread (1.4826 MAD), the share of gross errors
   (> 10 mm), the share of those pixels that got a point, and how many points fell off the plane (background).

`python -m experiments.fisheye_rig`; writes experiments/results/fisheye_rig.{md,json}. Several minutes on one core
(rendering 2 x 2 x N_VIEWS board views dominates).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent / "results"
ROOT = Path(__file__).resolve().parents[1]
N_VIEWS = 20
SQUARE_MM = 25.0
PLANE_DISTANCE_MM, PLANE_TILT_DEG = 450.0, 20.0


def _cli(*args) -> None:
    cmd = [sys.executable, "-m", "dstereo.cli", *map(str, args)]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)}: {done.stderr.strip()}")


def rectification_vs_opencv(rig) -> dict:
    import cv2

    from dstereo.models.stereo_calibration import StereoCalibration
    from dstereo.stereo.rectify_fisheye import field_of_view, rectification_maps, rectify_any

    left, right = rig.left, rig.right
    R, T = rig.rotation_translation()
    calib = StereoCalibration(left.matrix(), left.coeffs(), right.matrix(), right.coeffs(), R, T, left.image_size,
                              models=(left.lens, right.lens))
    out = {}
    for balance in (0.0, 0.5, 1.0):
        rect = rectify_any(calib, alpha=balance, zero_disparity=True)
        ref = cv2.fisheye.stereoRectify(left.matrix(), left.coeffs()[:4], right.matrix(), right.coeffs()[:4],
                                        left.image_size, R, T.reshape(3, 1), cv2.CALIB_ZERO_DISPARITY,
                                        balance=balance, fov_scale=1.0)
        rel = {n: float(np.abs(np.asarray(a) - b).max() / np.abs(b).max())
               for n, a, b in zip(("R1", "R2", "P1", "P2", "Q"), (rect.R1, rect.R2, rect.P1, rect.P2, rect.Q), ref)}
        maps = rectification_maps(calib, rect)
        diff, share = 0.0, []
        for (mx, my), cam, Rk, P in zip(maps, (left, right), (rect.R1, rect.R2), (rect.P1, rect.P2)):
            rx, ry = cv2.fisheye.initUndistortRectifyMap(cam.matrix(), cam.coeffs()[:4], np.asarray(Rk),
                                                         np.asarray(P), rect.size, cv2.CV_32FC1)
            both = np.isfinite(mx) & np.isfinite(rx)
            diff = max(diff, float(np.abs(mx - rx)[both].max()), float(np.abs(my - ry)[both].max()))
            share.append(float(both.mean()))
        out[f"balance {balance:g}"] = {"relative_difference": rel, "map_max_difference_px": diff,
                                       "map_share_both_defined": share, "field_of_view": field_of_view(rect)}
    return out


def _write_calibration_folders(rig, folder: Path, seed: int) -> dict:
    from dstereo.synth import calibration_set
    from dstereo.synth.writers import write_calibration_set

    cset = calibration_set(rig.left, rig.right, rig.T_right_left, pattern=(9, 6), square=SQUARE_MM,
                           n_views=N_VIEWS, seed=seed)
    write_calibration_set(folder, cset)
    return cset.truth


def calibrate(rig, work: Path, mixed: bool, seed: int) -> tuple[Path, dict, float]:
    t0 = time.perf_counter()
    _write_calibration_folders(rig, work / "boards", seed)
    render_s = time.perf_counter() - t0
    models = ["--model", "default", "--model-right", "fisheye"] if mixed else ["--model", "fisheye"]
    t0 = time.perf_counter()
    _cli("calibrate", "--left", work / "boards" / "images_left", "--right", work / "boards" / "images_right",
         "--pattern", "9x6", "--square", SQUARE_MM, *models, "--out", work / "calib", "--quiet")
    calib_s = time.perf_counter() - t0
    from dstereo.io.calib_files import read_stereo_calibration

    calib = read_stereo_calibration(work / "calib" / "stereo.yml")
    summary = json.loads((work / "calib" / "stereo.json").read_text())
    rows = {}
    for side, cam, K in (("left", rig.left, calib.K1), ("right", rig.right, calib.K2)):
        std = json.loads((work / "calib" / side / "summary.json").read_text())["full_set"]["std"]
        truth = np.asarray(cam.k)
        got = StereoK(K)
        rows[side] = {
            "lens": cam.lens,
            "fx_rel_error": float(got[0] / truth[0] - 1), "fy_rel_error": float(got[1] / truth[1] - 1),
            "cx_error_px": float(got[2] - truth[2]), "cy_error_px": float(got[3] - truth[3]),
            "cx_sigma_px": float(std["cx"]), "cy_sigma_px": float(std["cy"]),
            "cx_in_sigmas": float((got[2] - truth[2]) / std["cx"]),
            "cy_in_sigmas": float((got[3] - truth[3]) / std["cy"]),
            "rms_px": float(summary["individual"][side]["rms"]),
        }
    R_true, T_true = rig.rotation_translation()
    dR = calib.R @ R_true.T
    pairs = [line.split(",") for line in (work / "calib" / "stereo_pairs.csv").read_text().splitlines()[1:]]
    worst = max(pairs, key=lambda p: float(p[2]))
    rejected = [w for w in summary["warnings"] if "rejected whole" in w]
    rows["pairs"] = {"count": len(pairs), "median_rms_px": float(np.median([float(p[2]) for p in pairs])),
                     "worst": f"{worst[0]} / {worst[1]}", "worst_rms_px": float(worst[2]),
                     "views_rejected_whole": rejected}
    rows["rig"] = {"baseline_error_mm": float(np.linalg.norm(calib.T) - np.linalg.norm(T_true)),
                   "T_error_mm": float(np.linalg.norm(calib.T - T_true)),
                   "rotation_error_deg": float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))),
                   "stereo_rms_px": float(summary["full_set"]["rms"]), "models": list(calib.models),
                   "render_s": render_s, "calibrate_s": calib_s}
    return work / "calib" / "stereo.yml", rows, render_s


def calibrate_cameras(rig, work: Path) -> dict:
    """The same board images as a `--cameras` folder (cam_a = left, cam_b = right, frames named alike):
    `dstereo calibrate --cameras DIR --model fisheye` writes stereo_cam_a_cam_b.yml; its cameras and rig against
    the truth."""
    from dstereo.io.calib_files import read_stereo_calibration

    cams = work / "cameras"
    for label, side in (("cam_a", "left"), ("cam_b", "right")):
        (cams / label).mkdir(parents=True)
        for image in sorted((work / "boards" / f"images_{side}").glob("*.png")):
            (cams / label / image.name.split("_", 1)[1]).symlink_to(image)
    t0 = time.perf_counter()
    _cli("calibrate", "--cameras", cams, "--pattern", "9x6", "--square", SQUARE_MM, "--model", "fisheye", "--out",
         work / "cameras_out", "--quiet")
    seconds = time.perf_counter() - t0
    calib = read_stereo_calibration(work / "cameras_out" / "stereo_cam_a_cam_b.yml")
    R_true, T_true = rig.rotation_translation()
    dR = calib.R @ R_true.T
    return {"file": "stereo_cam_a_cam_b.yml", "models": list(calib.models),
            "fx_rel_error": [float(K[0, 0] / c.k[0] - 1) for K, c in ((calib.K1, rig.left), (calib.K2, rig.right))],
            "T_error_mm": float(np.linalg.norm(calib.T - T_true)),
            "rotation_error_deg": float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))),
            "calibrate_s": seconds}


def StereoK(K) -> np.ndarray:
    return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])


def plane_pose() -> np.ndarray:
    from scipy.spatial.transform import Rotation

    from dstereo.models.pose import rotation_vector

    rmat = Rotation.from_euler("y", PLANE_TILT_DEG, degrees=True).as_matrix()
    return np.concatenate([rotation_vector(rmat), [0.0, 0.0, PLANE_DISTANCE_MM]])


def render_plane(rig, folder: Path, seed: int) -> np.ndarray:
    """Writes left.png / right.png of the plane; returns the plane's rendered-pixel mask in the left image."""
    import cv2

    from dstereo.synth import Plane, object_pair

    pair = object_pair(rig, Plane(260.0, 200.0), plane_pose(), seed=seed, speckle_mm=4.0)
    folder.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(folder / "left.png"), pair.left)
    cv2.imwrite(str(folder / "right.png"), pair.right)
    return np.isfinite(pair.truth_left["depth"])


def write_true_calibration(rig, path: Path) -> Path:
    from dstereo.io.calib_files import write_opencv_stereo
    from dstereo.models.stereo_calibration import StereoCalibration

    R, T = rig.rotation_translation()
    write_opencv_stereo(path, StereoCalibration(rig.left.matrix(), rig.left.coeffs(), rig.right.matrix(),
                                                rig.right.coeffs(), R, T, rig.left.image_size,
                                                models=(rig.left.lens, rig.right.lens)))
    return path


def plane_mask_rectified(calib_path: Path, mask: np.ndarray) -> np.ndarray:
    """The plane's rendered pixels (left image) carried onto the rectified left grid of `calib_path`'s
    rectification: a rectified pixel is on the plane when its source pixel (nearest) is."""
    from dstereo.io.calib_files import read_stereo_calibration
    from dstereo.stereo.rectify_fisheye import rectification_maps, rectify_any

    calib = read_stereo_calibration(calib_path)
    mx, my = rectification_maps(calib, rectify_any(calib, zero_disparity=False))[0]  # reconstruct's defaults
    h, w = mask.shape
    ok = np.isfinite(mx) & np.isfinite(my) & (mx > -0.5) & (my > -0.5) & (mx < w - 0.5) & (my < h - 0.5)
    u, v = (np.clip(np.rint(np.nan_to_num(m)), 0, n - 1).astype(int) for m, n in ((mx, w), (my, h)))
    return ok & mask[v, u]


def plane_errors(points: np.ndarray, on_plane: np.ndarray) -> dict:
    """Distances (mm) of the points on the plane's rectified pixels to the true plane: RMS, robust spread,
    gross errors (> 10 mm), and the share of those pixels that got a point."""
    from dstereo.models.pose import rotation_matrix

    pose = plane_pose()
    n = np.asarray(rotation_matrix(pose[:3]))[:, 2]
    e = (points - pose[3:]) @ n
    got = on_plane & np.isfinite(e)
    e = e[got]
    return {"surface_rms_mm": float(np.sqrt(np.mean(e ** 2))), "median_mm": float(np.median(e)),
            "robust_std_mm": float(1.4826 * np.median(np.abs(e - np.median(e)))),
            "gross_share": float(np.mean(np.abs(e) > 10.0)), "points": int(got.sum()),
            "coverage": float(got.sum() / max(on_plane.sum(), 1)),
            "points_off_the_plane": int((np.isfinite(points).all(axis=2) & ~on_plane).sum())}


def reconstruct(calib_path: Path, images: Path, out: Path, mask: np.ndarray) -> dict:
    t0 = time.perf_counter()
    _cli("reconstruct", "--calib", calib_path, "--left", images / "left.png", "--right", images / "right.png",
         "--out", out, "--z-min", 250, "--z-max", 900)
    seconds = time.perf_counter() - t0
    errors = plane_errors(np.load(out / "points.npy"), plane_mask_rectified(calib_path, mask))
    summary = json.loads((out / "summary.json").read_text())
    return {**errors, "reconstruct_s": seconds, "warnings": summary.get("warnings", [])}


def main() -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    from dstereo.synth import fisheye_rig

    import os

    results = {"views": N_VIEWS, "square_mm": SQUARE_MM, "load_average_start": os.getloadavg()[0]}
    with tempfile.TemporaryDirectory(prefix="fisheye_rig_") as tmp:
        for name, mixed in (("fisheye pair", False), ("pinhole + fisheye", True)):
            rig = fisheye_rig(mixed=mixed)
            work = Path(tmp) / name.replace(" ", "_").replace("+", "")
            entry = {"rectification_vs_opencv": rectification_vs_opencv(rig) if not mixed else None}
            calib_path, entry["calibration"], _ = calibrate(rig, work, mixed, seed=1)
            entry["cameras_run"] = None if mixed else calibrate_cameras(rig, work)
            mask = render_plane(rig, work / "plane", seed=2)
            entry["plane_pixels"] = int(mask.sum())
            entry["reconstruction_calibrated"] = reconstruct(calib_path, work / "plane", work / "rec_calibrated", mask)
            true_path = write_true_calibration(rig, work / "true_stereo.yml")
            entry["reconstruction_true_calibration"] = reconstruct(true_path, work / "plane", work / "rec_true", mask)
            results[name] = entry
    results["load_average_end"] = os.getloadavg()[0]
    OUT.mkdir(exist_ok=True)
    (OUT / "fisheye_rig.json").write_text(json.dumps(results, indent=1))
    (OUT / "fisheye_rig.md").write_text(report(results))
    return results


def _pairs_line(p: dict) -> str:
    line = (f"Pairs: {p['count']}, median pair RMS {p['median_rms_px']:.4f} px, worst {p['worst']} "
            f"{p['worst_rms_px']:.3f} px. Views the cameras' outlier rejection dropped whole: "
            f"{len(p['views_rejected_whole'])}.")
    names = p["worst"].split(" / ")
    if all(any(f"view {n} rejected whole" in w for w in p["views_rejected_whole"]) for n in names):
        line += (" Both views of the worst pair are those: a pair whose views were both dropped stays in the rig "
                 "solve with all its corners (calib/stereo.py `_pair_mask`: a pair without inlier corners keeps them "
                 "all), which lifts the stereo RMS above the median pair's.")
    return line


def report(r: dict) -> str:
    lines = ["# Stereo rigs with fisheye cameras (experiments/fisheye_rig.py)", "",
             f"Renders with known truth: {r['views']} board views (9x6, {r['square_mm']:g} mm squares), 640 x 480 px; "
             f"a speckled plane tilted {PLANE_TILT_DEG:g} deg at {PLANE_DISTANCE_MM:g} mm. Rigs: "
             "`dstereo.synth.fisheye_rig` (two cv2.fisheye lenses, ~128 deg across; or a 75 deg pinhole left).", "",
             "Timings (render, calibrate, reconstruct s) were taken on a shared 2-core machine under load: "
             + (f"load average {r['load_average_start']:.1f} at the start, {r['load_average_end']:.1f} at the end."
                if "load_average_start" in r else "load average 9-22 during this run (`uptime`)."), ""]
    rect = r["fisheye pair"]["rectification_vs_opencv"]
    lines += ["## Rectification vs cv2.fisheye.stereoRectify / initUndistortRectifyMap (fisheye pair)", "",
              "| balance | R1 | R2 | P1 | P2 | Q | maps max diff (px) | both defined | field kept (h x v deg) |",
              "|---|---|---|---|---|---|---|---|---|"]
    for k, v in rect.items():
        d, fov = v["relative_difference"], v["field_of_view"]
        lines.append(f"| {k.split()[1]} | {d['R1']:.1e} | {d['R2']:.1e} | {d['P1']:.1e} | {d['P2']:.1e} | "
                     f"{d['Q']:.1e} | {v['map_max_difference_px']:.1e} | "
                     f"{min(v['map_share_both_defined']):.3f} | "
                     f"{fov['horizontal_deg']:.1f} x {fov['vertical_deg']:.1f} |")
    lines += ["", "Relative differences: max |ours - cv2| / max |cv2|. The maps differ by cv2's float32 output "
              "(half a float32 step at 640 px is 3e-5 px).", ""]
    for name in ("fisheye pair", "pinhole + fisheye"):
        e = r[name]
        lines += [f"## {name}", "", "| camera | lens | fx rel. error | fy rel. error | cx error (sigmas) | "
                  "cy error (sigmas) | RMS (px) |", "|---|---|---|---|---|---|---|"]
        for side in ("left", "right"):
            c = e["calibration"][side]
            lines.append(f"| {side} | {c['lens']} | {c['fx_rel_error']:+.2e} | {c['fy_rel_error']:+.2e} | "
                         f"{c['cx_error_px']:+.4f} px ({c['cx_in_sigmas']:+.2f}) | {c['cy_error_px']:+.4f} px "
                         f"({c['cy_in_sigmas']:+.2f}) | {c['rms_px']:.4f} |")
        if e.get("cameras_run"):
            m = e["cameras_run"]
            lines += ["", f"`--cameras` on the same images (`--model fisheye`): {m['file']} with models {m['models']}, "
                      f"fx errors {m['fx_rel_error'][0]:+.2e} / {m['fx_rel_error'][1]:+.2e}, T error "
                      f"{m['T_error_mm']:.4f} mm, rotation error {m['rotation_error_deg']:.4f} deg "
                      f"({m['calibrate_s']:.0f} s)."]
        g = e["calibration"]["rig"]
        lines += ["", f"Rig: |T| error {g['baseline_error_mm']:+.4f} mm, T error {g['T_error_mm']:.4f} mm, rotation "
                  f"error {g['rotation_error_deg']:.4f} deg, stereo RMS {g['stereo_rms_px']:.4f} px; stereo.yml "
                  f"models {g['models']}. Render {g['render_s']:.0f} s, calibrate {g['calibrate_s']:.0f} s.", "",
                  _pairs_line(e["calibration"]["pairs"]), "",
                  f"Plane: {e['plane_pixels']} rendered pixels in the left image.", "",
                  "| calibration | surface RMS (mm) | median (mm) | robust std (mm) | > 10 mm | points | coverage | "
                  "points off the plane |", "|---|---|---|---|---|---|---|---|"]
        for key, label in (("reconstruction_calibrated", "calibrated stereo.yml"),
                           ("reconstruction_true_calibration", "true calibration")):
            rec = e[key]
            lines.append(f"| {label} | {rec['surface_rms_mm']:.3f} | {rec['median_mm']:+.3f} | "
                         f"{rec['robust_std_mm']:.3f} | {100 * rec['gross_share']:.2f} % | {rec['points']} | "
                         f"{100 * rec['coverage']:.1f} % | {rec['points_off_the_plane']} |")
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
    print((OUT / "fisheye_rig.md").read_text())
