"""`dstereo diff` on two halves of each shared real camera, against `--cross-validate`'s split, through the CLI.

For each camera of ../shared/data: `dstereo calibrate --cross-validate N` on all its views; then, for each split,
(1) `dstereo diff` on the split's halves as the run wrote them (cross_validation/split_<k>/a, b): the same
statistic on the same numbers, so it must read the split's ratio exactly; (2) each half calibrated from its own
images by `dstereo calibrate` (its own outlier rejection, board sag, view effects: what a user would run), then
`dstereo diff` on the two results folders at the cross-validation's distance. (2) differs from the split only by
what each half's own run does differently (the corners its outlier rejection keeps).

Run: .venv/bin/python -m experiments.diff_halves_real [OUT_DIR] [--splits=N]   (~10 min a camera on 2 cores)."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
SETS = [("opencv_stereo L", "opencv_stereo", "left*.jpg", None), ("rig640 L", "rig640", "left*.jpg", None),
        ("rig640 R", "rig640", "right*.jpg", None), ("fisheye640 fisheye", "fisheye640", "view*.jpg", "fisheye")]
SPLITS = 4
RESULTS = Path(__file__).resolve().parent / "results"


def _cli(*args) -> subprocess.CompletedProcess:
    out = subprocess.run([sys.executable, "-m", "dstereo.cli", *map(str, args)], capture_output=True, text=True,
                         env={**__import__("os").environ, "DSTEREO_SERVE": "0"})
    if out.returncode != 0:
        raise RuntimeError(f"dstereo {' '.join(map(str, args))}: {out.stderr.strip().splitlines()[-1:]}")
    return out


def camera(label: str, folder: str, glob: str, model: str | None, out: Path, splits: int) -> dict:
    res = out / label.replace(" ", "_")
    common = ["--pattern", "9x6", "--square", "10", "-q"] + (["--model", model] if model else [])
    t0 = time.perf_counter()
    _cli("calibrate", "--images", DATA / folder, "--glob", glob, *common, "--cross-validate", splits,
         "--out", res / "all", "--force")
    s = json.loads((res / "all" / "summary.json").read_text())
    x, used = s["cross_validation"], s["images"]["used"]
    rows = []
    for k, (a, b) in enumerate(x["halves"]):
        split = res / "all" / "cross_validation" / f"split_{k + 1}"
        _cli("diff", split / "a", split / "b", "--out", res / f"diff_written_{k + 1}", "--force")
        written = json.loads((res / f"diff_written_{k + 1}" / "diff.json").read_text())["prediction"]
        halves = []
        for h, part in zip("ab", (a, b)):
            images = res / f"images_{k + 1}{h}"
            images.mkdir(parents=True, exist_ok=True)
            for old in images.iterdir():
                old.unlink()
            for i in part:
                (images / used[i]).symlink_to((DATA / folder / used[i]).resolve())
            _cli("calibrate", "--images", images, *common, "--out", res / f"half_{k + 1}{h}", "--force")
            halves.append(res / f"half_{k + 1}{h}")
        _cli("diff", *halves, "--distance", x["range"], "--out", res / f"diff_cli_{k + 1}", "--force")
        cli = json.loads((res / f"diff_cli_{k + 1}" / "diff.json").read_text())
        rows.append({"split": k + 1, "ratio_tool": x["ratios"][k], "ratio_written": written["ratio"],
                     "mahalanobis_tool": x["mahalanobis_medians"][k],
                     "mahalanobis_written": written["mahalanobis_median"],
                     "ratio_cli": cli["prediction"]["ratio"], "mahalanobis_cli": cli["prediction"]["mahalanobis_median"],
                     "band_cli": cli["prediction"]["band_if_right"]["ratio"],
                     "ratio_vs_maps_cli": cli["prediction"]["ratio_vs_pose_compensated_maps"],
                     "observed_rms_cli": cli["observed_rms_px"], "predicted_rms_cli": cli["prediction"]["predicted_rms_px"]})
        print(label, rows[-1], flush=True)
    return {"label": label, "views": len(used), "range": x["range"], "splits": rows,
            "ratio_geometric_mean": x["ratio_geometric_mean"], "band_if_right": x["band_if_right"],
            "ratio_vs_maps": x["ratio_vs_pose_compensated_maps"], "trusted": x["trusted"],
            "seconds": time.perf_counter() - t0}


def main(out: Path, splits: int = SPLITS) -> None:
    out.mkdir(parents=True, exist_ok=True)
    data = [camera(*s, out, splits) for s in SETS]
    lines = ["| camera | views | split | `--cross-validate` ratio / Mahalanobis | `dstereo diff` on the written halves | "
             "`dstereo diff` on halves calibrated by the CLI | its band if right (5-95 %) | CLI halves: rms observed / "
             "predicted px | CLI halves: ratio vs maps alone |", "|---|---|---|---|---|---|---|---|---|"]
    for cam in data:
        for r in cam["splits"]:
            lines.append(f"| {cam['label']} | {cam['views']} | {r['split']} | {r['ratio_tool']:.3f} / "
                         f"{r['mahalanobis_tool']:.2f} | {r['ratio_written']:.3f} / {r['mahalanobis_written']:.2f} | "
                         f"{r['ratio_cli']:.3f} / {r['mahalanobis_cli']:.2f} | {r['band_cli'][0]:.2f}-"
                         f"{r['band_cli'][1]:.2f} | {r['observed_rms_cli']:.3f} / {r['predicted_rms_cli']:.3f} | "
                         f"{r['ratio_vs_maps_cli']:.2f} |")
    pooled = [f"- {c['label']}: geometric mean {c['ratio_geometric_mean']:.2f} over {len(c['splits'])} splits, a right "
              f"prediction reads {c['band_if_right']['ratio'][0]:.2f}-{c['band_if_right']['ratio'][1]:.2f} here; "
              f"against the maps alone {c['ratio_vs_maps']:.2f}; {c['seconds']:.0f} s" for c in data]
    text = ("# `dstereo diff` on two halves of the real cameras (experiments/diff_halves_real.py)\n\n"
            + __doc__.split("\n\n")[1] + "\n\n" + "\n".join(lines) + "\n\n" + "\n".join(pooled) + "\n")
    (RESULTS / "diff_halves_real.md").write_text(text)
    (RESULTS / "diff_halves_real.json").write_text(json.dumps(data, indent=1))
    print(text)


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    n = [int(a.split("=")[1]) for a in sys.argv[1:] if a.startswith("--splits=")]
    main(Path(args[0]) if args else Path("/tmp/dstereo_diff_halves"), n[0] if n else SPLITS)
