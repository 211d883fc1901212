"""A stereo calibration job (thesis 4.2.2.2): both cameras individually, then the rig, its subsets and steps.

Where the images come from (`stereo_sources`):
- flags `--left L --right R`: a folder each, or a file pattern such as `DATA/left*.jpg`; the same images serve
  the individual calibrations and the stereo pairs;
- the thesis's layout under the project's images folder: `images_left`, `images_right` (individual
  calibrations; `calibrate_left`/`calibrate_right` as in the thesis's template comment are accepted too) and,
  optionally, `images_stereo_left`, `images_stereo_right` (the pairs; without them the individual images are
  the pairs).
Pairs are matched by name (`io.pairing`: left05 with right05); a pair missing the board on either side is dropped with the reason.

The job: detect the pairs (errors about the pairs come before any long work), calibrate each camera with the
one-camera pipeline and its own steps, fix the intrinsics at each camera's final values, solve the rig on all
pairs, then (with images per set m) on the C(pairs, m) subsets, filtered by the stereo steps on the columns
stereo_re, Tnorm, Tx, Ty, Tz, RVnorm, RVx, RVy, RVz. Nothing here prints or writes files.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from dstereo.calib.calibrations import FLAT_BOARD_NOTE, RigSag, StereoCalibrationJob, StereoSources
from dstereo.jobs.calibrate_camera import Progress, calibrate_camera, camera_of
from dstereo.calib.rig_consistency import RIG_RMS_FACTOR, of_stereo
from dstereo.calib.robust_steps import run_steps
from dstereo.calib.stereo import STEP_COLUMNS, StereoSubsetSolutions, calibrate_stereo, \
    solve_stereo_subsets
from dstereo.config.calibration import Config
from dstereo.errors import DstereoError
from dstereo.io.corners import list_images
from dstereo.io.pairing import LEFT_FOLDERS, RIGHT_FOLDERS
from dstereo.io.stereo_files import DroppedPair, detect_pairs
from dstereo.uncertainty.rig import FIXED_STRUCTURE, JOINT_STRUCTURE

STEREO_FOLDERS = ("images_stereo_left", "images_stereo_right")


def _files(source: Path, image_format: str | None, flag: str) -> tuple[Path, ...]:
    """A folder's images of the given format, or the files matching a pattern such as DIR/left*.jpg."""
    source = Path(source)
    if source.is_dir():
        return tuple(list_images(source, image_format))
    if any(ch in source.name for ch in "*?["):
        if not source.parent.is_dir():
            raise DstereoError(f"{flag}: folder {source.parent} does not exist")
        files = tuple(sorted(p for p in source.parent.glob(source.name) if p.is_file()))
        if not files:
            raise DstereoError(f"{flag}: no file matches {source}; check the pattern")
        return files
    raise DstereoError(f"{flag}: {source} is neither a folder nor a file pattern such as DIR/left*.jpg")


def stereo_sources(images: Path | None, config: Config, left: Path | None = None,
                   right: Path | None = None) -> StereoSources:
    """Resolve the flags or the thesis layout (module docstring) into lists of image files."""
    fmt_l = config.image_format_left or config.image_format
    fmt_r = config.image_format_right or config.image_format
    if left is not None or right is not None:
        if left is None or right is None:
            raise DstereoError("stereo: give both `left` and `right` (a folder or a pattern such as DIR/left*.jpg)")
        files_l, files_r = _files(left, fmt_l, "`left`"), _files(right, fmt_r, "`right`")
        return StereoSources(files_l, files_r, files_l, files_r, f"--left {left} --right {right}")
    if images is None or not Path(images).is_dir():
        raise DstereoError(f"stereo: image folder {images} does not exist; give a PROJECT with images/images_left and "
                           "images/images_right, or `left` DIR `right` DIR")
    images = Path(images)
    found = [next((images / n for n in names if (images / n).is_dir()), None)
             for names in (LEFT_FOLDERS, RIGHT_FOLDERS)]
    if None in found:
        raise DstereoError(f"stereo: {images} needs the folders images_left and images_right (thesis 4.2.2.2); "
                           "or give `left` DIR `right` DIR")
    mono_l, mono_r = _files(found[0], fmt_l, str(found[0])), _files(found[1], fmt_r, str(found[1]))
    pair_dirs = [images / n for n in STEREO_FOLDERS]
    present = [d.is_dir() for d in pair_dirs]
    if any(present) and not all(present):
        raise DstereoError(f"stereo: {images} has only one of {', '.join(STEREO_FOLDERS)}; give both (stereo pairs) "
                           "or neither (the individual images are then the pairs)")
    if all(present):
        pairs_l = _files(pair_dirs[0], fmt_l, str(pair_dirs[0]))
        pairs_r = _files(pair_dirs[1], fmt_r, str(pair_dirs[1]))
        return StereoSources(mono_l, mono_r, pairs_l, pairs_r, f"{images} (individual and stereo folders)")
    return StereoSources(mono_l, mono_r, mono_l, mono_r, f"{images} (the same images for both uses)")


