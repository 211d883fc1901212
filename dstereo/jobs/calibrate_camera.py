"""A camera's stage of the calibration job (`jobs.calibrate_cameras.calibrate_rig`, which runs it for every camera;
for one camera it is the whole job): detect -> full-set solve -> outliers -> subsets -> robust steps -> the
survivors' solve -> a `CameraCalibration`.

Nothing here prints or writes files; `dstereo.io` writes the results folder and the CLI renders the console.

Each subset's reprojection error `re` is its RMS over all its points, sqrt(SSE / points): the number
cv2.calibrateCamera returns (the thesis calls it the mean reprojection error).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from dstereo.calib.coverage import corner_coverage
from dstereo.calib.calibrations import CameraCalibration
from dstereo.calib.robust_steps import run_steps
from dstereo.config.calibration import Config, Step, validate
from dstereo.errors import DstereoError

Progress = Callable[[str, int, int], None]  # (stage, done, total)

# Presets from the richest to the simplest: where to look for a simpler, identifiable model.
MODEL_LADDER = ("rational", "k1k2k3p1p2", "k1k2p1p2", "k1k2", "k1")


def suggest_model(free: tuple[str, ...], identifiable: bool, weak: Sequence[str]) -> str | None:
    """None when the model is identifiable; else which simpler preset to use (and why)."""
    from dstereo.models.distortion import PRESETS

    if identifiable:
        return None
    weak_coeffs = set(weak) & set(PRESETS["rational"])
    simpler = [p for p in MODEL_LADDER if set(PRESETS[p]) < set(free)]
    dropping = [p for p in simpler if weak_coeffs - set(PRESETS[p])]
    choice = (dropping or simpler or [None])[0]
    weak_text = ", ".join(weak) or "none named"
    if choice is None:
        return (f"model {','.join(free) or 'none'} is not identifiable from these views (weak: {weak_text}); "
                "add views that tilt the board and fill the image corners")
    return (f"model {','.join(free)} is not identifiable from these views (weak: {weak_text}); use the simpler "
            f"model --model {choice} ({','.join(PRESETS[choice])}), let held-out views choose (--model auto), or "
            "add views that fill the image corners")


def list_camera_images(folder: Path, config: Config, image_format: str | None = None) -> list[Path]:
    """The images of one camera: `config.glob` inside `folder` if set, else every file of the image format."""
    from dstereo.io.corners import list_images

    folder = Path(folder)
    if config.glob is None:
        return list_images(folder, image_format or config.image_format)
    if not folder.is_dir():
        list_images(folder)  # the one message for a file or a missing folder
    files = sorted(p for p in folder.glob(config.glob) if p.is_file())
    if not files:
        raise DstereoError(f"images: no file in {folder} matches {config.glob!r}; check `glob`")
    return files


def camera_of(cal: CameraCalibration):
    """The `Camera` a calibration's file holds (its final values), with the free set a rig's joint solve refines:
    what every rig starts from."""
    from dstereo.models.camera import Camera

    f = cal.final
    return Camera.create(f["fx"], f["fy"], f["cx"], f["cy"], cal.final_coefficients,
                         tuple(cal.full.camera().dist.free), cal.detection.image_size)


def calibrate_camera(
    folder: Path,
    config: Config,
    files: Sequence[Path] | None = None,
    steps: Sequence[Step] | None = None,
    progress: Progress | None = None,
    use_cache: bool = True,
    scratch: Path | None = None,
    after_steps: Callable | None = None,
    in_rig: bool = False,
    cross_validate: int = 0,
    projection_range: float | None = None,
    projection_method: str = "pose-compensated",
) -> CameraCalibration:
    """Detect, solve the full set and (with `config.per_set`) every subset, then run `steps` (default
    `config.steps`). Raises DstereoError for unreadable files, m > N, a step that leaves no subset, or a run
    that cannot fit this machine (figures in the message).

    `scratch`: folder for the per-subset table of a huge run (default the system temp folder; the CLI passes
    the results folder's parent). `progress` may carry a `note(text)` method: the run's estimate goes there.
    `after_steps(filtering, full)`: called once the subsets' steps are done, before the survivors' solve (the
    command starts drawing their figures then, `io.results.EarlyFigures`). `in_rig`: a camera of a rig, whose
    `--model auto` chooses among the parametric lenses (`reconstruct` rectifies no splined lens).
    `cross_validate`: that many random halvings of the views (`calib/cross_validation.py`, at `projection_range`).
    The result is finished (`calib.finished`: the +-, the projection-uncertainty map at `projection_range` by
    `projection_method`, the solved board) for the writers, which compute nothing."""
    from dstereo.calib.mono import calibrate_full
    from dstereo.calib.subsets import plan_subsets
    from dstereo.io.corners import detect_folder

    validate(config)
    steps = config.steps if steps is None else tuple(steps)
    files = list_camera_images(folder, config) if files is None else list(files)
    timings, warnings = {}, list(config.warnings)
    t0 = time.perf_counter()
    if progress is not None:
        progress("detect", 0, len(files))
    det = detect_folder(folder, config.pattern, config.square, files=files, use_cache=use_cache,
                        progress=None if progress is None else (lambda i, n: progress("detect", i, n)))
    timings["detect_s"] = time.perf_counter() - t0
    unreadable = {n: r for n, r in det.rejected.items() if r.startswith("unreadable")}
    if unreadable:
        name = next(iter(unreadable))
        raise DstereoError(f"images: {Path(folder) / name} is not an image file OpenCV can decode "
                           f"({len(unreadable)} such file(s)); remove it or narrow the image format / `glob`")
    used = [n for n in det.names if n in det.corners]
    obs = np.stack([det.corners[n] for n in used])
    for name, reason in det.rejected.items():
        warnings.append(f"image {name} rejected: {reason}")
    choice = None
    if config.model_auto:  # before the plan: the subsets, steps and files run with the chosen model
        config, choice = _choose_model(config, det, obs, progress, in_rig)
        timings["model_choice_s"] = choice.timings["model_choice_s"]
    plan = None
    if config.per_set is not None:
        from dstereo.calib.subset_runs import check_subset_run

        # Before the plan: a sample of 1e11 subsets would need 800 GB for its ranks alone.
        check_subset_run(len(used), config.per_set, config.max_subsets, 5 + len(config.model), scratch,
                         getattr(progress, "note", None))  # columns re, fx, fy, cx, cy + the free coefficients
        plan = plan_subsets(len(used), config.per_set, cap=config.max_subsets, seed=config.seed)  # checks m <= N

    t0 = time.perf_counter()
    if progress is not None:
        progress("full-set solve", 0, 1)
    # Without subsets that share the full set's compiled program (masked ones), its solves run unpadded
    # (`mono.calibrate_full`'s `alone`: 54 -> 8 ms a solve at 20 views, measured)
    from dstereo.calib.subset_solve import gathers

    alone = plan is None or gathers(plan.per_set, len(used), len(plan))
    # --model auto compares the candidates on a flat board; the chosen one is solved again with the board's sag when
    # that is asked (the default): before, its flat solve was kept and the sag silently dropped (found by
    # tests/commands/test_every_feature.py)
    full = choice.chosen_candidate.solution if choice is not None and not config.board_sag else \
        calibrate_full(det.object_points, obs, det.image_size, free=tuple(config.model), board_warp=config.board_sag,
                       alone=alone)
    if progress is not None:
        progress("full-set solve", 1, 1)
    timings["full_solve_s"] = time.perf_counter() - t0
    from dstereo.calib.misfit import solution_pattern

    # Before rejection too: a model too simple for the lens puts its worst residuals at the edges, and rejecting
    # them as outliers would hide the pattern (k1,k2 on fisheye640: p = 9e-24 before, 2e-4 after)
    pattern_all = solution_pattern(obs, full)
    n_before = len(used)
    full, used, obs, outliers = _reject_outliers(config, det, used, obs, full, warnings, alone)
    timings["outliers_s"] = time.perf_counter() - t0 - timings["full_solve_s"]
    if config.per_set is not None and len(used) < n_before:  # views rejected whole: plan the rest
        if config.per_set > len(used):
            raise DstereoError(f"per-set: m = {config.per_set} but only {len(used)} views are left after outlier "
                               "rejection; lower `per_set` (or `outlier_rejection`)")
        plan = plan_subsets(len(used), config.per_set, cap=config.max_subsets, seed=config.seed)
    if plan is not None and len(plan) < 2 and steps:
        raise DstereoError(f"per-set: m = {config.per_set} of {len(used)} usable images gives a single subset; "
                           "the steps need several: lower `per_set`")
    if not full.converged:
        warnings.append(f"full-set solve did not converge ({full.status_text}); its values are unreliable")
    columns = ("re",) + tuple(full.names)
    if choice is not None:  # the data chose this model: no advice to swap it, only a note if not identifiable
        from dstereo.calib.model_choice import choice_warning

        advice = choice_warning(choice)
    else:
        from dstereo.calib.model_choice import residual_structure

        advice = suggest_model(tuple(config.model), full.conditioning.identifiable,
                               full.conditioning.weak_parameters)
        structure = residual_structure(obs, full.residuals[:, 0], full.values[:4])
        if structure:
            advice = structure if advice is None else f"{advice}; {structure}"
    if advice:
        warnings.append(advice)
    if full.conditioning.wild:
        warnings.append(full.conditioning.message())
    pattern = solution_pattern(obs, full) if outliers.enabled else pattern_all
    worst = min((pattern, pattern_all), key=lambda p: (not p.significant, p.p_value))
    from dstereo.models.distortion import model_label

    if worst.message(model_label(config.model)):
        where = "" if worst is pattern else " (on every corner, before outlier rejection)"
        warnings.append(worst.message(model_label(config.model)) + where)

    subsets = filtering = final_solution = subset_mean = None
    final = dict(zip(full.names, map(float, full.values)))
    spread = {n: float("nan") for n in full.names}
    if plan is not None:
        t0 = time.perf_counter()
        if progress is not None:
            progress("subsets", 0, len(plan))
        subsets, table = _solve_subsets(det.object_points, obs, plan, full, columns, scratch, progress)
        timings["subsets_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        usable = table.status > 0
        for j in range(len(columns)):
            usable &= np.isfinite(table.column(j))
        if not usable.any():
            table.close()
            raise DstereoError(f"none of the {len(table)} subset solves converged; check the images and `pattern`")
        if not usable.all():
            bad = np.flatnonzero(~usable)
            warnings.append(f"{len(bad)} of {len(table)} subset solves did not converge and are left out of the "
                            f"statistics (subsets {', '.join(map(str, bad[:10]))}{', ...' if len(bad) > 10 else ''})")
        try:
            filtering = run_steps(table, columns, steps, usable, config.min_subsets)
        except BaseException:
            table.close()
            raise
        timings["steps_s"] = time.perf_counter() - t0
        warnings += [s.message for s in filtering.steps if s.stopped_by_minimum]
        if after_steps is not None:
            after_steps(filtering, full)
        stats = filtering.stats(len(filtering.steps))
        subset_mean = {n: stats[n]["mean"] for n in full.names}
        spread = {n: stats[n]["std"] for n in full.names}
        final_solution = _final_solution(config, filtering, plan, det, obs, full, subset_mean, warnings)
        final = final_solution.final
        timings["final_s"] = time.perf_counter() - t0 - timings["steps_s"]

    coverage = corner_coverage(obs.reshape(-1, 2), det.image_size)
    warnings += list(coverage.warnings)
    from dstereo.calib.view_checks import view_warnings

    warnings += view_warnings(used, full, {n: det.corners[n] for n in used}, config.pattern)
    cv = None
    if cross_validate:
        from dstereo.calib.cross_validation import cross_validate as run_cross_validation

        t0 = time.perf_counter()
        cv = run_cross_validation(full, det.object_points, obs, det.image_size, cross_validate, seed=config.seed or 0,
                                  range_=projection_range)
        if not cv.trusted:
            warnings.append(cv.verdict())
        timings["cross_validation_s"] = time.perf_counter() - t0
    cal = CameraCalibration(
        config=config, folder=Path(folder), files=list(files), detection=det, used=used, observations=obs,
        full=full, plan=plan, subsets=subsets, filtering=filtering, columns=columns, final=final, spread=spread,
        coverage=coverage, model_advice=advice, warnings=warnings, timings=timings, final_solution=final_solution,
        subset_mean=subset_mean, outliers=outliers, residual_pattern=pattern,
        residual_pattern_all=pattern_all, model_choice=choice, cross_validation=cv, projection_method=projection_method,
    )
    from dstereo.calib.finished import finish_camera

    t0 = time.perf_counter()
    cal.finished = finish_camera(cal, projection_range, projection_method)  # what the results folder shows
    timings["finish_s"] = time.perf_counter() - t0
    return cal


def _reject_outliers(config, det, used, obs, full, warnings, alone: bool = False):
    """(full, used, obs, OutlierReport): the full-set solve on the inlier corners of the kept views."""
    from dstereo.calib.outliers import OutlierReport, reject_outliers

    if not config.outlier_rejection:
        return full, used, obs, OutlierReport(False)
    full, keep, report = reject_outliers(det.object_points, obs, det.image_size, tuple(config.model), used, full,
                                         alone=alone)
    warnings += report.warnings()
    return full, [used[i] for i in keep], obs[keep], report


def _choose_model(config, det, obs, progress, in_rig: bool = False):
    """--model auto: (the config with the chosen model, the ModelChoice)."""
    from dataclasses import replace

    from dstereo.calib.model_choice import CANDIDATES, PARAMETRIC, choose_model

    report = None if progress is None else (lambda i, n: progress("model choice", i, n))
    # the subset analysis is not available for the splined lens (~160 knots), nor a rig's rectification: with
    # `per_set` or in a rig, parametric only
    candidates = CANDIDATES if config.per_set is None and not in_rig else PARAMETRIC
    choice = choose_model(det.object_points, obs, det.image_size, candidates, progress=report)
    return validate(replace(config, model=choice.chosen_candidate.free, model_auto=False)), choice


def _final_solution(config, filtering, plan, det, obs, full, subset_mean, warnings):
    """`final_solution.camera_final`, and a warning with the figures when the subset mean fits visibly worse."""
    from dstereo.calib.final_solution import camera_final

    fs = camera_final(config.final, filtering, plan, det.object_points, obs, full, det.image_size, subset_mean)
    if fs.check.mean_worse:
        held = ("camera.yml holds it (--final mean); use --final survivors for the consistent solve"
                if fs.choice == "mean" else "camera.yml holds the solve; the mean is only reported")
        warnings.append(f"{fs.check.text()}; {held}")
    if not fs.solution.converged:
        warnings.append(f"the solve on the surviving views did not converge ({fs.solution.status_text})")
    return fs


def _solve_subsets(obj, obs, plan, full, columns, scratch, progress):
    """(SubsetSolutions or None, SubsetTable): every subset solved block by block (`subset_runs`); the whole
    SubsetSolutions only up to KEEP_SOLUTIONS subsets (above, the table holds what the steps need)."""
    from dstereo.calib.mono import solve_subsets
    from dstereo.calib.subsets import SubsetSolutions
    from dstereo.calib.subset_solve import chunk_size
    from dstereo.calib.subset_runs import NOTE_ABOVE, solve_in_blocks

    m, n_views = plan.per_set, len(obs)

    def solve_block(block, report):
        sol = solve_subsets(obj, obs, block, full, progress=report, plan_size=len(plan))
        return np.column_stack([sol.rms, sol.values]), sol.status, sol

    table, kept = solve_in_blocks(
        plan, columns, solve_block, chunk_size(n_views, m, obs.shape[1], len(plan)), scratch,
        progress=None if progress is None else (lambda i, n: progress("subsets", i, n)),
        note=getattr(progress, "note", None) if len(plan) > NOTE_ABOVE else None,
        key=(obj, obs, full.values, full.poses, "all" if full.inliers is None else full.camera_inliers(),
             tuple(full.camera().dist.free)))
    if not kept:
        return None, table
    cat = lambda name: np.concatenate([getattr(s, name) for s in kept])  # noqa: E731
    return SubsetSolutions(plan=plan, names=full.names, values=cat("values"), std=cat("std"), rms=cat("rms"),
                           iterations=cat("iterations"), status=cat("status"),
                           timings={"solve_s": sum(s.timings["solve_s"] for s in kept)}), table
