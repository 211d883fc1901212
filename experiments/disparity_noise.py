"""Per-pixel disparity noise (`dstereo.stereo.disparity_noise`) against the truth and against real boards.

1. Renders (`dstereo.synth`, the true calibration, known read noise): a tilted plane whose left half carries a
   speckle of full contrast and whose right half the same speckle at low contrast (`contrast_pair`). For each
   texture region: the robust std (1.4826 MAD) of the depth error about the true plane against the RMS of the
   predicted random sigma_z on the same pixels, with and without --refine, at two noise levels; and the model
   BEFORE the plane check's scaling (what the physics alone predicts) as well as after.
2. Real boards (`../shared/data/opencv_stereo`, `rig640`, calibrated by `dstereo calibrate` into
   CALIB_DIR/<set>/stereo.yml, square 25 mm assumed: ratios are scale-free): each pair reconstructed with the
   depth range of its board (from the corners and the calibration), the board's region from its detected
   corners (the convex hull shrunk by a square), a plane fitted to its points (robust, twice trimmed at 4 sigma);
   observed robust scatter of the distances along z vs the predicted random sigma_z (RMS) on the same pixels.

3. Middlebury 2014 (quarter size, `middlebury_rows`): the error against the ground-truth disparity.

Run: .venv/bin/python experiments/disparity_noise.py [--renders] [--real] [--middlebury] [--calib-dir DIR]
(calibrate first: dstereo calibrate --left 'DATA/SET/left*.jpg' --right 'DATA/SET/right*.jpg' --pattern 9x6
--square 25 --out DIR/opencv (and DIR/rig640); no flag: all parts; --table: only rewrite the .md)
Writes experiments/results/disparity_noise.md (and .json).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
OUT = ROOT / "experiments" / "results"
MAD = 1.4826


def robust_std(x: np.ndarray) -> float:
    return float(MAD * np.median(np.abs(x - np.median(x))))


# --- renders ------------------------------------------------------------------------------------------------


def contrast_pair(noise_dn: float, size=(320, 240), low_contrast: float = 0.3, seed: int = 0):
    """(left, right uint8, true StereoCalibration, plane (n, c) in the left frame: n . x = c, (object origin,
    object x axis) in the left frame: the low-contrast half is object x > 0)."""
    import jax.numpy as jnp

    from dstereo.io.calib_files import StereoCalibration
    from dstereo.synth import Plane, RenderOptions, Speckle, camera_rays, compose
    from dstereo.synth.poses import pose_matrix
    from dstereo.synth.reference_scenes import reference_rig
    from dstereo.synth.render import object_images
    from dstereo.synth.sensor import expose

    rig = reference_rig(image_size=size, focal_px=400.0, baseline_mm=100.0, distance_mm=400.0)
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_euler("xy", [10.0, 25.0], degrees=True)
    T_world_obj = np.r_[rot.as_rotvec(), 0.0, 0.0, 400.0]
    options = RenderOptions(supersample=2, defocus_sigma_px=0.5, read_noise_dn=noise_dn)
    hi, lo = Speckle.create(seed, 2.5, contrast=2.0), Speckle.create(seed, 2.5, contrast=2.0 * low_contrast)
    surface = Plane(300.0, 300.0)
    images = []
    t_left = compose(rig.T_left_world, T_world_obj)
    for c, (cam, pose) in enumerate(((rig.left, t_left), (rig.right, compose(rig.T_right_left, t_left)))):
        rays, centre = camera_rays(cam, 2), camera_rays(cam, 1)
        light = np.array([0.3, -0.4, 1.0]) / np.linalg.norm([0.3, -0.4, 1.0])
        rad = [np.asarray(object_images(rays, centre, jnp.asarray(pose), surface, tex, jnp.asarray(light), 0.25,
                                        0.04)[0]) for tex in (hi, lo)]
        _, depth, _ = object_images(rays, centre, jnp.asarray(pose), surface, hi, jnp.asarray(light), 0.25, 0.04)
        xy = np.asarray(centre)[:, :, 0, :]
        p_cam = np.concatenate([xy, np.ones(xy.shape[:2] + (1,))], axis=2) * np.asarray(depth)[..., None]
        m = pose_matrix(pose)
        x_obj = (p_cam - m[:3, 3]) @ m[:3, :3]  # R^T (p - t)
        low = x_obj[..., 0] > 0
        radiance = np.where(low, rad[1], rad[0])
        images.append(expose(radiance, np.asarray(cam.k[2:4]), options, np.random.default_rng([seed, c, 7])))
    r, t = rig.rotation_translation()
    calib = StereoCalibration(rig.left.matrix(), rig.left.coeffs(), rig.right.matrix(), rig.right.coeffs(), r, t,
                              tuple(rig.left.image_size), source="truth")
    m = pose_matrix(t_left)
    n = m[:3, 2]
    return images[0], images[1], calib, (n, float(n @ m[:3, 3])), (m[:3, 3], m[:3, 0])


def render_rows(noise_levels=(1.0, 3.0)) -> list[dict]:
    from dstereo.stereo.reconstruct import ReconstructionConfig, reconstruct_calibrated

    rows = []
    for noise in noise_levels:
        left, right, calib, (n, c), (origin, x_axis) = contrast_pair(noise)
        for refine in (False, True):
            t0 = time.perf_counter()
            res = reconstruct_calibrated(calib, left, right, ReconstructionConfig(depth_range=(250.0, 600.0),
                                                                                  refine=refine), "render")
            p = res.points
            valid = np.all(np.isfinite(p), axis=2)
            # error along the ray to the true plane, in z
            scale = c / (p @ n)
            dz = p[..., 2] - p[..., 2] * scale
            # the low-contrast half in the rectified grid: where the left pixel's point has object x > 0 is the
            # same test as in the render; here by the points themselves (truth plane coordinates)
            info = res.summary["disparity_noise"]
            pred = res.uncertainty.sigma_z_disparity / info["scaled_by"]  # the model before the check's scaling
            x_obj = (p - origin) @ x_axis  # object-frame x: > 0 on the low-contrast half (contrast_pair)
            for region in ("speckle", "low contrast"):
                mask = valid & ((x_obj > 10.0) if region == "low contrast" else (x_obj < -10.0))  # off the border
                err, sp = dz[mask], pred[mask]
                keep = np.abs(err - np.median(err)) < 6 * robust_std(err)
                rows.append({"noise_dn": noise, "refine": refine, "region": region, "pixels": int(mask.sum()),
                             "observed_mm": robust_std(err[keep]), "bias_mm": float(np.median(err)),
                             "predicted_mm": float(np.sqrt(np.mean(sp[keep] ** 2))),
                             "ratio_model": robust_std(err[keep]) / float(np.sqrt(np.mean(sp[keep] ** 2))),
                             "check_ratio": info["plane_check"].get("ratio"), "scaled_by": info["scaled_by"],
                             "check_p25_p75": info["plane_check"].get("ratio_p25_p75"),
                             "sigma_d_median_px": info["sigma_d_px"]["median"],
                             "image_noise_dn": info["image_noise_dn"][0]["sigma"],
                             "seconds": time.perf_counter() - t0})
                print(rows[-1], flush=True)
    return rows


# --- real boards --------------------------------------------------------------------------------------------


def board_rows(calib_dir: Path, sets=("opencv_stereo", "rig640"), pairs_per_set: int = 4, square: float = 25.0):
    import cv2
    from matplotlib.path import Path as Polygon

    from dstereo.io.calib_files import read_stereo_calibration
    from dstereo.stereo.reconstruct import ReconstructionConfig, reconstruct_calibrated
    from dstereo.io.images import read_image

    rows = []
    for name, cal in zip(sets, ("opencv", "rig640")):
        calib = read_stereo_calibration(calib_dir / cal / "stereo.yml")
        lefts = sorted((DATA / name).glob("left*.jpg"))
        done = 0
        for lp in lefts:
            if done >= pairs_per_set:
                break
            rp = lp.with_name(lp.name.replace("left", "right"))
            left, right = read_image(lp), read_image(rp)
            grey = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY)
            found, corners = cv2.findChessboardCorners(grey, (9, 6))
            if not found:
                continue
            obj = np.zeros((54, 3))
            obj[:, :2] = np.mgrid[0:9, 0:6].T.reshape(-1, 2) * square
            ok, rvec, tvec = cv2.solvePnP(obj, corners, calib.K1, np.ravel(calib.D1)[:8])
            z = (cv2.Rodrigues(rvec)[0] @ obj.T + tvec).T[:, 2]
            config = ReconstructionConfig(depth_range=(0.8 * z.min(), 1.2 * z.max()))
            for refine in (False, True):
                res = reconstruct_calibrated(calib, left, right, replace(config, refine=refine), lp.stem)
                # the board's region on the rectified left grid: corners through the rectification
                R1, P1 = res.matrices["R1"], res.matrices["P1"]
                rc = cv2.undistortPoints(corners, calib.K1, np.ravel(calib.D1)[:8], R=R1, P=P1).reshape(-1, 2)
                hull = cv2.convexHull(rc.astype(np.float32)).reshape(-1, 2)
                centre = hull.mean(axis=0)
                hull = centre + 0.85 * (hull - centre)  # shrink: stay off the board's border
                h, w = res.disparity.shape
                vv, uu = np.mgrid[0:h, 0:w]
                inside = Polygon(hull).contains_points(np.c_[uu.ravel(), vv.ravel()]).reshape(h, w)
                p = res.points
                mask = inside & np.all(np.isfinite(p), axis=2)
                if mask.sum() < 500:
                    rows.append({"set": name, "pair": lp.stem, "refine": refine, "pixels": int(mask.sum()),
                                 "note": "too few points on the board"})
                    continue
                pts = p[mask]
                keep = np.ones(len(pts), bool)
                for _ in range(3):
                    a = np.c_[pts[keep, 0], pts[keep, 1], np.ones(keep.sum())]
                    coef, *_ = np.linalg.lstsq(a, pts[keep, 2], rcond=None)
                    r = pts[:, 2] - np.c_[pts[:, 0], pts[:, 1], np.ones(len(pts))] @ coef
                    keep = np.abs(r - np.median(r[keep])) < 4 * robust_std(r[keep])
                info = res.summary["disparity_noise"]
                pred_after = res.uncertainty.sigma_z_disparity[mask][keep]
                pred_model = pred_after / info["scaled_by"]
                obs = robust_std(r[keep])
                rows.append({"set": name, "pair": lp.stem, "refine": refine, "pixels": int(keep.sum()),
                             "board_z_mm": float(np.median(pts[keep, 2])), "observed_mm": obs,
                             "predicted_model_mm": float(np.sqrt(np.mean(pred_model ** 2))),
                             "predicted_after_check_mm": float(np.sqrt(np.mean(pred_after ** 2))),
                             "ratio_model": obs / float(np.sqrt(np.mean(pred_model ** 2))),
                             "ratio_after_check": obs / float(np.sqrt(np.mean(pred_after ** 2))),
                             "check_ratio": info["plane_check"].get("ratio"),
                             "check_tiles": info["plane_check"]["tiles"], "scaled_by": info["scaled_by"],
                             "check_p25_p75": info["plane_check"].get("ratio_p25_p75"),
                             "image_noise_dn": info["image_noise_dn"][0]["sigma"]})
                print(rows[-1], flush=True)
            done += 1
    return rows


def middlebury_rows(scenes=("Adirondack", "Motorcycle", "Piano", "Pipes", "Teddy")) -> list[dict]:
    """Middlebury 2014 (quarter size, ground-truth disparity): robust std of d - d_GT over non-occluded pixels
    with |d - d_GT| < 2 px (gross mismatches are not noise) vs the RMS predicted sigma_d there, before and
    after the plane check; and the same per quartile of the predicted sigma (does it track?)."""
    import cv2

    from dstereo.io.calib_files import read_pfm, read_stereo_calibration
    from dstereo.stereo.reconstruct import ReconstructionConfig, reconstruct_calibrated
    from dstereo.io.images import read_image

    rows = []
    for scene in scenes:
        folder = DATA / "middlebury2014q" / scene
        calib = read_stereo_calibration(folder / "calib.txt")
        gt = read_pfm(folder / "disp0GT.pfm")
        nocc = cv2.imread(str(folder / "mask0nocc.png"), cv2.IMREAD_GRAYSCALE) == 255
        left, right = read_image(folder / "im0.png"), read_image(folder / "im1.png")
        for refine in (False, True):
            res = reconstruct_calibrated(calib, left, right, ReconstructionConfig(refine=refine), scene)
            s = res.uncertainty.sigma_d_map
            e = res.disparity - gt
            ok = np.isfinite(e) & nocc & np.isfinite(s) & (np.abs(np.nan_to_num(e, nan=9.0)) < 2.0)
            info = res.summary["disparity_noise"]
            obs, pred = robust_std(e[ok]), float(np.sqrt(np.mean(s[ok] ** 2)))
            q = np.quantile(s[ok], [0, 0.25, 0.5, 0.75, 1.0])
            quart = []
            for a, b in zip(q[:-1], q[1:]):
                m = ok & (s >= a) & (s <= b)
                quart.append([robust_std(e[m]), float(np.sqrt(np.mean(s[m] ** 2)))])
            rows.append({"scene": scene, "refine": refine, "pixels": int(ok.sum()), "observed_px": obs,
                         "predicted_after_px": pred, "predicted_model_px": pred / info["scaled_by"],
                         "ratio_after": obs / pred, "ratio_model": obs * info["scaled_by"] / pred,
                         "check_ratio": info["plane_check"].get("ratio"), "quartiles_obs_pred": quart,
                         "check_p25_p75": info["plane_check"].get("ratio_p25_p75")})
            print(rows[-1], flush=True)
    return rows


def markdown(render: list[dict], boards: list[dict], middlebury: list[dict] = ()) -> str:
    lines = ["# Per-pixel disparity noise: predicted random sigma vs observed scatter", "",
             "Written by `experiments/disparity_noise.py` (module docstring: method). ratio = observed robust "
             "std / RMS predicted sigma_z on the same pixels; 'model' = before the plane check's scaling, 'after' "
             "= the sigma written to sigma_z_disparity.npy.", ""]
    if render:
        lines += ["## Renders (320 x 240, true calibration, known read noise; plane tilted 10/25 deg at 400 mm, "
                  "speckle | 0.3x-contrast halves)", "",
                  "| noise DN | refine | region | pixels | observed mm | bias mm | predicted mm | ratio model | "
                  "check ratio | scaled by | ratio after | image noise est. DN (left, per brightness) |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in render:
            lines.append(f"| {r['noise_dn']:g} | {r['refine']} | {r['region']} | {r['pixels']} | "
                         f"{r['observed_mm']:.4f} | {r['bias_mm']:+.4f} | {r['predicted_mm']:.4f} | "
                         f"{r['ratio_model']:.2f} | {_f(r['check_ratio'])} | {r['scaled_by']:.2f} | "
                         f"{r['ratio_model'] / r['scaled_by']:.2f} | "
                         f"{', '.join(f'{s:.2f}' for s in r['image_noise_dn'])} |")
    if boards:
        lines += ["", "## Real boards (plane fitted to the board's points; region from the detected corners)", "",
                  "| set | pair | refine | pixels | z mm | observed mm | predicted model mm | ratio model | "
                  "check ratio (tiles) | scaled by | ratio after |", "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in boards:
            if "note" in r:
                lines.append(f"| {r['set']} | {r['pair']} | {r['refine']} | {r['pixels']} | {r['note']} |||||||")
                continue
            lines.append(f"| {r['set']} | {r['pair']} | {r['refine']} | {r['pixels']} | {r['board_z_mm']:.0f} | "
                         f"{r['observed_mm']:.3f} | {r['predicted_model_mm']:.3f} | {r['ratio_model']:.2f} | "
                         f"{_f(r['check_ratio'])} ({r['check_tiles']}) | {r['scaled_by']:.2f} | "
                         f"{r['ratio_after_check']:.2f} |")
    if middlebury:
        lines += ["", "## Middlebury 2014 quarter size (ground-truth disparity; non-occluded, |error| < 2 px)", "",
                  "| scene | refine | pixels | observed px | predicted model px | ratio model | check ratio | "
                  "ratio after | per quartile of predicted: observed / predicted (after) |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in middlebury:
            quart = "; ".join(f"{o:.3f}/{p:.3f}" for o, p in r["quartiles_obs_pred"])
            lines.append(f"| {r['scene']} | {r['refine']} | {r['pixels']} | {r['observed_px']:.3f} | "
                         f"{r['predicted_model_px']:.3f} | {r['ratio_model']:.2f} | {_f(r['check_ratio'])} | "
                         f"{r['ratio_after']:.2f} | {quart} |")
    return "\n".join(lines) + "\n"


def _f(x):
    return "-" if x is None else f"{x:.2f}"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--renders", action="store_true")
    ap.add_argument("--real", action="store_true")
    ap.add_argument("--calib-dir", type=Path, default=Path("/tmp/noise/cal"))
    ap.add_argument("--pairs", type=int, default=4)
    ap.add_argument("--middlebury", action="store_true")
    ap.add_argument("--table", action="store_true", help="only rewrite the .md from the stored .json")
    args = ap.parse_args()
    both = not (args.renders or args.real or args.middlebury or args.table)
    render = render_rows() if args.renders or both else []
    boards = board_rows(args.calib_dir, pairs_per_set=args.pairs) if args.real or both else []
    middlebury = middlebury_rows() if args.middlebury or both else []
    OUT.mkdir(parents=True, exist_ok=True)
    stem = OUT / "disparity_noise"
    old = json.loads(stem.with_suffix(".json").read_text()) if stem.with_suffix(".json").exists() else {}
    data = {"renders": render or old.get("renders", []), "boards": boards or old.get("boards", []),
            "middlebury": middlebury or old.get("middlebury", [])}
    stem.with_suffix(".json").write_text(json.dumps(data, indent=1, default=float))
    stem.with_suffix(".md").write_text(markdown(data["renders"], data["boards"], data["middlebury"]))


if __name__ == "__main__":
    main()