SAG_ALARM_Z = 3.0  # a sag this many of its own (reported) sigmas from zero: the flat board this rig assumes is wrong


def flat_board_check(cams: dict, warnings: list[str]) -> str:
    """A rig asked to solve on a flat board (--no-board-sag); check that assumption on each camera's own views: solve
    the camera once
    with the board's sag (one more full-set solve each, ~0.1 s) and, where the sag lies beyond SAG_ALARM_Z of its
    sigma, warn with the figures and how far the camera's focal length moves (the synthetic 0.3 mm sag biased a flat
    solve's fx by 8.6 px; the real boards here sag 3-23 sigma). Returns the summary's `board_sag` text."""
    from dstereo.calib.mono import calibrate_full
    from dstereo.uncertainty.view_effects import reported_std

    found = []
    for side, cal in cams.items():
        flat = cal.full
        sagged = calibrate_full(cal.detection.object_points, cal.observations, cal.detection.image_size,
                                free=tuple(flat.free), inliers=flat.inliers, board_warp=True)
        if not sagged.converged:
            continue
        std = reported_std(sagged)
        z = np.abs(sagged.board_sag) / np.maximum(std[-2:], 1e-300)
        if np.max(z) > SAG_ALARM_Z:
            dfx = float(sagged.values[0] - flat.values[0])
            found.append(f"{side} camera: sag x {sagged.board_sag[0]:+.4g}, y {sagged.board_sag[1]:+.4g} "
                         f"{cal.config.unit} ({np.max(z):.1f} sigma), RMS {flat.rms:.4f} -> {sagged.rms:.4f} px, "
                         f"fx moves {dfx:+.3g} px ({abs(dfx) / std[0]:.1f} sigma)")
    if not found:
        return FLAT_BOARD_NOTE
    text = ("the board is not flat, but --no-board-sag assumes it is: " + "; ".join(found)
            + ". The cameras and the rig are biased by it; leave --no-board-sag out to solve the sag")
    warnings.append(text)
    return FLAT_BOARD_NOTE + ". Measured on each camera's own views: " + "; ".join(found)


SAG_DISAGREE_Z = 3.0  # the two cameras' sags this many sigmas apart: one board cannot sag two ways


