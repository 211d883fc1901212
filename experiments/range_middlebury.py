"""Middlebury 2014 (quarter size) with no flags vs the previous defaults vs plain OpenCV SGBM given the file's
ndisp (issue 14), and the same scenes upscaled 2x with ndisp/vmin/vmax removed from calib.txt (the range must
then come from the pair itself).

bad-2.0: % of the non-occluded pixels with ground truth whose disparity is off by more than 2 px, a missing
estimate counted as bad (Middlebury's "all" density convention); `valid` counts only pixels with an estimate.
At 2x the threshold is 4 px (the same error in the original pixels).

- dstereo, no flags: `reconstruct_calibrated` with `ReconstructionConfig()`;
- previous defaults: the code before issue 14 (commit d39f7a9, `ReconstructionConfig()`: search 0..63 px, no
  border padding) run from a checkout of it given by --old-tree (a `git worktree add --detach DIR d39f7a9`);
- plain OpenCV: `cv2.StereoSGBM_create(0, ceil16(ndisp), blockSize=5, P1=8*25, P2=32*25, disp12MaxDiff=1,
  uniquenessRatio=10, speckleWindowSize=100, speckleRange=2)` on the grey pair (OpenCV's stereo_match sample).

    python -m experiments.range_middlebury --old-tree /tmp/range_old [--out experiments/results/range_middlebury.md]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from dstereo.io.calib_files import read_middlebury_calib, read_pfm
from dstereo.stereo.reconstruct import ReconstructionConfig, reconstruct_calibrated
from dstereo.io.images import read_image

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "middlebury2014q"
SCENES = ("Adirondack", "Motorcycle", "Piano", "Pipes", "Teddy")


def ceil16(n: float) -> int:
    return max(16, 16 * int(np.ceil(n / 16)))


def bad(d: np.ndarray, gt: np.ndarray, nocc: np.ndarray, threshold: float) -> tuple[float, float, float]:
    """(bad all %, bad of valid %, density %)."""
    est = nocc & np.isfinite(d)
    err = np.abs(d - gt)
    n_bad = np.sum(err[est] > threshold)
    return (float(100 * (n_bad + np.sum(nocc & ~est)) / nocc.sum()), float(100 * n_bad / max(est.sum(), 1)),
            float(100 * est.sum() / nocc.sum()))


def plain_opencv(left, right, ndisp: float) -> np.ndarray:
    import cv2

    grey = [cv2.cvtColor(x, cv2.COLOR_BGR2GRAY) for x in (left, right)]
    sgbm = cv2.StereoSGBM_create(0, ceil16(ndisp), 5, P1=8 * 25, P2=32 * 25, disp12MaxDiff=1, uniquenessRatio=10,
                                 speckleWindowSize=100, speckleRange=2)
    raw = sgbm.compute(*grey)
    return np.where(raw >= 0, raw / 16.0, np.nan)


def upscaled(scene: Path, tmp: Path, factor: int = 2) -> Path:
    """The scene resized by `factor` (cv2.resize, cubic), calib.txt scaled and stripped of ndisp/vmin/vmax,
    ground truth disparities multiplied by `factor`."""
    import cv2

    from dstereo.io.calib_files import write_pfm

    out = tmp / f"{scene.name}_x{factor}"
    out.mkdir()
    for name in ("im0.png", "im1.png"):
        img = cv2.imread(str(scene / name))
        cv2.imwrite(str(out / name), cv2.resize(img, None, fx=factor, fy=factor, interpolation=cv2.INTER_CUBIC))
    mask = cv2.imread(str(scene / "mask0nocc.png"), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(out / "mask0nocc.png"), cv2.resize(mask, None, fx=factor, fy=factor,
                                                       interpolation=cv2.INTER_NEAREST))
    gt = read_pfm(scene / "disp0GT.pfm")
    write_pfm(out / "disp0GT.pfm", factor * cv2.resize(gt, None, fx=factor, fy=factor,
                                                       interpolation=cv2.INTER_NEAREST))
    calib = read_middlebury_calib(scene / "calib.txt")
    lines = []
    for cam, K in (("cam0", calib.K1), ("cam1", calib.K2)):
        # resize maps pixel centre x to factor x + (factor - 1) / 2
        f, cx, cy = factor * K[0, 0], factor * K[0, 2] + (factor - 1) / 2, factor * K[1, 2] + (factor - 1) / 2
        lines.append(f"{cam}=[{f:.4f} 0 {cx:.4f}; 0 {f:.4f} {cy:.4f}; 0 0 1]")
    e = calib.extras
    lines += [f"doffs={factor * e['doffs']:.4f}", f"baseline={e['baseline']}", f"width={factor * int(e['width'])}",
              f"height={factor * int(e['height'])}"]
    (out / "calib.txt").write_text("\n".join(lines) + "\n")
    return out


def old_disparity(scene: Path, old_tree: Path) -> np.ndarray:
    """The previous code's default disparity of a scene (run in a subprocess from that checkout)."""
    import os
    import subprocess
    import sys

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "d.npy"
        subprocess.run([sys.executable, __file__, "--old-tree", str(old_tree), "--old-disparity", str(scene), str(out)],
                       check=True,
                       env=os.environ | {"PYTHONPATH": str(old_tree)})
        return np.load(out)


