"""Issue 28's stress run: the subset solver on random problem sizes must end, every time.

Each trial draws a problem (5-60 views, a 4x3-12x9 board, a lens model of every kind, 1 or 2 threads), solves the
full set, then its held-out folds (as `--model auto` does, the case that hung) and a block of random subsets (as
`--subsets` does), in a child process of its own with the solver's own watchdog off (DSTEREO_WATCHDOG=0): the
experiment's time-out, not the library's, decides whether a trial hung. Corners come from the odd wide-angle lens
(dstereo/synth/odd_lens.py) projected directly, not rendered: what is stressed is the compiled solver's
concurrency, not corner detection. A trial ends as "ended" (with its seconds), "failed" (an exception: its last
line is kept) or "timed out" (killed at TIMEOUT_S; its CPU time tells a slow trial from a hung one).

    .venv/bin/python -m experiments.stress_subsets [--trials 200] [--seed 0]

Writes experiments/results/stress_subsets.json (every trial) and prints the tally.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results" / "stress_subsets.json"
TIMEOUT_S = 600  # the slowest healthy trial (60 views, splined, compile included) took well under this
MODELS = ("none", "k1k2", "k1k2p1p2", "default", "rational", "fisheye", "splined")

CHILD = textwrap.dedent("""
    import json, sys, time
    import numpy as np
    import jax
    jax.config.update("jax_enable_x64", True)
    from dstereo.synth.odd_lens import OddLens, board_points, views
    from dstereo.calib.model_choice import fold_plan
    from dstereo.calib.mono import calibrate_full, solve_subsets
    from dstereo.calib.subsets import plan_subsets
    from dstereo.models.distortion import PRESETS

    t = json.loads(sys.argv[1])
    lens = OddLens(f=t["f"], image_size=(t["w"], t["h"]), wave_px=t["wave"])
    obj = board_points(t["cols"], t["rows"], 1.0)
    obs = views(lens, obj, t["views"], seed=t["seed"], noise_px=0.15)
    t0 = time.perf_counter()
    full = calibrate_full(obj, obs, (t["w"], t["h"]), free=PRESETS[t["model"]])
    folds, _ = fold_plan(len(obs))
    a = solve_subsets(obj, obs, folds, full, n_threads=t["threads"])
    per_set = max(3, min(len(obs) - 1, int(round(0.6 * len(obs)))))
    b = solve_subsets(obj, obs, plan_subsets(len(obs), per_set, cap=200, seed=t["seed"]), full,
                      n_threads=t["threads"])
    print(json.dumps({"seconds": time.perf_counter() - t0, "folds": len(folds), "subsets": len(b.values),
                      "finite": bool(np.all(np.isfinite(a.values)) and np.all(np.isfinite(b.values)))}))
""")


def draw(rng: np.random.Generator, i: int) -> dict:
    cols = int(rng.integers(4, 13))
    rows = int(rng.integers(3, min(cols, 9) + 1))
    w = int(rng.choice([640, 1280, 1920]))
    return {"trial": i, "views": int(rng.integers(5, 61)), "cols": cols, "rows": rows, "model": MODELS[i % len(MODELS)],
            "threads": int(rng.integers(1, 3)), "w": w, "h": w * 3 // 4, "f": float(w * rng.uniform(0.3, 0.9)),
            "wave": float(rng.uniform(0.0, 2.0)), "seed": int(rng.integers(1 << 30))}


def _children_cpu() -> float:
    use = resource.getrusage(resource.RUSAGE_CHILDREN)
    return use.ru_utime + use.ru_stime


def run_trial(t: dict) -> dict:
    """One trial in a child process; `cpu_s` its CPU time: a trial killed at the time-out that used about as much
    CPU as wall time was slow (a splined lens on a tiny board), one near 0 % CPU was hung."""
    env = {**os.environ, "DSTEREO_WATCHDOG": "0", "DSTEREO_THREADS": str(t["threads"])}
    t0, c0 = time.perf_counter(), _children_cpu()
    try:
        done = subprocess.run([sys.executable, "-c", CHILD, json.dumps(t)], env=env, capture_output=True, text=True,
                              timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        wall = time.perf_counter() - t0
        return {**t, "outcome": "timed out", "wall_s": wall, "cpu_s": _children_cpu() - c0}
    wall = time.perf_counter() - t0
    t = {**t, "cpu_s": _children_cpu() - c0}
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["(no output)"])[-1]
        return {**t, "outcome": "failed", "wall_s": wall, "error": last, "code": done.returncode}
    return {**t, "outcome": "ended", "wall_s": wall, **json.loads(done.stdout.strip().splitlines()[-1])}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    trials = [draw(rng, i) for i in range(args.trials)]
    out = []
    for t in trials:
        r = run_trial(t)
        out.append(r)
        print(f"{t['trial']:3d} {t['model']:9s} {t['views']:2d} views {t['cols']}x{t['rows']} {t['threads']} thr: "
              f"{r['outcome']} {r['wall_s']:.1f} s {r.get('error', '')}", flush=True)
        RESULTS.parent.mkdir(exist_ok=True)
        RESULTS.write_text(json.dumps({"cpu_count": os.cpu_count(), "load_at_end": os.getloadavg()[0],
                                       "trials": out}, indent=1))
    tally = {k: sum(r["outcome"] == k for r in out) for k in ("ended", "failed", "timed out")}
    walls = [r["wall_s"] for r in out if r["outcome"] == "ended"]
    print(f"{len(out)} trials: {tally}; wall per ended trial median {np.median(walls):.1f} s, max {max(walls):.1f} s"
          if walls else f"{len(out)} trials: {tally}")


if __name__ == "__main__":
    main()