def rig_board_sag(det, cams: dict, warnings: list[str]) -> RigSag | None:
    """The board's sag for the rig: each camera solved it on its own views (the one-camera default); the rig is
    solved on the board sagged by their inverse-variance mean, held there as the subsets hold a camera's (one board
    in every frame; re-estimating it in the rig adds the cameras' noise only). Sets `det.solved_board` (the
    board every rig solve uses; corners.npz's `object_points_solved`) and returns it (None when a camera solved none); warns when
    the two cameras' sags disagree beyond SAG_DISAGREE_Z of their sigmas (another board in one folder, or a sag
    the two-parameter model does not describe)."""
    from dstereo.calib.problem import sagged_board
    from dstereo.uncertainty.view_effects import reported_std

    sags, variances = [], []
    for cal in cams.values():
        if cal.full.board_sag is None:
            return None
        sags.append(np.asarray(cal.full.board_sag, float))
        variances.append(np.maximum(reported_std(cal.full)[-2:], 1e-300) ** 2)
    sags, variances = np.array(sags), np.array(variances)
    weights = 1.0 / variances
    sag = np.sum(weights * sags, axis=0) / weights.sum(axis=0)
    sigma = np.sqrt(1.0 / weights.sum(axis=0))
    det.solved_board = sagged_board(det.board.object_points(), sag)
    unit = next(iter(cams.values())).config.unit
    per = "; ".join(f"{side} {s[0]:+.4g} +- {np.sqrt(v[0]):.2g}, {s[1]:+.4g} +- {np.sqrt(v[1]):.2g}"
                    for side, s, v in zip(cams, sags, variances))
    z = np.abs(sags[0] - sags[1]) / np.sqrt(variances.sum(axis=0))
    if np.max(z) > SAG_DISAGREE_Z:
        warnings.append(f"board sag: the left and right cameras measure different sags of the one board ({per} "
                        f"{unit}; {np.max(z):.1f} sigma apart): another board in one folder, or a board that bends "
                        "in a way the two-parameter sag does not describe; the rig uses their weighted mean")
    return RigSag(sag, sigma, f"solved: x {sag[0]:+.4g} +- {sigma[0]:.2g}, y {sag[1]:+.4g} +- {sigma[1]:.2g} {unit}, "
                  f"the weighted mean of each camera's own solve ({per}), held in the rig solve and its subsets")


class _Prefixed:
    """A progress callback whose stages (and notes) are prefixed with the camera's side."""

    def __init__(self, progress, side: str):
        self.progress, self.side = progress, side

    def __call__(self, stage: str, done: int, total: int) -> None:
        self.progress(f"{self.side} {stage}", done, total)

    def note(self, text: str) -> None:
        if getattr(self.progress, "note", None) is not None:
            self.progress.note(f"{self.side} camera: {text}")


def _prefixed(progress: Progress | None, side: str) -> Progress | None:
    return None if progress is None else _Prefixed(progress, side)


def _solve_stereo_subsets(obj, obs_l, obs_r, plan, full, scratch, progress):
    """(StereoSubsetSolutions or None, SubsetTable of STEP_COLUMNS): block by block, as the mono pipeline."""
    from dstereo.calib.subset_runs import NOTE_ABOVE, solve_in_blocks
    from dstereo.calib.subset_solve import chunk_size

    note = getattr(progress, "note", None) if len(plan) > NOTE_ABOVE else None

    def solve_block(block, report):
        sol = solve_stereo_subsets(obj, obs_l, obs_r, block, full, progress=report)
        cols = sol.columns()
        return np.column_stack([cols[k] for k in STEP_COLUMNS]), sol.status, sol

    report = None if progress is None else (lambda d, n: progress("stereo subsets", d, n))
    chunk = chunk_size(len(obs_l), plan.per_set, 2 * obs_l.shape[1])
    table, kept = solve_in_blocks(plan, STEP_COLUMNS, solve_block, chunk, scratch, progress=report,
                                  note=None if note is None else (lambda text: note("stereo " + text)))
    if not kept:
        return None, table
    cat = lambda name: np.concatenate([getattr(s, name) for s in kept])  # noqa: E731
    return StereoSubsetSolutions(
        plan=plan, names=full.names, values=cat("values"), std=cat("std"), norm_std=cat("norm_std"), rms=cat("rms"),
        stereo_re=cat("stereo_re"), iterations=cat("iterations"), status=cat("status"),
        timings={"solve_s": sum(s.timings["solve_s"] for s in kept)}), table


