"""Stereo pairs and stereo calibration files at the OpenCV edge.

- `detect_pairs`: board corners in both cameras' images, pairs matched by name (`io.pairing`: left05 with
  right05); a pair where either image lacks the full board is listed in `dropped` with the reason, never dropped
  silently, and images without a partner are listed in `warnings`.
- `write_stereo_yml`: OpenCV FileStorage YAML with the keys of OpenCV's stereo_calib sample (M1 D1 M2 D2 R T)
  plus E, F and `imageSize` [w, h] (`imageSize2` when the right camera's differs), readable by
  `dstereo.io.calib_files.read_stereo_calibration`. A rig with a fisheye camera adds `distortion_model1` and
  `distortion_model2` (pinhole or fisheye); a fisheye camera's D is then cv2.fisheye's 1x4 (k1 k2 k3 k4).
- `write_stereo_json`, `write_stereo_corners` (`left/<file>`, `right/<file>`, `object_points`).
Every file is written under a temporary name and renamed, so none is ever left half-written.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
import numpy as np

from dstereo.errors import DstereoError
from dstereo.io.corners import Detection, detect_folder, list_images
from dstereo.io.pairing import check_enough_pairs, pair_by_name
from dstereo.models.board import Board


@dataclass(frozen=True)
class DroppedPair:
    left: str
    right: str
    reason: str


@dataclass
class StereoDetection:
    """Corners of both cameras and the stereo pairs (left name, right name) that show the board in both."""

    left: Detection
    right: Detection
    pairs: list[tuple[str, str]]
    dropped: list[DroppedPair] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)  # images left out for want of a partner named like them
    # (n, 3) the board the rig was solved on when it is not flat (the board's sag, `stereo_pipeline.rig_board_sag`)
    solved_board: np.ndarray | None = None

    @property
    def board(self) -> Board:
        return self.left.board  # both cameras were detected on the one board

    @property
    def object_points(self) -> np.ndarray:
        """The board's corners the rig was solved on: sagged when solved so (corners.npz's `object_points_solved`)."""
        return self.board.object_points() if self.solved_board is None else self.solved_board

    def observations(self) -> tuple[np.ndarray, np.ndarray]:
        """(V, n, 2) left and right corners of the pairs, in pair order."""
        return (np.stack([self.left.corners[a] for a, _ in self.pairs]),
                np.stack([self.right.corners[b] for _, b in self.pairs]))


def image_files(source: str | Path | list, suffix: str | None = None) -> list[Path]:
    """A folder's images (sorted by name), or an explicit sequence of image paths kept in its order."""
    if isinstance(source, (str, Path)):
        return list_images(Path(source), suffix)
    files = [Path(p) for p in source]
    missing = [str(p) for p in files if not p.is_file()]
    if missing:
        raise DstereoError(f"images: {missing[:3]} do not exist; check the image list")
    if not files:
        raise DstereoError("images: the image list is empty")
    return files


def _where(source, files: list[Path]) -> str:
    return str(source) if isinstance(source, (str, Path)) else f"the list starting {files[0]}"


def detect_pairs(left, right, pattern: tuple[int, int], square: float, suffix: str | None = None,
                 use_cache: bool = True, progress=None) -> StereoDetection:
    """Detect the board in `left` and `right` (folders or image lists), the images paired by name
    (`io.pairing`): images without a partner are left out with a warning; too few pairs are refused before any
    detection."""
    files_l, files_r = image_files(left, suffix), image_files(right, suffix)
    named = pair_by_name(files_l, files_r)
    check_enough_pairs(named, _where(left, files_l), _where(right, files_r))
    same = [a for a, b in named.pairs if a.resolve() == b.resolve()]
    if same:
        raise DstereoError(f"stereo images: {same[0]} is given as both the left and the right image"
                           + (f" ({len(same) - 1} more)" if len(same) > 1 else "")
                           + "; give each camera's own images (`left` and `right` point at different files)")
    files_l, files_r = [a for a, _ in named.pairs], [b for _, b in named.pairs]
    det_l = detect_folder(files_l[0].parent, pattern, square, files=files_l, use_cache=use_cache, progress=progress)
    det_r = detect_folder(files_r[0].parent, pattern, square, files=files_r, use_cache=use_cache, progress=progress)
    pairs, dropped = match_pairs(det_l, det_r, [p.name for p in files_l], [p.name for p in files_r])
    if not pairs:
        raise DstereoError(
            f"stereo images: no pair shows the full {pattern[0]}x{pattern[1]} board in both cameras (left boards "
            f"in {sorted(det_l.corners) or 'none'}, right boards in {sorted(det_r.corners) or 'none'}); check that "
            "the left and right images are taken at the same moments and named alike"
        )
    warnings = [named.warning()] if named.warning() else []
    warnings += _align_right_order(det_l, det_r, pairs, pattern)
    return StereoDetection(det_l, det_r, pairs, dropped, warnings)


