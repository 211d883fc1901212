"""A whole `dstereo calibrate` run of a million subsets on real images: its time and peak memory.

../shared/data/rig640's first 23 left images, m = 11 (C(23, 11) = 1,352,078 subsets, a random sample of 1e6 of
them; m < n/2, so each subset's own frames are gathered, the cheaper plan per subset),
default steps and results folder with every figure, in a new process. Peak memory: the kernel's high-water mark of
the calibrating process (VmHWM, read from /proc while it runs and at its end with getrusage of the child), and
separately the figure workers' (spawned processes, ~100 MB each); the resident memory of the main process is
also sampled every 5 s, so a growth with C would show. Before it the printed estimate, after it the timings line.

    python -m experiments.huge_run_1e6 [--subsets 1000000] [--images 23] [--per-set 11]

writes experiments/results/huge_run_1e6.md.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "rig640"


def _status(pid: int, field: str) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])  # kB
    except (OSError, ValueError):
        return None
    return None


def _children(pid: int) -> list[int]:
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--subsets", type=int, default=1_000_000)
    ap.add_argument("--images", type=int, default=23)
    ap.add_argument("--per-set", type=int, default=11)
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="dstereo-1e6-"))
    images = work / "images"
    images.mkdir()
    for p in sorted(DATA.glob("left*.jpg"))[:args.images]:
        (images / p.name).symlink_to(p)
    cmd = [str(Path(sys.executable).with_name("dstereo")), "calibrate", "--images", str(images), "--pattern", "9x6",
           "--per-set", str(args.per_set), "--max-subsets", str(args.subsets), "--out", str(work / "out"), "--force"]
    load = [subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()]
    samples, worker_peak, stop = [], {}, threading.Event()
    t0 = time.perf_counter()
    # in its own process (never handed to a running `dstereo serve`, nor starting one): its memory is measured
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "DSTEREO_SERVE": "0"})

    def watch():
        while not stop.is_set():
            rss, hwm = _status(proc.pid, "VmRSS"), _status(proc.pid, "VmHWM")
            if rss is not None:
                samples.append((time.perf_counter() - t0, rss, hwm))
            for child in _children(proc.pid):
                peak = _status(child, "VmHWM")
                if peak is not None:
                    worker_peak[child] = max(worker_peak.get(child, 0), peak)
            stop.wait(5.0)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    output = proc.stdout.read()
    proc.wait()
    wall = time.perf_counter() - t0
    stop.set()
    watcher.join()
    child_peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss  # kB: the largest child (the CLI)
    load.append(subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())
    if proc.returncode != 0:
        raise SystemExit(f"failed ({proc.returncode}):\n{output[-3000:]}")
    lines = [ln for ln in output.splitlines() if ln.startswith(("subsets:", "timings:", "dstereo: warning: subsets"))
             and " ETA " not in ln]  # the progress lines (not a terminal: one per update) left out
    csv = work / "out" / "subsets.csv"
    rows = sum(1 for _ in csv.open()) - 1 if csv.exists() else None
    rss_text = ", ".join(f"{t:.0f} s {r / 1024:.0f} MB" for t, r, _ in samples[:: max(1, len(samples) // 12)])
    text = "\n".join([
        "# A million subsets, whole run (`python -m experiments.huge_run_1e6`)", "",
        f"rig640 left, {len(list(images.iterdir()))} real images, m = {args.per_set}, {args.subsets} subsets sampled, "
        "default steps, results folder and figures; new process.", "",
        f"Machine: {os.cpu_count()} cores, shared; load before: {load[0]}; after: {load[1]}.", "",
        "| what | measured |", "|---|---|",
        f"| wall time, whole process | {wall:.0f} s ({wall / 60:.1f} min) |",
        f"| peak resident memory, calibrating process (getrusage of the child, VmHWM) | {child_peak / 1024:.0f} MB |",
        f"| peak resident memory, each figure worker | {', '.join(f'{v / 1024:.0f} MB' for v in worker_peak.values())} |",
        f"| all processes together, at most | {(child_peak + sum(worker_peak.values())) / 1024:.0f} MB |",
        f"| rows in subsets.csv | {rows} |", "",
        f"Resident memory of the calibrating process over the run (every 5 s, thinned): {rss_text}.", "",
        "The command's own lines:", "", "```", *lines, "```", ""])
    out = ROOT / "experiments" / "results" / "huge_run_1e6.md"
    out.write_text(text)
    print(text)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
