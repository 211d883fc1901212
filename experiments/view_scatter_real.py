"""View scatter (the cluster-robust check of the Jacobian covariance, `uncertainty/view_scatter.py`) and the
cross-validation it changes, on the real cameras of ../shared/data, through the CLI:
`dstereo calibrate --cross-validate 12` (outlier rejection on, the default), 12 random half splits pooled.
Run: .venv/bin/python -m experiments.view_scatter_real [OUT_DIR] [--board-sag]   (a few minutes of CPU; with
--board-sag the board's sag is solved too and the table goes to view_scatter_real_sag.md)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
SETS = [("opencv_stereo L", "opencv_stereo", "left*.jpg", None), ("opencv_stereo R", "opencv_stereo", "right*.jpg", None),
        ("rig640 L", "rig640", "left*.jpg", None), ("rig640 R", "rig640", "right*.jpg", None),
        ("fisheye640 rational", "fisheye640", "view*.jpg", "rational"),
        ("fisheye640 fisheye", "fisheye640", "view*.jpg", "fisheye")]
SPLITS = 12


def main(out: Path, sag: bool = False) -> None:
    out.mkdir(parents=True, exist_ok=True)
    rows = ["| camera | views | RMS px | kappa (1 +- se if independent) | reported / Jacobian std (view effects) | "
            "cross-validation ratio | median Mahalanobis | parameter d'C^-1d/G | trusted |",
            "|---|---|---|---|---|---|---|---|---|"]
    for label, folder, glob, model in SETS:
        res = out / label.replace(" ", "_")
        cmd = [sys.executable, "-m", "dstereo.cli", "calibrate", "--images", str(DATA / folder), "--glob", glob,
               "--pattern", "9x6", "--cross-validate", str(SPLITS), "--out", str(res), "--force", "-q"]
        cmd += ["--board-sag"] if sag else []
        subprocess.run(cmd + (["--model", model] if model else []), check=True, capture_output=True)
        s = json.loads((res / "summary.json").read_text())
        x, vs = s["cross_validation"], s["full_set"]["view_scatter"]
        r = sorted(s["full_set"]["view_effects"]["std_ratio"].values())
        rows.append(f"| {label} | {len(s['images']['used'])} | {s['full_set']['rms']:.3f} | {vs['kappa']:.2f} (1 +- "
                    f"{vs['standard_error']:.2f}) | {r[0]:.2f}-{r[-1]:.2f} | {x['ratio_geometric_mean']:.2f} | "
                    f"{x['mahalanobis_median']:.2f} | {x['parameter_chi2_mean']:.2f} | {x['trusted']} |")
        print(rows[-1], flush=True)
    text = ("# View scatter and cross-validation on the real cameras (experiments/view_scatter_real.py)\n\n"
            f"`dstereo calibrate --cross-validate {SPLITS}` with its defaults (outlier rejection on, board sag "
            f"{'on: --board-sag' if sag else 'off'}); "
            "each half's uncertainty carries its own views' effects (`uncertainty/view_effects.py`), as every "
            "calibration's does. Target: ratio 0.67-1.5 and median Mahalanobis <= 1.8; the parameter column is 1 if "
            "right.\n\n" + "\n".join(rows) + "\n")
    name = "view_scatter_real_sag.md" if sag else "view_scatter_real.md"
    (Path(__file__).parent / "results" / name).write_text(text)


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if a != "--board-sag"]
    main(Path(args[0]) if args else Path("/tmp/dstereo_view_scatter"), "--board-sag" in sys.argv)
