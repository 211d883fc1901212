"""A plain calibration of a data set of a new size, served, against mrcal-calibrate-cameras on the same corners
(issue 33's acceptance: "no slower than mrcal").

mrcal is NOT a dependency: Debian's `mrcal` package (apt-get install -y mrcal python3-mrcal) gives the
`mrcal-calibrate-cameras` command timed here; where it is absent this script says so and stops.

On rig640's left camera (one camera, the default lens model, dstereo's defaults):
  1. a private server (its own socket folder and compilation cache, nothing shared with the user's) serves a warm-up
     calibration of W views; its background builder (dstereo/runtime/prebuild.py) is waited for until N's bucket is
     built, as on a user's machine after the first command;
  2. the first served calibration of the new size N is timed (nothing of N's size ran before);
  3. then `repeat` rounds alternate one mrcal-calibrate-cameras run and one served dstereo repeat, so each pair
     sees the same load.
mrcal gets dstereo's own detected corners (corners.npz of the first run, written as mrcal's corners.vnl) so that
neither side's time includes corner detection (dstereo's corners come from its cache on every run here), and its
defaults: LENSMODEL_OPENCV5 (dstereo's default k1 k2 p1 p2 k3), outlier rejection, regularisation, the board's warp.
Both write their results (dstereo: its results folder with figures and report; mrcal: its .cameramodel).

    python -m experiments.bench_vs_mrcal [--views 23] [--warmup 20] [--repeat 3]
writes experiments/results/bench_vs_mrcal.md and .json.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from experiments.bench_new_size import uptime, wait_for_builder

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "rig640"
DSTEREO = [str(Path(sys.executable).parent / "dstereo")]
PATTERN, SQUARE, FOCAL = (9, 6), 10.0, 520.0


def views(work: Path, n: int) -> Path:
    folder = work / f"left{n}"
    folder.mkdir(exist_ok=True)
    for p in sorted(DATA.glob("left*.jpg"))[:n]:
        if not (folder / p.name).exists():
            (folder / p.name).symlink_to(p)
    return folder


def timed(cmd: list[str], env: dict, cwd: Path = ROOT) -> float:
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=cwd)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"failed: {' '.join(cmd)}\n{done.stderr[-3000:]}")
    return wall


def calibrate(folder: Path, out: Path) -> list[str]:
    return [*DSTEREO, "calibrate", "--images", str(folder), "--pattern", f"{PATTERN[0]}x{PATTERN[1]}", "--square",
            str(SQUARE), "--out", str(out), "--force", "-q"]


def write_vnl(results: Path, folder: Path) -> Path:
    """dstereo's corners of the run in `results` as mrcal's corners.vnl (filename x y level; OpenCV's row-major
    corner order is mrcal's, the board's width along the rows)."""
    summary = json.loads((results / "summary.json").read_text())
    with np.load(results / "corners.npz") as c:
        lines = ["# filename x y level"]
        for name in summary["images"]["used"]:
            for x, y in np.asarray(c[name]).reshape(-1, 2):
                lines.append(f"{name} {x:.6f} {y:.6f} 0")
    vnl = folder / "corners.vnl"
    vnl.write_text("\n".join(lines) + "\n")
    return vnl


def mrcal_command(folder: Path, vnl: Path, out: Path) -> list[str]:
    out.mkdir(parents=True, exist_ok=True)  # mrcal writes into an existing folder
    return ["mrcal-calibrate-cameras", "--corners-cache", str(vnl), "--lensmodel", "LENSMODEL_OPENCV5", "--focal",
            str(FOCAL), "--object-spacing", str(SQUARE), "--object-width-n", str(PATTERN[0]), "--object-height-n",
            str(PATTERN[1]), "--outdir", str(out), "left*.jpg"]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--views", type=int, default=23, help="the new size N (views never run before)")
    ap.add_argument("--warmup", type=int, default=20, help="the warm-up's size W (another bucket than N's)")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    if shutil.which("mrcal-calibrate-cameras") is None:
        raise SystemExit("bench_vs_mrcal: mrcal-calibrate-cameras is not installed (apt-get install -y mrcal)")
    from dstereo.runtime.buckets import views as bucket

    work = Path(tempfile.mkdtemp(prefix="dstereo-vs-mrcal-"))
    env = dict(os.environ, DSTEREO_SERVE_DIR=str(work / "serve"), DSTEREO_JAX_CACHE=str(work / "jax"))
    env.pop("DSTEREO_SERVE", None)
    env.pop("DSTEREO_PREBUILD", None)
    load = [f"before: {uptime()}"]
    server = subprocess.Popen([*DSTEREO, "serve"], env=env, cwd=ROOT, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    try:
        out: dict = {"views": args.views, "warmup": args.warmup, "bucket_new": bucket(args.views),
                     "bucket_warmup": bucket(args.warmup)}
        time.sleep(2.0)
        out["warmup_s"] = timed(calibrate(views(work, args.warmup), work / "warm"), env)
        out["builder"] = wait_for_builder(work / "jax", bucket(args.views))
        new = views(work, args.views)
        out["first_served_s"] = timed(calibrate(new, work / "first"), env)
        vnl = write_vnl(work / "first", new)
        out["served_s"], out["mrcal_s"] = [], []
        for k in range(args.repeat):
            out["mrcal_s"].append(timed(mrcal_command(new, vnl, work / f"mrcal{k}"), env, cwd=new))
            out["served_s"].append(timed(calibrate(new, work / f"again{k}"), env))
            print(f"mrcal {out['mrcal_s'][-1]:.2f} s, served {out['served_s'][-1]:.2f} s", flush=True)
        status = subprocess.run([*DSTEREO, "serve", "--status"], env=env, capture_output=True, text=True).stdout
        out["server_status"] = status.strip()
    finally:
        subprocess.run([*DSTEREO, "serve", "--stop"], env=env, capture_output=True)
        server.wait(timeout=60)
        # the private cache's background builder (detached, its own session) would go on for up to an hour
        subprocess.run(["pkill", "-f", f"dstereo.jobs.prebuild {work}"], capture_output=True)
    load.append(f"after: {uptime()}")
    out["load"] = load
    best_mrcal = min(out["mrcal_s"])
    lines = ["# A new size's plain calibration, served, against mrcal-calibrate-cameras (`python -m "
             "experiments.bench_vs_mrcal`)", "",
             f"Machine: {os.cpu_count()} cores, shared; load {load[0]}; {load[1]}. rig640 left, N = {args.views} "
             f"views (bucket {out['bucket_new']}), warm-up W = {args.warmup} (bucket {out['bucket_warmup']}), the "
             f"builder waited for {out['builder']['waited_s']:.0f} s. mrcal {_mrcal_version()} on dstereo's corners, "
             "LENSMODEL_OPENCV5, its defaults.", "",
             "| run | wall s | / mrcal's best |", "|---|---|---|",
             f"| dstereo, first served run of size N | {out['first_served_s']:.2f} | "
             f"{out['first_served_s'] / best_mrcal:.2f}x |"]
    for k, (m, s) in enumerate(zip(out["mrcal_s"], out["served_s"])):
        lines.append(f"| mrcal-calibrate-cameras, round {k + 1} | {m:.2f} | {m / best_mrcal:.2f}x |")
        lines.append(f"| dstereo served repeat, round {k + 1} | {s:.2f} | {s / best_mrcal:.2f}x |")
    lines += ["", f"Server: {out['server_status'].splitlines()[0] if out['server_status'] else '-'}"]
    text = "\n".join(lines) + "\n"
    print(text)
    dest = ROOT / "experiments" / "results" / "bench_vs_mrcal.md"
    dest.write_text(text)
    dest.with_suffix(".json").write_text(json.dumps(out, indent=1) + "\n")


def _mrcal_version() -> str:
    done = subprocess.run(["dpkg-query", "-W", "-f", "${Version}", "mrcal"], capture_output=True, text=True)
    return done.stdout.strip() or "(version unknown)"


if __name__ == "__main__":
    main()