def _align_right_order(det_l: Detection, det_r: Detection, pairs: list[tuple[str, str]],
                       pattern: tuple[int, int]) -> list[str]:
    """Renumber a right image's corners that OpenCV numbered from another corner of the board than the left's
    (`calib.view_checks.align_order`); otherwise the pair's corners would not correspond. Returns the warning."""
    from dstereo.calib.view_checks import align_order

    turned = []
    for a, b in pairs:
        aligned, turn = align_order(det_l.corners[a], det_r.corners[b], pattern)
        if turn:
            det_r.corners[b] = aligned
            turned.append(f"{a} / {b} ({turn} deg)")
    if not turned:
        return []
    return [f"{len(turned)} stereo pair(s) had their right corners numbered from another corner of the board than the "
            f"left ({', '.join(turned[:6])}{' ...' if len(turned) > 6 else ''}); renumbered to match the left, as the "
            f"{pattern[0]}x{pattern[1]} grid's symmetry allows"]


def match_pairs(det_left: Detection, det_right: Detection, names_left: list[str],
                names_right: list[str]) -> tuple[list[tuple[str, str]], list[DroppedPair]]:
    """Pair left and right images by name (`io.pairing`); pairs missing the board on either side are dropped with
    the reason, and so is an image without a partner."""
    named = pair_by_name([Path(n) for n in names_left], [Path(n) for n in names_right])
    pairs, dropped = [], []
    for a, b in ((str(a), str(b)) for a, b in named.pairs):
        reasons = [f"{side} {name}: {det.rejected.get(name, 'no board')}"
                   for side, name, det in (("left", a, det_left), ("right", b, det_right)) if name not in det.corners]
        if reasons:
            dropped.append(DroppedPair(a, b, "; ".join(reasons)))
        else:
            pairs.append((a, b))
    dropped += [DroppedPair(str(a), "", "no right image named like it") for a in named.left_alone]
    dropped += [DroppedPair("", str(b), "no left image named like it") for b in named.right_alone]
    return pairs, dropped


# --- writers ---------------------------------------------------------------------------------------------------


from dstereo.io.atomic_files import replace_atomically as _replace_atomically  # noqa: E402


