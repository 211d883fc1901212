"""Issue 30: what the default matching decides on the shared real rigs (no ground truth: the decisions and their
figures, against the matching before issue 30). For every pair of rig640 (25) and opencv_stereo (13), with their
stored calibrations and no flags: the views' brightness/contrast gap (`stereo.matching.lighting_mismatch`), the cost
auto took, the share of the pixels the rank check found disagreeing and the share it dropped
(`stereo.cost_check`), whether the fill ran (`stereo.fill.fill_wanted`), the valid share against `--cost intensity
--no-fill`, and the times (one BLAS thread, as the CLI runs). The chessboard in view is a plane: where its corners
are found on the rectified left image, a robust plane fit to the matching before over the corners' hull stands in
for the truth, and the table gives the share of the board's pixels the check dropped that lie within 1 px of that
plane, and of those it kept (a check that drops mostly off-plane pixels drops mostly wrong ones).

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


def board_figures(before, default) -> tuple[int, float, float]:
    """(board pixels the check dropped, % of them within 1 px of the board's plane, % of the kept within 1 px):
    the board is the hull of the 9 x 6 corners found on the rectified left image, its plane a robust fit (three
    re-weightings at 3 robust stds) to the matching before over it; (0, nan, nan) without a board or a drop."""
    import cv2

    from dstereo.stereo.pair_result import grey

    found, corners = cv2.findChessboardCorners(grey(before.left_rect), (9, 6))
    d = before.disparity
    if not found:
        return 0, float("nan"), float("nan")
    mask = np.zeros(d.shape, np.uint8)
    cv2.fillConvexPoly(mask, cv2.convexHull(corners.reshape(-1, 2)).astype(np.int32), 1)
    v, u = np.nonzero(mask.astype(bool) & np.isfinite(d))
    basis = np.stack([np.ones_like(u), u, v], axis=1).astype(float)
    keep = np.ones(len(u), bool)
    for _ in range(4):
        coef = np.linalg.lstsq(basis[keep], d[v, u][keep].astype(float), rcond=None)[0]
        r = d[v, u] - basis @ coef
        keep = np.abs(r) <= 3 * max(1.4826 * np.median(np.abs(r)), 0.1)
    on = np.abs(r) <= 1.0
    dropped = ~np.isfinite(default.disparity[v, u])
    if not dropped.any():
        return 0, float("nan"), 100 * float(on.mean())
    return int(dropped.sum()), 100 * float(on[dropped].mean()), 100 * float(on[~dropped].mean())


def main() -> None:
    from dstereo.io.calib_files import read_stereo_calibration
    from dstereo.io.images import read_image
    from dstereo.stereo.reconstruct import ReconstructionConfig, reconstruct_calibrated

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    default = ReconstructionConfig(uncertainty=False)
    before = ReconstructionConfig(uncertainty=False, matching_cost="intensity", fill=False)
    text = ("| rig | pair | gap | cost | disagree % | dropped % | fill | valid % before / default | board px dropped | "
            "on the board's plane % dropped / kept | s before / default |\n|---|---|---|---|---|---|---|---|---|---|---|\n")
    rows = []
    for rig in RIGS:
        calib = read_stereo_calibration(DATA / rig / "intrinsics.yml")
        for name, left_path, right_path in pairs(rig):
            left, right = read_image(left_path), read_image(right_path)
            out = {}
            for label, config in (("before", before), ("default", default)):
                t0 = time.perf_counter()
                result = reconstruct_calibrated(calib, left, right, config, name)
                out[label] = (result.summary, time.perf_counter() - t0, result)
            board = board_figures(out["before"][2], out["default"][2])
            s = out["default"][0]
            cost = s["search_range"]["matching_cost"]
            check = cost.get("cross_check") or {}
            fill = s["fill"]
            row = (rig, name, cost.get("lighting_mismatch", float("nan")), cost["cost"],
                   100 * check.get("disagree_share", float("nan")), 100 * check.get("dropped_share", float("nan")),
                   f"{fill.get('filled_points', 0)} points" if fill["enabled"] else "off",
                   100 * out["before"][0]["valid_fraction"], 100 * s["valid_fraction"], *board, out["before"][1],
                   out["default"][1])
            rows.append(row)
            line = ("| {} | {} | {:.3f} | {} | {:.2f} | {:.2f} | {} | {:.1f} / {:.1f} | {} | {:.0f} / {:.0f} | "
                    "{:.1f} / {:.1f} |".format(*row))
            print(line, flush=True)
            text += line + "\n"
    dropped = [r[5] for r in rows if np.isfinite(r[5])]
    boards = [r for r in rows if r[9] > 0 and r[11] >= 50]  # a board whose plane holds most of its kept pixels
    on = sum(r[9] * r[10] / 100 for r in boards) / max(sum(r[9] for r in boards), 1)
    text += (f"\n{len(rows)} pairs: cost rank on {sum(r[3] == 'rank' for r in rows)}, the check dropped "
             f"{min(dropped):.2f}-{max(dropped):.2f} % of the pixels (median {np.median(dropped):.2f} %), the fill ran on "
             f"{sum(r[6] != 'off' for r in rows)}. gap: the larger |log| ratio of the views' median grey levels and "
             "10-90 % spreads (rank above 0.25); disagree / dropped: shares of the pixels with a source in both "
             "images; valid: summary.json's valid_fraction; board: the pixels of the chessboard's corner hull with a "
             f"match before that the check dropped, and the shares of those and of the kept ones within 1 px of the "
             f"board's plane (over the {len(boards)} pairs with board pixels dropped and a plane that holds at least half "
             f"of the kept ones: {sum(r[9] for r in boards)} pixels dropped, {100 * on:.0f} % of them "
             "on the plane); s: reconstruction time on the shared 2-core machine (under load).\n")
    print(text)
    if args.out is not None:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
