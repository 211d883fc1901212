"""Where one frame of `dstereo recession` spends its time after start-up, this tree against another (issue 19).

A rendered 640x480 recession sequence (`dstereo.jobs.synthetic_recession`, the reduced Plasmatron rig) is measured
by two server processes, one importing dstereo from this tree and one from `--against` (default /work/main),
each warmed up on the reference frame (compilation, rectification) and then asked for the same frames in
turn, alternating which goes first, so that both see the same load on a shared machine. Reported: the median
time of a frame (unprofiled; wall and the process's CPU time), its stages (median over the profiled frames,
cProfile's cumulative CPU times, which add cProfile's overhead to both alike), whether the frame's outcome
(heights, standard errors, random sigmas, noise check, search range) is equal bit for bit (else by how much it
differs), and the stagnation-point RMS of a whole serial run against the rendered truth in both.

    python -m experiments.frame_profile [--frames 10] [--against /work/main]
        [--out experiments/results/frame_profile.md]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

# (label, function names whose cumulative time is the stage); the first that appears in a profile counts
STAGES = [
    ("load images", ["read_image"]),
    ("rectification maps (JAX)", ["rectify_map", "rectify_calibration", "rectified_maps"]),
    ("remap (cv2, bilinear)", ["<remap>", "<built-in method cv2.remap>"]),
    ("SGBM + search range", ["match_in_range"]),
    ("exact cubic re-rectification", ["exact_pair"]),
    ("sub-pixel refinement", ["refine_disparity"]),
    ("triangulation", ["points_and_summary"]),
    ("noise map: image noise", ["image_noise"]),
    ("noise map: refined sigma", ["refined_sigma"]),
    ("noise map: plane check", ["plane_check"]),
    ("point sigma vectors", ["point_sigma_vectors"]),
    ("surface fit (cell heights)", ["_frame_heights"]),
    ("cell random sigma", ["_cell_random_sigma"]),
    ("writing the frame (store)", ["save"]),
]

SERVER = r'''
import cProfile, hashlib, json, pstats, sys, tempfile, time
from pathlib import Path
import numpy as np
from dstereo.io.partial_store import PartialStore
from dstereo.io.calib_files import read_stereo_calibration
from dstereo.recession import RecessionConfig
from dstereo.io.sequence_files import discover
from dstereo.jobs.recession import run_recession
from dstereo.recession.analysis import _measure, measure_frame
from dstereo.jobs.recession import FrameReconstructor
from dstereo.stereo.reconstruct import ReconstructionConfig

try:  # this tree's serial runner holds BLAS to one thread while frames run; an older tree's does not
    from dstereo.runtime.blas_threads import one_blas_thread
except ImportError:
    from contextlib import nullcontext as one_blas_thread
folder = Path(sys.argv[1])
frames = discover(folder)
calib = read_stereo_calibration(folder / "stereo.yml")
cfg = RecessionConfig(grid_mm=0.5)
rec = FrameReconstructor(calib, ReconstructionConfig(), True)
_, ref = _measure(frames[0], rec, cfg)
store = PartialStore(Path(tempfile.mkdtemp()) / "out", "k").open(False, True)

def digest(o):
    h = hashlib.sha256()
    for k in o.ARRAYS:
        a = getattr(o, k)
        h.update(b"none" if a is None else np.ascontiguousarray(a).tobytes())
    h.update(json.dumps([o.status, o.reason, o.valid_fraction, o.check, o.log], sort_keys=True, default=str).encode())
    return h.hexdigest()

def one(i, profile):
    prof = cProfile.Profile(time.process_time) if profile else None
    t0, c0 = time.perf_counter(), time.process_time()
    if prof: prof.enable()
    with one_blas_thread():
        o = measure_frame(frames[i], rec, ref, cfg)
    store.save(f"{i:06d}", *o.to_store(frames[i].key))
    if prof: prof.disable()
    out = {"seconds": time.perf_counter() - t0, "cpu": time.process_time() - c0, "digest": digest(o)}
    if not profile:
        np.savez(Path(sys.argv[2]) / f"{i:06d}.npz", **{k: getattr(o, k) for k in o.ARRAYS})
        out["check"] = o.check
    if prof:
        stats = pstats.Stats(prof).stats
        cum = {}
        for (file, line, name), (cc, nc, tt, ct, callers) in stats.items():
            key = name if file != "~" else name
            cum[key] = cum.get(key, 0.0) + ct
        out["cumulative"] = cum
    return out

print(json.dumps({"ready": True}), flush=True)
for line in sys.stdin:
    cmd = json.loads(line)
    if cmd["do"] == "frame":
        print(json.dumps(one(cmd["i"], cmd["profile"])), flush=True)
    elif cmd["do"] == "rms":
        truth = json.loads((folder / "truth.json").read_text())
        result = run_recession(frames, calib, cfg, ReconstructionConfig())
        got = np.array([f.recession.value for f in result.frames])
        rms = float(np.sqrt(np.nanmean((got - np.array(truth["recession_stagnation_mm"])) ** 2)))
        print(json.dumps({"rms": rms, "heights": hashlib.sha256(result.heights.tobytes()).hexdigest()}), flush=True)
    else:
        break
'''


class Server:
    def __init__(self, tree: Path, folder: Path, arrays: Path):
        env = dict(os.environ, PYTHONPATH=str(tree))
        self.tree, self.arrays = tree, arrays
        arrays.mkdir(parents=True)
        self.proc = subprocess.Popen([sys.executable, "-c", SERVER, str(folder), str(arrays)], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, env=env, cwd=str(tree))
        assert json.loads(self.proc.stdout.readline())["ready"]

    def ask(self, **cmd) -> dict:
        self.proc.stdin.write(json.dumps(cmd) + "\n")
        self.proc.stdin.flush()
        return json.loads(self.proc.stdout.readline())

    def close(self) -> None:
        self.proc.stdin.write(json.dumps({"do": "stop"}) + "\n")
        self.proc.stdin.close()
        self.proc.wait()


def compare_arrays(servers: dict, i: int, got: dict, diffs: dict) -> None:
    """Per array of the frame's outcome: whether it is equal bit for bit, else the largest difference relative
    to the array's largest value; and the noise check's ratio."""
    a, b = (np.load(s.arrays / f"{i:06d}.npz") for s in servers.values())
    for k in a.files:
        x, y = a[k], b[k]
        same = np.array_equal(x, y, equal_nan=True)
        rel = 0.0 if same else float(np.nanmax(np.abs(x - y)) / np.nanmax(np.abs(y)))
        diffs.setdefault(k, []).append(rel)
    ra, rb = (got[name]["check"].get("ratio") for name in servers)
    diffs.setdefault("noise check ratio", []).append(0.0 if ra == rb else abs(ra / rb - 1))


def stage_times(cumulative: dict) -> dict:
    out = {}
    for label, names in STAGES:
        out[label] = next((cumulative[n] for n in names if n in cumulative), 0.0)
    return out


def load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=10, help="frames of the rendered sequence (>= 4)")
    parser.add_argument("--against", type=Path, default=Path("/work/main"))
    parser.add_argument("--sequence", type=Path, default=None, help="a rendered sequence folder to reuse")
    parser.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "frame_profile.md")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="frame_profile_") as tmp:
        folder = args.sequence
        if folder is None:
            from dstereo.jobs.synthetic_recession import write_synthetic_sequence

            folder = Path(tmp) / "seq"
            write_synthetic_sequence(folder, n_frames=args.frames, duration_s=40.0, total_mm=2.0,
                                     image_size=(640, 480))
        from dstereo.io.sequence_files import discover

        n = len(discover(folder))
        loads = {"start": load()}
        servers = {"this tree": Server(ROOT, folder, Path(tmp) / "a"),
                   "against": Server(args.against, folder, Path(tmp) / "b")}
        plain = {k: [] for k in servers}
        cpu = {k: [] for k in servers}
        stages = {k: [] for k in servers}
        equal, diffs = [], {}
        order = list(servers)
        for i in range(1, n):
            got = {}
            for name in order:
                got[name] = servers[name].ask(do="frame", i=i, profile=False)
                plain[name].append(got[name]["seconds"])
                cpu[name].append(got[name]["cpu"])
            equal.append(got["this tree"]["digest"] == got["against"]["digest"])
            compare_arrays(servers, i, got, diffs)
            order.reverse()
        loads["timed"] = load()
        for i in range(1, n):
            for name in order:
                stages[name].append(stage_times(servers[name].ask(do="frame", i=i, profile=True)["cumulative"]))
            order.reverse()
        loads["profiled"] = load()
        rms = {name: s.ask(do="rms") for name, s in servers.items()}
        loads["end"] = load()
        for s in servers.values():
            s.close()
    write_report(args.out, args.against, n, plain, cpu, stages, equal, diffs, rms, loads)


def write_report(path: Path, against: Path, n: int, plain, cpu, stages, equal, diffs, rms, loads) -> None:
    med = {k: float(np.median(v)) for k, v in plain.items()}
    med_cpu = {k: float(np.median(v)) for k, v in cpu.items()}
    lines = ["# One frame of `dstereo recession` after start-up: stages, this tree against another (issue 19)", "",
             f"Rendered 640x480 sequence ({n} frames, 0 -> 2 mm), `python -m experiments.frame_profile`: two "
             f"server processes (this tree, and `{against}`), each warmed up on the reference frame, asked for "
             "the same frames in turn (alternating which goes first). Frame = `measure_frame` (read, rectify, "
             "SGBM, refine, triangulate, noise map, cell heights) plus storing it (`PartialStore.save`). "
             f"{os.cpu_count()} cores shared with other jobs; load averages (1, 5, 15 min): "
             + "; ".join(f"{k}: {v}" for k, v in loads.items()) + ".", "",
             "| | this tree | against | ratio |", "|---|---|---|---|",
             f"| median s per frame (unprofiled, {len(plain['this tree'])} frames) | {med['this tree']:.3f} | "
             f"{med['against']:.3f} | {med['against'] / med['this tree']:.2f}x |",
             f"| median CPU s per frame (unprofiled) | {med_cpu['this tree']:.3f} | {med_cpu['against']:.3f} | "
             f"{med_cpu['against'] / med_cpu['this tree']:.2f}x |"]
    for label, _ in STAGES:
        a = float(np.median([s[label] for s in stages["this tree"]]))
        b = float(np.median([s[label] for s in stages["against"]]))
        lines.append(f"| {label} (profiled, median CPU s) | {a:.4f} | {b:.4f} | "
                     + (f"{b / a:.2f}x" if a > 0 else "-") + " |")
    lines += [f"| stagnation RMS of a serial run against the truth, mm | {rms['this tree']['rms']:.5f} | "
              f"{rms['against']['rms']:.5f} | |", "",
              f"Frame outcomes equal bit for bit (every array, the noise check, the log): {sum(equal)} of "
              f"{len(equal)}; whole-run height maps equal: "
              f"{'yes' if rms['this tree']['heights'] == rms['against']['heights'] else 'NO'}. Per array over "
              "the frames (largest difference / largest value of the array; 0 = equal bit for bit): "
              + "; ".join(f"{k} {max(v):.2g}" for k, v in diffs.items()) + ".", ""]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