def write_stereo_yml(path, K1, D1, K2, D2, R, T, E, F, image_size: tuple[int, int],
                     image_size_right: tuple[int, int] | None = None, rms: float | None = None, *,
                     cov: np.ndarray | None = None, cov_names: tuple[str, ...] | None = None,
                     cov_structure: str | None = None, models: tuple[str, str] = ("pinhole", "pinhole"),
                     unit: str = "mm") -> Path:
    """OpenCV YAML with M1 D1 M2 D2 R T E F imageSize (+ imageSize2, rms) and `unit`, the length unit of T (and of
    the board depths appended after): readers convert from it (`calib_files.read_opencv_stereo`). The default, mm,
    is a `StereoCalibration`'s unit; a calibration's writer passes its board unit. D as 1x8 rows in OpenCV's order.

    With `cov`: the calibration covariance as `cov` (G x G matrix), `cov_names` (one string, comma separated:
    left.fx .. left.<free coefficients>, right.*, RVx RVy RVz Tx Ty Tz; RV is the axis-angle vector of R) and
    `cov_structure` (how it was obtained), read back into `StereoCalibration.extras` by `read_stereo_calibration`.
    """
    import cv2

    from dstereo.config.units import check_unit
    from dstereo.io.calib_files import LENS_MODELS

    unit = check_unit(unit, f"{path}: unit {unit!r}")
    if any(m not in LENS_MODELS for m in models):
        raise DstereoError(f"{path}: lens models {models}; each is one of {list(LENS_MODELS)}")
    D1, D2 = (np.asarray(d, float).ravel()[:4] if m == "fisheye" else d for d, m in zip((D1, D2), models))
    if cov is not None:
        cov = np.asarray(cov, dtype=float)
        if cov_names is None or cov.shape != (len(cov_names), len(cov_names)):
            raise DstereoError(f"{path}: covariance {cov.shape} needs one name per row ({cov_names})")

    def write(tmp: Path) -> None:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        if not fs.isOpened():
            raise DstereoError(f"{path}: cannot be written; check that the folder exists and is writable")
        try:
            for key, value, shape in (("M1", K1, (3, 3)), ("D1", D1, (1, -1)), ("M2", K2, (3, 3)), ("D2", D2, (1, -1)),
                                      ("R", R, (3, 3)), ("T", T, (3, 1)), ("E", E, (3, 3)), ("F", F, (3, 3))):
                fs.write(key, np.asarray(value, dtype=float).reshape(shape))
            fs.write("unit", unit)
            if "fisheye" in models:  # without the fields a reader takes both cameras as OpenCV's pinhole model
                fs.write("distortion_model1", models[0])
                fs.write("distortion_model2", models[1])
            fs.write("imageSize", np.array(image_size, dtype=np.int32).reshape(1, 2))
            if image_size_right is not None and tuple(image_size_right) != tuple(image_size):
                fs.write("imageSize2", np.array(image_size_right, dtype=np.int32).reshape(1, 2))
            if rms is not None:
                fs.write("rms", float(rms))
            if cov is not None:
                fs.write("cov_names", ",".join(cov_names))
                fs.write("cov", cov)
                fs.write("cov_structure", cov_structure or "")
        finally:
            fs.release()

    return _replace_atomically(Path(path), write)


def board_depth_range(solution, object_points: np.ndarray) -> dict:
    """Nearest and farthest board corner depth (left camera z, the calibration's unit) over the solution's
    board poses: `reconstruct` uses it as a search-range prior when a pair has too few sparse matches."""
    from dstereo.models.pose import rotation_matrix

    obj = np.asarray(object_points, float).reshape(-1, 3)
    z = np.concatenate([obj @ rotation_matrix(p[:3])[2] + p[5] for p in np.asarray(solution.poses)])
    return {"board_depth_min": float(z.min()), "board_depth_max": float(z.max())}


def corner_angle_range(solution, object_points: np.ndarray) -> dict:
    """{'corner_angle_max1', 'corner_angle_max2'}: the widest angle (degrees) off each camera's optical axis of the
    board corners at the solution's poses (x_right = R x_left + T): where each lens model was measured, written to
    stereo.yml so that `reconstruct` takes a fisheye's field no farther."""
    from dstereo.models.pose import rotation_matrix

    obj = np.asarray(object_points, float).reshape(-1, 3)
    left = np.concatenate([obj @ np.asarray(rotation_matrix(p[:3])).T + p[3:6] for p in np.asarray(solution.poses)])
    right = left @ np.asarray(solution.R, float).T + np.asarray(solution.T, float).reshape(3)
    def widest(p):
        return float(np.degrees(np.arccos(np.clip(p[:, 2] / np.linalg.norm(p, axis=1), -1.0, 1.0))).max())

    return {"corner_angle_max1": widest(left), "corner_angle_max2": widest(right)}


def append_board_depths(path: Path, depths: dict) -> None:
    """Add `board_depth_range`'s two scalars to a written stereo.yml (top-level OpenCV YAML nodes, optional:
    readers that do not know them ignore them)."""
    with Path(path).open("a") as fh:
        fh.writelines(f"{key}: {value!r}\n" for key, value in depths.items())


def write_json(path, data: dict) -> Path:
    """Any nest of dicts, lists, numpy arrays and scalars as indented JSON (non-finite numbers as null)."""
    from dstereo.io.json_files import json_text

    text = json_text(data, indent=1)
    return _replace_atomically(Path(path), lambda tmp: tmp.write_text(text))


