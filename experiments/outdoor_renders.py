"""ETH3D-style check on rendered outdoor scenes (issue 30): the matching before issue 30 against today's defaults,
on accuracy and density against the known depth.

Scenes: `dstereo.synth.outdoor` (a parallel rig 1.5 m above slanted ground with multi-scale texture, a low-texture
road and wall, rocks, a backdrop near infinity, a textureless sky), one per seed, each as rendered and with the
right view exposed differently: gain 0.85 (a camera pair's own auto-exposure, 15 % apart as rig640's cameras are)
and relit as the Middlebury check does (gain 0.7, gamma 1.3). Configurations, each with no other flags
(`ReconstructionConfig()`: the range from the pair's own sparse matches and the rig's geometric bounds):
- before: `--cost intensity`, no fill (the matching before issue 30);
- default: no flags (views exposed alike: the grey levels checked by the rank cost, no fill; exposed
  differently: the rank cost and the fill);
- fill: `--fill`;
- rank fill: `--cost rank --fill`.

Scored on the left pixels the right camera also sees (`synth.outdoor.visible_in_right`), as ETH3D's two-view
benchmark scores disparities: density = share with an estimate; over the estimates, the mean |d - d_true| (px),
bad 1 = share off by more than 1 px, and the median of |Z - Z_true| / Z_true (%); good = share of the seen pixels
with an estimate within 1 px (a hole counts as not good: accuracy and density in one figure); filled obs / pred =
the filled pixels' robust std of the disparity error over the RMS of their sigma. The backdrop near 1.7 px
holds a 1 % depth error only within 0.02 px: disparity errors in px are the fair measure of a wide-range scene.

    python -m experiments.outdoor_renders [--seeds 4] [--out experiments/results/outdoor_renders.md]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as `dstereo` runs (dstereo/cli.py), before numpy loads

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from dstereo.stereo.reconstruct import ReconstructionConfig, reconstruct_calibrated
from dstereo.synth.outdoor import OutdoorRig, exposed, outdoor_pair, true_disparity, visible_in_right
from experiments._validation import report

DEFAULT = ReconstructionConfig(uncertainty=False)
CONFIGS = {"before": replace(DEFAULT, matching_cost="intensity", fill=False), "default": DEFAULT,
           "fill": replace(DEFAULT, fill=True), "rank fill": replace(DEFAULT, matching_cost="rank", fill=True)}
FILLED = ("default", "fill", "rank fill")
VARIANTS = {"as rendered": None, "right gain 0.85": (0.85, 1.0), "right gain 0.7, gamma 1.3": (0.7, 1.3)}
MAD_TO_STD = 1.4826


def robust_std(x: np.ndarray) -> float:
    return float(MAD_TO_STD * np.median(np.abs(x - np.median(x))))


def score(result, depth: np.ndarray, seen: np.ndarray, disparity_true: np.ndarray) -> dict:
    """The figures of one reconstruction against the render's truth (module docstring)."""
    est = seen & np.isfinite(result.depth) & np.isfinite(result.disparity)
    rel = np.abs(result.depth - depth)[est] / depth[est]
    err = np.abs(result.disparity[est].astype(np.float64) - disparity_true[est])
    filled = est & (result.filled if result.filled is not None else False)
    row = {"density_pct": 100.0 * est.sum() / seen.sum(), "mean_px": float(np.mean(err)),
           "bad1_pct": 100.0 * float(np.mean(err > 1.0)), "median_pct": 100.0 * float(np.median(rel)),
           "good_pct": 100.0 * float((err <= 1.0).sum() / seen.sum()),
           "cost": result.summary["search_range"]["matching_cost"]["cost"],
           "filled_pct": 100.0 * filled.sum() / max(est.sum(), 1), "obs_pred": None,
           "dropped_pct": 100.0 * (result.summary["search_range"]["matching_cost"].get("cross_check") or
                                   {"dropped_share": 0.0})["dropped_share"]}
    if filled.sum() >= 100:
        err = result.disparity[filled].astype(np.float64) - disparity_true[filled]
        row["obs_pred"] = robust_std(err) / float(np.sqrt(np.mean(result.fill_sigma[filled] ** 2)))
    return row


def run_scene(seed: int, rig: OutdoorRig, configs=CONFIGS, variants=VARIANTS) -> list[tuple[str, dict]]:
    """[(variant, {config: figures})] for one rendered scene."""
    render = outdoor_pair(rig, seed)
    calib = rig.calibration()
    depth = render.truth_left["depth"]
    seen = visible_in_right(render, rig)
    d_true = true_disparity(render, rig)
    rows = []
    for variant, change in variants.items():
        right = render.right if change is None else exposed(render.right, *change)
        figures = {}
        for name, config in configs.items():
            t0 = time.perf_counter()
            result = reconstruct_calibrated(calib, render.left, right, config, f"outdoor{seed}")
            figures[name] = score(result, depth, seen, d_true) | {"seconds": time.perf_counter() - t0}
        rows.append((variant, figures))
    return rows


def table(rows: list[tuple[int, str, dict]]) -> str:
    names = list(CONFIGS)
    both = " / ".join(names)
    fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
    each = lambda r, key, spec: " / ".join(format(r[n][key], spec) for n in names)  # noqa: E731
    text = (f"| seed | right view | default's cost | default: dropped by the check % | density % {both} | mean error px {both} | bad 1 px % {both} | "
            f"median depth error % {both} | good % {both} | filled % {' / '.join(FILLED)} | "
            f"filled obs / pred {' / '.join(FILLED)} |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|\n")
    for seed, variant, r in rows:
        text += (f"| {seed} | {variant} | {r['default']['cost']} | {r['default']['dropped_pct']:.2f} | "
                 f"{each(r, 'density_pct', '.1f')} | "
                 f"{each(r, 'mean_px', '.3f')} | {each(r, 'bad1_pct', '.2f')} | {each(r, 'median_pct', '.2f')} | "
                 f"{each(r, 'good_pct', '.1f')} | {' / '.join(format(r[n]['filled_pct'], '.2f') for n in FILLED)} | "
                 f"{' / '.join(fmt(r[n]['obs_pred']) for n in FILLED)} |\n")
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--out", type=Path, default=None, help="markdown file for the table (default: print only)")
    args = parser.parse_args()
    rig = OutdoorRig()
    rows = []
    for seed in range(args.seeds):
        for variant, figures in run_scene(seed, rig):
            rows.append((seed, variant, figures))
            print(table(rows[-1:]).splitlines()[-1], flush=True)
    text = (f"Rendered outdoor scenes (`dstereo.synth.outdoor`, {rig.size[0]} x {rig.size[1]}, f {rig.focal_px:g} px, "
            f"baseline {rig.baseline_mm:g} mm), scored on the pixels both cameras see. before: `--cost intensity`, "
            "no fill (the matching before issue 30); default: no flags; fill: `--fill`; rank fill: "
            "`--cost rank --fill`.\n\n"
            + table(rows))
    report(text, args.out)


if __name__ == "__main__":
    main()
