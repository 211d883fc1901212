"""`dstereo calibrate`: one camera from a project folder (thesis layout) or from flags alone."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from dstereo.commands.progress import progress_bars


def calibrate(
    project: Optional[Path] = typer.Argument(
        None, help="Project folder: a configuration file (dstereo.toml or the thesis's .ini) and images/."),
    config: Optional[Path] = typer.Option(None, "--config", help="Configuration file (TOML or thesis .ini)."),
    images: Optional[Path] = typer.Option(None, "--images", help="Image folder (default PROJECT/images)."),
    glob: Optional[str] = typer.Option(None, "--glob", help="Only images whose name matches, e.g. 'left*.jpg'."),
    image_format: Optional[str] = typer.Option(None, "--format", help="Image file extension, e.g. jpg."),
    pattern: Optional[str] = typer.Option(None, "--pattern", help="Inner corners COLSxROWS, e.g. 9x6."),
    square: Optional[float] = typer.Option(None, "--square", help="Square size of the board."),
    unit: Optional[str] = typer.Option(
        None, "--unit", help="Unit of the square size, a length: um, mm, cm, dm, m, in, ft (mm when --square is "
        "given; without it the board's squares). Written into every calibration file; reconstruct converts it to mm."),
    model: Optional[str] = typer.Option(
        None, "--model", help="Free distortion coefficients: k1,k2,p1,p2,k3 or a preset (k1, k1k2, k1k2p1p2, "
        "k1k2k3p1p2, rational), or fisheye (cv2.fisheye's k1..k4, as fk1,fk2,fk3,fk4), or splined (a smooth "
        "correction surface over a stereographic lens, splined:NXxNY knots, default 10x8; one camera, full set), or "
        "auto (the model that best predicts held-out views, of k1k2, default, fisheye, rational, splined; in a rig "
        "each camera chooses on its own views among the parametric ones)."),
    model_right: Optional[str] = typer.Option(
        None, "--model-right", help="Stereo: the right camera's lens model when it differs from the left's --model "
        "(e.g. fisheye); default: --model for both."),
    per_set: Optional[int] = typer.Option(
        None, "--per-set", help="Images per subset m (subset analysis); without it only the full set is solved."),
    max_subsets: Optional[int] = typer.Option(None, "--max-subsets", help="Cap on subsets (random sample above)."),
    seed: Optional[int] = typer.Option(None, "--seed", help="Seed of the subset sample."),
    step: list[str] = typer.Option(
        [], "--step", help="An optimisation step NAME=MAX[,NAME=MAX...] (repeat, in order; replaces the file's "
        "steps of that kind), e.g. --step re=0.5 --step p1=1.5,p2=1.5; stereo steps name stereo_re, Tnorm, Tx, Ty, "
        "Tz, RVnorm, RVx, RVy, RVz, e.g. --step stereo_re=3 --step Tnorm=0.75"),
    min_subsets: Optional[int] = typer.Option(
        None, "--min-subsets", help="A step stops before it would leave fewer subsets."),
    final: Optional[str] = typer.Option(
        None, "--final", help="What camera.yml/stereo.yml hold with subsets: survivors (default: the solve on the "
        "surviving subsets' views) or mean (the thesis's per-parameter subset mean)."),
    no_outlier_rejection: bool = typer.Option(
        False, "--no-outlier-rejection", help="Keep every detected corner and view (default: iterative k-sigma "
        "rejection of outlier corners and views, each one reported)."),
    board_sag: Optional[bool] = typer.Option(
        None, "--board-sag/--no-board-sag", help="Solve the board's sag (two parameters, x and y, in the board "
        "unit, as mrcal) with the rest, reported with its sigma (default on, for one camera and every rig). "
        "--no-board-sag: a flat board, as OpenCV."),
    out: Optional[Path] = typer.Option(None, "--out", help="Results folder (default PROJECT/results)."),
    force: bool = typer.Option(False, "--force", help="Replace an existing results folder."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress and no table (warnings still on stderr)."),
    no_cache: bool = typer.Option(False, "--no-cache", help="Detect corners again instead of using the cache."),
    left: Optional[Path] = typer.Option(
        None, "--left", help="Stereo: left camera's images, a folder or a pattern such as DIR/left*.jpg."),
    right: Optional[Path] = typer.Option(
        None, "--right", help="Stereo: right camera's images; partners by name (left05 / right05, L_05 / R_05, "
        "im0 / im1)."),
    cameras: Optional[Path] = typer.Option(
        None, "--cameras", help="N cameras: a folder with one subfolder of images per camera (sorted; the first is "
        "the reference), frames matched by file name, missing files allowed. Writes cameras.yml and a stereo file "
        "per adjacent pair."),
    pair: Optional[str] = typer.Option(
        None, "--pair", help="With --cameras: write the stereo file of this pair only, A,B (subfolder names)."),
    projection_range: Optional[float] = typer.Option(
        None, "--projection-range", help="Distance (board unit) of the projection-uncertainty map "
        "(plots/projection_uncertainty.png); default: the mean board distance."),
    projection_method: str = typer.Option(
        "pose-compensated", "--projection-method", help="Projection uncertainty: pose-compensated (a point fixed in "
        "the boards' frame, as mrcal) or intrinsics-only (fixed in the camera frame)."),
    cross_validate: int = typer.Option(
        0, "--cross-validate", help="Split the views in random halves N times (N >= 4 recommended), calibrate each "
        "half and check the projection difference against the predicted one (report, cross_validation.npz); for a "
        "rig, the frames: each half's joint solve, the cameras' placements and intrinsics against their +-."),
) -> None:
    """Calibrate one camera (or a stereo rig: --left/--right, or images/images_left + images_right): full-set
    solve, subset analysis and the thesis's robust optimisation steps."""
    from dstereo.config.calibration import build_config, file_layer, find_project_config, parse_step_flags, validate
    from dstereo.config.calibration_flags import flag_layer
    from dstereo.config.capabilities import RIGHT_LENS, STEREO_STEPS, refuse
    from dstereo.errors import DstereoError

    started = time.perf_counter()
    from dstereo.runtime import figure_pool

    # One figure worker now, before JAX is imported (next line): its imports (matplotlib, its fonts) then run on the
    # core that JAX's single-threaded import leaves idle; the others once that is done (`figure_pool.start`)
    figure_pool.start(now=1)
    from dstereo.uncertainty.projection import METHODS

    if projection_method not in METHODS:
        raise DstereoError(f"--projection-method {projection_method}: use one of {', '.join(METHODS)}")
    if cross_validate < 0:
        raise DstereoError(f"--cross-validate {cross_validate}: give a number of splits (4 or more), or leave it out")
    if projection_range is not None and not projection_range > 0:
        raise DstereoError(f"--projection-range {projection_range}: give a positive distance in the board's unit")
    if pair is not None and cameras is None:
        raise DstereoError("--pair: only with --cameras DIR (a rig of several cameras)")
    config_path = config if config is not None else (find_project_config(project) if project is not None else None)
    flags = flag_layer(dict(  # parameter -> flag value (dstereo.config.options.CALIBRATE)
        pattern=pattern, square=square, unit=unit, images=images, image_format=image_format, glob=glob, model=model,
        model_right=model_right, per_set=per_set, max_subsets=max_subsets, seed=seed, min_subsets=min_subsets,
        final=final, outlier_rejection=no_outlier_rejection, board_sag=board_sag, steps=step))
    cfg = build_config(*([file_layer(config_path)] if config_path is not None else []), flags)
    stereo_steps = flags.get("stereo_steps")
    cfg = validate(cfg)
    use_cache = not no_cache  # checked once the inputs and the results folder are (`_corner_cache_usable`)
    figure_pool.start_rest()  # JAX is imported: the other workers warm up on the core the full-set solve leaves
    _refuse_splined_where_unsupported(cfg, cameras is not None or left is not None or right is not None,
                                      cross_validate)
    if cameras is not None:
        if left is not None or right is not None or images is not None:
            raise DstereoError("--cameras: give the cameras' folder alone, without --images/--left/--right")
        if cfg.model_right is not None:
            refuse(RIGHT_LENS, "--cameras", _as_given(cfg, "model_right", "--model-right"))
        _run_cameras(cameras, cfg, _pair(pair), project, out, force, quiet, use_cache, started, projection_range,
                     cross_validate)
        return
    stereo_images = images if images is not None else (project / cfg.images if project is not None else None)
    if left is not None or right is not None or (stereo_images is not None and _stereo_layout(stereo_images)):
        _refuse_splined_where_unsupported(cfg, True, cross_validate)  # a stereo layout found in the images folder
        _run_stereo(stereo_images, cfg, left, right, project, out, force, quiet, use_cache, started,
                    projection_range, cross_validate)
        return
    if cfg.model_right is not None:
        refuse(RIGHT_LENS, "one camera", _as_given(cfg, "model_right", "--model-right"))
    if stereo_steps:
        refuse(STEREO_STEPS, "one camera", f"--step {', '.join(s for s in step if parse_step_flags([s])[1])}")
    if cfg.mode != "individual":
        raise DstereoError(f"{cfg.source or 'configuration'}: a stereo configuration needs the stereo images: put them "
                           "in images/images_left and images/images_right, or give --left DIR --right DIR")
    base = project if project is not None else (config_path.parent if config_path is not None else None)
    if images is None:
        if base is None:
            raise DstereoError("no images: give a PROJECT folder (with images/) or --images DIR")
        images = base / cfg.images
    from dstereo.calib.pipeline import list_camera_images
    from dstereo.io.pairing import check_one_camera

    check_one_camera(list_camera_images(images, cfg), str(images))
    out = _results_folder(out, project, force, cfg, inputs=[images, config_path])
    _run(images, cfg, out, force, quiet, use_cache, started, projection_range, projection_method, cross_validate)


