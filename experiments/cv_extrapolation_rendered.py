"""What the cross-validation reads where the default lens model extrapolates a radial profile it does not have
(issue 32, item 3): a rendered camera whose boards all lie in one part of the image.

The truth: f 800 px, 640 x 480, a rational radial profile (OpenCV's k6 = 3 in the denominator: 1 / (1 + k6 r^6)
adds r^8, r^10, r^12 terms), which the default polynomial (k1 k2 p1 p2 k3) follows to 0.0004 px rms on exact
corners over the radii the boards reach, and misses by 20-30 px at the image corners beyond them (measured, noise
free); the control: the same views through a truth the default model has exactly (k6 = 0). The boards: drawn by
`synth.poses.board_pose_set` and kept only when the whole board lies right of 45 % of the width and within 75 % of
the half-diagonal from the principal point (one side, the image corners unreached). Exact corners (`synth.board.true_corners`) plus N(0,
0.2 px); each seed draws its own poses and noise. Per seed: `calibrate_full` (default model), then
`cross_validate` (the tool's statistic and its simulated band) over the pixels inside the corners' field and outside
it.

Run: .venv/bin/python -m experiments.cv_extrapolation_rendered [SEEDS] [SPLITS]   (results/cv_extrapolation_rendered.md, .json)
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
SIZE, PATTERN, SQUARE, NOISE = (640, 480), (9, 6), 25.0, 0.2
K = (800.0, 805.0, 322.0, 238.0)
RADIAL = (-0.25, 0.1, 1e-3, -5e-4, -0.02)
TRUTHS = {"rational (k6 3)": RADIAL + (0.0, 0.0, 3.0), "in the model (k6 0)": RADIAL + (0.0, 0.0, 0.0)}
REACH = 0.75  # of the half-diagonal
ALL8 = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")


def one_sided_views(cam, seed: int, n_views: int):
    """(poses (V, 6), corners (V, n, 2)) of boards wholly right of 0.45 W and within REACH of the half-diagonal."""
    from dstereo.synth.board import Board, true_corners
    from dstereo.synth.poses import board_pose_set

    poses = board_pose_set([cam], [np.zeros(6)], Board(PATTERN, SQUARE, SQUARE), 40 * n_views, seed,
                           fill=(0.25, 0.4))
    centre = np.array(K[2:])
    keep_p, keep_c = [], []
    for p in poses:
        c = np.asarray(true_corners(cam, p, PATTERN, SQUARE))
        if c[:, 0].min() > 0.45 * SIZE[0] and np.hypot(*(c - centre).T).max() < REACH * np.hypot(*centre):
            keep_p.append(p)
            keep_c.append(c)
        if len(keep_p) == n_views:
            break
    return np.array(keep_p), np.array(keep_c)


def run(seeds: int, splits: int, n_views: int = 16) -> list[dict]:
    from dstereo.calib.cross_validation import cross_validate
    from dstereo.calib.mono import calibrate_full
    from dstereo.errors import DstereoError
    from dstereo.models.camera import Camera
    from dstereo.synth.board import object_points

    obj = object_points(PATTERN, SQUARE)
    rows = []
    for truth, coeffs in TRUTHS.items():
        cam = Camera.create(*K, list(coeffs), ALL8, SIZE)
        for seed in range(seeds):
            t0 = time.time()
            poses, corners = one_sided_views(cam, seed, n_views)
            obs = corners + np.random.default_rng(100 + seed).normal(0, NOISE, corners.shape)
            try:
                full = calibrate_full(obj, obs, SIZE)
            except DstereoError as exc:  # a start that fails on these views: recorded, not hidden
                rows.append({"truth": truth, "seed": seed, "error": str(exc)})
                print(f"{truth} seed {seed}: {exc}", flush=True)
                continue
            xv = cross_validate(full, obj, obs, SIZE, splits=splits, seed=seed)
            s = xv.summary()
            rows.append({"truth": truth, "seed": seed, "views": len(obs), "rms_px": float(full.rms),
                         "ratio": s["ratio_geometric_mean"], "mahalanobis": s["mahalanobis_median"],
                         "band": s["band_if_right"], "diagnosis": s["diagnosis"],
                         "field": s.get("field"), "verdict": s["verdict"], "seconds": time.time() - t0})
            d = s["diagnosis"] or {}
            print(f"{truth} seed {seed}: views {len(obs)} rms {full.rms:.3f} ratio {rows[-1]['ratio']:.2f} band "
                  f"{s['band_if_right']['ratio'] if s['band_if_right'] else None} inside "
                  f"{d.get('ratio_pooled_inside_corner_field', float('nan')):.2f} outside "
                  f"{d.get('ratio_pooled_outside_corner_field', float('nan')):.2f} "
                  f"({time.time() - t0:.0f} s)", flush=True)
    return rows


def main(argv):
    seeds = int(argv[0]) if argv else 6
    splits = int(argv[1]) if len(argv) > 1 else 4
    rows = run(seeds, splits)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "cv_extrapolation_rendered.json").write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main(sys.argv[1:])
