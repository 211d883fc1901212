"""The K = 3 subset case of bench_subsets: many frame subsets of a rendered 3-camera rig, solved batched.

The rig is `synth.multiview_set(3, 60, seed=3)` (tests/calib/test_multiview.py's K = 3 case), corners detected
and ordered, float32. dstereo solves every subset with `calib.multiview.solve_view_subsets` from the full solve,
in joint mode (everything refined) and in fixed mode (OpenCV's intrinsics held); OpenCV solves each subset with
`calibrateMultiviewExtended`, once its own way (per-camera calibrateCamera, then extrinsics) and once with the
same intrinsics held (CALIB_USE_INTRINSIC_GUESS), one process, one subset after another. Fixed mode and OpenCV
held solve the same problem, so their translations are compared subset by subset.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from tests.calib.opencv_reference import FIVE, calibrate_multiview, float32_corners, opencv_cameras

N_CAMERAS, SEED, PER_SET, CAP = 3, 3, 40, 200


def render_case(n_cameras: int, seed: int, folder: Path):
    """The CameraFolders of one rendered rig written to `folder`."""
    from dstereo.io.camera_folders import read_camera_folders
    from dstereo.synth import multiview_set, write_multiview_set

    mset = multiview_set(n_cameras, 60, seed)
    write_multiview_set(folder, mset, force=True)
    board = mset.truth["board"]
    return read_camera_folders(folder, tuple(board["pattern"]), board["square"], use_cache=False)


def _translations(names, values: np.ndarray, n_cams: int) -> np.ndarray:
    """(C, K-1, 3) camera translations from subset values (C, G) laid out by `names` ('cam1.Tx', ...)."""
    idx = [[names.index(f"cam{k}.T{a}") for a in "xyz"] for k in range(1, n_cams)]
    return np.stack([values[:, i] for i in idx], axis=1)


def _opencv_subsets(args, index, K0=None, D0=None) -> tuple[float, np.ndarray]:
    obj, obs, visible, sizes = args
    t0 = time.perf_counter()
    ts = [calibrate_multiview(obj, obs[rows], visible[rows], sizes, K0=K0, D0=D0).T[1:] for rows in index]
    return time.perf_counter() - t0, np.stack(ts)


def multiview_subset_case() -> dict:
    """One row of figures for the K = 3 case (module docstring)."""
    from dstereo.calib.multiview import calibrate_views, solve_view_subsets
    from dstereo.calib.subsets import plan_subsets

    with tempfile.TemporaryDirectory() as tmp:
        folders = render_case(N_CAMERAS, SEED, Path(tmp) / "rig")
    obs = float32_corners(folders.obs)
    args = (folders.object_points, obs, folders.visible, folders.image_sizes)
    cv_full = calibrate_multiview(*args)
    joint = calibrate_views(*args, free=FIVE, mode="joint")
    fixed = calibrate_views(*args, free=FIVE, mode="fixed", cameras=opencv_cameras(cv_full, folders.image_sizes))
    plan = plan_subsets(len(folders.frames), PER_SET, cap=CAP)
    timings = {}
    for label, start in (("joint", joint), ("fixed", fixed)):
        t0 = time.perf_counter()
        solve_view_subsets(folders.object_points, obs, folders.visible, plan.index, start)
        timings[f"{label}_cold_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        subs = solve_view_subsets(folders.object_points, obs, folders.visible, plan.index, start)
        timings[f"{label}_warm_s"] = time.perf_counter() - t0
        timings[f"{label}_converged"] = int(np.sum(subs.converged))
        if label == "fixed":
            t_fixed = _translations(list(subs.names), subs.values, N_CAMERAS)
    timings["opencv_s"], _ = _opencv_subsets(args, plan.index)
    timings["opencv_held_s"], t_held = _opencv_subsets(args, plan.index, cv_full.K, cv_full.D)
    rel = np.linalg.norm(t_fixed - t_held, axis=-1) / np.linalg.norm(t_held, axis=-1)
    return {"subsets": len(plan.index), "per_set": PER_SET, "frames": len(folders.frames),
            "images": int(folders.visible.sum()), "max_rel_T_fixed_vs_held": float(rel.max()), **timings}


def report_lines(r: dict) -> list[str]:
    n = r["subsets"]
    rate = lambda s: f"{r[s]:.2f} s ({n / r[s]:.0f}/s)"  # noqa: E731
    return [
        "", f"## K = 3 rig, frame subsets (rendered, {r['frames']} frames, {r['images']} images; C={n}, "
        f"m={r['per_set']} frames)", "",
        "| solve | dstereo cold (incl. compile) | dstereo warm | converged | OpenCV 1 proc, one subset at a time |",
        "|---|---|---|---|---|",
        f"| joint (dstereo) / OpenCV's own (per-camera calibrateCamera + extrinsics) | {rate('joint_cold_s')} | "
        f"{rate('joint_warm_s')} | {r['joint_converged']} | {rate('opencv_s')} |",
        f"| fixed (OpenCV's intrinsics held) / OpenCV held (CALIB_USE_INTRINSIC_GUESS) | {rate('fixed_cold_s')} | "
        f"{rate('fixed_warm_s')} | {r['fixed_converged']} | {rate('opencv_held_s')} |",
        "", f"Fixed vs OpenCV held, same subsets: largest relative translation difference "
        f"{r['max_rel_T_fixed_vs_held']:.1e}. The joint row refines 27 more parameters than OpenCV's own, which "
        "never refines intrinsics together with the rig.",
    ]