def _corner_cache_usable() -> bool:
    """Whether the corner cache can be written; if not, one warning line now and the run goes on without it. Called
    after every refusal of the input (a refused run prints its one error line only), before the detection."""
    from dstereo.io.corners import corner_cache_problem

    problem = corner_cache_problem()
    if problem is not None:
        typer.echo(f"dstereo: warning: {problem}", err=True)
    return problem is None


def _results_folder(out, project, force: bool, cfg, inputs=()):
    """--out, else PROJECT/results; refused before any work if it exists without --force, or if it holds an input
    (images, configuration). Prints config warnings."""
    from dstereo.errors import DstereoError
    from dstereo.io.output_location import check_not_inputs
    from dstereo.io.results import check_output

    if out is None:
        if project is None:
            raise DstereoError("no results folder: give --out DIR (or a PROJECT folder, which gets PROJECT/results)")
        out = project / "results"
    check_not_inputs(out, inputs)
    check_output(out, force)
    for warning in cfg.warnings:
        typer.echo(f"dstereo: warning: {warning}", err=True)
    return out


def _stereo_layout(images: Path) -> bool:
    from dstereo.io.pairing import has_stereo_layout

    return has_stereo_layout(images)


def _run_stereo(images, cfg, left, right, project, out, force, quiet, use_cache, started,
                projection_range=None, cross_validate: int = 0) -> None:
    """Stereo mode (thesis 4.2.2.2): both cameras, then the rig; see dstereo.calib.stereo_pipeline."""
    from dstereo.calib.stereo_pipeline import calibrate_stereo_project, stereo_sources, summary_lines
    from dstereo.errors import DstereoError
    from dstereo.io.stereo_files import write_stereo_results

    if left is not None and right is not None and left.is_dir() and left.resolve() == Path(right).resolve():
        raise DstereoError(f"--left and --right are the same folder {left}; give each camera's images, e.g. "
                           f"--left '{left}/left*.jpg' --right '{left}/right*.jpg'")
    sources = stereo_sources(images, cfg, left, right)
    out = _results_folder(out, project, force, cfg, inputs=[*sources.mono_left, *sources.mono_right,
                                                             *sources.stereo_left, *sources.stereo_right])
    use_cache = use_cache and _corner_cache_usable()
    with progress_bars(quiet) as progress:
        job = calibrate_stereo_project(sources, cfg, progress=progress, use_cache=use_cache, scratch=Path(out).parent,
                                       cross_validate=cross_validate)
        write_stereo_results(out, job, force, projection_range=projection_range)
    job.timings["total_s"] = time.perf_counter() - started
    for warning in job.warnings:
        typer.echo(f"dstereo: warning: {warning}", err=True)
    if not quiet:
        typer.echo("\n".join(summary_lines(job, out)))


