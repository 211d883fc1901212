"""Issue 30: what the default matching decides on the shared real rigs (no ground truth: the decisions and their
figures, against the matching before issue 30). For every pair of rig640 (25) and opencv_stereo (13), with their
stored calibrations and no flags: the views' brightness/contrast gap (`stereo.matching.lighting_mismatch`), the cost
auto took, the share of the pixels the rank check found disagreeing and the share it dropped
(`stereo.cost_check`), whether the fill ran (`stereo.fill.fill_wanted`), the valid share against `--cost intensity
--no-fill`, and the times (one BLAS thread, as the CLI runs).

    python -m experiments.default_matching_real [--out experiments/results/default_matching_real.md]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as `dstereo` runs (dstereo/cli.py), before numpy loads

import argparse
import time
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
RIGS = ("rig640", "opencv_stereo")


def pairs(rig: str):
    folder = DATA / rig
    for left in sorted(folder.glob("left*.jpg")):
        right = folder / left.name.replace("left", "right")
        if right.is_file():
            yield left.stem[4:], left, right


def main() -> None:
    from dstereo.io.calib_files import read_stereo_calibration
    from dstereo.io.images import read_image
    from dstereo.stereo.reconstruct import ReconstructionConfig, reconstruct_calibrated

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    default = ReconstructionConfig(uncertainty=False)
    before = ReconstructionConfig(uncertainty=False, matching_cost="intensity", fill=False)
    text = ("| rig | pair | gap | cost | disagree % | dropped % | fill | valid % before / default | s before / "
            "default |\n|---|---|---|---|---|---|---|---|---|\n")
    rows = []
    for rig in RIGS:
        calib = read_stereo_calibration(DATA / rig / "intrinsics.yml")
        for name, left_path, right_path in pairs(rig):
            left, right = read_image(left_path), read_image(right_path)
            out = {}
            for label, config in (("before", before), ("default", default)):
                t0 = time.perf_counter()
                result = reconstruct_calibrated(calib, left, right, config, name)
                out[label] = (result.summary, time.perf_counter() - t0)
            s = out["default"][0]
            cost = s["search_range"]["matching_cost"]
            check = cost.get("cross_check") or {}
            fill = s["fill"]
            row = (rig, name, cost.get("lighting_mismatch", float("nan")), cost["cost"],
                   100 * check.get("disagree_share", float("nan")), 100 * check.get("dropped_share", float("nan")),
                   f"{fill.get('filled_points', 0)} points" if fill["enabled"] else "off",
                   100 * out["before"][0]["valid_fraction"], 100 * s["valid_fraction"], out["before"][1],
                   out["default"][1])
            rows.append(row)
            line = ("| {} | {} | {:.3f} | {} | {:.2f} | {:.2f} | {} | {:.1f} / {:.1f} | {:.1f} / {:.1f} |"
                    .format(*row))
            print(line, flush=True)
            text += line + "\n"
    dropped = [r[5] for r in rows if np.isfinite(r[5])]
    text += (f"\n{len(rows)} pairs: cost rank on {sum(r[3] == 'rank' for r in rows)}, the check dropped "
             f"{min(dropped):.2f}-{max(dropped):.2f} % of the pixels (median {np.median(dropped):.2f} %), the fill ran on "
             f"{sum(r[6] != 'off' for r in rows)}. gap: the larger |log| ratio of the views' median grey levels and "
             "10-90 % spreads (rank above 0.25); disagree / dropped: shares of the pixels with a source in both "
             "images; valid: summary.json's valid_fraction; s: reconstruction time on the shared 2-core machine "
             "(under load).\n")
    print(text)
    if args.out is not None:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
