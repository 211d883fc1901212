"""Does solving the board's sag (two parameters, `calib/problem.py: sag_basis`) make the real cameras' uncertainty
pass cross-validation? Each camera of ../shared/data: corners detected, outliers rejected (the default k-sigma),
then 6 random half splits pooled (`calib/cross_validation.py`), flat board against sagging board, same corners,
same splits. Writes experiments/results/board_sag_real.md.
Run: .venv/bin/python -m experiments.board_sag_real  (a few minutes on 2 cores)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
RESULTS = Path(__file__).resolve().parent / "results" / "board_sag_real.md"
SETS = [("opencv_stereo L", "opencv_stereo", "left", "default"), ("opencv_stereo R", "opencv_stereo", "right", "default"),
        ("rig640 L", "rig640", "left", "default"), ("rig640 R", "rig640", "right", "default"),
        ("fisheye640", "fisheye640", "view", "rational")]


def main() -> None:
    from dstereo.calib.cross_validation import cross_validate
    from dstereo.calib.mono import calibrate_full
    from dstereo.calib.outliers import reject_outliers
    from dstereo.io.corners import detect_folder
    from dstereo.models.distortion import PRESETS

    lines = ["# Board sag and cross-validation on the real cameras (`experiments/board_sag_real.py`)", "",
             "Outliers rejected (k-sigma, default), 6 random half splits pooled, seed 0. ratio: geometric mean of "
             "observed / predicted projection difference (1 is honest; acceptance 0.67-1.5); Mahalanobis: median "
             "(about 1.18 is perfect; acceptance <= 1.8). Sag in the board unit (squares).", "",
             "| camera | board | RMS px | sag x | sag y | ratio | pooled rms ratio | Mahalanobis median | trusted |",
             "|---|---|---|---|---|---|---|---|---|"]
    for label, folder, prefix, model in SETS:
        root = DATA / folder
        det = detect_folder(root, (9, 6), 1.0, files=sorted(root.glob(f"{prefix}*.jpg")))
        names = sorted(det.corners)
        obj, obs = det.object_points, np.stack([det.corners[n] for n in names])
        for warp in (False, True):
            first = calibrate_full(obj, obs, det.image_size, PRESETS[model], board_warp=warp)
            sol, keep, _ = reject_outliers(obj, obs, det.image_size, PRESETS[model], names, first)
            xv = cross_validate(sol, obj, obs[keep], det.image_size, 6, seed=0)
            sag = ("-", "-") if sol.board_sag is None else tuple(
                f"{v:.4f} +- {s:.4f}" for v, s in zip(sol.board_sag, sol.std[-2:]))
            row = (f"| {label} ({model}) | {'sag' if warp else 'flat'} | {sol.rms:.4f} | {sag[0]} | {sag[1]} | "
                   f"{xv.ratio:.2f} | {xv.ratio_pooled:.2f} | {xv.mahalanobis_median:.2f} | {xv.trusted} |")
            print(row, flush=True)
            lines.append(row)
    RESULTS.write_text("\n".join(lines) + "\n")
    print("wrote", RESULTS)


if __name__ == "__main__":
    main()
