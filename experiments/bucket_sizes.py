"""What a shape bucket costs: the solver's compile time against the time of its padded work (issue 33).

For each view count V (one camera, and a stereo rig solved jointly, both with the board's sag, the defaults), in a
new process with no compilation cache (DSTEREO_JAX_CACHE=0) and exact shapes (DSTEREO_SHAPE_BUCKETS=0):
  - the full-set solve in its own program (one problem, `rows=1`, as a plain calibration runs it): first call
    (trace + compile + solve) and the best of the next calls (solve only);
  - a chunk of masked subsets (`chunk_rows(V)` problems, each leaving out a fifth of the views, starting at the full
    set's solution, the subsets' program): the same two times, and the time per pass of a problem;
  - the same solves of round(V / PAD) views padded to V (weight 0: `problem.run` with the bucket forced to V), in
    the program just compiled: what padding costs measured directly, against those counts' own exact runs.
Wall and CPU seconds both (the machine is shared: CPU time is the steadier figure of the work); `uptime` before and
after. Then, for candidate bucket lists, the number of buckets between 5 and 60 views (programs to compile ahead)
and the padded work's worst and mean share over every V in 5..60 from the measured per-pass times (a line fitted
through them).

`python -m experiments.bucket_sizes [--views 6,8,12,16,24,32,48,64] [--kinds mono,stereo]`; writes
experiments/results/bucket_sizes.md and .json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "experiments" / "results"
PAD = 1.25  # the padded case: round(V / PAD) views solved at V
REPEAT = 3


def _scene(kind: str, n_views: int, seed: int = 0):
    """(problem, g0 start, poses start (V, 6), obs (V, K, n, 2), shared): exact corners + 0.2 px noise, the start
    perturbed from the truth."""
    from dstereo.calib.problem import Problem, shared_data
    from dstereo.models.distortion import PRESETS

    rng = np.random.default_rng([seed, n_views])
    free = PRESETS["default"]
    if kind == "mono":
        from dstereo.synth import board_views

        cam, poses, obj, corners = board_views.scene(n_views, seed=seed)
        obs = (corners + rng.normal(0, 0.2, corners.shape))[:, None]
        truth = np.r_[np.asarray(cam.k), np.asarray(cam.dist.coeffs)[:5], 0.0, 0.0]
        problem = Problem.of([free], board_warp=True)
        shared = shared_data(obj, np.zeros((1, 4)), np.zeros((1, 8)))
    else:
        from dstereo.synth.rig_corners import rig_corners

        d = rig_corners(n_cameras=2, n_frames=n_views, seed=seed, noise_px=0.2)
        obj, obs, poses = d["obj"], d["obs"], d["poses"]
        rig = d["rig"]
        ext = np.r_[rig.T_cam_ref[1]]
        intr = [np.r_[np.asarray(c.k), np.asarray(c.dist.coeffs)[:5]] for c in rig.cameras]
        truth = np.r_[ext, intr[0], intr[1], 0.0, 0.0]
        problem = Problem.of([free, free], board_warp=True)
        shared = shared_data(obj, np.zeros((2, 4)), np.zeros((2, 8)))
    g0 = truth * (1 + 1e-3 * rng.normal(size=truth.shape)) + 1e-4 * rng.normal(size=truth.shape)
    p0 = np.asarray(poses, float) + np.r_[[1e-3] * 3, [0.5] * 3] * rng.normal(size=np.shape(poses))
    return problem, g0, p0, np.asarray(obs, float), shared


def _timed(fn):
    t, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t, time.process_time() - c


def _case(kind: str, n_views: int, seed: int = 0) -> dict:
    """Times of the full-set solve and of a chunk of subsets of `n_views` views (module docstring)."""
    from dstereo.calib.problem import chunk_rows, run
    from dstereo.solver.lm import LMOptions

    problem, g0, p0, obs, shared = _scene(kind, n_views, seed)
    opts = LMOptions()

    def full():
        return run(problem, opts, g0[None], p0[None], obs[None], np.ones((1, n_views)), np.array([1e-3]), shared,
                   rows=1)

    out, first_w, first_c = _timed(full)
    reps = [_timed(full)[1:] for _ in range(REPEAT)]
    res = {"views": n_views, "full_first_s": first_w, "full_first_cpu_s": first_c,
           "full_s": min(r[0] for r in reps), "full_cpu_s": min(r[1] for r in reps),
           "full_iterations": int(out.iterations[0]), "full_status": int(out.status[0])}
    rows = chunk_rows(n_views, obs.shape[1] * obs.shape[2], problem)
    rng = np.random.default_rng([seed, 1])
    weight = (rng.random((rows, n_views)) > 0.2).astype(float)
    g_sol, p_sol = out.g[0], out.p[0]

    def subsets():
        return run(problem, opts._replace(lambda0=1e-6), np.repeat(g_sol[None], rows, 0),
                   np.repeat(p_sol[None], rows, 0), np.repeat(obs[None], rows, 0), weight, np.full(rows, 1e-6), shared,
                   rows=rows)

    sub, sfirst_w, sfirst_c = _timed(subsets)
    sreps = [_timed(subsets)[1:] for _ in range(REPEAT)]
    passes = int(np.max(sub.iterations)) + 1  # a chunk runs until its slowest problem stops
    res.update({"chunk_rows": rows, "chunk_first_s": sfirst_w, "chunk_first_cpu_s": sfirst_c,
                "chunk_s": min(r[0] for r in sreps), "chunk_cpu_s": min(r[1] for r in sreps),
                "chunk_passes": passes,
                "per_problem_pass_cpu_us": 1e6 * min(r[1] for r in sreps) / (rows * passes),
                "full_pass_cpu_us": 1e6 * res["full_cpu_s"] / (res["full_iterations"] + 1)})
    return res


def _padded(kind: str, bucket: int, seed: int = 0) -> dict:
    """The full-set solve of round(bucket / PAD) views padded to `bucket`, in the program `_case(kind, bucket)` just
    compiled (the bucket forced: `runtime.buckets.views`)."""
    from dstereo.calib.problem import run
    from dstereo.runtime import buckets
    from dstereo.solver.lm import LMOptions

    n_views = max(3, int(round(bucket / PAD)))
    problem, g0, p0, obs, shared = _scene(kind, n_views, seed)
    real_views = buckets.views
    buckets.views = lambda n: bucket if n == n_views else real_views(n)
    try:
        def full():
            return run(problem, LMOptions(), g0[None], p0[None], obs[None], np.ones((1, n_views)), np.array([1e-3]),
                       shared, rows=1)
        out, first_w, _ = _timed(full)
        reps = [_timed(full)[1:] for _ in range(REPEAT)]
    finally:
        buckets.views = real_views
    return {"views": n_views, "bucket": bucket, "first_s": first_w, "full_s": min(r[0] for r in reps),
            "full_cpu_s": min(r[1] for r in reps), "iterations": int(out.iterations[0]),
            "pass_cpu_us": 1e6 * min(r[1] for r in reps) / (int(out.iterations[0]) + 1)}


def _worker(kind: str, n_views: int) -> None:
    res = _case(kind, n_views)
    res["padded"] = _padded(kind, n_views) if n_views >= 6 else None
    print("RESULT " + json.dumps(res), flush=True)


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


CANDIDATES = {
    "powers of 2": (4, 8, 16, 32, 64),
    "x1.5": (4, 6, 9, 14, 21, 32, 48, 72),
    "x1.25": (4, 5, 6, 8, 10, 12, 15, 19, 24, 30, 37, 46, 58, 72),
    "x1.12 (chosen)": None,  # runtime.buckets.VIEW_BUCKETS
    "steps of 4": tuple(range(4, 65, 4)),
}


def _padding_table(curves: dict) -> list[str]:
    """Per candidate list: buckets in 5..60, worst and mean padded share of a subset chunk's and a full solve's
    work over V = 5..60 (per-pass CPU times: a line fitted to the measured counts)."""
    from dstereo.runtime import buckets

    lines = ["| buckets | count in 5-60 views | padded work, worst / mean (subset chunk, per problem-pass) | "
             "padded work, worst / mean (full-set solve, per pass) |", "|---|---|---|---|"]
    for name, sizes in CANDIDATES.items():
        sizes = buckets.VIEW_BUCKETS if sizes is None else sizes
        row = [name, str(len({min(b for b in sizes if b >= v) for v in range(5, 61)}))]
        for key in ("per_problem_pass_cpu_us", "full_pass_cpu_us"):
            parts = []
            for kind, cases in curves.items():
                vs = np.array([c["views"] for c in cases], float)
                ts = np.array([c[key] for c in cases], float)
                # a straight line a + b V through the measured costs (least squares): on a shared machine the points
                # scatter by tens of percent, and interpolating between them would turn that noise into "padding"
                b, a = np.polyfit(vs, ts, 1)
                cost = lambda v: a + b * v  # noqa: E731
                shares = [cost(min(b for b in sizes if b >= v)) / cost(v) - 1 for v in range(5, 61)]
                parts.append(f"{kind} {100 * max(shares):.0f} / {100 * np.mean(shares):.0f} %")
            row.append(", ".join(parts))
        lines.append("| " + " | ".join(row) + " |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--views", default="6,8,12,16,24,32,48,64")
    ap.add_argument("--kinds", default="mono,stereo")
    ap.add_argument("--worker", nargs=2, metavar=("KIND", "VIEWS"))
    ap.add_argument("--report-only", action="store_true", help="rewrite the report from the saved .json")
    args = ap.parse_args()
    if args.worker:
        _worker(args.worker[0], int(args.worker[1]))
        return
    if args.report_only:
        saved = json.loads((OUT / "bucket_sizes.json").read_text())
        report(saved["curves"], saved["load"])
        return
    env = dict(os.environ, DSTEREO_JAX_CACHE="0", DSTEREO_AOT="0", DSTEREO_SHAPE_BUCKETS="0")
    load = [f"before: {uptime()}"]
    curves: dict = {}
    for kind in args.kinds.split(","):
        for v in (int(s) for s in args.views.split(",")):
            done = subprocess.run([sys.executable, "-m", "experiments.bucket_sizes", "--worker", kind, str(v)],
                                  capture_output=True, text=True, env=env, cwd=ROOT)
            line = next((ln for ln in done.stdout.splitlines() if ln.startswith("RESULT ")), None)
            if line is None:
                raise SystemExit(f"{kind} {v}: failed\n{done.stderr[-3000:]}")
            res = json.loads(line[7:])
            curves.setdefault(kind, []).append(res)
            print(kind, json.dumps(res), flush=True)
    load.append(f"after: {uptime()}")
    report(curves, load)


def report(curves: dict, load: list[str]) -> None:
    lines = ["# Shape buckets: compile time against padded work", "",
             "`python -m experiments.bucket_sizes` (module docstring); " + "; ".join(load), "",
             "| kind | views | full solve: first call s (CPU s: the compile) | full solve s (CPU s) | iterations | "
             "chunk rows | chunk: first call s (CPU s) | chunk s (CPU s) | passes | per problem-pass CPU us | "
             "padded: views -> bucket, "
             "s (CPU s), per-pass CPU us vs exact |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for kind, cases in curves.items():
        for c in cases:
            p = c["padded"]
            exact = next((e for e in cases if p and e["views"] == p["views"]), None)
            pad_txt = "" if p is None else (
                f"{p['views']} -> {p['bucket']}: {p['full_s']:.3f} ({p['full_cpu_s']:.3f}), {p['pass_cpu_us']:.0f} us"
                + (f" vs {exact['full_pass_cpu_us']:.0f} us" if exact else ""))
            lines.append(f"| {kind} | {c['views']} | {c['full_first_s']:.1f} ({c['full_first_cpu_s']:.1f}) | "
                         f"{c['full_s']:.3f} ({c['full_cpu_s']:.3f}) | {c['full_iterations']} | {c['chunk_rows']} | "
                         f"{c['chunk_first_s']:.1f} ({c['chunk_first_cpu_s']:.1f}) | {c['chunk_s']:.3f} "
                         f"({c['chunk_cpu_s']:.3f}) | "
                         f"{c['chunk_passes']} | {c['per_problem_pass_cpu_us']:.0f} | {pad_txt} |")
    lines += ["", *_padding_table(curves), ""]
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "bucket_sizes.md").write_text("\n".join(lines))
    (OUT / "bucket_sizes.json").write_text(json.dumps({"load": load, "curves": curves}, indent=1))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
