"""Does a code move change any result a user sees? Runs the commands on the shared real rig (one camera, the
stereo rig with subsets, the same rig as `--cameras`, a reconstruction from its stereo.yml; one camera with subsets,
steps and cross-validation on rig640's left, opencv_stereo's left and fisheye640) in the checkout it is
started from, then compares two such runs file by file: every number in the JSON, YAML, CSV and text files and
every array in the .npz and .ply files, timings and paths left out.

    python -m experiments.outputs_unchanged run OUT          # in each checkout (cwd first on sys.path)
    python -m experiments.outputs_unchanged compare A B      # max relative difference per file; exit 1 above 1e-9

Where a number differs, the run's own figures say whether it is rounding (a different summation order moves a
solve by ~1e-12 relative) or a change of result (anything a user would read, 1e-6 and up).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

OTHER = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
DATA = OTHER / "rig640"
LIMIT = 1e-9  # relative; rounding between two builds of one computation is ~1e-12, a changed result >= 1e-6
SKIP_WORDS = ("time", "second", "elapsed", "date", "version", "/", "took", "host", "cpu", "thread", "pid")
NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")


def _cli(*args: str) -> None:
    env = dict(os.environ, DSTEREO_SERVE="0")
    done = subprocess.run([sys.executable, "-m", "dstereo.cli", *args], env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"outputs_unchanged: dstereo {' '.join(args)} failed:\n{done.stderr[-2000:]}")


def run(out: Path) -> None:
    import dstereo

    print("dstereo from", Path(dstereo.__file__).parent)
    out.mkdir(parents=True)
    cams = out / "cameras_in"
    for side, label in (("left", "cam0"), ("right", "cam1")):  # the rig as N = 2 cameras: links, not copies
        (cams / label).mkdir(parents=True)
        for f in sorted(DATA.glob(f"{side}*.jpg")):
            (cams / label / f.name.replace(side, "frame")).symlink_to(f.resolve())
    board = ("--pattern", "9x6", "--square", "10")
    _cli("calibrate", "--images", str(DATA), "--glob", "left*.jpg", *board, "--out", str(out / "one"), "-q")
    # one camera with every stage: subsets, steps, the survivors' solve, cross-validation (rig640, opencv_stereo's
    # left camera, the fisheye640 lens)
    steps = ("--step", "re=1", "--step", "fx=1.5,fy=1.5")
    _cli("calibrate", "--images", str(DATA), "--glob", "left*.jpg", *board, "--per-set", "12", "--max-subsets", "60",
         *steps, "--cross-validate", "4", "--out", str(out / "one_subsets"), "-q")
    _cli("calibrate", "--images", str(OTHER / "opencv_stereo"), "--glob", "left*.jpg", *board, "--per-set", "8",
         "--max-subsets", "40", *steps, "--out", str(out / "one_opencv_left"), "-q")
    _cli("calibrate", "--images", str(OTHER / "fisheye640"), *board, "--model", "fisheye", "--per-set", "10",
         "--max-subsets", "40", *steps, "--out", str(out / "one_fisheye"), "-q")
    _cli("calibrate", "--left", str(DATA / "left*.jpg"), "--right", str(DATA / "right*.jpg"), *board,
         "--per-set", "12", "--max-subsets", "60", "--out", str(out / "rig"), "-q")
    _cli("calibrate", "--cameras", str(cams), *board, "--out", str(out / "cameras"), "-q")
    _cli("reconstruct", "--calib", str(out / "rig" / "stereo.yml"), "--left", str(DATA / "left01.jpg"),
         "--right", str(DATA / "right01.jpg"), "--out", str(out / "rec"))


def _numbers(path: Path) -> dict[str, np.ndarray]:
    """Every number of a results file, by where it sits (arrays for .npz/.ply, one vector for text)."""
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            return {k: np.asarray(z[k], float).ravel() for k in z.files if np.asarray(z[k]).dtype.kind in "biuf"}
    if path.suffix == ".npy":
        return {"array": np.asarray(np.load(path, allow_pickle=False), float).ravel()}
    if path.suffix == ".ply":
        import trimesh

        cloud = trimesh.load(path, process=False)
        return {"vertices": np.asarray(cloud.vertices, float).ravel()}
    if path.suffix == ".json":
        found: dict[str, list[float]] = {}

        def walk(value, key):
            if any(w in key.lower() for w in SKIP_WORDS[:4]) or key.endswith(("_s", "timings")):
                return
            if isinstance(value, dict):
                for k, v in value.items():
                    walk(v, f"{key}.{k}")
            elif isinstance(value, list):
                for v in value:
                    walk(v, key)
            elif isinstance(value, (int, float)) and not isinstance(value, bool):
                found.setdefault(key, []).append(float(value))

        walk(json.loads(path.read_text()), "")
        return {k: np.array(v) for k, v in found.items()}
    lines = [ln for ln in path.read_text(errors="replace").splitlines() if not any(w in ln.lower() for w in SKIP_WORDS)]
    return {"text": np.array([float(x) for ln in lines for x in NUMBER.findall(ln)])}


def compare(a: Path, b: Path) -> int:
    kinds = (".json", ".yml", ".csv", ".md", ".txt", ".npz", ".npy", ".ply", ".toml", ".cameramodel")
    files_a = {p.relative_to(a) for p in a.rglob("*") if p.is_file() and p.suffix in kinds and "cameras_in" not in p.parts}
    files_b = {p.relative_to(b) for p in b.rglob("*") if p.is_file() and p.suffix in kinds and "cameras_in" not in p.parts}
    for only, where in ((files_a - files_b, a), (files_b - files_a, b)):
        for p in sorted(only):
            print(f"only in {where}: {p}")
    worst, bad = 0.0, 0
    for rel in sorted(files_a & files_b):
        na, nb = _numbers(a / rel), _numbers(b / rel)
        diff = 0.0
        for key in sorted(set(na) | set(nb)):
            x, y = na.get(key), nb.get(key)
            if x is None or y is None or x.shape != y.shape:
                print(f"{rel} [{key}]: {None if x is None else x.size} vs {None if y is None else y.size} numbers")
                bad += 1
                continue
            both = np.isfinite(x) & np.isfinite(y)
            if not np.array_equal(np.isfinite(x), np.isfinite(y)):
                print(f"{rel} [{key}]: finite in one run, not in the other")
                bad += 1
            if both.any():
                scale = np.maximum(np.abs(x[both]), np.abs(y[both]))
                rel_d = np.abs(x[both] - y[both]) / np.where(scale > 0, scale, 1.0)
                diff = max(diff, float(rel_d.max()))
        worst = max(worst, diff)
        flag = "  <-- above the limit" if diff > LIMIT else ""
        bad += diff > LIMIT
        print(f"{diff:9.2e}  {rel}{flag}")
    print(f"{len(files_a & files_b)} files compared; worst relative difference {worst:.2e} (limit {LIMIT:g}); "
          f"{bad} differences")
    return 1 if bad else 0


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "run":
        run(Path(sys.argv[2]))
    elif len(sys.argv) == 4 and sys.argv[1] == "compare":
        raise SystemExit(compare(Path(sys.argv[2]), Path(sys.argv[3])))
    else:
        raise SystemExit(__doc__)