def calibrate_stereo_project(sources: StereoSources, config: Config, progress: Progress | None = None,
                             use_cache: bool = True, scratch: Path | None = None,
                             cross_validate: int = 0, projection_range: float | None = None) -> StereoCalibrationJob:
    """Run the job of the module docstring. Raises DstereoError for bad pairs, sizes, counts or steps, or a
    subset run that cannot fit this machine. `scratch`: folder for huge runs' per-subset tables (as mono).
    `cross_validate`: that many random halvings of the pairs, each solved jointly (`calib/rig_cross_validation.py`;
    it checks the joint solve's +-, the one stereo.json's `rig_consistency` compares, not the fixed-mode propagated
    +- that stereo.yml carries)."""
    from dstereo.calib.subset_runs import check_subset_run
    from dstereo.calib.subsets import plan_subsets
    from dstereo.models.rig import essential_matrix, fundamental_matrix
    from dstereo.models.pose import rodrigues

    if config.stereo_steps and config.per_set is None:
        raise DstereoError("stereo steps need subsets of pairs; set images per set (`per_set` m)")
    timings, warnings = {}, []
    t0 = time.perf_counter()
    if progress is not None:
        progress("stereo pairs", 0, 1)
    det = detect_pairs(list(sources.stereo_left), list(sources.stereo_right), config.pattern, config.square,
                       use_cache=use_cache)
    if progress is not None:
        progress("stereo pairs", 1, 1)
    timings["pairs_s"] = time.perf_counter() - t0
    warnings += det.warnings + [f"stereo pair {d.left} / {d.right} dropped: {d.reason}" for d in det.dropped]
    cams = {}
    for side, files, fmt in (("left", sources.mono_left, config.image_format_left),
                             ("right", sources.mono_right, config.image_format_right)):
        t0 = time.perf_counter()
        own = config.model_right if side == "right" else None  # the right camera's own lens model: not chosen
        cfg = config.with_overrides(image_format=fmt, model=own, model_auto=False if own is not None else None)
        if cfg.model != config.model:  # the right camera's own lens model: its steps are checked against it
            from dstereo.config.calibration import validate

            cfg = validate(cfg)
        try:
            cams[side] = calibrate_camera(files[0].parent, cfg, files=list(files), progress=_prefixed(progress, side),
                                          use_cache=use_cache, scratch=scratch, in_rig=True,
                                          projection_range=projection_range)
        except DstereoError as exc:
            raise DstereoError(f"{side} camera: {exc}") from None
        timings[f"{side}_s"] = time.perf_counter() - t0
        warnings += [f"{side} camera: {w}" for w in cams[side].warnings if w not in config.warnings]
        stereo_size = (det.left if side == "left" else det.right).image_size
        if cams[side].detection.image_size != stereo_size:
            raise DstereoError(f"{side} camera: individual images are {cams[side].detection.image_size} px but its "
                               f"stereo images are {stereo_size} px; one camera has one image size")
    _drop_pairs_rejected_by_both(det, cams, warnings)
    rig_sag = rig_board_sag(det, cams, warnings) if config.board_sag else None
    board_note = rig_sag.note if rig_sag is not None else flat_board_check(cams, warnings)
    obs_l, obs_r = det.observations()
    t0 = time.perf_counter()
    if progress is not None:
        progress("stereo solve", 0, 1)
    inliers = _pair_inliers(det, cams, obs_l, obs_r)
    full = calibrate_stereo(det.object_points, obs_l, obs_r, camera_of(cams["left"]), camera_of(cams["right"]), "fixed",
                            inliers=inliers)
    check_rig_fits(full, cams, len(det.pairs))
    check_baseline(full, det.board, config.unit)
    from dstereo.calib.view_checks import outlying_views

    warnings += outlying_views([f"{a} / {b}" for a, b in det.pairs], full.per_pair_rms, what="stereo pair")
    # the rig with the intrinsics refined too: the solve the consistency test compares with each camera alone
    joint = calibrate_stereo(det.object_points, obs_l, obs_r, camera_of(cams["left"]), camera_of(cams["right"]), "joint",
                             inliers=inliers)
    consistency = of_stereo(joint, det.object_points, obs_l, obs_r, det.pairs)
    if consistency.warning() is not None:
        warnings.append("stereo: " + consistency.warning())
    cv = None
    if cross_validate:
        from dstereo.calib.rig_cross_validation import cross_validate_rig

        t_cv = time.perf_counter()
        data = np.stack([obs_l, obs_r], axis=1)
        cv = cross_validate_rig(det.object_points, data, np.ones(data.shape[:2], bool),
                                [det.left.image_size, det.right.image_size],
                                [camera_of(cams["left"]), camera_of(cams["right"])], ("left", "right"), cross_validate,
                                seed=config.seed or 0, inliers=inliers)
        if not cv.trusted:
            warnings.append("stereo: " + cv.verdict())
        timings["rig_cross_validation_s"] = time.perf_counter() - t_cv
    if progress is not None:
        progress("stereo solve", 1, 1)  # before the subsets: a rig with no baseline is not worth them
    timings["stereo_s"] = time.perf_counter() - t0
    if not full.converged:
        warnings.append(f"stereo full-set solve did not converge ({full.status_text}); its values are unreliable")
    final = full.columns()
    spread = {k: float("nan") for k in STEP_COLUMNS}
    plan = subsets = filtering = rig_fs = subset_mean = None
    if config.per_set is not None:
        t0 = time.perf_counter()
        check_subset_run(len(det.pairs), config.per_set, config.max_subsets, len(STEP_COLUMNS), scratch,
                         getattr(progress, "note", None), label="stereo ")
        plan = plan_subsets(len(det.pairs), config.per_set, cap=config.max_subsets, seed=config.seed)
        subsets, table = _solve_stereo_subsets(det.object_points, obs_l, obs_r, plan, full, scratch, progress)
        usable = table.status > 0
        for j in range(len(STEP_COLUMNS)):
            usable &= np.isfinite(table.column(j))
        if not usable.any():
            table.close()
            raise DstereoError(f"none of the {len(table)} stereo subset solves converged; check the pairs")
        if not usable.all():
            warnings.append(f"{int((~usable).sum())} of {len(table)} stereo subset solves did not converge and are "
                            "left out of the statistics")
        try:
            filtering = run_steps(table, STEP_COLUMNS, config.stereo_steps, usable, config.min_subsets)
        except BaseException:
            table.close()
            raise
        warnings += [f"stereo {s.message}" for s in filtering.steps if s.stopped_by_minimum]
        stats = filtering.stats(len(filtering.steps))
        subset_mean = {k: stats[k]["mean"] for k in STEP_COLUMNS}
        spread = {k: stats[k]["std"] for k in STEP_COLUMNS}
        from dstereo.calib.final_solution import rig_final

        rig_fs = rig_final(config.final, filtering, plan, det.object_points, obs_l, obs_r, full, subset_mean)
        final = rig_fs.final
        if rig_fs.check.mean_worse:
            warnings.append("stereo: " + rig_fs.check.text("rig") + (
                "; stereo.yml holds it (--final mean)" if rig_fs.choice == "mean" else
                "; stereo.yml holds the solve; the mean is only reported"))
        timings["stereo_subsets_s"] = time.perf_counter() - t0
    rvec = np.array([final["RVx"], final["RVy"], final["RVz"]])
    T = np.array([final["Tx"], final["Ty"], final["Tz"]])
    E = np.asarray(essential_matrix(rvec, T))
    F = np.asarray(fundamental_matrix(full.left.k, full.right.k, E))
    job = StereoCalibrationJob(
        config=config, sources=sources, left=cams["left"], right=cams["right"], detection=det, full=full, plan=plan,
        subsets=subsets, filtering=filtering, final=final, spread=spread, R=np.asarray(rodrigues(rvec)), T=T, E=E,
        F=F, warnings=warnings, timings=timings, rig_final=rig_fs, subset_mean=subset_mean, board_sag=board_note,
        consistency=consistency, rig_sag=rig_sag, cross_validation=cv,
    )
    from dstereo.calib.final_solution import attach_rig_uncertainty

    t0 = time.perf_counter()
    attach_rig_uncertainty(job)
    timings["rig_covariance_s"] = time.perf_counter() - t0
    return job


