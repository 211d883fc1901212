"""Outlier rejection, wild-fit and residual-pattern checks on every camera of ../shared/data (issue 15, items 4, 6).

Per camera and model: corners rejected, RMS before / after, the largest parameter move in units of the
all-corner solve's sigma, the identifiability verdict and the residual-pattern test before and after rejection.
Run: .venv/bin/python -m experiments.outliers_misfit_real (about a minute on 2 cores).
"""

from pathlib import Path

import numpy as np

from dstereo.calib import mono
from dstereo.calib.misfit import solution_pattern
from dstereo.calib.outliers import reject_outliers
from dstereo.io.corners import detect_folder
from dstereo.models.distortion import PRESETS

ROOT = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
CAMERAS = [("opencv_stereo", "left"), ("opencv_stereo", "right"), ("rig640", "left"), ("rig640", "right"),
           ("fisheye640", "view")]


def main() -> None:
    for folder, prefix in CAMERAS:
        d = detect_folder(ROOT / folder, (9, 6), 1.0, files=sorted((ROOT / folder).glob(f"{prefix}*.jpg")))
        names = sorted(d.corners)
        obs = np.stack([d.corners[n] for n in names])
        for model in ("k1", "k1k2", "default", "rational") + (("fisheye",) if folder == "fisheye640" else ()):
            free = PRESETS[model]
            first = mono.calibrate_full(d.object_points, obs, d.image_size, free)
            sol, keep, rep = reject_outliers(d.object_points, obs, d.image_size, free, names, first)
            z = (sol.values - first.values) / first.std
            j = int(np.argmax(np.abs(z)))
            before, after = solution_pattern(obs, first), solution_pattern(obs[keep], sol)
            print(f"{folder}/{prefix} {model}: {len(rep.corners)} of {rep.n_corners} corners, {len(rep.views)} views "
                  f"rejected (k = {rep.k:.2f}); RMS {first.rms:.4f} -> {sol.rms:.4f} px; largest move {first.names[j]} "
                  f"{z[j]:+.2f} sigma; fx {z[0]:+.2f} sigma; pattern p {before.p_value:.1g} -> {after.p_value:.1g} "
                  f"(warn {before.significant or after.significant}); {sol.conditioning.message()[:90]}")


if __name__ == "__main__":
    main()