def write_stereo_corners(path, detection: StereoDetection) -> Path:
    """corners.npz: `left/<file>`, `right/<file>` (n, 2) px of the stereo pairs, `object_points` (n, 3) the nominal
    flat board and, when the rig was solved on a sagged one, `object_points_solved` (as one camera's corners.npz)."""
    arrays = {"object_points": detection.board.object_points()}
    if detection.solved_board is not None:
        arrays["object_points_solved"] = detection.solved_board
    for a, b in detection.pairs:
        arrays[f"left/{a}"] = detection.left.corners[a]
        arrays[f"right/{b}"] = detection.right.corners[b]

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)

    return _replace_atomically(Path(path), write)


# --- the stereo results folder -------------------------------------------------------------------------------------

STEREO_TITLE = "STEREO PARAMETERS"
STEREO_UNITS = {"stereo_re": "px", "RVnorm": "rad", "RVx": "rad", "RVy": "rad", "RVz": "rad"}


def write_stereo_results(out, job: StereoCalibrationJob, force: bool = False) -> Path:
    """The results folder of a `stereo_pipeline.StereoCalibrationJob`, filled under a temporary name:
        left/, right/            each camera's folder, as `dstereo calibrate` writes for one camera
        stereo.yml, stereo.json  M1 D1 M2 D2 R T E F imageSize (final values) / everything, with std; both
                                 carry the calibration covariance (cov, cov_names, cov_structure)
        corners.npz              left/<file>, right/<file> of the stereo pairs, object_points
        stereo_pairs.csv         each pair's RMS reprojection error (both cameras, left, right), full-set solve
        stereo_subsets.csv, stereo_stats/   per subset and per step (with images per set)
        plots/                   T.png, RV.png (thesis Figures 5.15/5.16), <param>.png, rig.png, pair_rms.png
        summary.json, report.md
    """
    from dstereo.io.results import atomic_folder, fill_camera_folder

    out = Path(out)
    try:
        with atomic_folder(out, force) as tmp:
            for side, cal in (("left", job.left), ("right", job.right)):
                (tmp / side).mkdir()
                fill_camera_folder(tmp / side, cal)
            _fill_stereo_folder(tmp, job)
    finally:  # huge runs' per-subset files (now in the CSVs) go
        for filtering in (job.left.filtering, job.right.filtering, job.filtering):
            if filtering is not None:
                filtering.table.close()
    return out


