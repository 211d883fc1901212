"""The results folder of every `dstereo calibrate` (`write_results`, a finished `calib.calibrations.MultiviewJob`).
One camera (`--images`): the camera's folder (`io.results.fill_camera_folder`). A rig (`--cameras DIR`,
`--left/--right`, the thesis's stereo layout):

    <camera>/                    each camera alone, as `dstereo calibrate` writes one camera (corners.npz, ...)
    cameras.yml, cameras.json    per camera i: K_i, D_i, R_i, T_i (x_cam_i = R_i x_ref + T_i), image size; the
                                 json adds every parameter's std, the held (fixed-intrinsics) solve's values
                                 beside and the rig-consistency test (`calib/rig_consistency.py`)
    rig_<camera>.cameramodel     mrcal's file of each camera in the rig's frame (the reference first), where mrcal
                                 has the lens model
    rig_<camera>_projection_uncertainty.npz   that camera's projection uncertainty in the joint solve (mrcal's
                                 method for a rig's camera, `calib/rig_projection.py`)
    stereo_<a>_<b>.yml           a pair that `dstereo reconstruct` accepts (each adjacent pair, or --pair A,B; a
                                 stereo rig's one pair: stereo.yml, which reconstruct finds in the folder),
                                 with the pair's calibration covariance (`uncertainty.rig.pair_covariance`) and,
                                 as a stereo job's stereo.yml, the board depths and corner angles of the frames
                                 both cameras saw
    frames.csv                   which camera saw which frame, each view's RMS (joint solve)
    rig_subsets.csv, rig_stats/  with images per set m: each rig subset (its frames, every pair's stereo columns
                                 NAME@a-b, its fate) and the thesis's statistics files per step
    plots/                       rig.png (the rig and every frame's board), rig_consistency.png (each frame's
                                 share of the consistency statistic); with subsets T.png, RV.png (the thesis's
                                 Figures 5.15/5.16; per pair T_<a>-<b>.png, RV_<a>-<b>.png for K > 2)
    summary.json, report.md, report.html   (report.html: the same in one page a browser opens, `io.report_html`)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dstereo.io.results import atomic_folder, distortion_vector, fill_camera_folder, write_json

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the finished result this module writes
    from dstereo.calib.calibrations import MultiviewJob


def _distortion(cam) -> np.ndarray:
    return distortion_vector(np.asarray(cam.dist.coeffs), tuple(cam.dist.free))


def _lens(cam) -> str:
    from dstereo.models.distortion import lens_model

    return lens_model(tuple(cam.dist.free))


def write_cameras_yml(path: Path, job: MultiviewJob) -> None:
    import cv2

    sol = job.solution
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        fs.write("camera_count", len(job.labels))
        fs.write("camera_names", ",".join(job.labels))
        fs.write("rms", float(sol.rms))
        fs.write("unit", job.config.unit)  # of every T_i
        for i, (cam, R, T) in enumerate(zip(sol.cameras, sol.R, sol.T)):
            fs.write(f"K_{i}", np.asarray(cam.matrix(), float))
            fs.write(f"D_{i}", _distortion(cam).reshape(1, -1))
            if _lens(cam) != "pinhole":
                fs.write(f"distortion_model_{i}", _lens(cam))
            fs.write(f"R_{i}", np.asarray(R, float))
            fs.write(f"T_{i}", np.asarray(T, float).reshape(3, 1))
            fs.write(f"image_size_{i}", np.array(cam.image_size, np.int32).reshape(1, 2))
    finally:
        fs.release()


def cameras_summary(job: MultiviewJob) -> dict:
    sol, held = job.solution, job.held
    cams = []
    for i, (label, cam, R, T) in enumerate(zip(job.labels, sol.cameras, sol.R, sol.T)):
        own = job.cameras[i]
        cams.append({
            "name": label, "camera_matrix": np.asarray(cam.matrix()).tolist(),
            "distortion_coefficients": _distortion(cam).tolist(), "distortion_model": _lens(cam),
            "image_size": list(cam.image_size), "R": np.asarray(R).tolist(), "T": np.asarray(T).tolist(),
            "views": int(job.visible[:, i].sum()), "rms_joint": float(sol.camera_rms()[i]),
            "rms_alone": float(own.full.rms), "rms_held": float(held.camera_rms()[i]),
        })
    return {
        "sources": job.sources, "reference": job.labels[0], "convention": "x_cam_i = R_i x_ref + T_i (board unit)",
        "unit": job.config.unit, "frames": len(job.frames), "cameras": cams,
        "joint": {"rms": float(sol.rms), "status": sol.status_text, "iterations": sol.iterations,
                  "parameters": dict(zip(sol.names, map(float, sol.values))),
                  "std": dict(zip(sol.names, map(float, sol.std))),  # with the frames' effects (`view_effects`)
                  "std_jacobian": (None if sol.std_jacobian is None
                                   else dict(zip(sol.names, map(float, sol.std_jacobian))))},
        # the held solve's own std would leave out the intrinsics' uncertainty (it read 0.005 deg where the joint
        # solve then moved that rotation by 0.3 deg on a real rig): its values only; the joint std is the rig's +-
        "held": {"rms": float(held.rms), "status": held.status_text,
                 "parameters": dict(zip(held.names, map(float, held.values))),
                 "note": "each camera held at its own calibration; no std: it would omit the intrinsics' "
                         "uncertainty (the joint solve's std is the rig's)"},
        "rig_consistency": None if job.consistency is None else job.consistency.as_dict(),
        "rig_cross_validation": None if job.cross_validation is None else job.cross_validation.as_dict(),
        "rig_subsets": None if job.subsets is None else job.subsets.as_dict(),
        "rejected_frames": [{"frame": n, "statistic_per_constraint": r} for n, r in job.rejected_frames],
        "flipped_views": [[job.labels[c], job.frames[f]] for f, c in sol.flipped],
        "warnings": list(job.warnings), "timings_s": dict(job.timings),
    }


def _write_pair(folder: Path, job: MultiviewJob, pair) -> tuple[str | None, str | None]:
    """(file name, None) written, or (None, why not). `pair`: a `calib.rig_pairs.PairCalibration` (with the
    covariance, so reconstruct's point sigmas carry the calibration's)."""
    from dstereo.io.stereo_files import append_board_depths, board_depth_range, corner_angle_range, write_stereo_yml

    sol, a, b = job.solution, pair.a, pair.b
    ca, cb = sol.cameras[a], sol.cameras[b]
    name = job.pair_file or f"stereo_{job.labels[a]}_{job.labels[b]}.yml"
    write_stereo_yml(folder / name, ca.matrix(), _distortion(ca), cb.matrix(), _distortion(cb), pair.R, pair.T,
                     pair.E, pair.F, ca.image_size, cb.image_size, rms=float(sol.rms), models=(_lens(ca), _lens(cb)),
                     unit=job.config.unit, cov=pair.cov, cov_names=pair.cov_names, cov_structure=pair.structure)
    if len(pair.poses):  # the nearest and farthest board, the widest corner angles: as a stereo job's stereo.yml
        append_board_depths(folder / name, board_depth_range(pair, pair.board) | corner_angle_range(pair, pair.board))
    if tuple(ca.image_size) != tuple(cb.image_size):
        return name, (f"{name}: the cameras' images differ in size ({ca.image_size} / {cb.image_size}); dstereo "
                      "reconstruct rectifies both to the first camera's size (imageSize; imageSize2 holds the second's)")
    return name, None


def write_frames_csv(path: Path, job: MultiviewJob) -> None:
    sol = job.solution
    head = "frame," + ",".join(f"{lab}_seen,{lab}_rms_px" for lab in job.labels)
    rows = [head]
    for f, name in enumerate(job.frames):
        cells = []
        for k in range(len(job.labels)):
            seen = bool(job.visible[f, k])
            cells += [str(int(seen)), f"{sol.per_view_rms[f, k]:.6f}" if seen else ""]
        rows.append(f"{name}," + ",".join(cells))
    path.write_text("\n".join(rows) + "\n")


def report_markdown(summary: dict) -> str:
    lines = [f"# {len(summary['cameras'])} cameras, {summary['frames']} frames", "",
             f"Reference: {summary['reference']}; {summary['convention']}.", "",
             "| camera | views | fx | fy | cx | cy | RMS alone (px) | RMS held (px) | RMS joint (px) | \\|T\\| |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for c in summary["cameras"]:
        K = np.array(c["camera_matrix"])
        lines.append(f"| {c['name']} | {c['views']} | {K[0, 0]:.3f} | {K[1, 1]:.3f} | {K[0, 2]:.3f} | {K[1, 2]:.3f} | "
                     f"{c['rms_alone']:.4f} | {c['rms_held']:.4f} | {c['rms_joint']:.4f} | "
                     f"{np.linalg.norm(c['T']):.4f} |")
    std = summary["joint"]["std"]
    lines += ["", f"Joint solve: RMS {summary['joint']['rms']:.4f} px ({summary['joint']['status']}); held "
              f"(each camera at its own calibration): RMS {summary['held']['rms']:.4f} px.", "",
              "| parameter | joint | std |", "|---|---|---|"]
    lines += [f"| {n} | {v:.6g} | {std[n]:.3g} |" for n, v in summary["joint"]["parameters"].items()]
    from dstereo.io.rig_report import consistency_markdown, cross_validation_markdown, subsets_markdown

    lines += consistency_markdown(summary.get("rig_consistency"))
    lines += cross_validation_markdown(summary.get("rig_cross_validation"))
    lines += subsets_markdown(summary.get("rig_subsets"))
    if summary["flipped_views"]:
        lines += ["", "Views re-read in reversed corner order: "
                  + ", ".join(f"{c}/{f}" for c, f in summary["flipped_views"])]
    for pair in summary.get("pairs", []):
        lines += ["", f"## Pair {pair['left']}-{pair['right']} ({pair['file']}: x_{pair['right']} = R x_{pair['left']} "
                  "+ T; T in the board unit, RV in rad)", "", "| parameter | value | std (the file's covariance) |",
                  "|---|---|---|"]
        lines += [f"| {n} | {c['value']:.6g} | {c['std']:.3g} |" for n, c in pair["columns"].items()]
    if summary["stereo_files"] or summary["stereo_notes"]:
        lines += ["", "Stereo files: " + ", ".join(summary["stereo_files"]) + "".join(
            f"\n- {n}" for n in summary["stereo_notes"])]
    lines += ["", "## Figures", "", "![rig](plots/rig.png)", "",
              "![rig consistency per frame](plots/rig_consistency.png)"]
    lines += [x for name in summary.get("subset_figures", []) for x in ("", f"![{name}]({name})")]
    if summary["warnings"]:
        lines += ["", "## Warnings"] + [f"- {w}" for w in summary["warnings"]]
    return "\n".join(lines) + "\n"


def _rig_subset_files(folder: Path, job: MultiviewJob) -> list[str]:
    """With rig subsets: rig_subsets.csv (each subset's frames, every pair's stereo columns, its fate), rig_stats/
    (the thesis's statistics files per step and column) and, per camera pair, the thesis's box plots of T and RV
    (Figures 5.15/5.16: plots/T.png, RV.png for a stereo rig; T_<a>-<b>.png ... for K > 2). Returns the figures."""
    from dstereo.io.results import write_stats_files, write_subsets_csv
    from dstereo.io.rig_figures import box_plots

    sub = job.subsets
    if sub is None:
        return []
    write_subsets_csv(folder / "rig_subsets.csv", sub.plan, sub.filtering)
    write_stats_files(folder / "rig_stats", sub.filtering, "RIG PARAMETERS")
    figures = []
    pairs = [c.split("@")[1] for c in sub.columns if c.startswith("Tnorm@")]
    for pair in pairs:
        tail = "" if len(pairs) == 1 else f"_{pair}"
        for names, stem, title in ((("Tnorm", "Tx", "Ty", "Tz"), "T", "translation vector T"),
                                   (("RVnorm", "RVx", "RVy", "RVz"), "RV", "rotation vector RV")):
            name = f"plots/{stem}{tail}.png"
            box_plots(sub.filtering, [f"{n}@{pair}" for n in names], folder / name, f"{title} ({pair})",
                      job.config.unit)
            figures.append(name)
    return figures


def _rig_figures(plots: Path, job: MultiviewJob) -> None:
    """plots/rig.png (the rig in the reference's frame with every frame's board) and plots/rig_consistency.png."""
    from dstereo.io.rig_figures import consistency_figure, rig_view

    plots.mkdir()
    sol = job.solution
    cams = [(np.asarray(c.k), c.image_size) for c in sol.cameras]
    board = job.cameras[0].detection.board
    rig_view(cams, np.concatenate([sol.rvecs, sol.T], axis=1), job.labels, sol.poses, board.object_points(),
             board.pattern, plots / "rig.png", job.config.unit, title=f"rig of {len(job.labels)} cameras")
    if job.consistency is not None:
        consistency_figure(job.consistency, plots / "rig_consistency.png")


def write_results(out, job: MultiviewJob, force: bool = False, early=None) -> Path:
    """The results folder of any calibration (`calib.calibrations.MultiviewJob`), written under a temporary name and
    renamed into place at the end: one camera's folder (`io.results.fill_camera_folder`; `early`: its parameter
    figures drawn already, `io.results.EarlyFigures`) for one camera, the folder of the module docstring for a rig
    (the pair files are `job.pair_files`, `MultiviewJob.choose_pairs`)."""
    out = Path(out)
    try:
        with atomic_folder(out, force) as tmp:
            if not job.is_rig:  # one camera: its folder is the results folder
                fill_camera_folder(tmp, job.cameras[0], early=early)
                return out
            for label, cal in zip(job.labels, job.cameras):
                (tmp / label).mkdir()
                fill_camera_folder(tmp / label, cal)
            write_cameras_yml(tmp / "cameras.yml", job)
            summary = cameras_summary(job)
            summary["stereo_files"], summary["stereo_notes"], summary["pairs"] = [], [], []
            for pair in job.pair_files:
                name, note = _write_pair(tmp, job, pair)
                if name:
                    summary["stereo_files"].append(name)
                    summary["pairs"].append({"file": name, "left": job.labels[pair.a], "right": job.labels[pair.b],
                                             "columns": {k: {"value": v, "std": e}
                                                         for k, (v, e) in pair.columns().items()}})
                if note:
                    summary["stereo_notes"].append(note)
                    job.warnings.append(note)  # printed by the command too, not only in report.md
            from dstereo.io.cameramodel import write_cameramodels_of_rig  # mrcal's format, the reference first

            sol = job.solution
            solve, why = _rig_solve(job)
            summary["cameramodels"] = write_cameramodels_of_rig(
                tmp, [(c.matrix(), c.coeffs(), c.dist.free, c.image_size) for c in sol.cameras],
                [f"rig_{label}" for label in job.labels], np.concatenate([sol.rvecs, sol.T], axis=1), solve, why)
            summary["rig_projection_uncertainty"] = _write_rig_maps(tmp, job)
            summary["warnings"] = list(job.warnings)
            write_json(tmp / "cameras.json", summary)
            write_frames_csv(tmp / "frames.csv", job)
            _rig_figures(tmp / "plots", job)
            summary["subset_figures"] = _rig_subset_files(tmp, job)
            write_json(tmp / "summary.json", summary)
            (tmp / "report.md").write_text(report_markdown(summary))
            from dstereo.io.report_headlines import rig_headline
            from dstereo.io.report_html import write_report_html

            write_report_html(tmp, rig_headline(summary))
    finally:
        for cal in job.cameras:
            if cal.filtering is not None:
                cal.filtering.table.close()
    return out


def _write_rig_maps(folder: Path, job: MultiviewJob) -> dict:
    """rig_<camera>_projection_uncertainty.npz (u, v, std, cov, range, mask, method, as one camera's
    projection_uncertainty.npz) of each camera in the joint solve (`calib/rig_projection.py`: mrcal's method for a
    rig's camera); returns the summary entries."""
    out = {}
    for label, pmap in zip(job.labels, job.projection or []):
        name = f"rig_{label}_projection_uncertainty.npz"
        np.savez(folder / name, u=pmap.u, v=pmap.v, std=pmap.std, cov=pmap.cov, range=pmap.range_, mask=pmap.mask,
                 method=pmap.method)
        out[label] = {**pmap.summary(), "file": name, "unit": job.config.unit,
                      "note": "the joint rig solve's, pose-compensated over every frame (mrcal's method for a "
                              "camera of a rig), Jacobian covariance sigma^2 = SSE / (N - p)"}
    return out


def _rig_solve(job: MultiviewJob):
    """(the joint rig solve cameras.yml holds as io.cameramodel.BoardSolve, or None and why): the frames, corners
    and inliers it was solved on, as it read them (the job's `solved_observations`, `solved_inliers`)."""
    from dstereo.io.cameramodel import BoardSolve

    sol = job.solution
    frees = {tuple(c.dist.free) for c in sol.cameras}
    if len(frees) != 1:
        return None, "no optimization inputs: the cameras have different lens models, and mrcal's solve has one"
    if job.solved_observations is None:
        return None, "no optimization inputs: the job kept no corners as its solve read them"
    obs, inliers = job.solved_observations, job.solved_inliers
    board = job.cameras[0].detection.board
    return BoardSolve(frees.pop(), np.array([np.asarray(c.k, float) for c in sol.cameras]),
                      np.array([np.asarray(c.coeffs(), float) for c in sol.cameras]),
                      tuple(tuple(c.image_size) for c in sol.cameras),
                      np.concatenate([sol.rvecs, sol.T], axis=1)[1:], np.asarray(sol.poses, float), obs,
                      np.asarray(sol.visible, bool), inliers, (board.cols, board.rows), float(board.square),
                      sol.board_sag), ""
