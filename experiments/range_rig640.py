"""A real board from `rig640` reconstructed with defaults: board depth vs its solvePnP distance (issue 14).

Needs the rig calibrated first (square 25 mm: the true size is unknown, and depth ratios do not depend on it):

    dstereo calibrate --left '../shared/data/rig640/left*.jpg' --right '../shared/data/rig640/right*.jpg' \
        --pattern 9x6 --square 25 --out /tmp/rig640cal
    python -m experiments.range_rig640 --calib /tmp/rig640cal/stereo.yml [--pairs 05 12 20] [--md OUT.md]
    PYTHONPATH=OLD_CHECKOUT python experiments/range_rig640.py ...   (the previous code, from a checkout of it)

Per pair: the board's corners found in the original left image, solvePnP with the calibrated left camera gives
their depths; the reconstruction's depth at the same corners (mapped to the rectified grid by R1/P1, median of a
5 x 5 window) is compared with them. Defaults only (`ReconstructionConfig()`).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np

from dstereo.io.calib_files import read_stereo_calibration
from dstereo.stereo.reconstruct import ReconstructionConfig, reconstruct_calibrated
from dstereo.io.images import read_image

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "rig640"


def board_check(calib, name: str, config: ReconstructionConfig) -> dict:
    import cv2

    left, right = read_image(DATA / f"left{name}.jpg"), read_image(DATA / f"right{name}.jpg")
    grey = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY)
    found, corners = cv2.findChessboardCorners(grey, (9, 6))
    if not found:
        return {"pair": name, "error": "no board"}
    corners = cv2.cornerSubPix(grey, corners, (5, 5), (-1, -1), (3, 30, 1e-3))
    obj = np.zeros((54, 3))
    obj[:, :2] = np.mgrid[0:9, 0:6].T.reshape(-1, 2) * 25.0
    _, rvec, tvec = cv2.solvePnP(obj, corners, calib.K1, calib.D1)
    z_pnp = (cv2.Rodrigues(rvec)[0] @ obj.T + tvec).T[:, 2]
    result = reconstruct_calibrated(calib, left, right, replace(config, uncertainty=False), name)
    m = result.matrices
    rect = cv2.undistortPoints(corners, calib.K1, calib.D1, R=m["R1"], P=m["P1"]).reshape(-1, 2)
    z_rec = []
    for u, v in np.rint(rect).astype(int):
        window = result.depth[max(v - 2, 0): v + 3, max(u - 2, 0): u + 3]
        z_rec.append(np.nanmedian(window) if np.isfinite(window).any() else np.nan)
    z_rec = np.array(z_rec)
    ok = np.isfinite(z_rec)
    s = result.summary.get("search_range") or {"min_disparity": result.summary["sgbm"]["min_disparity"],
                                                "max_disparity": result.summary["sgbm"]["min_disparity"]
                                                + result.summary["sgbm"]["num_disparities"] - 1,
                                                "source": "fixed (code before issue 14)", "widened": 0}
    return {"pair": name, "pnp_mm": float(np.median(z_pnp)), "recon_mm": float(np.median(z_rec[ok])) if ok.any()
            else float("nan"), "corners_with_depth": int(ok.sum()),
            "rel_err_pct": float(100 * (np.median(z_rec[ok]) / np.median(z_pnp) - 1)) if ok.any() else float("nan"),
            "range": f"{s['min_disparity']}..{s['max_disparity']} ({s['source']}, widened {s['widened']})",
            "warnings": result.warnings}


def main():
    import json

    ap = argparse.ArgumentParser()
    ap.add_argument("--calib", required=True)
    ap.add_argument("--pairs", nargs="*", default=["05", "12", "20"])
    ap.add_argument("--md", help="also write the rows as a markdown table")
    args = ap.parse_args()
    calib = read_stereo_calibration(args.calib)
    rows = [board_check(calib, name, ReconstructionConfig()) for name in args.pairs]
    for row in rows:
        print(json.dumps(row))
    if args.md:
        lines = ["| pair | solvePnP depth mm | reconstructed mm | error % | corners with depth | search range | "
                 "warnings |", "|---|---|---|---|---|---|---|"]
        lines += [f"| {r['pair']} | {r['pnp_mm']:.1f} | {r['recon_mm']:.1f} | {r['rel_err_pct']:+.2f} | "
                  f"{r['corners_with_depth']}/54 | {r['range']} | {len(r['warnings'])} |" for r in rows]
        Path(args.md).write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