def stereo_summary(job: StereoCalibrationJob) -> dict:
    """summary.json / stereo.json of a stereo job."""
    from dstereo.config.calibration import as_dict
    from dstereo.models.distortion import coeff_slots

    s, det = job.full, job.detection
    cams = {side: {"camera_matrix": c.matrix(), "lens": c.lens,  # a fisheye's coefficients are named fk1..fk4
                   "coeffs": {n: float(v) for n, v in zip(coeff_slots(tuple(c.dist.free)), c.coeffs()) if n},
                   "free": list(c.dist.free), "image_size": list(c.image_size)}
            for side, c in (("left", s.left), ("right", s.right))}
    full_std = dict(zip(s.names, map(float, s.std))) | {"Tnorm": s.baseline_std, "RVnorm": s.angle_std}
    sigma = getattr(job, "full_set_sigma", None)  # calib/final_solution.py: the honest +- (intrinsics carried)
    if sigma is not None:
        full_std |= sigma.std
    summary = {
        "config": as_dict(job.config), "sources": job.sources.description, "same_images": job.sources.shared,
        "board_sag": job.board_sag,
        "board_sag_solved": None if getattr(job, "rig_sag", None) is None else job.rig_sag.as_dict(),
        "rig_consistency": None if getattr(job, "consistency", None) is None else job.consistency.as_dict(),
        "rig_cross_validation": (None if getattr(job, "cross_validation", None) is None
                                 else job.cross_validation.as_dict()),
        "cameras": cams, "pattern": {"columns": det.board.cols, "rows": det.board.rows,
                                     "square": det.board.square, "unit": job.config.unit},
        "final": {"R": job.R, "rvec": [job.final[k] for k in ("RVx", "RVy", "RVz")], "T": job.T, "E": job.E,
                  "F": job.F, **job.final},
        "final_spread": job.spread,
        "final_source": (f"mean over the {int(job.filtering.survivors.sum())} surviving subsets (the thesis's answer)"
                         if job.filtering is not None else "full-set solve (no subsets: set images per set)"),
        "full_set": {"mode": s.mode, "R": s.R, "rvec": s.rvec, "T": s.T, "E": s.E, "F": s.F, **s.columns(),
                     "std": full_std,
                     "std_kind": sigma.label if sigma is not None else "Jacobian with the pairs' effects (view_effects)",
                     "std_jacobian": None if s.std_jacobian is None else dict(zip(s.names, map(float, s.std_jacobian))),
                     "std_intrinsics_exact": None if sigma is None else sigma.intrinsics_exact,
                     "baseline": {"value": s.baseline, "std": full_std["Tnorm"]},
                     "rms": s.rms, "stereo_re": s.stereo_re, "status": s.status_text, "iterations": s.iterations,
                     "conditioning": s.conditioning.message(), "covariance": s.cov, "names": list(s.names)},
        "reprojection_error": "rms: sqrt(SSE / corners) over both cameras (cv2.stereoCalibrate's value); stereo_re: "
                              "the mean over pairs of each pair's RMS (thesis 4.2.2.2)",
        "pairs": [{"left": a, "right": b, "rms": float(e)} for (a, b), e in zip(det.pairs, s.per_pair_rms)],
        "dropped": [{"left": d.left, "right": d.right, "reason": d.reason} for d in det.dropped],
        "individual": {side: {"rms": float(c.full.rms), "images": len(c.used), "final": c.final}
                       for side, c in (("left", job.left), ("right", job.right))},
        "subsets": None, "warnings": list(job.warnings), "timings": dict(job.timings),
    }
    if getattr(job, "rig_final", None) is not None:
        summary["final_source"] = job.rig_final.source()
        summary["final_check"] = job.rig_final.as_dict(det.pairs)
        summary["subset_mean"] = dict(job.subset_mean)
    if job.filtering is not None:
        f, plan = job.filtering, job.plan
        summary["subsets"] = {"per_set": int(plan.per_set), "solved": int(len(plan)),
                              "sampling": plan.describe(), "initial_count": int(f.usable.sum()),
                              "final_count": int(f.survivors.sum()), "initial": f.stats(0),
                              "final": f.stats(len(f.steps)),
                              "steps": [{"step": s.number, "parameters": list(s.parameters),
                                         "max_error": list(s.max_error), "before": s.before, "survivors": s.after,
                                         "message": s.message} for s in f.steps]}
    return summary