# A rig's baseline that is within this many of its own sigmas of zero is not measured at all. Identical left and
# right images (a right folder holding copies of the left's) fit with |T| = 2.2e-9 mm and a sigma as small (the
# residuals are zero), so the second limit, a fraction of the board's size, is what catches them: two cameras sit
# at least a lens apart, and a board is seen by both from a distance of a few board sizes at most (a 1e-3 board
# baseline: 0.24 mm against the 83 mm of the opencv_stereo rig, whose board is 236 mm across with 25 mm squares).
SAME_PLACE_SIGMAS = 3.0
SAME_PLACE_BOARD_FRACTION = 1e-3


def check_rig_fits(full, cams: dict, n_pairs: int) -> None:
    """Refuse a rig that does not fit its pairs at all (`rig_consistency.RIG_RMS_FACTOR`)."""
    rig, left, right = float(full.rms), float(cams["left"].full.rms), float(cams["right"].full.rms)
    if rig > max(RIG_RMS_FACTOR * max(left, right), 1.0):
        raise DstereoError(
            f"stereo: the rig fits the {n_pairs} pairs with RMS {rig:.3g} px while the cameras alone fit their views "
            f"with {left:.3g} / {right:.3g} px: the left and right images do not show the board at the same moments "
            "(partners are matched by name; check the names, the cameras' synchronisation and that both folders "
            "come from this rig); nothing written")