def _pair(spec: Optional[str]):
    from dstereo.errors import DstereoError

    if spec is None:
        return None
    names = [p.strip() for p in spec.split(",")]
    if len(names) != 2 or not all(names):
        raise DstereoError(f"--pair {spec}: give two camera subfolder names, A,B")
    return tuple(names)


def _run_cameras(root, cfg, pair, project, out, force, quiet, use_cache, started, projection_range=None,
                 cross_validate: int = 0) -> None:
    """N cameras (--cameras DIR): see dstereo.calib.multiview_job."""
    import numpy as np

    from dstereo.calib.multiview_job import calibrate_cameras_project, camera_folders
    from dstereo.io.cameras_files import write_multiview_results

    folders = camera_folders(root, cfg)
    out = _results_folder(out, project, force, cfg, inputs=[root, *folders])
    use_cache = use_cache and _corner_cache_usable()
    with progress_bars(quiet) as progress:
        job = calibrate_cameras_project(root, cfg, progress=progress, use_cache=use_cache, scratch=Path(out).parent,
                                        cross_validate=cross_validate)
        job.pairs(pair)  # a wrong --pair is refused before anything is written
        write_multiview_results(out, job, force, pairs=pair, projection_range=projection_range)
    job.timings["total_s"] = time.perf_counter() - started
    for warning in job.warnings:
        typer.echo(f"dstereo: warning: {warning}", err=True)
    if not quiet:
        sol = job.solution
        for label, cam, T, rms in zip(job.labels, sol.cameras, sol.T, sol.camera_rms()):
            typer.echo(f"{label}: fx {float(cam.k[0]):.3f} fy {float(cam.k[1]):.3f} cx {float(cam.k[2]):.3f} "
                       f"cy {float(cam.k[3]):.3f}  |T| {np.linalg.norm(T):.4f}  RMS {rms:.4f} px "
                       f"({int(job.visible[:, job.labels.index(label)].sum())} views)" + _chosen(job, label))
        typer.echo(f"rig: {len(job.frames)} frames, joint RMS {sol.rms:.4f} px (held {job.held.rms:.4f} px)")
        if job.consistency is not None:
            typer.echo(job.consistency.line())
        if job.cross_validation is not None:
            typer.echo(job.cross_validation.verdict())
        if job.subsets is not None:
            typer.echo("\n".join(job.subsets.lines()))
        typer.echo(f"wrote {out}")