def _fill_stereo_folder(folder: Path, job: StereoCalibrationJob) -> None:
    from dstereo.io.results import write_stats_files, write_subsets_csv

    s, det = job.full, job.detection
    if job.calibration_covariance is None:
        raise ValueError("the stereo job was not finished: calib.final_solution.attach_rig_uncertainty sets the "
                         "calibration covariance stereo.yml carries")
    cov_names, cov, cov_structure = job.calibration_covariance
    from dstereo.models.distortion import lens_model

    write_stereo_yml(folder / "stereo.yml", s.left.matrix(), s.left.coeffs(), s.right.matrix(), s.right.coeffs(),
                     job.R, job.T, job.E, job.F, s.left.image_size, s.right.image_size, s.rms, cov=cov,
                     cov_names=cov_names, cov_structure=cov_structure,
                     models=tuple(lens_model(tuple(c.dist.free)) for c in (s.left, s.right)), unit=job.config.unit)
    summary = stereo_summary(job)
    from dstereo.io.cameramodel import write_rig_cameramodels  # mrcal's format, the left camera as reference

    summary["cameramodels"] = write_rig_cameramodels(folder, [(c.matrix(), c.coeffs(), c.dist.free, c.image_size)
                                                              for c in (s.left, s.right)], job.R, job.T)
    summary["board_depth_range"] = board_depth_range(s, det.object_points)
    append_board_depths(folder / "stereo.yml", summary["board_depth_range"])
    summary["corner_angle_max_deg"] = corner_angle_range(s, det.object_points)
    append_board_depths(folder / "stereo.yml", summary["corner_angle_max_deg"])
    summary["calibration_covariance"] = {"names": list(cov_names), "cov": cov, "structure": cov_structure,
                                         "std": dict(zip(cov_names, np.sqrt(np.maximum(np.diag(cov), 0.0))))}
    write_json(folder / "stereo.json", summary)
    write_stereo_corners(folder / "corners.npz", det)
    rms_l = np.sqrt(np.mean(np.sum(s.residuals[:, 0] ** 2, axis=2), axis=1))
    rms_r = np.sqrt(np.mean(np.sum(s.residuals[:, 1] ** 2, axis=2), axis=1))
    lines = ["left,right,rms_px,left_rms_px,right_rms_px"]
    lines += [f"{a},{b},{e!r},{el!r},{er!r}" for (a, b), e, el, er in
              zip(det.pairs, s.per_pair_rms.tolist(), rms_l.tolist(), rms_r.tolist())]
    (folder / "stereo_pairs.csv").write_text("\n".join(lines) + "\n")
    plots = folder / "plots"
    plots.mkdir()
    if job.filtering is not None:
        f = job.filtering
        write_stats_files(folder / "stereo_stats", f, STEREO_TITLE)
        write_subsets_csv(folder / "stereo_subsets.csv", job.plan, f, f.table.status)
        from dstereo.io import plots as mono_plots

        full_values = s.columns()
        for name in f.columns:
            mono_plots.parameter_figure(name, f.values(name, 0), f.values(name, len(f.steps)),
                                        plots / f"{name}.png", STEREO_UNITS.get(name, job.config.unit),
                                        full_values[name])
        for names, target, title in ((("Tnorm", "Tx", "Ty", "Tz"), "T.png", "translation vector T"),
                                     (("RVnorm", "RVx", "RVy", "RVz"), "RV.png", "rotation vector RV")):
            box_plots(f, names, plots / target, title, job.config.unit)
    rig_figure(s, det, plots / "rig.png", job.config.unit)
    if getattr(job, "consistency", None) is not None:
        from dstereo.io.rig_figures import consistency_figure

        consistency_figure(job.consistency, plots / "rig_consistency.png")
    pair_rms_figure([a for a, _ in det.pairs], s.per_pair_rms, rms_l, rms_r, plots / "pair_rms.png")
    write_json(folder / "summary.json", summary)
    (folder / "report.md").write_text(report_markdown(job, summary))


from dstereo.io.figures import pyplot as _pyplot  # noqa: E402 - the figures below share io/figures' backend

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the finished result this module writes
    from dstereo.calib.calibrations import StereoCalibrationJob


def box_plots(filtering, names, path: Path, title: str, unit: str) -> None:
    """Thesis Figures 5.15/5.16: one panel per parameter, box plots of the initial and the optimised subsets."""
    from dstereo.io.plots import box_stats

    plt = _pyplot()
    fig, axes = plt.subplots(1, len(names), figsize=(3.2 * len(names), 3.8))
    for ax, name in zip(axes, names):
        col = filtering.column(name)
        ax.bxp([box_stats(col[filtering.alive_after(0)], "initial"), box_stats(col[filtering.survivors], "final")],
               widths=0.6)
        ax.set_xticks([1, 2], ["initial", "optimised"])
        ax.set_title(f"{name} ({STEREO_UNITS.get(name, unit)})")
        ax.ticklabel_format(axis="y", useOffset=False)
    fig.suptitle(f"{title}: {int(filtering.usable.sum())} initial, {int(filtering.survivors.sum())} optimised subsets")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def rig_figure(solution, detection: StereoDetection, path: Path, unit: str) -> None:
    """3D view in the left camera's frame: both cameras, the baseline and every pair's board (`io.rig_figures`)."""
    from dstereo.io.rig_figures import rig_view

    rts = np.stack([np.zeros(6), np.concatenate([solution.rvec, solution.T])])
    cams = [(np.asarray(c.k), c.image_size) for c in (solution.left, solution.right)]
    rig_view(cams, rts, ("left", "right"), solution.poses, detection.object_points, detection.board.pattern, path,
             unit, title=f"rig: baseline {solution.baseline:.4g} {unit}")


