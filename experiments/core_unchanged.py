"""Does one N-camera core change any existing result? Runs the mono and stereo solves (full set, fixed and joint
rigs, subsets: masked and gathered) on every shared real set and saves the values; run it in two checkouts and
compare with `--compare A.npz B.npz` (max relative difference per quantity, and whether the subset survivors of
the thesis's steps are the same).

    python -m experiments.core_unchanged OUT.npz          # in the checkout to measure (cwd first on sys.path)
    python -m experiments.core_unchanged --compare A.npz B.npz
"""

import sys
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
SETS = [("opencv_stereo", "left", "jpg"), ("opencv_stereo", "right", "jpg"), ("rig640", "left", "jpg"),
        ("rig640", "right", "jpg")]


def _views(folder, prefix, ext):
    from dstereo.io.corners import detect_folder

    d = detect_folder(DATA / folder, (9, 6), 1.0, files=sorted((DATA / folder).glob(f"{prefix}*.{ext}")))
    return d, sorted(d.corners)


def measure(out: Path) -> None:
    import dstereo
    from dstereo.calib import mono
    from dstereo.calib.multiview import calibrate_views, solve_view_subsets
    from dstereo.calib.rig_subsets import STEP_COLUMNS, subset_table
    from dstereo.calib.subsets import plan_subsets
    from dstereo.models.distortion import PRESETS

    print("dstereo from", Path(dstereo.__file__).parent)
    res = {}
    cams = {}
    for folder, prefix, ext in SETS:
        d, names = _views(folder, prefix, ext)
        obs = np.stack([d.corners[n] for n in names])
        for model in ("default", "rational"):
            key = f"{folder}.{prefix}.{model}"
            full = mono.calibrate_full(d.object_points, obs, d.image_size, PRESETS[model])
            res[key + ".full"] = full.values
            res[key + ".rms"] = np.array([full.rms])
            for m in (4, len(obs) - 3):  # gathered (2m < V) and masked
                plan = plan_subsets(len(obs), m, cap=60, seed=0)
                sub = mono.solve_subsets(d.object_points, obs, plan, full)
                res[f"{key}.subsets{m}"] = sub.values
                res[f"{key}.subsets{m}.rms"] = sub.rms
                res[f"std:{key}.subsets{m}"] = sub.std
                res[f"dof:{key}.subsets{m}"] = np.array([2 * m * d.object_points.shape[0] - sub.values.shape[1] - 6 * m])
            if model == "default":
                cams[(folder, prefix)] = (full.camera(), d, names)
    for folder in ("opencv_stereo", "rig640"):
        (left, dl, nl), (right, dr, nr) = cams[(folder, "left")], cams[(folder, "right")]
        common = sorted(set(n.replace("left", "") for n in nl) & set(n.replace("right", "") for n in nr))
        obs = np.stack([np.stack([dl.corners["left" + c], dr.corners["right" + c]]) for c in common])
        vis = np.ones(obs.shape[:2], bool)
        for mode in ("fixed", "joint"):  # the K = 2 rig (calib/multiview.py), which --left/--right runs
            sol = calibrate_views(dl.object_points, obs, vis, [dl.image_size, dr.image_size], mode=mode,
                                  cameras=[left, right])
            res[f"{folder}.stereo.{mode}"] = sol.values
            res[f"{folder}.stereo.{mode}.rms"] = np.array([sol.rms])
            for m in (4, len(common) - 3):
                plan = plan_subsets(len(common), m, cap=40, seed=0)
                sub = solve_view_subsets(dl.object_points, obs, vis, plan.index, sol)
                table = subset_table(sub, sol, dl.object_points, obs, vis, None, [(0, 1)])
                res[f"{folder}.stereo.{mode}.subsets{m}"] = sub.values
                res[f"{folder}.stereo.{mode}.subsets{m}.re"] = table[:, STEP_COLUMNS.index("stereo_re")]
                res[f"std:{folder}.stereo.{mode}.subsets{m}"] = sub.std
                res[f"dof:{folder}.stereo.{mode}.subsets{m}"] = np.array([4 * m * dl.object_points.shape[0]
                                                                          - sub.values.shape[1] - 6 * m])
    np.savez(out, **res)
    print("wrote", out, len(res), "arrays")


def compare(a: Path, b: Path) -> None:
    A, B = np.load(a), np.load(b)
    worst, worst_std = 0.0, 0.0
    for k in sorted(f for f in A.files if f.startswith("std:")):
        name = k[4:]
        # two LM solves that stop on ftol end within 2 sqrt(ftol (n - p)) std of each other (tests/conftest.py)
        bound = 2 * np.sqrt(1e-12 * float(A["dof:" + name][0]))
        z = np.abs(A[name] - B[name]) / A[k]
        worst_std = max(worst_std, float(z.max()))
        print(f"{name:48s} max |diff| / std {z.max():.2e}  (ftol bound {bound:.1e}){'  OVER' if z.max() > bound else ''}")
    for k in sorted(f for f in A.files if ":" not in f):
        x, y = A[k], B[k]
        scale = np.maximum(np.abs(x), np.abs(y))
        rel = np.abs(x - y) / np.where(scale > 0, scale, 1)
        # parameters near 0 (p1, Ty, ...) compared on the set's largest value of that column
        col = np.abs(x).max(axis=0) if x.ndim == 2 else np.abs(x).max()
        rel_col = np.abs(x - y) / np.where(col > 0, col, 1)
        worst = max(worst, float(rel_col.max()))
        print(f"{k:48s} max rel {rel.max():.2e}  (of column scale {rel_col.max():.2e})")
    print(f"largest difference relative to each quantity's scale: {worst:.2e}; largest in subset std: {worst_std:.2e}")


if __name__ == "__main__":
    if sys.argv[1] == "--compare":
        compare(Path(sys.argv[2]), Path(sys.argv[3]))
    else:
        measure(Path(sys.argv[1]))