def _chosen(job, label: str) -> str:
    """", model auto: <preset>" for a camera whose lens --model auto chose."""
    choice = job.cameras[job.labels.index(label)].model_choice
    return "" if choice is None else f", model auto: {choice.chosen}"


def _as_given(cfg, name: str, flag: str, value: str | None = None) -> str:
    """A configuration value as the user gave it: "--model auto" from the flag, "FILE [calibration] model = auto"
    from a file (`Config.origins`), so a message does not put a file's value on a flag."""
    origin = cfg.origins.get(name, flag)
    if value is None:
        return origin
    return f"{origin} {value}" if origin.startswith("-") else f"{origin} = {value}"


def _refuse_splined_where_unsupported(cfg, rig: bool, cross_validate: int) -> None:
    """The splined lens (models/splined.py) is for one camera's full-set calibration (issue 16 item 2)."""
    from dstereo.errors import DstereoError
    from dstereo.models.distortion import lens_model

    right = getattr(cfg, "model_right", None)
    from dstereo.config.capabilities import SPLINED, refuse

    if rig and right is not None and lens_model(tuple(right)) == "splined":
        refuse(SPLINED, "--left/--right", _as_given(cfg, "model_right", "--model-right", "splined"))
    if lens_model(tuple(cfg.model)) != "splined":
        return
    if rig:
        refuse(SPLINED, "--cameras", _as_given(cfg, "model", "--model", "splined"))
    if cross_validate or cfg.per_set is not None:
        raise DstereoError(f"{_as_given(cfg, 'model', '--model', 'splined')}: subsets (`per_set`) and --cross-validate "
                           "are not available for the "
                           "splined lens (its knots are ~160 parameters); run it on the full set alone")


def _run(images: Path, cfg, out: Path, force: bool, quiet: bool, use_cache: bool, started: float,
         projection_range: float | None = None, projection_method: str = "pose-compensated",
         cross_validate: int = 0) -> None:
    from dstereo.io.results import EarlyFigures

    use_cache = use_cache and _corner_cache_usable()
    early = EarlyFigures(out)  # the parameter figures, drawn while the survivors' solve and the writing run
    try:
        _run_and_write(images, cfg, out, force, quiet, use_cache, started, projection_range, projection_method,
                       cross_validate, early)
    finally:
        early.discard()


