"""Where a warm `dstereo calibrate` run's time goes, with the executables on disk (runtime/aot.py) and without
(DSTEREO_AOT=0: JAX traces and lowers every program, then fetches its compile from the persistent cache).

Cases, each in a new process, back to back and alternating (so a change of load hits both alike): the plain run
(20 rig640 left images, no subsets) and C = 4845 (m = 16), both with the results folder and figures, after
warm-up runs that fill both caches. The corners are cached by the warm-up, so detection costs ~0. Each run goes
through experiments/_profiled_cli.py, which adds JAX's own durations (jax.monitoring: tracing, lowering, XLA
compile or cache fetch, cache fetch) and the executable loads; the command's `timings` line gives the stages.
Also timed apart, in new processes: `import jax`, `import numpy, cv2`, `import dstereo.cli`, and a Python that
does nothing. `python -m experiments.startup_breakdown [--repeat 3]` writes experiments/results/startup_breakdown.md.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "rig640"
CASES = {"plain": [], "C=4845": ["--per-set", "16", "--max-subsets", "4845"]}
COLUMNS = ("wall_s", "jax_imported_at_s", "trace_s", "lower_s", "xla_compile_or_fetch_s", "cache_fetch_s",
           "aot_load_s", "full_solve", "outliers", "subsets", "final", "write")


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def run(images: Path, out: Path, cache: Path, flags: list[str], aot: bool) -> dict:
    env = dict(os.environ, DSTEREO_JAX_CACHE=str(cache), DSTEREO_AOT="1" if aot else "0")
    cmd = [sys.executable, "-m", "experiments._profiled_cli", "calibrate", "--images", str(images), "--pattern",
           "9x6", "--out", str(out), "--force", "-q", *flags]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"failed: {' '.join(cmd)}\n{done.stderr[-3000:]}")
    profile = json.loads(next(ln for ln in done.stderr.splitlines() if ln.startswith("PROFILE "))[8:])
    row = {"wall_s": wall, **profile["totals"]}
    return row


def import_time(code: str, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT, capture_output=True)
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="dstereo-startup-"))
    images = work / "images"
    images.mkdir()
    for p in sorted(DATA.glob("left*.jpg"))[:20]:
        (images / p.name).symlink_to(p)
    cache = work / "jax"
    load = [uptime()]
    for flags in CASES.values():  # warm-up: both caches, both kinds of program
        for aot in (True, False):
            run(images, work / "out", cache, flags, aot)
    rows: dict = {(case, aot): [] for case in CASES for aot in (True, False)}
    for _ in range(args.repeat):
        for case, flags in CASES.items():
            for aot in (True, False):
                rows[case, aot].append(run(images, work / "out", cache, flags, aot))
                r = rows[case, aot][-1]
                print(f"{case} aot={aot}: wall {r['wall_s']:.2f} s, trace {r.get('trace_s', 0):.2f} s", flush=True)
    imports = {name: import_time(code, args.repeat) for name, code in (
        ("python doing nothing", "pass"), ("import numpy, cv2", "import numpy, cv2"), ("import jax", "import jax"),
        ("import dstereo.cli (typer, commands)", "import dstereo.cli"))}
    load.append(uptime())
    med = lambda xs: statistics.median(xs) if xs else 0.0  # noqa: E731
    lines = ["# Warm-run breakdown (`python -m experiments.startup_breakdown`)", "",
             f"Machine: {os.cpu_count()} cores, shared with other jobs; load before: {load[0]}; after: {load[1]}.",
             "", "Medians of the repeats (s); `aot` = executables loaded from disk, `traced` = DSTEREO_AOT=0.", "",
             "| case | " + " | ".join(COLUMNS) + " |", "|---|" + "---|" * len(COLUMNS)]
    for (case, aot), rs in rows.items():
        lines.append(f"| {case}, {'aot' if aot else 'traced'} | "
                     + " | ".join(f"{med([r.get(c, 0.0) for r in rs]):.2f}" for c in COLUMNS) + " |")
    lines += ["", "All walls (s): " + "; ".join(
        f"{case} {'aot' if aot else 'traced'}: " + ", ".join(f"{r['wall_s']:.2f}" for r in rs)
        for (case, aot), rs in rows.items()), "",
        "| new process | best of the repeats |", "|---|---|"]
    lines += [f"| {name} | {t:.2f} s |" for name, t in imports.items()]
    lines += ["", "Columns: wall_s the whole process; jax_imported_at_s when `import jax` had finished; trace_s, "
              "lower_s, xla_compile_or_fetch_s, cache_fetch_s JAX's own sums over every program compiled in the run "
              "(a fetch from the persistent cache counts in xla_compile_or_fetch_s too); aot_load_s reading and "
              "loading executables; the rest the command's `timings` (s)."]
    text = "\n".join(lines) + "\n"
    print(text)
    out = ROOT / "experiments" / "results" / "startup_breakdown.md"
    out.write_text(text)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
