"""Issue 14's own case: a converging rig with fx 4700 / 4900 px, 100 mm baseline, 600 mm, a tilted sample, and
`dstereo recession` with no depth flags (issue 14 follow-up).

Renders the domed sample turned `--yaw` deg (side wall in view) with `jobs.synthetic_recession.converging_rig`, runs
the `dstereo recession` CLI with defaults only, and reports the search range it printed, the share of the true
face (grid cells within `head radius - 1.5 mm` of the true stagnation point, in the tool's face coordinates)
that has a height in the reference frame, the axis error, the stagnation point's offset, the stagnation RMS
against the truth, the rate error and whether the truth lies inside the 95 % interval. The issue measured,
before: 36 % of the face dropped (everything behind ~602 mm), the point 2.7-3.7 mm off, rate 1 % off, truth
outside the interval, no range printed.

    python -m experiments.range_converging [--sizes 640x480] [--seeds 0 1] [--yaw 12]
        [--out experiments/results/range_converging.md]
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def one(size, seed: int, yaw: float, tmp: Path) -> dict:
    from dstereo.jobs.synthetic_recession import write_synthetic_sequence

    scale = size[0] / 640.0
    seq = tmp / f"seq_{size[0]}_{seed}"
    truth = write_synthetic_sequence(seq, n_frames=11, image_size=size, seed=seed, yaw_deg=yaw,
                                     focal_px=(4700.0 * scale, 4900.0 * scale))
    out = tmp / f"out_{size[0]}_{seed}"
    grid = "0.5" if size[0] >= 640 else "1"
    cli = str(Path(sys.executable).parent / "dstereo")
    run = subprocess.run([cli, "recession", str(seq), "--calib", str(seq / "stereo.yml"), "--out", str(out),
                          "--grid", grid], capture_output=True, text=True)
    if run.returncode != 0:
        return {"size": f"{size[0]}x{size[1]}", "seed": seed, "error": run.stderr.strip()[-300:]}
    return evaluate(truth, out, run.stdout, run.stderr) | {"size": f"{size[0]}x{size[1]}", "seed": seed}


def evaluate(truth: dict, out: Path, stdout: str, stderr: str) -> dict:
    """Figures of one run from its output folder (summary.json, recession.csv, recession_maps.npz)."""
    s = json.loads((out / "summary.json").read_text())
    axis = np.array(s["sample"]["axis"])
    angle = float(np.degrees(np.arccos(np.clip(axis @ np.array(truth["axis"]), -1, 1))))
    point = np.array(s["sample"]["stagnation_point_mm"])
    true_point = np.array(truth["stagnation_point_mm"])
    with (out / "recession.csv").open() as fh:
        rows = [r for r in csv.DictReader(fh)]
    measured = np.array([float(r["recession_mm"]) if r["recession_mm"] else np.nan for r in rows])
    true = np.array(truth["recession_stagnation_mm"])
    ok = np.isfinite(measured)
    rate, true_rate = s["rate"]["rate"], truth["rate_stagnation_mm_s"]
    return {"range_line": next((line for line in stdout.splitlines() if "disparity search range" in line), "(none)"),
            "face_share": face_share(out, truth, s), "axis_err_deg": angle,
            "axis_sigma_deg": s["sample"]["axis_sigma_deg"], "point_offset_mm": float(np.linalg.norm(point - true_point)),
            "rms_mm": float(np.sqrt(np.mean((measured[ok] - true[ok]) ** 2))),
            "rate_err_pct": 100 * (rate / true_rate - 1),
            "truth_in_ci95": bool(s["rate"]["ci95"][0] <= true_rate <= s["rate"]["ci95"][1]),
            "frames_used": s["frames_used"], "warnings": len(s["warnings"]) + stderr.count("warning")}


def face_share(out: Path, truth: dict, s: dict) -> float:
    """Share of the true face's cells (within head radius - 1.5 mm of the true stagnation point) with a height
    in the reference frame."""
    maps = np.load(out / "recession_maps.npz")
    heights = maps["heights_mm"][int(np.flatnonzero(maps["ok"])[0])]
    uu, vv = np.meshgrid(maps["u_mm"], maps["v_mm"])
    axes = np.array([s["sample"]["e1"], s["sample"]["e2"]])
    du, dv = axes @ (np.array(truth["stagnation_point_mm"]) - np.array(s["sample"]["stagnation_point_mm"]))
    inside = np.hypot(uu - du, vv - dv) <= truth["sample"]["head_radius"] - 1.5
    return float(np.isfinite(heights[inside]).mean())


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", nargs="*", default=["640x480"])
    ap.add_argument("--seeds", nargs="*", type=int, default=[0, 1])
    ap.add_argument("--yaw", type=float, default=12.0)
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results" / "range_converging.md"))
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.sizes:
            w, h = (int(x) for x in size.split("x"))
            for seed in args.seeds:
                rows.append(one((w, h), seed, args.yaw, Path(tmp)))
                print(json.dumps(rows[-1]), flush=True)
    lines = ["# Issue 14's case: converging rig fx 4700 / 4900 px, 100 mm, 600 mm, tilted sample, no depth flags", "",
             f"Generated by `python -m experiments.range_converging` (yaw {args.yaw:g} deg, 11 frames, 2 mm at the "
             "stagnation point over 40 s; `dstereo recession SEQ --calib stereo.yml --out OUT --grid G`, grid 0.5 mm "
             "at 640x480, 1 mm at 320x240, focal lengths scaled with the size). Face share: cells of the true face "
             "(within head radius - 1.5 mm of the true stagnation point) with a height in the reference frame. "
             "The issue measured before: 36 % of the face dropped, point 2.7-3.7 mm off, rate 1 % off, truth "
             "outside the interval, no range printed.", "",
             "| size | seed | printed | face share % | axis error deg (sigma) | point offset mm | RMS mm | rate error % "
             "| truth in 95 % | frames | warnings |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['size']} | {r['seed']} | failed: {r['error']} |")
            continue
        lines.append(f"| {r['size']} | {r['seed']} | {r['range_line']} | {100 * r['face_share']:.1f} | "
                     f"{r['axis_err_deg']:.3f} ({r['axis_sigma_deg']:.3f}) | {r['point_offset_mm']:.2f} | "
                     f"{r['rms_mm']:.4f} | {r['rate_err_pct']:+.2f} | {r['truth_in_ci95']} | {r['frames_used']} | "
                     f"{r['warnings']} |")
    text = "\n".join(lines) + "\n"
    Path(args.out).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