def check_baseline(full, board, unit: str) -> None:
    """Refuse a rig whose baseline is not significantly different from zero (see SAME_PLACE_SIGMAS): its left and
    right images show the board from one place, and reconstruct would triangulate nothing with it."""
    baseline = float(np.linalg.norm(np.asarray(full.T, float)))
    cov = np.asarray(full.cov, float)[3:6, 3:6]
    sigma = float(np.sqrt(max(np.trace(cov), 0.0))) if np.all(np.isfinite(cov)) else 0.0
    size = board.square * float(np.hypot(board.cols - 1, board.rows - 1))  # the inner corners' diagonal
    if baseline < max(SAME_PLACE_SIGMAS * sigma, SAME_PLACE_BOARD_FRACTION * size):
        raise DstereoError(
            f"stereo: the rig's baseline |T| = {baseline:.3g} {unit} (sigma {sigma:.2g} {unit}; the board is "
            f"{size:.3g} {unit} across) is not different from zero: the left and right images show the board from "
            "the same place: are they the same images? Give each camera's own images (--left, --right); nothing "
            "written")


def _drop_pairs_rejected_by_both(det, cams, warnings: list[str]) -> None:
    """A pair whose two images were both rejected whole by their cameras' outlier rejection leaves the rig solve:
    kept, it would have no inlier corner, and the solve would have to fit all its (bad) corners to place it."""
    gone = [{v for v, _ in cams[side].outliers.views} if cams[side].outliers is not None else set()
            for side in ("left", "right")]
    bad = [(a, b) for a, b in det.pairs if a in gone[0] and b in gone[1]]
    if not bad:
        return
    if len(det.pairs) - len(bad) < 3:
        raise DstereoError(f"stereo: only {len(det.pairs) - len(bad)} pairs left after both cameras' outlier rejection "
                           f"dropped {len(bad)}; add pairs or check --pattern")
    reason = "both images rejected whole by their cameras' outlier rejection"
    det.pairs = [p for p in det.pairs if p not in bad]
    det.dropped += [DroppedPair(a, b, reason) for a, b in bad]
    warnings += [f"stereo pair {a} / {b} dropped: {reason}" for a, b in bad]


