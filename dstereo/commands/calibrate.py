"""`dstereo calibrate`: one camera, a stereo pair (--left/--right, the thesis layout) or N cameras (--cameras): parse,
check the request (calibrate_checks.py), run the job and print (calibrate_runs.py)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from dstereo.config.options import CALIBRATE  # the standard library only: the flags' table


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
    mrcal_convert: bool = CALIBRATE.option("mrcal_convert", False),
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
    workers: Optional[int] = CALIBRATE.option("workers"),
    scheduler: Optional[str] = CALIBRATE.option("scheduler"),
    resume: bool = CALIBRATE.option("resume", False),
) -> None:
    """Calibrate one camera (or a stereo rig: --left/--right, or images/images_left + images_right): full-set
    solve, subset analysis and the thesis's robust optimisation steps."""
    started = time.perf_counter()
    with _subset_placement(workers, scheduler, resume, force, out, project):
        _calibrate(project, config, images, glob, image_format, pattern, square, unit, model, model_right, per_set,
                   max_subsets, seed, step, min_subsets, final, no_outlier_rejection, board_sag, mrcal_convert, out,
                   force, quiet, no_cache, left, right, cameras, pair, projection_range, projection_method,
                   cross_validate, started)


def _subset_placement(workers, scheduler, resume, force, out, project):
    """Where subset blocks run (`runtime.placement`): on a Dask cluster with --workers N (N > 1) or --scheduler, else
    here; with the blocks of long runs kept in OUT.partial (--resume continues from them; removed once the run has
    ended with its results). Refuses bad values and an earlier run's blocks without --resume or --force, first."""
    import contextlib

    from dstereo.errors import DstereoError
    from dstereo.runtime.placement import Placement, placed

    runner = None
    if workers is not None or scheduler is not None:
        from dstereo.runtime.tasks import FrameRunner

        runner = FrameRunner(workers if workers is not None else 1, scheduler)
    target = out if out is not None else (project / "results" if project is not None else None)
    store = None
    if target is not None:
        from dstereo.io.partial_store import PartialStore, partial_folder

        folder = partial_folder(target)
        if folder.exists() and not resume and not force:
            raise DstereoError(f"{folder} holds the subset blocks of an earlier run; pass --resume to continue it, or "
                               "--force to start afresh")
        if resume and not folder.exists():
            raise DstereoError(f"--resume: {folder} does not exist: no earlier run of {target} to continue; run "
                               "without --resume")
        opened: dict = {}

        def store(key):
            """The blocks of one subset stage (a run may have several: each camera's, the rig's) in a folder of
            their own in OUT.partial, named by the stage's inputs."""
            if key not in opened:
                opened[key] = PartialStore(folder / key[:16], key).open(resume, force)
            return opened[key]

    @contextlib.contextmanager
    def around():
        with placed(Placement(runner, store)):
            yield
        _build_ahead()
        if target is not None:  # the run ended with its results: its kept blocks are done with
            from dstereo.io.partial_store import PartialStore

            PartialStore(target, "").remove()

    return around()


def _build_ahead() -> None:
    """The programs this run used whose shapes follow the view count, built for the other view buckets in the
    background (`runtime/prebuild.py`); said once per executables folder."""
    from dstereo.runtime import buckets, prebuild

    records, sizes = buckets.noted(), buckets.noted_sizes()
    buckets.clear_noted()
    if prebuild.start(records, sizes):
        told = prebuild.folder() / "told"
        if not told.exists():
            told.touch()
            typer.echo("dstereo: note: building this calibration's programs for other view counts (5-60) in the "
                       "background, one core at low priority, so that a data set of another size starts without "
                       "compiling; off: DSTEREO_PREBUILD=0 (this note is shown once)", err=True)


def _calibrate(project, config, images, glob, image_format, pattern, square, unit, model, model_right, per_set,
               max_subsets, seed, step, min_subsets, final, no_outlier_rejection, board_sag, mrcal_convert, out,
               force, quiet, no_cache, left, right, cameras, pair, projection_range, projection_method,
               cross_validate, started) -> None:
    from dstereo.config.calibration import build_config, file_layer, find_project_config, parse_step_flags, validate
    from dstereo.config.calibration_flags import flag_layer
    from dstereo.commands.calibrate_checks import as_given, check_run_options, pair_of, \
        refuse_splined_where_unsupported, results_folder, stereo_layout
    from dstereo.commands.calibrate_runs import run_camera, run_cameras, run_stereo
    from dstereo.config.capabilities import RIGHT_LENS, STEREO_STEPS, refuse
    from dstereo.errors import DstereoError
    from dstereo.runtime import figure_pool

    # One figure worker now, before JAX is imported (next line): its imports (matplotlib, its fonts) then run on the
    # core that JAX's single-threaded import leaves idle; the others once that is done (`figure_pool.start`)
    figure_pool.start(now=1)
    check_run_options(projection_method, cross_validate, projection_range, pair, cameras)
    config_path = config if config is not None else (find_project_config(project) if project is not None else None)
    flags = flag_layer(dict(  # parameter -> flag value (dstereo.config.options.CALIBRATE)
        pattern=pattern, square=square, unit=unit, images=images, image_format=image_format, glob=glob, model=model,
        model_right=model_right, per_set=per_set, max_subsets=max_subsets, seed=seed, min_subsets=min_subsets,
        final=final, outlier_rejection=no_outlier_rejection, board_sag=board_sag, steps=step,
        mrcal_convert=mrcal_convert))
    cfg = build_config(*([file_layer(config_path)] if config_path is not None else []), flags)
    stereo_steps = flags.get("stereo_steps")
    cfg = validate(cfg)
    use_cache = not no_cache  # checked once the inputs and the results folder are (`corner_cache_usable`)
    figure_pool.start_rest()  # JAX is imported: the other workers warm up on the core the full-set solve leaves
    refuse_splined_where_unsupported(cfg, cameras is not None or left is not None or right is not None,
                                     cross_validate)
    if cameras is not None:
        if left is not None or right is not None or images is not None:
            raise DstereoError("--cameras: give the cameras' folder alone, without --images/--left/--right")
        if cfg.model_right is not None:
            refuse(RIGHT_LENS, "--cameras", as_given(cfg, "model_right", "--model-right"))
        run_cameras(cameras, cfg, pair_of(pair), project, out, force, quiet, use_cache, started, projection_range,
                    cross_validate)
        return
    stereo_images = images if images is not None else (project / cfg.images if project is not None else None)
    if left is not None or right is not None or (stereo_images is not None and stereo_layout(stereo_images)):
        refuse_splined_where_unsupported(cfg, True, cross_validate)  # a stereo layout found in the images folder
        run_stereo(stereo_images, cfg, left, right, project, out, force, quiet, use_cache, started,
                   projection_range, cross_validate)
        return
    if cfg.model_right is not None:
        refuse(RIGHT_LENS, "one camera", as_given(cfg, "model_right", "--model-right"))
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
    from dstereo.jobs.calibrate_camera import list_camera_images
    from dstereo.io.pairing import check_one_camera

    check_one_camera(list_camera_images(images, cfg), str(images))
    out = results_folder(out, project, force, cfg, inputs=[images, config_path])
    run_camera(images, cfg, out, force, quiet, use_cache, started, projection_range, projection_method, cross_validate)
