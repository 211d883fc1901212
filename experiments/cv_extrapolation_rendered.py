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
it; and the full-set solve against the truth (`against_truth`): its error inside and outside the field beside its
own map's claim there.

Run: .venv/bin/python -m experiments.cv_extrapolation_rendered [SEEDS] [SPLITS]   (results/cv_extrapolation_rendered.md, .json)
"""

from __future__ import annotations

import dataclasses
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


def against_truth(full, cam, coeffs, obs, range_) -> dict:
    """The full-set solve against the truth by `camera_diff.projection_diff` (the truth's rays at `range_`, the
    rigid transform fitted, weighted by the solve's own map as `dstereo diff` weights it: the truth is given the same
    map, so each pixel weighs 1 / (2 sigma^2), and the pixels the solve knows hold the fit), rms inside and outside
    the corners' field, beside the rms of the solve's own pose-compensated map there (the written map's claim)."""
    from dstereo.calib.finished import lens_covariance
    from dstereo.uncertainty.camera_diff import GRID, LensCamera, corner_field, grid_pixels, projection_diff
    from dstereo.uncertainty.projection import CAMERA_NAMES

    lc = lens_covariance(full)
    params = np.zeros(len(CAMERA_NAMES))
    params[[CAMERA_NAMES.index(n) for n in lc.names]] = lc.values
    fitted = LensCamera("pinhole", params, tuple(lc.names), lc.cov, SIZE, "fit", joint=lc.joint, poses=lc.poses)
    trace = fitted.pose_compensated_trace(range_, GRID, SIZE)
    true = LensCamera("pinhole", np.r_[K, coeffs, np.zeros(len(CAMERA_NAMES) - 4 - len(coeffs))], (), None, SIZE,
                      "truth", map_trace=trace)
    d = projection_diff(true, dataclasses.replace(fitted, joint=None, poses=None, map_trace=trace), range_, GRID,
                        SIZE)
    assert d.weighting == "pose-compensated maps"
    u, v, _ = grid_pixels(SIZE, GRID)
    field = corner_field(u, v, obs)
    err2 = np.sum(d.diff ** 2, axis=-1)
    out = {}
    for name, m in (("inside", field & d.ok), ("outside", ~field & d.ok)):
        out[f"{name}_rms_px"] = float(np.sqrt(np.mean(err2[m])))
        out[f"{name}_pixels"] = int(m.sum())
        out[f"{name}_map_px"] = float(np.sqrt(np.nanmean(trace[m])))
    out["outside_max_px"] = float(np.sqrt(np.max(err2[~field & d.ok])))
    z = np.sqrt(err2 / trace)  # the error in units of the map's own rms claim, per pixel
    out["inside_error_over_map_max"] = float(np.nanmax(z[field & d.ok]))
    out["outside_error_over_map_max"] = float(np.nanmax(z[~field & d.ok]))
    out["field_share"] = float(field.mean())
    out["pixels_without_ray"] = int((~d.ok).sum())
    return out


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
            truth_err = against_truth(full, cam, coeffs, obs, xv.range_)
            rows.append({"truth": truth, "seed": seed, "views": len(obs), "rms_px": float(full.rms),
                         "ratio": s["ratio_geometric_mean"], "mahalanobis": s["mahalanobis_median"],
                         "band": s["band_if_right"], "diagnosis": s["diagnosis"], "against_truth": truth_err,
                         "verdict": s["verdict"], "seconds": time.time() - t0})
            d = s["diagnosis"] or {}
            b = s["band_if_right"] or {}
            print(f"{truth} seed {seed}: views {len(obs)} rms {full.rms:.3f} ratio {rows[-1]['ratio']:.2f} band "
                  f"{np.round(b.get('ratio'), 2)} | pooled inside {d.get('ratio_pooled_inside_corner_field'):.2f} "
                  f"outside {d.get('ratio_pooled_outside_corner_field'):.2f} quotient {d.get('outside_over_inside'):.2f}"
                  f" band {np.round(d.get('outside_over_inside_band_if_right'), 2)} excess "
                  f"{d.get('extrapolation_excess')} | full set vs truth / its map (rms): inside "
                  f"{truth_err['inside_rms_px']:.3f} / {truth_err['inside_map_px']:.3f} px, outside "
                  f"{truth_err['outside_rms_px']:.3f} / {truth_err['outside_map_px']:.3f} px, "
                  f"worst outside {truth_err['outside_max_px']:.1f} px; error / map at worst: inside "
                  f"{truth_err['inside_error_over_map_max']:.1f}, outside {truth_err['outside_error_over_map_max']:.1f}"
                  f" ({time.time() - t0:.0f} s)", flush=True)
    return rows


def main(argv):
    seeds = int(argv[0]) if argv else 6
    splits = int(argv[1]) if len(argv) > 1 else 4
    rows = run(seeds, splits)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "cv_extrapolation_rendered.json").write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main(sys.argv[1:])