def _pair_inliers(det, cams, obs_l, obs_r) -> np.ndarray | None:
    """(V, 2, n) corner mask of the pairs from each camera's outlier rejection (calib/outliers.py): a pair's image
    that its camera's calibration used, with the same corners, takes that view's mask; an image the camera
    rejected whole has no inlier corner; an image the camera did not see (other folder) keeps all corners."""
    mask = np.ones((len(det.pairs), 2, obs_l.shape[1]), bool)
    for side, (cal, obs) in enumerate(((cams["left"], obs_l), (cams["right"], obs_r))):
        rejected = {v for v, _ in cal.outliers.views} if cal.outliers is not None else set()
        rows = {name: i for i, name in enumerate(cal.used)}
        for p, pair in enumerate(det.pairs):
            name = pair[side]
            if name in rejected:
                mask[p, side] = False
            elif name in rows and cal.full.inliers is not None and np.allclose(cal.observations[rows[name]], obs[p]):
                mask[p, side] = cal.full.inliers[rows[name]]
    return None if mask.all() else mask


def summary_lines(job: StereoCalibrationJob, out: Path) -> list[str]:
    """Console text of a finished job (the CLI prints it)."""
    s, pm = job.full, (lambda v, e: f"{v:.6g} +- {e:.3g}" if e == e else f"{v:.6g}")  # noqa: E731
    unit = job.config.unit
    full_std = dict(zip(("RVx", "RVy", "RVz", "Tx", "Ty", "Tz"), s.std))
    full_std |= {"Tnorm": s.baseline_std, "RVnorm": s.angle_std, "stereo_re": float("nan")}
    kind = "Jacobian with the pairs' effects"
    if job.full_set_sigma is not None:  # the honest +-: intrinsics errors carried into the rig
        full_std |= job.full_set_sigma.std
        kind = job.full_set_sigma.label.split(":")[0]
    chosen = [f"{side} {cal.model_choice.chosen}" for side, cal in (("left", job.left), ("right", job.right))
              if cal.model_choice is not None]
    lines = [f"model auto (each camera on its own views, parametric lenses): {', '.join(chosen)}"] if chosen else []
    lines += [f"individual: left RMS {job.left.full.rms:.4f} px ({len(job.left.used)} images), right RMS "
             f"{job.right.full.rms:.4f} px ({len(job.right.used)} images)",
             f"stereo: {len(job.detection.pairs)} pairs ({len(job.detection.dropped)} dropped), RMS {s.rms:.4f} px, "
             f"stereo_re {s.stereo_re:.4f} px, {s.status_text}",
             f"{'parameter':>9}  {'full set +- std (' + kind + ')':>28}  " + (
                 f"subset mean +- spread of {int(job.filtering.survivors.sum())} subsets" if job.filtering
                 else "final")]
    full_vals = s.columns()
    shown = job.subset_mean if job.subset_mean is not None else job.final
    for k in STEP_COLUMNS:
        lines.append(f"{k:>9}  {pm(full_vals[k], full_std[k]):>28}  {pm(shown[k], job.spread[k])}")
    lines.append(f"baseline |T| = {s.baseline:.6g} +- {full_std['Tnorm']:.3g} {unit} (full set, {kind})")
    if job.consistency is not None:
        lines.append(job.consistency.line())
    if job.cross_validation is not None:
        lines.append(job.cross_validation.verdict())
    if job.rig_final is not None:
        c = job.rig_final.check
        lines.append(f"stereo.yml: {job.rig_final.source()}")
        lines.append(f"  fit on the surviving pairs (poses refitted): rig solve {c.rms_solution:.4f} px, subset mean "
                     f"{c.rms_mean:.4f} px ({c.ratio:.3f}x)")
    structure = JOINT_STRUCTURE if s.mode == "joint" else FIXED_STRUCTURE
    lines.append("stereo.yml carries the calibration covariance: " + structure.split(":")[0])
    if job.filtering is not None:
        lines += [f"  stereo {st.message}" for st in job.filtering.steps]
    lines.append("timings: " + ", ".join(f"{k[:-2]} {v:.1f} s" for k, v in job.timings.items()))
    lines.append(f"wrote {out}")
    return lines