def _run_and_write(images, cfg, out, force, quiet, use_cache, started, projection_range, projection_method,
                   cross_validate, early) -> None:
    from dstereo.calib.pipeline import calibrate_camera
    from dstereo.io.results import write_camera_results

    with progress_bars(quiet) as progress:
        cal = calibrate_camera(images, cfg, progress=progress, use_cache=use_cache, scratch=Path(out).parent,
                               after_steps=early.parameters, cross_validate=cross_validate,
                               projection_range=projection_range)
        cal.projection_method = projection_method
        t0 = time.perf_counter()
        if progress is not None:
            progress("writing results", 0, 1)
        write_camera_results(out, cal, force, projection_range=projection_range, early=early)
        if progress is not None:
            progress("writing results", 1, 1)
    cal.timings["write_s"] = time.perf_counter() - t0
    cal.timings["total_s"] = time.perf_counter() - started
    for warning in cal.warnings:
        if warning not in cfg.warnings:
            typer.echo(f"dstereo: warning: {warning}", err=True)
    if not quiet:
        _render(cal, out)


def _pm(value: float, spread: float) -> str:
    if spread != spread:  # NaN: no subsets
        return "-"
    return f"{value:.6g} +- {spread:.3g}"


def _render(cal, out: Path) -> None:
    """Final console table: full set +- std (Jacobian x view scatter), subset mean +- spread; then counts and timings."""
    from dstereo.uncertainty.view_effects import reported_std

    full = cal.full
    mean = cal.subset_mean if cal.subset_mean is not None else cal.final
    rows = [(n, _pm(float(v), float(s)), _pm(mean[n], cal.spread[n]))
            for n, v, s in zip(full.names, full.values, reported_std(full)) if full.lens_model != "splined" or
            n[:3] not in ("sx_", "sy_")]  # a splined lens's knots (~160) are in camera.yml's splined section
    subsets = "subset mean +- spread"
    if cal.filtering is not None:
        subsets += f" ({int(cal.filtering.survivors.sum())} of {int(cal.filtering.usable.sum())} subsets)"
    try:
        from rich.console import Console
        from rich.table import Table

        table = Table(title=f"camera: {len(cal.used)} images, RMS {full.rms:.4f} px (full set)")
        for title in ("parameter", "full set +- std", subsets):
            table.add_column(title, justify="right")
        for row in rows:
            table.add_row(*row)
        Console(width=110).print(table)
    except ImportError:
        width = max(len(r[1]) for r in rows) + 2
        typer.echo(f"{'parameter':>9}  {'full set +- std':>{width}}  {subsets}")
        for name, a, b in rows:
            typer.echo(f"{name:>9}  {a:>{width}}  {b}")
    if cal.outliers is not None:
        typer.echo(cal.outliers.summary())
        worst = sorted(cal.outliers.corners, key=lambda c: -c[3])[:5]
        if worst:
            typer.echo("  worst: " + "; ".join(f"{i} corner {c} {r:.2f} px ({z:.1f} sigma)" for i, c, r, z in worst)
                       + " (all in report.md / summary.json)")
    if cal.filtering is not None:
        for s in cal.filtering.steps:
            typer.echo(f"  {s.message}")
    if cal.final_solution is not None:
        c = cal.final_solution.check
        typer.echo(f"camera.yml: {cal.final_solution.source(cal.used)}")
        typer.echo(f"  fit on the surviving views (poses refitted): solve {c.rms_solution:.4f} px, subset mean "
                   f"{c.rms_mean:.4f} px ({c.ratio:.3f}x)")
    if cal.model_choice is not None:
        from dstereo.models.distortion import model_label

        c = cal.model_choice.chosen_candidate
        others = ", ".join(f"{o.preset} {o.heldout_rms:.4f}" for o in cal.model_choice.candidates if o is not c)
        typer.echo(f"model auto: {c.preset} ({model_label(c.free)}), held-out RMS {c.heldout_rms:.4f} px (others: "
                   f"{others}); the table is in report.md")
    t = cal.timings
    typer.echo("timings: " + ", ".join(f"{k[:-2]} {v:.1f} s" for k, v in t.items()))
    typer.echo(f"wrote {out}")
