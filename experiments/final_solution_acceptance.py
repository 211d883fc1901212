"""Issue 15, scope 1: is the written camera a solution, and is the rig's +- honest?

(a) Every camera in ../shared/data (opencv_stereo L/R, rig640 L/R, fisheye640; model k1 k2 p1 p2 k3), the
    thesis's steps (m = 10, re <= 0.5 px | p1, p2 1.5 IQR | k1, k2, k3 1.5 IQR | fx, fy, cx, cy 1 IQR, at most
    `--cap` subsets): the camera dstereo writes (default `final = survivors`) and the thesis's subset mean,
    each fitted to the surviving views' corners with every board pose refitted by OpenCV (cv2.solvePnP,
    iterative, then solvePnPRefineLM), against the full-set solve on the same views (cv2.calibrateCamera on
    those corners, its RMS; dstereo's own solve on them beside it).
(b) Rig cross-validation: the pairs of rig640 and opencv_stereo split into disjoint halves (several splits),
    each half calibrated separately by `--left/--right`'s job (the K-camera job, K = 2, full sets);
    z = (a - b) / sqrt(sa^2 + sb^2) for RVx..Tz with sa, sb the +- each half's stereo.yml carries (its pair
    covariance) and, for comparison, the joint solve's Jacobian std alone (without the frames' effects; the
    "sigma_intrinsics_exact" columns, named so when the rig was the fixed-intrinsics solve). Acceptance: RMS
    z <= 1.5.

`python -m experiments.final_solution_acceptance [--cap 300] [--rational]`; writes
experiments/results/final_solution.{md,json} (--rational: the cameras with the rational model, *_rational.*).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
OUT = Path(__file__).resolve().parent / "results"
CAMERAS = (("opencv_stereo", "left*.jpg"), ("opencv_stereo", "right*.jpg"), ("rig640", "left*.jpg"),
           ("rig640", "right*.jpg"), ("fisheye640", "view*.jpg"))
RIG = ("RVx", "RVy", "RVz", "Tx", "Ty", "Tz")


MODEL = ("k1", "k2", "p1", "p2", "k3")


def thesis_config(cap: int, per_set: int | None = 10):
    from dstereo.config.calibration import Config, Step

    steps = (Step(("re",), (0.5,)), Step(("p1", "p2"), (1.5, 1.5)), Step(("k1", "k2", "k3"), (1.5,) * 3),
             Step(("fx", "fy", "cx", "cy"), (1.0,) * 4)) if per_set else ()
    return Config(pattern=(9, 6), square=1.0, per_set=per_set, max_subsets=cap, steps=steps, model=MODEL)


def opencv_refit_rms(K, D, obj, obs, inliers=None) -> float:
    """RMS px over the (inlier) corners of a fixed camera, each view's pose by solvePnP (iterative) +
    solvePnPRefineLM."""
    import cv2

    sse, n = 0.0, 0
    for i, v in enumerate(obs):
        keep = np.ones(len(v), bool) if inliers is None else inliers[i]
        v, o = v[keep], obj[keep]
        ok, rvec, tvec = cv2.solvePnP(o, v, K, D, flags=cv2.SOLVEPNP_ITERATIVE)
        rvec, tvec = cv2.solvePnPRefineLM(o, v, K, D, rvec, tvec,
                                          (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12))
        proj, _ = cv2.projectPoints(o, rvec, tvec, K, D)
        sse += float(np.sum((proj.reshape(-1, 2) - v) ** 2))
        n += len(v)
    return float(np.sqrt(sse / n))


def camera_study(folder: str, glob: str, cap: int) -> dict:
    import cv2

    from dstereo.calib.mono import calibrate_full
    from dstereo.jobs.calibrate_camera import calibrate_camera
    from dstereo.models.distortion import COEFF_NAMES

    cfg = thesis_config(cap).with_overrides(glob=glob)
    t0 = time.perf_counter()
    cal = calibrate_camera(DATA / folder, cfg)
    fs = cal.final_solution
    flat = cal.detection.object_points.astype(np.float64)
    # the board the written camera was solved with (the tool's default solves its sag; corners.npz
    # object_points_solved): a camera is refitted on its own board
    obj = flat.copy()
    if fs.solution.board_sag is not None:
        from dstereo.calib.problem import sag_basis

        obj[:, 2] += np.asarray(sag_basis(obj)) @ fs.solution.board_sag
    obs = cal.observations[fs.views]
    # the camera's own corners: those its solve kept (outlier rejection, on by default, drops stray corners)
    inl = np.ones(obs.shape[:2], bool) if cal.full.inliers is None else cal.full.camera_inliers()[fs.views]
    mat = lambda f: np.array([[f["fx"], 0, f["cx"]], [0, f["fy"], f["cy"]], [0, 0, 1.0]])  # noqa: E731
    vec = lambda f: np.array([f.get(n, 0.0) for n in COEFF_NAMES])[:8 if "k4" in MODEL else 5]  # noqa: E731
    written = opencv_refit_rms(mat(cal.final), vec(cal.final), obj, obs, inl)
    mean = opencv_refit_rms(mat(fs.subset_mean), vec(fs.subset_mean), obj, obs, inl)
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | (cv2.CALIB_RATIONAL_MODEL if "k4" in MODEL else 0)  # dstereo's model
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 500, 1e-15)
    cv_rms, *_ = cv2.calibrateCamera([obj[k].astype(np.float32) for k in inl],
                                     [o[k].astype(np.float32) for o, k in zip(obs, inl)],
                                     cal.detection.image_size, mat(cal.final), vec(cal.final), flags=flags,
                                     criteria=crit)  # on the solved board, held (OpenCV cannot solve a sag)
    sagged = fs.solution.board_sag is not None
    own = calibrate_full(flat, obs, cal.detection.image_size, free=tuple(cal.full.camera().dist.free),
                         board_warp=sagged, inliers=inl).rms
    # for comparison: the flat-board world of OpenCV, its own solve against the written camera refitted flat
    cv_flat, *_ = cv2.calibrateCamera([flat[k].astype(np.float32) for k in inl],
                                      [o[k].astype(np.float32) for o, k in zip(obs, inl)],
                                      cal.detection.image_size, mat(cal.final), vec(cal.final), flags=flags,
                                      criteria=crit)
    written_flat = opencv_refit_rms(mat(cal.final), vec(cal.final), flat, obs, inl)
    out = {"camera": f"{folder}/{glob}", "views": int(len(cal.used)), "surviving_views": int(fs.views.sum()),
           "subsets": int(len(cal.filtering)), "surviving_subsets": int(cal.filtering.survivors.sum()),
           "full_set_solve_rms_opencv": float(cv_rms), "full_set_solve_rms_dstereo": float(own),
           "written_rms_solvepnp": written, "written_vs_full": written / float(own) - 1.0,
           "mean_rms_solvepnp": mean, "mean_vs_full": mean / float(own) - 1.0,
           "mean_rms_tool_refit": fs.check.rms_mean, "tool_warns": bool(fs.check.mean_worse),
           "board_sag": None if not sagged else fs.solution.board_sag.tolist(),
           "flat_board_opencv_rms": float(cv_flat), "written_rms_flat_board": written_flat,
           "seconds": time.perf_counter() - t0}
    for f in (cal.filtering,):
        f.table.close()
    return out


def split_halves(n: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Disjoint halves: odd/even, first/second, and random permutations."""
    idx = np.arange(n)
    splits = [(idx[0::2], idx[1::2]), (idx[: n // 2], idx[n // 2:])]
    rng = np.random.default_rng(seed)
    for _ in range(2):
        p = rng.permutation(n)
        splits.append((np.sort(p[: n // 2]), np.sort(p[n // 2:])))
    return splits


def rig_half(files_l, files_r):
    """(R, T values; the +- stereo.yml carries, its pair covariance; the joint solve's Jacobian std alone, without
    the frames' effects) of one half's `--left/--right` calibration (the K-camera job, K = 2)."""
    from dstereo.calib.calibrations import StereoSources
    from dstereo.jobs.calibrate_stereo import calibrate_stereo_project
    from dstereo.models.pose import rotation_vector

    src = StereoSources(tuple(files_l), tuple(files_r), tuple(files_l), tuple(files_r), "half")
    job = calibrate_stereo_project(src, thesis_config(2000, per_set=None))
    pair, sol = job.pair_files[0], job.solution
    vals = dict(zip(RIG, np.concatenate([np.asarray(rotation_vector(pair.R), float), np.ravel(pair.T)])))
    std = dict(zip(pair.cov_names, np.sqrt(np.maximum(np.diag(pair.cov), 0.0))))
    jac = dict(zip(sol.names, sol.std_jacobian)) if sol.std_jacobian is not None else {}
    return vals, {k: float(std[k]) for k in RIG}, {k: float(jac.get(f"right.{k}", np.nan)) for k in RIG}


def rig_study(folder: str, seed: int = 0) -> dict:
    files_l = sorted((DATA / folder).glob("left*.jpg"))
    files_r = sorted((DATA / folder).glob("right*.jpg"))
    rows, z_new, z_old = [], [], []
    for a, b in split_halves(len(files_l), seed):
        (va, sa, ea), (vb, sb, eb) = (rig_half([files_l[i] for i in h], [files_r[i] for i in h]) for h in (a, b))
        row = {"half_a": [files_l[i].name for i in a], "half_b": [files_l[i].name for i in b]}
        for k in RIG:
            d = va[k] - vb[k]
            zn, zo = d / np.hypot(sa[k], sb[k]), d / np.hypot(ea[k], eb[k])
            row[k] = {"a": va[k], "b": vb[k], "diff": d, "sigma_shown": float(np.hypot(sa[k], sb[k])),
                      "sigma_intrinsics_exact": float(np.hypot(ea[k], eb[k])), "z": zn, "z_intrinsics_exact": zo}
            z_new.append(zn)
            z_old.append(zo)
        rows.append(row)
    rms = lambda z: float(np.sqrt(np.mean(np.square(z))))  # noqa: E731
    return {"set": folder, "pairs": len(files_l), "splits": rows, "rms_z": rms(z_new),
            "rms_z_intrinsics_exact": rms(z_old), "max_abs_z": float(np.max(np.abs(z_new)))}


def markdown(cams: list[dict], rigs: list[dict], cap: int) -> str:
    lines = ["# Issue 15 scope 1: the written camera is a solution; the rig's +- is honest", "",
             f"`python -m experiments.final_solution_acceptance --cap {cap}` (model {' '.join(MODEL)}, thesis steps, "
             f"m = 10, at most {cap} subsets; square = 1).", "",
             "## (a) RMS on the surviving views' corners, every pose refitted by cv2.solvePnP + RefineLM", "",
             "| camera | views (surviving) | subsets (surviving) | full-set solve RMS (OpenCV / dstereo) | written "
             "camera | vs full | thesis mean | vs full | mean, tool's refit | tool warns | board sag (x, y) | flat "
             "board: OpenCV's solve / the written camera refitted |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in cams:
        lines.append(f"| {c['camera']} | {c['views']} ({c['surviving_views']}) | {c['subsets']} "
                     f"({c['surviving_subsets']}) | {c['full_set_solve_rms_opencv']:.4f} / "
                     f"{c['full_set_solve_rms_dstereo']:.4f} | {c['written_rms_solvepnp']:.4f} | "
                     f"{100 * c['written_vs_full']:+.3f} % | {c['mean_rms_solvepnp']:.4f} | "
                     f"{100 * c['mean_vs_full']:+.2f} % | {c['mean_rms_tool_refit']:.4f} | {c['tool_warns']} | "
                     + ("-" if c["board_sag"] is None else f"{c['board_sag'][0]:+.4f}, {c['board_sag'][1]:+.4f}")
                     + f" | {c['flat_board_opencv_rms']:.4f} / {c['written_rms_flat_board']:.4f} |")
    lines += ["", "Acceptance: written camera within 1 % of the full-set solve on the same views (vs full: against "
              "dstereo's solve; OpenCV's calibrateCamera from dstereo's solve is beside it). RMS = sqrt(SSE / "
              "corners) over the camera's own corners (the inliers its solve kept; outlier rejection is on). The tool warns when its own refit (LM per view from three starts) puts the mean > 1 % "
              "above the solve. With the board's sag solved (the default), every refit and OpenCV's solve use the "
              "board the written camera was solved with (corners.npz object_points_solved); the last column is the "
              "flat-board world (OpenCV's own flat solve, and the written camera refitted on the flat board): a "
              "different board model, not a check of the camera.", ""]
    lower = [c for c in cams if c["full_set_solve_rms_opencv"] < 0.999 * c["full_set_solve_rms_dstereo"]]
    gain = lambda c: 100 * (1 - c["full_set_solve_rms_opencv"] / c["full_set_solve_rms_dstereo"])  # noqa: E731
    lines += [f"Found: on {c['camera']} cv2.calibrateCamera, started from dstereo's full-set solve, reaches RMS "
              f"{c['full_set_solve_rms_opencv']:.4f} px, {gain(c):.1f} % below dstereo's own solve: a lower minimum "
              "exists that dstereo's LM does not reach (not part of this change; the written camera is dstereo's "
              "solve)." for c in lower]
    lines += ([""] if lower else []) + [
              "## (b) Rig cross-validation over disjoint halves of the pairs", "",
              "z = (a - b) / sqrt(sa^2 + sb^2) per component RVx..Tz, pooled over the splits (odd/even, "
              "first/second, two random).", "",
              "| set | pairs | splits | RMS z (reported +-: propagated) | max abs z | RMS z (old: intrinsics held "
              "exact) |", "|---|---|---|---|---|---|"]
    for r in rigs:
        lines.append(f"| {r['set']} | {r['pairs']} | {len(r['splits'])} | {r['rms_z']:.2f} | {r['max_abs_z']:.2f} | "
                     f"{r['rms_z_intrinsics_exact']:.2f} |")
    lines += ["", "Per split and component (z propagated / z old):", ""]
    for r in rigs:
        for i, s in enumerate(r["splits"]):
            lines.append(f"- {r['set']} split {i}: " + ", ".join(
                f"{k} {s[k]['z']:+.2f} / {s[k]['z_intrinsics_exact']:+.1f}" for k in RIG))
    lines += ["", "Acceptance: RMS z <= 1.5.", ""]
    return "\n".join(lines)


def main() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)
    ap = argparse.ArgumentParser()
    ap.add_argument("--cap", type=int, default=300, help="subsets per camera (a seeded sample above)")
    ap.add_argument("--skip-cameras", action="store_true", help="rigs only: writes final_solution_rigs.md/.json")
    ap.add_argument("--rational", action="store_true", help="cameras only, rational model (k1..k6, p1, p2)")
    args = ap.parse_args()
    global MODEL
    if args.rational:
        MODEL = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
    cams = [] if args.skip_cameras else [camera_study(f, g, args.cap) for f, g in CAMERAS]
    for c in cams:
        print(json.dumps({k: c[k] for k in ("camera", "written_vs_full", "mean_vs_full", "tool_warns")}))
    rigs = [] if args.rational else [rig_study(s) for s in ("opencv_stereo", "rig640")]
    for r in rigs:
        print(r["set"], "RMS z", r["rms_z"], "old", r["rms_z_intrinsics_exact"])
    OUT.mkdir(exist_ok=True)
    name = "final_solution_rational" if args.rational else "final_solution_rigs" if args.skip_cameras else \
        "final_solution"
    (OUT / f"{name}.json").write_text(json.dumps({"model": MODEL, "cameras": cams, "rigs": rigs}, indent=1,
                                                 default=float))
    (OUT / f"{name}.md").write_text(markdown(cams, rigs, args.cap))


if __name__ == "__main__":
    main()
