"""A data set of a new size (issue 33): its first calibration against its repeat, with the shape buckets.

Whole `dstereo calibrate` runs in new processes (DSTEREO_SERVE=0, through experiments/_profiled_cli.py: the same CLI
plus a breakdown), on rig640's images (one camera: the left ones; a stereo rig: the pairs), each case with a
compilation cache of its own, side by side in one run:
  - cold: an empty cache, the new size N first, then again (the repeat);
  - same bucket: an empty cache, a warm-up on another size W1 of N's bucket, then N (nothing to compile);
  - built ahead: an empty cache, a warm-up on a size W2 of another bucket, whose background builder
    (runtime/prebuild.py) is left to finish (its time and CPU time reported), then N;
  - padding's cost on a repeat: N with the cache warm, buckets on and off (DSTEREO_SHAPE_BUCKETS=0) alternately.
Plain calibrations and subset runs (`--per-set`), one camera and a stereo rig. `uptime` before and after; each repeat
alternates the cases it compares, so they see the same load.

`python -m experiments.bench_new_size [--kinds mono,mono-subsets,stereo,stereo-subsets] [--repeat 2]`; writes
experiments/results/bench_new_size.md and .json. `make bench` runs it.
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

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "rig640"
DSTEREO = [sys.executable, "-m", "experiments._profiled_cli"]
NEW, SAME, OTHER = 23, 24, 20  # N (bucket 24), W1 (N's bucket), W2 (bucket 20)
SUBSETS = {"per_set": lambda n: n - 4, "max_subsets": 400}
KINDS = ("mono", "mono-subsets", "stereo", "stereo-subsets")


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def images(work: Path, n: int) -> Path:
    folder = work / f"pairs{n}"
    if not folder.exists():
        folder.mkdir()
        for side in ("left", "right"):
            for p in sorted(DATA.glob(f"{side}*.jpg"))[:n]:
                (folder / p.name).symlink_to(p)
    return folder


def command(kind: str, work: Path, n: int) -> list[str]:
    folder = images(work, n)
    where = (["--images", str(folder), "--glob", "left*.jpg"] if kind.startswith("mono") else
             ["--left", f"{folder}/left*.jpg", "--right", f"{folder}/right*.jpg"])
    extra = (["--per-set", str(SUBSETS["per_set"](n)), "--max-subsets", str(SUBSETS["max_subsets"])]
             if kind.endswith("subsets") else [])
    return [*DSTEREO, "calibrate", *where, "--pattern", "9x6", "--square", "10", *extra,
            "--out", str(work / f"out-{kind}-{n}"), "--force", "-q"]


def run(cmd: list[str], env: dict) -> dict:
    import resource

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)  # the command's own process (its detached builder is not
    # waited for, so not counted): CPU seconds, the steadier figure on a shared machine
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if done.returncode != 0:
        raise SystemExit(f"failed: {' '.join(cmd)}\n{done.stderr[-3000:]}")
    line = next(ln for ln in done.stderr.splitlines() if ln.startswith("PROFILE "))
    prof = json.loads(line[8:])
    return {"wall_s": wall, "cpu_s": cpu, "aot_builds": prof["counts"].get("aot_build_s", 0),
            "aot_build_s": prof["totals"].get("aot_build_s", 0.0), "compiles": prof["counts"].get("xla_compile_or_fetch_s", 0),
            "compile_s": prof["totals"].get("xla_compile_or_fetch_s", 0.0),
            "aot_loads": prof["counts"].get("aot_load_s", 0)}


def wait_for_builder(cache: Path, bucket: int, limit_s: float = 3600.0) -> dict:
    """Until the background builder (runtime/prebuild.py) has built every program at `bucket` (it builds the buckets
    next to the warm-up's first): then it is stopped (by its pid, from its log), so that it does not share the
    cores with the timed runs. Its log's bucket lines give each bucket's wall and CPU time."""
    import signal

    log_path = cache / "dstereo-aot" / "prebuild" / "prebuild.log"
    t0 = time.perf_counter()
    log = ""
    while time.perf_counter() - t0 < limit_s:
        log = log_path.read_text() if log_path.exists() else ""
        if f"prebuild: bucket {bucket} done" in log or "prebuild: done" in log:
            break
        time.sleep(1.0)
    pid = next((int(ln.split("pid ")[1].split(",")[0]) for ln in log.splitlines() if "started, pid" in ln), None)
    stopped = False
    if pid is not None and "prebuild: done" not in log:
        try:
            os.kill(pid, signal.SIGTERM)
            stopped = True
        except OSError:
            pass
    lines = [ln for ln in log.splitlines() if ln.startswith("prebuild: bucket")]
    cpu = [float(ln.split(", ")[-1].split(" s CPU")[0]) for ln in lines]
    return {"waited_s": time.perf_counter() - t0, "bucket_lines": lines, "buckets_built": len(lines),
            "cpu_per_bucket_s": sum(cpu) / len(cpu) if cpu else None, "stopped_early": stopped}


def case(kind: str, work: Path, repeat: int, same: bool = True) -> dict:
    base = dict(os.environ, DSTEREO_SERVE="0")
    base.pop("DSTEREO_SHAPE_BUCKETS", None)
    out: dict = {"kind": kind}
    fresh = lambda name, **kw: dict(base, DSTEREO_JAX_CACHE=str(work / f"jax-{kind}-{name}"), **kw)  # noqa: E731
    env = fresh("cold", DSTEREO_PREBUILD="0")
    out["cold_first"] = run(command(kind, work, NEW), env)
    out["cold_repeat"] = run(command(kind, work, NEW), env)
    if same:
        env = fresh("same", DSTEREO_PREBUILD="0")
        out["same_bucket_warmup"] = run(command(kind, work, SAME), env)
        out["same_bucket_first"] = run(command(kind, work, NEW), env)
    env = fresh("ahead")
    out["ahead_warmup"] = run(command(kind, work, OTHER), env)
    out["builder"] = wait_for_builder(work / f"jax-{kind}-ahead", 24)
    out["ahead_first"] = run(command(kind, work, NEW), dict(env, DSTEREO_PREBUILD="0"))
    env = dict(env, DSTEREO_PREBUILD="0")
    run(command(kind, work, NEW), dict(env, DSTEREO_SHAPE_BUCKETS="0"))  # exact shapes compiled once
    out["repeat_buckets"], out["repeat_exact"] = [], []
    for _ in range(repeat):
        out["repeat_buckets"].append(run(command(kind, work, NEW), env))
        out["repeat_exact"].append(run(command(kind, work, NEW), dict(env, DSTEREO_SHAPE_BUCKETS="0")))
    print(kind, json.dumps({k: v for k, v in out.items() if k != "builder"}), flush=True)
    return out


def table(results) -> list[str]:
    lines = ["| case | cold: N first | cold: N repeat | first / repeat | warm-up in N's bucket, then N | / repeat | "
             "warm-up in another bucket + builder, then N | / repeat | builder: buckets until N's, wait, CPU a bucket | "
             "repeats, buckets on | repeats, exact shapes | padding's cost |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    fmt = lambda r: f"{r['wall_s']:.1f} / {r.get('cpu_s', float('nan')):.1f} [{r['aot_builds']}/{r['compiles']}]"  # noqa: E731
    cpu = lambda r: r.get("cpu_s", r["wall_s"])  # noqa: E731
    best = lambda rs: min(cpu(r) for r in rs)  # noqa: E731
    walls = lambda rs: ", ".join(fmt(x) for x in rs)  # noqa: E731
    for r in results:
        rep = best(r["repeat_buckets"])
        b = r.get("builder", {})
        done = (f"{b['buckets_built']} bucket(s) first, {b['waited_s']:.0f} s; {b['cpu_per_bucket_s']:.1f} s CPU a "
                f"bucket" if b.get("cpu_per_bucket_s") is not None else "-")
        same = r.get("same_bucket_first")
        lines.append(f"| {r['kind']} | {fmt(r['cold_first'])} | {fmt(r['cold_repeat'])} | "
                     f"{cpu(r['cold_first']) / cpu(r['cold_repeat']):.2f}x | {fmt(same) if same else '-'} | "
                     f"{f'{cpu(same) / rep:.2f}x' if same else '-'} | {fmt(r['ahead_first'])} | "
                     f"{cpu(r['ahead_first']) / rep:.2f}x | {done} | {walls(r['repeat_buckets'])} | "
                     f"{walls(r['repeat_exact'])} | {100 * (rep / best(r['repeat_exact']) - 1):+.0f} % |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--kinds", default=",".join(KINDS))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-same", action="store_true", help="leave out the warm-up in N's bucket")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="dstereo-newsize-"))
    load = [f"before: {uptime()}"]
    results = [case(kind, work, args.repeat, not args.no_same) for kind in args.kinds.split(",")]
    load.append(f"after: {uptime()}")
    lines = ["# A data set of a new size: first run against its repeat (`make bench`, experiments/bench_new_size.py)",
             "", f"Machine: {os.cpu_count()} cores, shared; load {load[0]}; {load[1]}. Whole `dstereo calibrate` "
             f"runs in new processes (DSTEREO_SERVE=0), rig640; new size N = {NEW} views (frames), warm-ups at "
             f"{SAME} (N's bucket) and {OTHER} (another bucket); subsets m = N - 4, at most "
             f"{SUBSETS['max_subsets']}.", ""]
    lines += table(results)
    lines += ["", "Each cell: wall s / CPU s of the command's process [executables built / XLA compiles]. first / "
              "repeat: CPU against the best repeat's CPU with buckets on. padding's cost: best repeat CPU with "
              "buckets on against best with exact shapes (alternated)."]
    text = "\n".join(lines) + "\n"
    print(text)
    out = ROOT / "experiments" / "results" / "bench_new_size.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    out.with_suffix(".json").write_text(json.dumps({"load": load, "results": results}, indent=1) + "\n")


if __name__ == "__main__":
    main()
