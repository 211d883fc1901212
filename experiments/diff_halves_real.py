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
REUSE = False  # --reuse: calibrations already in OUT_DIR are read, not run again (the diffs are)


def _cli(*args) -> subprocess.CompletedProcess:
    out = subprocess.run([sys.executable, "-m", "dstereo.cli", *map(str, args)], capture_output=True, text=True,
                         env={**__import__("os").environ, "DSTEREO_SERVE": "0"})
    if out.returncode != 0:
        raise RuntimeError(f"dstereo {' '.join(map(str, args))}: {out.stderr.strip().splitlines()[-1:]}")
    return out


def unweighted(a: Path, b: Path, distance: float) -> dict:
    """The same two written halves compared with the transform fitted over the grid unweighted (as before this
    change): the ratio against the first-order prediction (what the fit absorbs removed), and against the two
    pose-compensated maps alone (the independent check of issue 32)."""
    from dstereo.io.diff_files import read_diff_input
    from dstereo.jobs.diff import _camera
    from dstereo.uncertainty.camera_diff import projection_diff

    cams = [_camera(read_diff_input(str(p), w), []) for p, w in ((a, "A"), (b, "B"))]
    weighted = projection_diff(*cams, distance)
    d = projection_diff(*cams, distance, weighted=False)
    d.map_trace = weighted.map_trace  # the maps do not depend on the weights
    return {"ratio": d.ratio, "ratio_raw": d.ratio_raw, "rms_px": d.rms, "predicted_px": d.predicted_rms,
            "ratio_raw_vs_maps": d.ratio_vs_maps, "weighted_ratio_raw": weighted.ratio_raw,
            "weighted_ratio_raw_vs_maps": weighted.ratio_vs_maps}


def camera(label: str, folder: str, glob: str, model: str | None, out: Path, splits: int) -> dict:
    res = out / label.replace(" ", "_")
    common = ["--pattern", "9x6", "--square", "10", "-q"] + (["--model", model] if model else [])
    t0 = time.perf_counter()
    if not (REUSE and (res / "all" / "summary.json").is_file()):
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
            halves.append(res / f"half_{k + 1}{h}")
            if REUSE and (halves[-1] / "summary.json").is_file():
                continue
            images = res / f"images_{k + 1}{h}"
            images.mkdir(parents=True, exist_ok=True)
            for old in images.iterdir():
                old.unlink()
            for i in part:
                (images / used[i]).symlink_to((DATA / folder / used[i]).resolve())
            _cli("calibrate", "--images", images, *common, "--out", halves[-1], "--force")
        _cli("diff", *halves, "--distance", x["range"], "--out", res / f"diff_cli_{k + 1}", "--force")
        cli = json.loads((res / f"diff_cli_{k + 1}" / "diff.json").read_text())
        _cli("diff", *halves, "--out", res / f"diff_cli_own_{k + 1}", "--force")  # at A's own distance
        own = json.loads((res / f"diff_cli_own_{k + 1}" / "diff.json").read_text())
        rows.append({"split": k + 1, "ratio_tool": x["ratios"][k], "ratio_written": written["ratio"],
                     "mahalanobis_tool": x["mahalanobis_medians"][k],
                     "mahalanobis_written": written["mahalanobis_median"],
                     "ratio_cli": cli["prediction"]["ratio"], "mahalanobis_cli": cli["prediction"]["mahalanobis_median"],
                     "band_cli": cli["prediction"]["band_if_right"]["ratio"],
                     "ratio_vs_maps_cli": cli["prediction"]["ratio_vs_pose_compensated_maps"],
                     "observed_rms_cli": cli["observed_rms_px"], "predicted_rms_cli": cli["prediction"]["predicted_rms_px"],
                     "ratio_cli_own_distance": own["prediction"]["ratio"], "own_distance": own["distance"],
                     "unweighted_cli": unweighted(*halves, x["range"])})
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
    lines += ["", "The same CLI halves with the transform fitted unweighted over the whole grid (as `--cross-validate` did "
              "before): ratio against the first-order prediction, its raw value, and the raw ratio against the two "
              "pose-compensated maps alone (the independent check); then the weighted fit's raw ratio against both.",
              "", "| camera | split | unweighted: ratio | raw | raw vs maps alone | rms observed / predicted px | "
              "weighted: raw | raw vs maps alone | weighted ratio at A's own distance |", "|---|---|---|---|---|---|---|---|---|"]
    for cam in data:
        for r in cam["splits"]:
            u = r["unweighted_cli"]
            lines.append(f"| {cam['label']} | {r['split']} | {u['ratio']:.2f} | {u['ratio_raw']:.2f} | "
                         f"{u['ratio_raw_vs_maps']:.2f} | {u['rms_px']:.2f} / {u['predicted_px']:.2f} | "
                         f"{u['weighted_ratio_raw']:.2f} | {u['weighted_ratio_raw_vs_maps']:.2f} | "
                         f"{r['ratio_cli_own_distance']:.2f} ({r['own_distance']:.4g}) |")
    pooled = [f"- {c['label']}: geometric mean {c['ratio_geometric_mean']:.2f} over {len(c['splits'])} splits, a right "
              f"prediction reads {c['band_if_right']['ratio'][0]:.2f}-{c['band_if_right']['ratio'][1]:.2f} here; "
              f"against the maps alone {c['ratio_vs_maps']:.2f}"
              + ("" if REUSE else f"; {c['seconds']:.0f} s") for c in data]
    text = ("# `dstereo diff` on two halves of the real cameras (experiments/diff_halves_real.py)\n\n"
            + __doc__.split("\n\n")[1] + "\n\n" + "\n".join(lines) + "\n\n" + "\n".join(pooled) + "\n")
    (RESULTS / "diff_halves_real.md").write_text(text)
    (RESULTS / "diff_halves_real.json").write_text(json.dumps(data, indent=1))
    print(text)


if __name__ == "__main__":
    REUSE = "--reuse" in sys.argv
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    n = [int(a.split("=")[1]) for a in sys.argv[1:] if a.startswith("--splits=")]
    main(Path(args[0]) if args else Path("/tmp/dstereo_diff_halves"), n[0] if n else SPLITS)
