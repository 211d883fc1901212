"""`dstereo diff`'s statistic on two calibrations of the same rendered camera, each from its own views and noise.

The synthetic webcam (`synth.board_views.webcam`: 640 x 480, f ~ 820 px, k1 k2) is rendered in two independent
sets of V board views (poses and sensor noise from different seeds), the corners detected by the project's
detector, each set calibrated as `dstereo calibrate` solves the full set (the default 5-coefficient model, board
sag, the reported covariance with the views' effects where fitted), and the two compared by
`camera_diff.projection_diff` at A's mean board distance. Over P pairs: each pair's ratio against the band its
own prediction says a right one falls in (5-95 %, simulated from the two covariances), the share inside, the
geometric mean; then the same pairs with both covariances claimed 2x too small in std (a planted wrong scale).

Run: .venv/bin/python -m experiments.diff_rendered [--pairs P] [--views V]   (~1 min a pair on 2 cores)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


def calibrated(cam, n_views: int, seed: int):
    from dstereo.calib.finished import lens_covariance
    from dstereo.calib.mono import calibrate_full
    from dstereo.synth.board_views import rendered_views
    from dstereo.uncertainty.camera_diff import LensCamera
    from dstereo.uncertainty.projection import mean_board_distance

    obj, obs = rendered_views(cam, n_views, seed)
    sol = calibrate_full(obj, obs, cam.image_size, ("k1", "k2", "p1", "p2", "k3"), board_warp=True)
    lc = lens_covariance(sol)
    params = np.concatenate([sol.values[:4], sol.camera().coeffs()])
    return (LensCamera("pinhole", params, lc.names, lc.cov, cam.image_size, joint=lc.joint, poses=lc.poses),
            mean_board_distance(sol.poses, obj), lc.kind)


def run(pairs: int, n_views: int) -> dict:
    from dstereo.synth.board_views import webcam
    from dstereo.uncertainty.camera_diff import projection_diff

    cam = webcam()
    rows, sims = [], []
    rng = np.random.default_rng(0)
    for p in range(pairs):
        t0 = time.perf_counter()
        (a, range_, kind_a), (b, _, kind_b) = calibrated(cam, n_views, 2 * p), calibrated(cam, n_views, 2 * p + 1)
        d = projection_diff(a, b, range_)
        small = lambda c: dataclasses.replace(c, cov=c.cov / 4, joint=c.joint / 4)  # noqa: E731
        bad = projection_diff(small(a), small(b), range_)
        band, band_bad = d.band(), bad.band()
        # 2000 right predictions of this pair (its own covariances), for the band of the pooled geometric mean
        sims.append(d.simulate(rng.normal(size=(2000, d.root_a.shape[1])) @ d.root_a.T,
                               rng.normal(size=(2000, d.root_b.shape[1])) @ d.root_b.T)[0])
        rows.append({"pair": p, "ratio": d.ratio, "mahalanobis": d.mahalanobis_median, "band": band["ratio"],
                     "band_mahalanobis": band["mahalanobis_median"], "rms_px": d.rms,
                     "predicted_px": d.predicted_rms, "modes": d.modes, "ratio_vs_maps": d.ratio_vs_maps,
                     "covariance": [kind_a, kind_b], "ratio_planted": bad.ratio, "band_planted": band_bad["ratio"],
                     "seconds": time.perf_counter() - t0})
        print(rows[-1], flush=True)
    ratio = np.array([r["ratio"] for r in rows])
    inside = [r["band"][0] <= r["ratio"] <= r["band"][1] for r in rows]
    bad = np.array([r["ratio_planted"] for r in rows])
    inside_bad = [r["band_planted"][0] <= r["ratio_planted"] <= r["band_planted"][1] for r in rows]
    pooled = np.exp(np.mean(np.log(sims), axis=0))  # (2000,) geometric means of right predictions over the pairs
    return {"views": n_views, "pairs": rows, "geometric_mean": float(np.exp(np.mean(np.log(ratio)))),
            "geometric_mean_band_if_right": np.percentile(pooled, [5, 95]).tolist(),
            "inside_band": float(np.mean(inside)), "observed_5_95": np.percentile(ratio, [5, 95]).tolist(),
            "band_median": np.median([r["band"] for r in rows], axis=0).tolist(),
            "planted_geometric_mean": float(np.exp(np.mean(np.log(bad)))), "planted_inside_band": float(np.mean(inside_bad))}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--pairs", type=int, default=20)
    ap.add_argument("--views", type=int, default=12)
    args = ap.parse_args()
    r = run(args.pairs, args.views)
    lines = ["| pair | ratio | its band if right (5-95 %) | median Mahalanobis | its band | rms observed / predicted px | "
             "ratio vs maps alone | covariances | planted (stds 2x too small): ratio, band |",
             "|---|---|---|---|---|---|---|---|---|"]
    for p in r["pairs"]:
        lines.append(f"| {p['pair']} | {p['ratio']:.2f} | {p['band'][0]:.2f}-{p['band'][1]:.2f} | "
                     f"{p['mahalanobis']:.2f} | {p['band_mahalanobis'][0]:.2f}-{p['band_mahalanobis'][1]:.2f} | "
                     f"{p['rms_px']:.3f} / {p['predicted_px']:.3f} | {p['ratio_vs_maps']:.2f} | "
                     f"{', '.join(p['covariance'])} | {p['ratio_planted']:.2f}, {p['band_planted'][0]:.2f}-"
                     f"{p['band_planted'][1]:.2f} |")
    text = ("# `dstereo diff` on two calibrations of one rendered camera (experiments/diff_rendered.py)\n\n"
            + __doc__.split("\n\n")[1] + f"\n\n{args.views} views a calibration, {len(r['pairs'])} pairs.\n\n"
            + "\n".join(lines) + "\n\n"
            f"Geometric mean of the ratios {r['geometric_mean']:.2f} (1 if right; {len(r['pairs'])} right predictions' "
            f"geometric means fall in {r['geometric_mean_band_if_right'][0]:.2f}-"
            f"{r['geometric_mean_band_if_right'][1]:.2f}, 5-95 %); inside its own band: "
            f"{100 * r['inside_band']:.0f} % of pairs (90 % if right); the ratios' own 5-95 % over the pairs "
            f"{r['observed_5_95'][0]:.2f}-{r['observed_5_95'][1]:.2f} against the median simulated band "
            f"{r['band_median'][0]:.2f}-{r['band_median'][1]:.2f}. Planted wrong scale (stds 2x too small): geometric mean "
            f"{r['planted_geometric_mean']:.2f}, inside its band {100 * r['planted_inside_band']:.0f} %.\n")
    (RESULTS / "diff_rendered.md").write_text(text)
    (RESULTS / "diff_rendered.json").write_text(json.dumps(r, indent=1))
    print(text)


if __name__ == "__main__":
    main()
