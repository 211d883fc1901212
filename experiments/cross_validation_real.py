"""Cross-validation (6 random half splits, pooled) on the real cameras of ../shared/data, through the CLI
(`dstereo calibrate --cross-validate 6`), then again on the same corners without the views whose RMS is over 3x
the median (a crude stand-in for the outlier rejection not built yet), to see whether rejection is needed.
Run: .venv/bin/python experiments/cross_validation_real.py [OUT_DIR]  (about a minute of CPU)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
SETS = [("opencv_stereo L", "opencv_stereo", "left*.jpg", None), ("opencv_stereo R", "opencv_stereo", "right*.jpg", None),
        ("rig640 L", "rig640", "left*.jpg", None), ("rig640 R", "rig640", "right*.jpg", None),
        ("fisheye640 rational", "fisheye640", "view*.jpg", "rational")]


def main(out: Path) -> None:
    from dstereo.calib.cross_validation import cross_validate
    from dstereo.calib.mono import calibrate_full

    out.mkdir(parents=True, exist_ok=True)
    for label, folder, glob, model in SETS:
        res = out / label.replace(" ", "_")
        cmd = [str(Path(sys.executable).parent / "dstereo"), "calibrate", "--images", str(DATA / folder), "--glob", glob,
               "--pattern", "9x6", "--cross-validate", "6", "--out", str(res), "--force", "-q"]
        subprocess.run(cmd + (["--model", model] if model else []), check=True, capture_output=True)
        s = json.loads((res / "summary.json").read_text())
        x, pu = s["cross_validation"], s["projection_uncertainty"]
        splits = ", ".join(f"{r:.2f}" for r in x["ratios"])
        print(f"{label}: {len(s['images']['used'])} views, RMS {s['full_set']['rms']:.3f} px; projection std "
              f"({pu['method']}) median {pu['std_px']['median']:.3g} px, {pu['masked_pixels']} masked; ratio "
              f"{x['ratio_geometric_mean']:.2f}, pooled rms {x['ratio_pooled_rms']:.2f} (splits {splits}), Mahalanobis "
              f"median {x['mahalanobis_median']:.2f}, vs maps {x['ratio_vs_pose_compensated_maps']:.2f}, "
              f"trusted {x['trusted']}; inside the corners' field: {x['inside_corner_field']}")
        c = np.load(res / "corners.npz")
        obj, obs = c["object_points"], np.stack([c[n] for n in s["images"]["used"]])
        rms = np.array([s["full_set"]["per_image_rms"][n] for n in s["images"]["used"]])
        keep = rms <= 3 * np.median(rms)
        if keep.all():
            continue
        free = tuple(s["model"])
        full = calibrate_full(obj, obs[keep], tuple(s["image_size"]), free)
        xv = cross_validate(full, obj, obs[keep], tuple(s["image_size"]), 6, seed=0)
        print(f"  without {int((~keep).sum())} view(s) over 3x the median RMS: RMS {full.rms:.3f} px, ratio "
              f"{xv.ratio:.2f}, pooled rms {xv.ratio_pooled:.2f}, Mahalanobis median {xv.mahalanobis_median:.2f}, trusted {xv.trusted}; inside the corners' field: "
              f"{xv.covered_figures()}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("/tmp/dstereo_xval_real"))
