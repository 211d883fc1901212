"""Subset blocks on a Dask cluster (issue 33): the same files as a serial run, the rate per worker, a stopped run resumed.

One camera, rig640's 25 left images, m = 20 (`--per-set`), whole `dstereo calibrate` runs in new processes
(DSTEREO_SERVE=0, experiments/_profiled_cli.py for the stage times), one compilation cache warmed first:
  - serial, pinned to one core (`taskset -c 0`, DSTEREO_THREADS=1): the subsets stage's time, subsets/s;
  - `--workers 2` (a local cluster of two one-core processes): the same, per worker; the cluster's start and each
    worker's first compile are in the stage's time (reported apart: the stage minus its blocks' own times is not
    measured here, so the per-worker rate is a lower bound);
  - a run stopped (SIGINT) once OUT.partial holds a few blocks, then `--resume`: its files against the serial run's.
subsets.csv and camera.yml are compared byte for byte. `uptime` before and after.

`python -m experiments.bench_dask_subsets [--subsets 30000]`; writes experiments/results/bench_dask_subsets.md/.json.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "rig640"
DSTEREO = [sys.executable, "-m", "experiments._profiled_cli"]


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def run(cmd, env, prefix=()) -> dict:
    t0 = time.perf_counter()
    done = subprocess.run([*prefix, *cmd], capture_output=True, text=True, env=env, cwd=ROOT)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"failed: {' '.join(cmd)}\n{done.stderr[-3000:]}")
    prof = json.loads(next(ln for ln in done.stderr.splitlines() if ln.startswith("PROFILE "))[8:])["totals"]
    return {"wall_s": wall, "subsets_s": prof.get("subsets", float("nan")), "total_s": prof.get("total_s")}


def same(a: Path, b: Path) -> dict:
    return {name: (a / name).read_bytes() == (b / name).read_bytes() for name in ("subsets.csv", "camera.yml")}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--subsets", type=int, default=30000)
    ap.add_argument("--per-set", type=int, default=20)
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="dstereo-dask-"))
    images = work / "images"
    images.mkdir()
    for p in sorted(DATA.glob("left*.jpg")):
        (images / p.name).symlink_to(p)
    env = dict(os.environ, DSTEREO_SERVE="0", DSTEREO_PREBUILD="0", DSTEREO_JAX_CACHE=str(work / "jax"))
    cmd = lambda out, *extra: [*DSTEREO, "calibrate", "--images", str(images), "--pattern", "9x6", "--square", "10",  # noqa: E731
                               "--per-set", str(args.per_set), "--max-subsets", str(args.subsets), "--out",
                               str(work / out), "--force", "-q", *extra]
    load = [f"before: {uptime()}"]
    run(cmd("warm"), env)  # the compilation cache (the serial programs)
    serial = run(cmd("serial"), dict(env, DSTEREO_THREADS="1"), prefix=("taskset", "-c", "0"))
    dask = run(cmd("dask", "--workers", "2"), env)
    dask_again = run(cmd("dask2", "--workers", "2"), env)  # the workers' compiles now in the persistent cache
    # stopped once a few blocks are kept, then resumed
    # SIGINT as a terminal's Ctrl-C sends it: its default action restored in the child (a process started in the
    # background by a shell inherits it ignored)
    proc = subprocess.Popen(cmd("stopped"), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env, cwd=ROOT,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.default_int_handler))
    partial = work / "stopped.partial"
    t0 = time.perf_counter()
    while proc.poll() is None and time.perf_counter() - t0 < 1800:
        if len(list(partial.glob("*/frames/*.json"))) >= 2:
            proc.send_signal(signal.SIGINT)
            break
        time.sleep(0.2)
    code = proc.wait()
    kept = len(list(partial.glob("*/frames/*.json")))
    if not partial.exists():
        raise SystemExit(f"the stopped run ended (exit {code}) without kept blocks: nothing to resume")
    resumed = run(cmd("stopped", "--resume"), env)
    load.append(f"after: {uptime()}")
    n = args.subsets
    rate = lambda r, workers=1: n / r["subsets_s"] / workers  # noqa: E731
    result = {"load": load, "subsets": n, "per_set": args.per_set, "serial_one_core": serial, "dask_2": dask,
              "dask_2_again": dask_again, "stopped_exit_code": code, "blocks_kept_when_stopped": kept,
              "resumed": resumed, "dask_files_equal_serial": same(work / "serial", work / "dask"),
              "resumed_files_equal_serial": same(work / "serial", work / "stopped"),
              "partial_removed": not partial.exists()}
    lines = ["# Subset blocks on a Dask cluster (`python -m experiments.bench_dask_subsets`)", "",
             f"Machine: {os.cpu_count()} cores, shared; load {load[0]}; {load[1]}. rig640 left, 25 views, m = "
             f"{args.per_set}, {n} subsets; whole runs in new processes.", "",
             "| run | subsets stage s | subsets/s | per worker | whole run s |", "|---|---|---|---|---|",
             f"| serial, one core | {serial['subsets_s']:.1f} | {rate(serial):.0f} | {rate(serial):.0f} | "
             f"{serial['wall_s']:.1f} |",
             f"| --workers 2 (cluster start and the workers' first compiles included) | {dask['subsets_s']:.1f} | "
             f"{rate(dask):.0f} | {rate(dask, 2):.0f} ({rate(dask, 2) / rate(serial):.2f}x serial) | "
             f"{dask['wall_s']:.1f} |",
             f"| --workers 2, again (compiles fetched) | {dask_again['subsets_s']:.1f} | {rate(dask_again):.0f} | "
             f"{rate(dask_again, 2):.0f} ({rate(dask_again, 2) / rate(serial):.2f}x serial) | "
             f"{dask_again['wall_s']:.1f} |", "",
             f"Files equal to the serial run's, byte for byte: --workers 2 {result['dask_files_equal_serial']}; "
             f"stopped (SIGINT, exit {code}, {kept} block(s) kept) then --resume {result['resumed_files_equal_serial']}"
             f" (resumed run {resumed['wall_s']:.1f} s, subsets stage {resumed['subsets_s']:.1f} s); OUT.partial "
             f"removed after: {result['partial_removed']}."]
    text = "\n".join(lines) + "\n"
    print(text)
    out = ROOT / "experiments" / "results" / "bench_dask_subsets.md"
    out.write_text(text)
    out.with_suffix(".json").write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
