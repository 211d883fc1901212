"""`dstereo calibrate`: one camera, a stereo pair (--left/--right, the thesis layout) or N cameras (--cameras): parse
the flags, check them as one request (calibrate_request.py), run the one job and print (calibrate_runs.py); where
its subset blocks run: calibrate_placement.py."""

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
    from dstereo.commands.calibrate_placement import subset_placement
    from dstereo.runtime import figure_pool

    started = time.perf_counter()
    with subset_placement(workers, scheduler, resume, force, out, project):
        # One figure worker now, before JAX is imported (by the request's checks): its imports (matplotlib, its
        # fonts) then run on the core that JAX's single-threaded import leaves idle; the others once that is done
        figure_pool.start(now=1)
        from dstereo.commands.calibrate_request import calibrate_request
        from dstereo.commands.calibrate_runs import run_request

        request = calibrate_request(project, config, images, glob, image_format, pattern, square, unit, model,
                                    model_right, per_set, max_subsets, seed, step, min_subsets, final,
                                    no_outlier_rejection, board_sag, mrcal_convert, out, force, quiet, no_cache, left,
                                    right, cameras, pair, projection_range, projection_method, cross_validate)
        run_request(request, started)
