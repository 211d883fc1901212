"""Issue 28's hang case end to end, as a new user met it: 35 rendered views of a board through a wide-angle
(equidistant, f = 520 px: 176 degrees across the diagonal; the renderer needs every ray under 90 degrees, so not the
f = 380 px of the solver-level test) 1280 x 960 camera, then `dstereo calibrate --pattern 9x6 --square 1 --model
auto` with default threads, in a process of its own (no server). The user's board was 8x6; the renderer draws only
odd x even boards (an unambiguous orientation), so 9x6 here. Before the fix it hung forever at 0 % CPU in 2 of 2
runs (the held-out folds on two threads). Prints the exit code, the wall time and the model chosen; writes
experiments/results/hang_case.md.

    .venv/bin/python -m experiments.hang_case [--runs 2]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent / "results" / "hang_case.md"
TIMEOUT_S = 900


def render(folder: Path, n_views: int = 35) -> None:
    import cv2

    from dstereo.models.camera import Camera
    from dstereo.models.distortion import PRESETS
    from dstereo.synth import Board, board_pose_set, camera_rays, render_board
    from dstereo.synth.scenes import CALIBRATION_OPTIONS

    cam = Camera.create(520.0, 520.0, 639.5, 479.5, (0.0, 0.0, 0.0, 0.0), PRESETS["fisheye"], (1280, 960))
    board = Board((9, 6), 40.0, 40.0)  # the renderer takes only odd x even boards (orientation); the user had 8x6
    poses = board_pose_set([cam], [np.zeros(6)], board, n_views=n_views, seed=3, fill=(0.35, 0.7))
    rays = camera_rays(cam, CALIBRATION_OPTIONS.supersample)
    folder.mkdir(parents=True)
    for i, pose in enumerate(poses):
        image, _ = render_board(cam, pose, board, CALIBRATION_OPTIONS, seed=i, rays=rays)
        cv2.imwrite(str(folder / f"view{i:02d}.png"), image)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--runs", type=int, default=2)
    args = parser.parse_args()
    root = Path(tempfile.mkdtemp(prefix="hang-case-"))
    t0 = time.perf_counter()
    render(root / "images")
    print(f"rendered 35 views in {time.perf_counter() - t0:.0f} s", flush=True)
    rows = []
    env = {k: v for k, v in os.environ.items() if k not in ("DSTEREO_THREADS",)}
    env["DSTEREO_SERVE"] = "0"
    for run in range(args.runs):
        out = root / f"run{run}"
        t0 = time.perf_counter()
        try:
            done = subprocess.run([sys.executable, "-m", "dstereo.cli", "calibrate", "--images", str(root / "images"),
                                   "--pattern", "9x6", "--square", "1", "--model", "auto", "--out", str(out)],
                                  env=env, capture_output=True, text=True, timeout=TIMEOUT_S)
            code, last = done.returncode, (done.stderr.strip().splitlines() or [""])[-1]
        except subprocess.TimeoutExpired:
            code, last = "hung", f"killed after {TIMEOUT_S} s"
        wall = time.perf_counter() - t0
        chosen = json.loads((out / "summary.json").read_text()).get("model_choice", {}).get("chosen") \
            if (out / "summary.json").is_file() else None
        rows.append(f"| {run + 1} | {code} | {wall:.1f} s | {chosen} | {last[:120]} |")
        print(rows[-1], flush=True)
    OUT.parent.mkdir(exist_ok=True)
    OUT.write_text("\n".join([
        "# Issue 28's hang case, end to end", "",
        f"35 rendered views, 9x6 board, equidistant f = 520 px at 1280 x 960; `dstereo calibrate --model auto`, "
        f"default threads ({os.cpu_count()} cores), no server. Load at the end {os.getloadavg()[0]:.1f}.", "",
        "| run | exit | wall | chosen | last line |", "|---|---|---|---|---|", *rows, ""]))


if __name__ == "__main__":
    main()