def score(scene: Path, old_tree: Path, factor: int = 1) -> dict:
    import cv2

    calib = read_middlebury_calib(scene / "calib.txt")
    left, right = read_image(scene / "im0.png"), read_image(scene / "im1.png")
    gt = read_pfm(scene / "disp0GT.pfm").astype(np.float64)
    nocc = (cv2.imread(str(scene / "mask0nocc.png"), cv2.IMREAD_GRAYSCALE) == 255) & np.isfinite(gt)
    thr = 2.0 * factor
    gt_lo, gt_hi = np.percentile(gt[np.isfinite(gt)], [0, 100])
    row = {"scene": scene.name, "gt_range": f"{gt_lo:.0f}..{gt_hi:.0f}"}
    new = reconstruct_calibrated(calib, left, right, ReconstructionConfig(uncertainty=False), scene.name)
    s = new.summary["search_range"]
    row["new"] = bad(new.disparity, gt, nocc, thr)
    row["new_range"] = f"{s['min_disparity']}..{s['max_disparity']} ({s['source']}, widened {s['widened']})"
    row["new_warnings"] = len(new.warnings)
    row["old"] = bad(old_disparity(scene, old_tree), gt, nocc, thr)
    ndisp = calib.extras.get("ndisp", gt_hi + 1)
    row["opencv"] = bad(plain_opencv(left, right, ndisp), gt, nocc, thr)
    return row


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results" / "range_middlebury.md"))
    ap.add_argument("--old-tree", type=Path, required=True)
    ap.add_argument("--old-disparity", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.old_disparity:
        scene = Path(args.old_disparity[0])
        r = reconstruct_calibrated(read_middlebury_calib(scene / "calib.txt"), read_image(scene / "im0.png"),
                                   read_image(scene / "im1.png"), ReconstructionConfig(uncertainty=False))
        np.save(args.old_disparity[1], r.disparity)
        return
    rows = [score(DATA / s, args.old_tree) for s in SCENES]
    with tempfile.TemporaryDirectory() as tmp:
        rows += [score(upscaled(DATA / s, Path(tmp)), args.old_tree, factor=2) for s in SCENES]
    lines = ["# Middlebury 2014q: search range from the data (issue 14)", "",
             "Generated by `python -m experiments.range_middlebury` (see its docstring for the three matchers).",
             "bad-2.0 all (missing = bad) / of valid estimates, %; density %. `_x2`: upscaled 2x, calib.txt without "
             "ndisp/vmin/vmax, threshold 4 px; plain OpenCV there is given ndisp = max GT + 1.", "",
             "| scene | GT disparities | dstereo no flags: range | bad-2 all / valid / density | previous defaults "
             "(before issue 14) | plain OpenCV, ndisp |", "|---|---|---|---|---|---|"]
    for r in rows:
        f = lambda t: f"{t[0]:.1f} / {t[1]:.1f} / {t[2]:.0f}"  # noqa: E731
        lines.append(f"| {r['scene']} | {r['gt_range']} | {r['new_range']} | {f(r['new'])} | {f(r['old'])} | "
                     f"{f(r['opencv'])} |")
    text = "\n".join(lines) + "\n"
    Path(args.out).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