def pair_rms_figure(names: list[str], rms: np.ndarray, left: np.ndarray, right: np.ndarray, path: Path) -> None:
    """Each pair's RMS reprojection error in the stereo full-set solve, both cameras and each camera."""
    plt = _pyplot()
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(max(6, 0.45 * len(names) + 2), 4))
    ax.bar(x - 0.27, rms, 0.27, label="both cameras", color="tab:purple")
    ax.bar(x, left, 0.27, label="left", color="tab:blue")
    ax.bar(x + 0.27, right, 0.27, label="right", color="tab:red")
    ax.axhline(float(np.mean(rms)), color="k", ls="--", lw=1, label=f"stereo_re {np.mean(rms):.3f} px")
    ax.set_xticks(x, names, rotation=60, ha="right", fontsize=8)
    ax.set_ylabel("RMS reprojection error (px)")
    ax.set_title("stereo reprojection error per pair (full-set solve)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def report_markdown(job: StereoCalibrationJob, summary: dict) -> str:
    """report.md of a stereo run."""
    s, det, unit = job.full, job.detection, job.config.unit
    fmt = lambda v: f"{v:.6g}" if v == v else "-"  # noqa: E731
    lines = [f"# Stereo calibration: {job.sources.description}", "",
             f"- individual calibrations: [left](left/report.md) RMS {job.left.full.rms:.4f} px, "
             f"[right](right/report.md) RMS {job.right.full.rms:.4f} px",
             f"- stereo pairs: {len(det.pairs)} used, {len(det.dropped)} dropped; intrinsics fixed at each camera's "
             "final values", f"- full-set solve: RMS {s.rms:.4f} px, stereo_re {s.stereo_re:.4f} px, {s.status_text}",
             f"- baseline |T| = {s.baseline:.6g} +- {summary['full_set']['baseline']['std']:.3g} {unit} "
             f"({summary['full_set']['std_kind'].split(':')[0]})",
             f"- calibration covariance in stereo.yml (for `dstereo reconstruct`'s point uncertainties): "
             f"{summary.get('calibration_covariance', {}).get('structure', 'none')}",
             f"- board sag: {summary['board_sag']}", ""]
    mean = job.subset_mean or {}
    lines += [f"| parameter | final | full set | +- std ({summary['full_set']['std_kind'].split(':')[0]}) | "
              "subset mean | subset spread |", "|---|---|---|---|---|---|"]
    full_vals, std = s.columns(), summary["full_set"]["std"]
    for k in job.columns:
        lines.append(f"| {k} | {fmt(job.final[k])} | {fmt(full_vals[k])} | {fmt(std.get(k, float('nan')))} | "
                     f"{fmt(mean.get(k, float('nan')))} | {fmt(job.spread[k])} |")
    lines += ["", f"+- std: {summary['full_set']['std_kind']}."]
    from dstereo.io.rig_report import consistency_markdown, cross_validation_markdown

    lines += consistency_markdown(summary.get("rig_consistency"))
    lines += cross_validation_markdown(summary.get("rig_cross_validation"))
    check = summary.get("final_check", {}).get("mean_check")
    if check is not None:
        lines += ["", f"Fit on the {check['views']} surviving pairs' corners, board poses refitted: the rig solve RMS "
                  f"{check['rms_solution_px']:.4f} px, the thesis's subset mean rig RMS {check['rms_mean_px']:.4f} px "
                  f"({check['ratio']:.3f}x)" + (": **the mean fits worse**." if check["mean_worse"] else ".")]
    lines += ["", f"Final values: {summary['final_source']}. Files: [stereo.yml](stereo.yml) (OpenCV), "
              "[stereo.json](stereo.json), [corners.npz](corners.npz), [stereo_pairs.csv](stereo_pairs.csv).", ""]
    if job.filtering is not None:
        lines += ["## Stereo steps", ""] + [f"- {st.message}" for st in job.filtering.steps] + [
            "", "![T](plots/T.png)", "", "![RV](plots/RV.png)", ""]
    lines += ["## Figures", "", "![rig](plots/rig.png)", "", "![pair rms](plots/pair_rms.png)", ""]
    if getattr(job, "consistency", None) is not None:
        lines += ["![rig consistency per pair](plots/rig_consistency.png)", ""]
    if det.dropped:
        lines += ["## Dropped pairs", ""] + [f"- {d.left} / {d.right}: {d.reason}" for d in det.dropped] + [""]
    if job.warnings:
        lines += ["## Warnings", ""] + [f"- {w}" for w in job.warnings] + [""]
    return "\n".join(lines)
