"""End-to-end benchmark: a whole `dstereo calibrate` run in a new process vs the thesis approach, and the plain
calibration vs a fresh Python process that calls cv2.calibrateCamera and writes its yml.

Same machine, same run, cases back to back, the same corners (../shared/data/rig640 left images, detected once
beforehand and cached, so neither side pays detection):
  - dstereo: `dstereo calibrate --images DIR --per-set m --max-subsets C --out OUT --force -q` in a new process,
    results folder and every figure included; "cold" = an empty JAX compilation cache, "warm" = the cache the
    cold run left;
  - thesis approach: a new process that runs cv2.calibrateCamera on every subset with one process per core
    (cv2.setNumThreads(1) in each worker), then writes its results (one CSV row per subset and a yml of the
    subset means), as the thesis's tool did per subset; no figures (in its favour);
  - plain: `dstereo calibrate` without subsets (warm cache, results folder included) vs a new Python process that
    loads the same corners, calls cv2.calibrateCamera once and writes its yml with cv2.FileStorage;
  - served, as a user gets it from the second command on: the same commands through the `dstereo` entry point's
    client with no server at first (the first command runs in its own process and starts one, runtime/autostart.py),
    then, once it answers, plain runs alternating with the cv2 process and (with C = 4845 among the sizes) the
    C = 4845 run alternating with the thesis approach; each first served command is timed apart;
    `--plain-only` runs the plain cases alone and writes bench_end_to_end_plain.md.
Each case runs `--repeat` times (best and all times printed); `uptime` before and after says the load. The dstereo
runs go through experiments/_profiled_cli.py (the same CLI, plus a breakdown: when JAX had imported, JAX's tracing,
lowering and compile-or-fetch sums, executables loaded from disk, and the command's own stage timings).
`python -m experiments.bench_end_to_end [--sizes 286,1140,4845] [--repeat 2]`; writes
experiments/results/bench_end_to_end.md and .json (every time, the load, the breakdowns).
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

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "rig640"
CASES = {286: (13, 10), 1140: (20, 17), 4845: (20, 16)}  # C: (images, m), every combination
DSTEREO = [sys.executable, "-m", "experiments._profiled_cli"]  # = the `dstereo` script, with a breakdown
BREAKDOWN = ("jax_imported_at_s", "trace_s", "lower_s", "xla_compile_or_fetch_s", "aot_load_s", "detect",
             "full_solve", "outliers", "subsets", "final", "write", "outside_s")

THESIS = r'''
import csv, itertools, os, sys, multiprocessing as mp
import numpy as np, cv2
d = np.load(sys.argv[1]); obj, obs, size = d["obj"].astype(np.float32), d["obs"].astype(np.float32), tuple(d["size"])
m, out = int(sys.argv[2]), sys.argv[3]
def init():
    cv2.setNumThreads(1)
def one(idx):
    rms, k, dist, _, _ = cv2.calibrateCamera([obj] * len(idx), [obs[i] for i in idx], size, None, None)
    return [*idx], [k[0, 0], k[1, 1], k[0, 2], k[1, 2], *dist.ravel()[:5], rms]
if __name__ == "__main__":
    subsets = list(itertools.combinations(range(len(obs)), m))
    with mp.get_context("fork").Pool(os.cpu_count(), initializer=init) as pool:
        rows = pool.map(one, subsets, chunksize=8)
    os.makedirs(out, exist_ok=True)
    names = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "rms"]
    with open(os.path.join(out, "subsets.csv"), "w", newline="") as fh:
        w = csv.writer(fh); w.writerow(["images", *names])
        for idx, vals in rows:
            w.writerow([" ".join(map(str, idx)), *map(repr, vals)])
    mean = np.mean([v for _, v in rows], axis=0)
    fs = cv2.FileStorage(os.path.join(out, "camera.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", np.array([[mean[0], 0, mean[2]], [0, mean[1], mean[3]], [0, 0, 1]]))
    fs.write("distortion_coefficients", mean[4:9].reshape(1, -1)); fs.release()
'''

PLAIN_CV2 = r'''
import sys, numpy as np, cv2
d = np.load(sys.argv[1]); obj, obs, size = d["obj"].astype(np.float32), d["obs"].astype(np.float32), tuple(d["size"])
rms, k, dist, _, _ = cv2.calibrateCamera([obj] * len(obs), list(obs), size, None, None)
fs = cv2.FileStorage(sys.argv[2], cv2.FILE_STORAGE_WRITE)
fs.write("image_width", int(size[0])); fs.write("image_height", int(size[1]))
fs.write("camera_matrix", k); fs.write("distortion_coefficients", dist.reshape(1, -1)); fs.release()
'''


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


PROFILES: dict = {}  # (case, kind) -> breakdowns of the dstereo runs


def timed(cmd: list[str], env: dict | None = None, profile: tuple | None = None) -> float:
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    elapsed = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"failed: {' '.join(cmd)}\n{done.stderr[-2000:]}")
    if profile is not None:
        line = next(ln for ln in done.stderr.splitlines() if ln.startswith("PROFILE "))
        row = json.loads(line[8:])["totals"]
        row["outside_s"] = elapsed - row["total_s"]  # Python before the wrapper's clock, the exit after its report
        PROFILES.setdefault(profile, []).append(row)
    return elapsed


def prepare(work: Path, n_images: int) -> tuple[Path, Path]:
    """A folder of symlinks to the first n left images, and their corners (detected and cached now)."""
    from dstereo.io.corners import detect_folder

    folder = work / f"images{n_images}"
    if not folder.exists():
        folder.mkdir()
        for p in sorted(DATA.glob("left*.jpg"))[:n_images]:
            (folder / p.name).symlink_to(p)
    det = detect_folder(folder, (9, 6), 1.0)
    names = sorted(det.corners)
    corners = work / f"corners{n_images}.npz"
    np.savez(corners, obj=det.object_points, obs=np.stack([det.corners[n] for n in names]),
             size=np.array(det.image_size))
    return folder, corners


CLIENT = [sys.executable, "-c", "import sys; sys.argv[0] = 'dstereo'; from dstereo.cli import main; main(end_process=True)"]


def served_cases(plain: list[str], cv2_run: list[str], subsets: list[str] | None, thesis_run: list[str] | None,
                 env: dict, work: Path, repeat: int) -> dict:
    """The same commands through the `dstereo` entry point's client, as a user gets them: no server at first, so
    the first command runs in its own process and starts one (runtime/autostart.py); once it answers, the first
    served command (the new server loads the run's executables) is timed apart, then `repeat` served plain runs
    alternate with the cv2 process and, with `subsets`, `repeat` served subset runs with the thesis approach, so
    each pair sees the same load. Checks from the server's count that every timed command was served."""
    env = dict(env, DSTEREO_SERVE_DIR=str(work / "serve"))
    for name in ("DSTEREO_SERVE", "CI", "PYTEST_CURRENT_TEST"):  # auto-start allowed, as outside tests and CI
        env.pop(name, None)
    client = [*CLIENT, *plain[len(DSTEREO):]]
    out: dict = {"plain": [], "cv2": [], "subsets": [], "thesis": []}
    try:
        out["autostart_first"] = timed(client, env)  # no server: runs here and starts one
        t0 = time.perf_counter()
        while "running at" not in subprocess.run([*CLIENT, "serve", "--status"], env=env, capture_output=True,
                                                 text=True).stdout:
            if time.perf_counter() - t0 > 300:
                raise SystemExit("the auto-started server did not come up")
            time.sleep(0.1)
        out["server_ready_after_s"] = time.perf_counter() - t0
        out["first_served"] = timed(client, env)
        for _ in range(repeat):
            out["plain"].append(timed(client, env))
            out["cv2"].append(timed(cv2_run))
            print(f"plain: served {out['plain'][-1]:.2f} s, cv2 process {out['cv2'][-1]:.2f} s", flush=True)
        expected = repeat + 1
        if subsets is not None:
            sub_client = [*CLIENT, *subsets[len(DSTEREO):]]
            out["first_served_subsets"] = timed(sub_client, env)  # the subsets' executables load (or compile)
            for _ in range(repeat):
                out["subsets"].append(timed(sub_client, env))
                out["thesis"].append(timed(thesis_run))
                print(f"subsets: served {out['subsets'][-1]:.2f} s, thesis {out['thesis'][-1]:.2f} s", flush=True)
            expected += repeat + 1
        status = subprocess.run([*CLIENT, "serve", "--status"], env=env, capture_output=True, text=True).stdout
        if f"{expected} command(s) served" not in status:  # a fallback to in-process would time the wrong thing
            raise SystemExit(f"not every timed command was served: {status}")
        out["server_rss_mb"] = server_memory(int(status.split(" pid ")[1].split(",")[0]))
    finally:
        subprocess.run([*CLIENT, "serve", "--stop"], env=env, capture_output=True)
    return out


def server_memory(pid: int) -> dict:
    """Resident memory (MB) of the idle server and of its descendants (multiprocessing's resource tracker, the
    figure workers), from /proc."""
    def rss(p: int) -> float:
        for line in Path(f"/proc/{p}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        return 0.0

    def children(p: int) -> list[int]:
        kids = [int(c) for t in Path(f"/proc/{p}/task").iterdir() for c in (t / "children").read_text().split()]
        return kids + [g for k in kids for g in children(k)]

    return {"server": rss(pid), "workers": [rss(c) for c in children(pid)]}


def best(times: list[float]) -> str:
    return f"{min(times):.2f} s" + (f" ({', '.join(f'{t:.2f}' for t in times)})" if len(times) > 1 else "")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="286,1140,4845")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--no-plain", action="store_true")
    ap.add_argument("--plain-only", action="store_true")
    args = ap.parse_args()
    sizes = [] if args.plain_only else [int(s) for s in args.sizes.split(",")]
    work = Path(tempfile.mkdtemp(prefix="dstereo-e2e-"))
    (work / "thesis.py").write_text(THESIS)
    (work / "plain_cv2.py").write_text(PLAIN_CV2)
    load = [f"before: {uptime()}"]
    rows, plain_row, served_row = [], None, None
    env_base = dict(os.environ)
    for c in sizes:
        n, m = CASES[c]
        folder, corners = prepare(work, n)
        cold, warm, thesis = [], [], []
        for r in range(args.repeat):
            env = dict(env_base, DSTEREO_JAX_CACHE=str(work / f"jax{c}-{r}"))  # a new empty cache each repeat
            run = [*DSTEREO, "calibrate", "--images", str(folder), "--pattern", "9x6", "--per-set", str(m),
                   "--max-subsets", str(c), "--out", str(work / "out"), "--force", "-q"]
            cold.append(timed(run, env, (c, "cold")))
            warm.append(timed(run, env, (c, "warm")))
            thesis.append(timed([sys.executable, str(work / "thesis.py"), str(corners), str(m), str(work / "th")]))
            print(f"C={c}: cold {cold[-1]:.2f} s, warm {warm[-1]:.2f} s, thesis {thesis[-1]:.2f} s", flush=True)
        rows.append((c, n, m, cold, warm, thesis))
    if not args.no_plain:
        folder, corners = prepare(work, 20)
        env = dict(env_base, DSTEREO_JAX_CACHE=str(work / "jax-plain"))
        run = [*DSTEREO, "calibrate", "--images", str(folder), "--pattern", "9x6", "--out", str(work / "plain"),
               "--force", "-q"]
        timed(run, env)  # fills the compile cache: the plain case is measured warm
        ds, cv = [], []
        for _ in range(max(args.repeat, 3)):
            ds.append(timed(run, env, ("plain", "warm")))
            cv.append(timed([sys.executable, str(work / "plain_cv2.py"), str(corners), str(work / "cv2.yml")]))
            print(f"plain: dstereo {ds[-1]:.2f} s, cv2 process {cv[-1]:.2f} s", flush=True)
        plain_row = (ds, cv)
        cv2_run = [sys.executable, str(work / "plain_cv2.py"), str(corners), str(work / "cv2.yml")]
        big = max((c for c in sizes if CASES[c][0] == 20), default=None)  # the served subset case: 20 views
        subsets = None if big is None else [*DSTEREO, "calibrate", "--images", str(folder), "--pattern", "9x6",
                                            "--per-set", str(CASES[big][1]), "--max-subsets", str(big),
                                            "--out", str(work / "served-out"), "--force", "-q"]
        thesis_run = None if big is None else [sys.executable, str(work / "thesis.py"), str(corners),
                                               str(CASES[big][1]), str(work / "th")]
        served_row = served_cases(run, cv2_run, subsets, thesis_run, env, work, max(args.repeat, 3))
        served_row["subsets_case"] = big
    load.append(f"after: {uptime()}")
    lines = ["# End-to-end benchmark (`make bench`, experiments/bench_end_to_end.py)", "",
             f"Machine: {os.cpu_count()} cores (shared with other jobs); load {load[0]}; {load[1]}.", "",
             "| C (images, m) | dstereo cold (empty compile cache) | dstereo warm | thesis approach, "
             f"{os.cpu_count()} processes | cold: x thesis | warm: x thesis |", "|---|---|---|---|---|---|"]
    for c, n, m, cold, warm, thesis in rows:
        lines.append(f"| {c} ({n}, {m}) | {best(cold)} | {best(warm)} | {best(thesis)} | "
                     f"{min(thesis) / min(cold):.2f}x | {min(thesis) / min(warm):.2f}x |")
    if plain_row is not None:
        ds, cv = plain_row
        lines += ["", "| plain calibration, 20 views | dstereo calibrate (warm cache, results folder) | "
                  "python + cv2.calibrateCamera + yml | ratio |", "|---|---|---|---|",
                  f"| whole run, new process | {best(ds)} | {best(cv)} | {min(ds) / min(cv):.2f}x |"]
        sv = served_row
        lines += [f"| whole run, first command with no server (runs in its own process, starts one) | "
                  f"{sv['autostart_first']:.2f} s | | |",
                  f"| whole run, served by the server it started (warm; cv2 timed alternately with it; server "
                  f"answering {sv['server_ready_after_s']:.2f} s after that command; its first served command "
                  f"{sv['first_served']:.2f} s) | {best(sv['plain'])} | {best(sv['cv2'])} | "
                  f"{min(sv['plain']) / min(sv['cv2']):.2f}x |"]
        mem = sv["server_rss_mb"]
        lines += ["", f"The idle server after these runs: {mem['server']:.0f} MB resident, its descendant processes "
                  "(resource tracker, figure workers) "
                  + ", ".join(f"{w:.0f}" for w in mem["workers"]) + " MB (VmRSS)."]
        if sv["subsets"]:
            c = sv["subsets_case"]
            lines += ["", f"| C = {c} ({CASES[c][0]}, {CASES[c][1]}), served | dstereo calibrate through the "
                      f"server | thesis approach, {os.cpu_count()} processes (alternately) | x thesis |",
                      "|---|---|---|---|",
                      f"| warm server (its first C = {c} command {sv['first_served_subsets']:.2f} s, not counted) | "
                      f"{best(sv['subsets'])} | {best(sv['thesis'])} | "
                      f"{min(sv['thesis']) / min(sv['subsets']):.2f}x |"]
    lines += ["", "Times: best of the repeats (all repeats in brackets), wall clock of the whole process.", "",
              "Breakdown of the dstereo runs (medians, s): jax_imported_at_s when `import jax` had finished in the "
              "process; trace_s, lower_s, xla_compile_or_fetch_s JAX's own sums over the run's programs; aot_load_s "
              "executables loaded from disk (dstereo/runtime/aot.py); the rest the command's stage timings; outside_s "
              "the wall clock outside the wrapper's (Python's start-up before it, the process's end after it).", "",
              "| run | wall | " + " | ".join(BREAKDOWN) + " |", "|---|---|" + "---|" * len(BREAKDOWN)]
    walls = {**{(c, "cold"): cold for c, _, _, cold, _, _ in rows}, **{(c, "warm"): warm for c, _, _, _, warm, _ in rows}}
    if plain_row is not None:
        walls["plain", "warm"] = plain_row[0]
    for key, profiles in PROFILES.items():
        med = lambda name: statistics.median([p.get(name, 0.0) for p in profiles])  # noqa: E731
        lines.append(f"| {key[0]} {key[1]} | {statistics.median(walls[key]):.2f} | "
                     + " | ".join(f"{med(name):.2f}" for name in BREAKDOWN) + " |")
    if not rows:  # --plain-only: no subset table
        lines = [ln for ln in lines if not ln.startswith("| C (") and ln != "|---|---|---|---|---|---|"]
    text = "\n".join(lines) + "\n"
    print(text)
    name = "bench_end_to_end_plain.md" if args.plain_only else "bench_end_to_end.md"  # a partial run: its own file
    out = ROOT / "experiments" / "results" / name
    out.write_text(text)
    record = {"cores": os.cpu_count(), "load_before": load[0], "load_after": load[1],
              "cases": [{"subsets": c, "images": n, "per_set": m, "cold_s": cold, "warm_s": warm, "thesis_s": thesis,
                         "warm_x_thesis": min(thesis) / min(warm), "cold_x_thesis": min(thesis) / min(cold)}
                        for c, n, m, cold, warm, thesis in rows],
              "plain": None if plain_row is None else {"dstereo_s": plain_row[0], "cv2_s": plain_row[1]},
              "served": served_row,
              "breakdown": {f"{k[0]} {k[1]}": v for k, v in PROFILES.items()}}
    out.with_suffix(".json").write_text(json.dumps(record, indent=1) + "\n")
    print(f"wrote {out} and {out.with_suffix('.json').name}")


if __name__ == "__main__":
    main()
