"""Frames per second against Dask workers for `dstereo recession` (issue 19).

A rendered recession sequence (`dstereo.jobs.synthetic_recession`, the reduced Plasmatron rig) per size is measured
serially in this process and on local clusters of N workers, side by side in one run (the machine's load is
recorded before and after: on a shared machine the speed-up is only as good as the load was steady). Reported
per size and worker count: the wall time of the frames after the reference (the parallel part; the reference
runs first, here), frames/s over it, the median time of one frame on a worker, the cluster's start-up (in the
wall time), the peak resident memory per worker process, and whether the results equal the serial ones.

    python -m experiments.bench_frames [--sizes 640x480 320x240] [--frames 20] [--workers 1 2] [--repeat 1]
        [--out experiments/results/bench_frames.md]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def measure(folder: Path, workers: int, grid: float) -> dict:
    from dstereo.runtime.tasks import FrameRunner
    from dstereo.runtime.tasks import _peak_rss_mb
    from dstereo.io.calib_files import read_stereo_calibration
    from dstereo.recession import RecessionConfig
    from dstereo.io.sequence_files import discover
    from dstereo.jobs.recession import run_recession
    from dstereo.stereo.reconstruct import ReconstructionConfig

    frames = discover(folder)
    calib = read_stereo_calibration(folder / "stereo.yml")
    runner = FrameRunner(workers)
    marks = {}

    def progress(stage, done, total):  # the reference is frame 0 here: the parallel part starts after it
        marks.setdefault(done, time.perf_counter())

    t0 = time.perf_counter()
    result = run_recession(frames, calib, RecessionConfig(grid_mm=grid), ReconstructionConfig(), progress=progress,
                           runner=runner)
    end = time.perf_counter()
    mapped = len(frames) - 1
    wall = end - marks[1]
    run = runner.describe()
    return {"workers": workers, "frames": len(frames), "total_s": end - t0, "reference_s": marks[1] - t0,
            "mapped_wall_s": wall, "frames_per_s": mapped / wall,
            "seconds_per_frame_median": run["seconds_per_frame_median"],
            "cpu_seconds_per_frame_median": run["cpu_seconds_per_frame_median"],
            "worker_peak_rss_mb": run["worker_peak_rss_mb"],
            "this_process_peak_rss_mb": _peak_rss_mb(),
            "heights": result.heights, "recession_stagnation": [f.recession.value for f in result.frames]}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["640x480", "320x240"])
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--workers", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--repeat", type=int, default=1, help="rounds of all worker counts, alternated (the load of "
                        "a shared machine changes between runs)")
    parser.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "bench_frames.md")
    args = parser.parse_args(argv)
    from dstereo.jobs.synthetic_recession import write_synthetic_sequence

    rows, loads = [], {"start": load()}
    with tempfile.TemporaryDirectory(prefix="bench_frames_") as tmp:
        for text in args.sizes:
            size = tuple(int(v) for v in text.split("x"))
            folder = Path(tmp) / f"seq_{text}"
            truth = write_synthetic_sequence(folder, n_frames=args.frames, duration_s=40.0, total_mm=2.0,
                                             image_size=size)
            grid = 0.5 if size[0] >= 640 else 1.0
            serial = None
            for rnd, w in ((rnd, w) for rnd in range(args.repeat) for w in args.workers):
                loads[f"{text} round {rnd + 1} w={w} before"] = load()
                row = measure(folder, w, grid)
                row["size"], row["round"] = text, rnd + 1
                rms = np.sqrt(np.nanmean((np.array(row["recession_stagnation"])
                                          - np.array(truth["recession_stagnation_mm"])) ** 2))
                row["stagnation_rms_mm"] = float(rms)
                heights = row.pop("heights")
                row.pop("recession_stagnation")
                if serial is None:
                    serial, row["equal_to_first"] = heights, True
                else:
                    row["equal_to_first"] = bool(np.array_equal(heights, serial, equal_nan=True))
                rows.append(row)
                print(json.dumps(row), flush=True)
        loads["end"] = load()
    write_report(args.out, rows, loads, os.cpu_count())


def write_report(path: Path, rows: list[dict], loads: dict, cores: int) -> None:
    lines = ["# Frames in parallel: `dstereo recession` frames/s against Dask workers (issue 19)", "",
             f"Rendered sequences (reduced Plasmatron rig, {rows[0]['frames']} frames, 0 -> 2 mm), measured side by "
             f"side in one run of `python -m experiments.bench_frames` on this machine ({cores} cores, shared with "
             "other jobs: load averages 1/5/15 min below). The reference frame (frame 0, with compilation) runs "
             "first in the calling process; *mapped* is the rest, on the workers (wall time includes starting the "
             "local cluster and each worker's first-frame start-up).", "",
             "| size | round | workers | mapped frames/s | speed-up | median s/frame on a worker | median CPU s/frame "
             "| steady frames/s | steady speed-up | mapped wall s | reference s | peak RSS per worker MB "
             "| stagnation RMS mm | same as serial |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    base, steady_base, cpu_base, ratios = {}, {}, {}, {}
    for r in rows:  # speed-ups against the serial run of the same round
        key = (r["size"], r.get("round", 1))
        steady = r["workers"] / r["seconds_per_frame_median"]
        if r["workers"] == 1:
            base[key], steady_base[key], cpu_base[key] = r["frames_per_s"], steady, r["cpu_seconds_per_frame_median"]
        base.setdefault(key, r["frames_per_s"])
        steady_base.setdefault(key, steady)
        cpu_base.setdefault(key, r["cpu_seconds_per_frame_median"])
        if r["workers"] > 1:
            ratios.setdefault((r["size"], r["workers"]), []).append(
                (r["frames_per_s"] / base[key], steady / steady_base[key],
                 r["workers"] * cpu_base[key] / r["cpu_seconds_per_frame_median"]))
        rss = ", ".join(f"{v:.0f}" for v in r["worker_peak_rss_mb"].values())
        lines.append(f"| {r['size']} | {key[1]} | {r['workers']} | {r['frames_per_s']:.2f} | "
                     f"{r['frames_per_s'] / base[key]:.2f}x | {r['seconds_per_frame_median']:.2f} | "
                     f"{r['cpu_seconds_per_frame_median']:.2f} | {steady:.2f} | {steady / steady_base[key]:.2f}x | "
                     f"{r['mapped_wall_s']:.1f} | {r['reference_s']:.1f} | {rss} | {r['stagnation_rms_mm']:.4f} | "
                     f"{'yes' if r['equal_to_first'] else 'NO'} |")
    for (size, workers), got in ratios.items():
        whole, steady, cpu = (float(np.median([g[i] for g in got])) for i in range(3))
        lines += ["", f"{size}, {workers} workers, median over {len(got)} round(s) against the serial run of the same "
                      f"round: {whole:.2f}x over the mapped run, {steady:.2f}x steady; from the CPU times, "
                      f"{workers} x serial CPU per frame / a worker's CPU per frame = {cpu:.2f}x (the steady rate "
                      f"{workers} workers would reach with a core each to themselves)."]
    lines += ["", "Load averages (1, 5, 15 min): " + "; ".join(f"{k}: {v}" for k, v in loads.items()), "",
              "*steady*: workers / median time of a frame on a worker (the workers ran concurrently, so it holds "
              "the contention between them), the rate once the cluster is up and every worker has done its first "
              "frame; *mapped* includes that start-up. *CPU*: the CPU time (user + system) of the process during a "
              "frame, median (less sensitive to the other jobs' load than the wall time). "
              "Serial (workers 1) runs in the calling process, whose peak RSS is the serial figure. *same as "
              "serial*: every height map equal bit for bit.", ""]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines))
    path.with_suffix(".json").write_text(json.dumps({"rows": rows, "loads": loads, "cores": cores}, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
