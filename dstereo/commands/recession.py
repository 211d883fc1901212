"""`dstereo recession`: surface recession over a sequence of stereo pairs, with rates and 95 % intervals."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def recession(
    sequence: Path = typer.Argument(
        ..., help="Sequence folder: left/ + right/ (or images_left/ + images_right/) with one image per frame and "
        "camera, partners named alike (left_007 / right_007)."),
    calib: Path = typer.Option(..., "--calib", help="stereo.yml (or any calibration `dstereo reconstruct` reads)."),
    out: Path = typer.Option(..., "--out", help="Results folder (refused if it exists, unless --force)."),
    timestamps: Optional[Path] = typer.Option(
        None, "--timestamps", help="CSV `name,time_s` (default SEQUENCE/timestamps.csv if present, else times in "
        "the names such as left_t=12.5s.png, or --fps)."),
    fps: Optional[float] = typer.Option(None, "--fps", help="Frame rate: time = frame number in the name / fps."),
    axis: Optional[str] = typer.Option(
        None, "--axis", help="Sample axis x,y,z in the left camera frame (default: estimated from the first frame)."),
    point: Optional[str] = typer.Option(None, "--point", help="Stagnation point x,y,z mm, left camera (with --axis)."),
    grid: float = typer.Option(0.5, "--grid", help="Grid cell size over the front face, mm."),
    stagnation_radius: Optional[float] = typer.Option(None, "--stagnation-radius", help="Radius of the stagnation disc, mm "
                                            "(default: 2 mm, or 4 grid cells on a grid coarser than 0.5 mm)."),
    stagnation_fit: str = typer.Option(
        "quadratic", "--stagnation-fit", help="Value at the stagnation point: quadratic (a + b u + c v + d rho^2 over "
        "the disc, unbiased at a peak) or mean."),
    min_points: int = typer.Option(8, "--min-points", help="Points a grid cell needs for a height (else empty)."),
    refine: bool = typer.Option(True, "--refine/--no-refine", help="Sub-pixel refinement of SGBM's disparity."),
    preset: Optional[str] = typer.Option(None, "--preset", help="SGBM preset: default, thesis-5.9, thesis-5.15."),
    sgbm: list[str] = typer.Option([], "--sgbm", help="SGBM parameter NAME=VALUE (repeat), e.g. block_size=7."),
    z_min: Optional[float] = typer.Option(None, "--z-min", help="Nearest depth of the sample, mm (sets the range)."),
    z_max: Optional[float] = typer.Option(None, "--z-max", help="Farthest depth of the sample, mm."),
    roi: Optional[str] = typer.Option(None, "--roi", help="x,y,w,h on the rectified left image: keep points inside."),
    workers: Optional[int] = typer.Option(
        None, "--workers", help="Frames in parallel on a local Dask cluster of this many processes (default: the "
        "machine's cores when the frames, timed on the first, would take over ~30 s serially; else one after "
        "another here; 1: always one after another in this process; at most 4 x the cores)."),
    scheduler: Optional[str] = typer.Option(
        None, "--scheduler", help="Address of a running Dask scheduler (tcp://host:8786): its workers run the "
        "frames (they need dstereo installed and the images at the same paths)."),
    resume: bool = typer.Option(
        False, "--resume", help="Continue an interrupted run from the frames kept in OUT.partial (same inputs and "
        "options required)."),
    retries: int = typer.Option(2, "--retries", help="Reruns of a frame whose worker process died, then it fails."),
    force: bool = typer.Option(False, "--force", help="Replace an existing results folder."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar and no summary."),
) -> None:
    """Recession of a sample's front face over time: a surface per stereo pair, recession along the sample axis
    on a grid over the face, at the stagnation point and as maps, and recession rates with 95 % intervals."""
    from dataclasses import asdict

    from dstereo import __version__
    from dstereo.io.partial_store import PartialStore, fingerprint
    from dstereo.runtime.tasks import FrameRunner

    from dstereo.commands.progress import progress_bars
    from dstereo.commands.matching_options import search_range_line, search_range_tries
    from dstereo.config import reconstruction as settings
    from dstereo.errors import DstereoError
    from dstereo.io.calib_files import read_stereo_calibration
    from dstereo.io.results import check_output
    from dstereo.recession import RecessionConfig
    from dstereo.io.sequence_files import check_sizes, discover
    from dstereo.jobs.recession import run_recession
    from dstereo.stereo.pair_result import calibration_size_check, check_rig
    from dstereo.io.recession_files import write_results

    from dstereo.io.output_location import check_not_inputs

    check_not_inputs(out, [sequence, calib, timestamps])
    check_output(out, force)
    if stagnation_fit not in ("quadratic", "mean"):
        raise DstereoError(f"--stagnation-fit {stagnation_fit!r}: use quadratic or mean")
    cfg = RecessionConfig(grid_mm=grid, stagnation_radius_mm=stagnation_radius, stagnation_model=stagnation_fit,
                          axis=_vector(axis, "--axis"), point=_vector(point, "--point"), min_points_per_cell=min_points,
                          refine_subpixel=refine)
    recon = settings.build(settings.flag_layer({"preset": preset, "sgbm": sgbm, "z_min": z_min, "z_max": z_max,
                                                "roi": roi}))
    settings.check(recon)
    runner = FrameRunner(workers, scheduler, retries)  # refuses a worker count or address it cannot use, first

    calibration = read_stereo_calibration(calib)
    check_rig(calibration)
    if calibration.rectified:
        raise DstereoError(f"calibration {calib}: a rectified (Middlebury) calibration has no camera frame for a "
                           "sample axis; give the stereo.yml of the rig")
    frames = discover(sequence, timestamps, fps)
    from dstereo.io.pairing import check_distinct_images

    for frame in frames:  # same file or byte copy (decoding every frame twice more would cost a long sequence)
        check_distinct_images(frame.left, frame.right, decode=False)
    size = check_sizes(frames, calibration.image_size, str(calib))
    settings.check(recon, size)  # the SGBM settings against the frames' size
    size_warning = calibration_size_check(calibration, size)
    if size_warning:
        typer.echo(f"dstereo: warning: {size_warning}", err=True)
    inputs = [p for f in frames for p in (f.left, f.right)]
    settings = (asdict(cfg), repr(recon), [(f.key, f.time_s) for f in frames], __version__)
    store = PartialStore(out, fingerprint([calib], inputs, settings)).open(resume, force)
    try:
        with progress_bars(quiet) as progress:
            result = run_recession(frames, calibration, cfg, recon, progress=progress, runner=runner, store=store)
            summary = write_results(out, result, calib, sequence, force, extra={"run": runner.describe()})
    except KeyboardInterrupt:
        typer.echo(f"dstereo: interrupted: {store.count()} finished frame(s) kept in {store.folder}; run the same "
                   "command with --resume to continue from them", err=True)
        raise typer.Exit(130)
    except DstereoError:
        if store.count() == 0:  # nothing worth keeping: leave no work folder behind
            store.remove()
        raise
    if runner.decision and not quiet:
        typer.echo(runner.decision)
    failed = [f for f in result.frames if f.status == "failed"]
    if failed:
        typer.echo(f"dstereo: warning: {len(failed)} frame(s) failed; the other frames are kept in {store.folder}: "
                   "`--resume --force` measures the failed ones and rewrites the results", err=True)
    else:
        store.remove()
    for f in result.frames:
        if not f.ok:
            typer.echo(f"dstereo: warning: frame {f.name} (t = {f.time_s:g} s) {f.status}: {f.reason}", err=True)
    for w in result.warnings:
        typer.echo(f"dstereo: warning: {w}", err=True)
    if quiet:
        return
    fit = result.fit
    typer.echo(search_range_line(summary.get("search_range")) + " (reference frame)")
    for line in search_range_tries(summary.get("search_range")):
        typer.echo(f"  {line}")
    typer.echo(f"{summary['frames_used']} of {summary['frames']} frames; stagnation point "
               f"{[round(v, 2) for v in result.sample.point.tolist()]} mm, axis "
               f"{[round(v, 4) for v in result.sample.axis.tolist()]} ({result.sample.source}"
               + (f"; axis sigma {result.sample.axis_sigma_deg:.2g} deg" if result.sample.axis_sigma_deg else "") + ")")
    last = [f for f in result.frames if f.ok][-1]
    typer.echo(f"recession at the stagnation point after {last.time_s - result.frames[result.reference].time_s:g} s: "
               f"{last.recession.value:.3f} +- {last.recession.se:.3f} mm")
    typer.echo(f"rate: {1000 * fit.rate:.4g} um/s, 95 % interval [{1000 * fit.ci95[0]:.4g}, {1000 * fit.ci95[1]:.4g}] "
               f"um/s (residual RMS {fit.residual_rms:.3g} mm, {fit.n} frames"
               + (f"; standard error {1000 * fit.rate_se_frames:.2g} from the frames' scatter, "
                  f"{1000 * fit.rate_se_common:.2g} common to all frames" if fit.rate_se_common is not None else "")
               + ")")
    typer.echo(f"wrote {out}")


def _vector(text: Optional[str], flag: str):
    if text is None:
        return None
    from dstereo.errors import DstereoError

    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3:
        raise DstereoError(f"{flag} {text!r}: write three numbers x,y,z, e.g. {flag} 0,0,1")
    return values
