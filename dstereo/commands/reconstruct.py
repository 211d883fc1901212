"""`dstereo reconstruct`: rectify, match and triangulate stereo pairs into a results folder."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def reconstruct(
    left: list[Path] = typer.Option(..., "--left", help="Left image (repeat for several pairs)."),
    right: list[Path] = typer.Option(..., "--right", help="Right image, in the same order as --left."),
    out: Path = typer.Option(..., "--out", help="Results folder (refused if it exists, unless --force)."),
    calib: Optional[Path] = typer.Option(
        None, "--calib", help="stereo.yml, OpenCV YAML with M1 D1 M2 D2 R T, or Middlebury calib.txt. "
        "Without it the uncalibrated path runs (needs --focal-mm or --focal-px)."),
    project: Optional[Path] = typer.Option(
        None, "--project", help="Project folder: its stereo.yml/calib.txt and dstereo.toml are used as defaults."),
    config: Optional[Path] = typer.Option(None, "--config", help="TOML/JSON file with [reconstruct] and [sgbm]."),
    preset: Optional[str] = typer.Option(None, "--preset", help="SGBM preset: default, thesis-5.9, thesis-5.15."),
    sgbm: list[str] = typer.Option([], "--sgbm", help="SGBM parameter NAME=VALUE (repeat), e.g. block_size=7."),
    z_min: Optional[float] = typer.Option(None, "--z-min", help="Nearest depth of the scene, mm (sets the range)."),
    z_max: Optional[float] = typer.Option(None, "--z-max", help="Farthest depth of the scene, mm."),
    alpha: Optional[float] = typer.Option(None, "--alpha", help="Rectification free scaling: -1 default, 0..1."),
    zero_disparity: Optional[bool] = typer.Option(
        None, "--zero-disparity/--own-centres", help="Share one principal point (OpenCV's default) or centre each view."),
    lr_check: Optional[float] = typer.Option(None, "--lr-check", help="Left-right consistency tolerance, px."),
    roi: Optional[str] = typer.Option(None, "--roi", help="x,y,w,h on the rectified left image: keep points inside."),
    outliers: Optional[int] = typer.Option(None, "--outliers", help="Statistical outlier removal: neighbours (0 off)."),
    outlier_std: Optional[float] = typer.Option(None, "--outlier-std", help="Outlier threshold in std devs."),
    max_jump: Optional[float] = typer.Option(None, "--max-jump", help="Relative depth step that breaks the mesh."),
    refine: Optional[bool] = typer.Option(
        None, "--refine/--no-refine", help="Refine SGBM's pixel-locked sub-pixel disparity (cubic re-rectification + "
        "Lucas-Kanade); pixels it cannot refine are dropped. Default off: it helps on well-textured, smooth "
        "surfaces (speckle), not on scenes with many slanted or occluding edges."),
    focal_mm: Optional[float] = typer.Option(None, "--focal-mm", help="Uncalibrated: lens focal length, mm."),
    pixel_size_mm: Optional[float] = typer.Option(None, "--pixel-size-mm", help="Uncalibrated: pixel pitch, mm."),
    crop_factor: Optional[float] = typer.Option(None, "--crop-factor", help="Uncalibrated: crop factor (36 mm)."),
    focal_px: Optional[float] = typer.Option(None, "--focal-px", help="Uncalibrated: focal length in px."),
    baseline_mm: Optional[float] = typer.Option(
        None, "--baseline-mm", help="Uncalibrated: baseline, mm (without it the output is unscaled)."),
    disparity_sigma: Optional[str] = typer.Option(
        None, "--disparity-sigma", help="Disparity noise in rectified px for the point uncertainties, or 'auto' "
        "(default: per pixel from the image gradients and the image noise, checked on smooth parts of the map)."),
    no_uncertainty: bool = typer.Option(False, "--no-uncertainty", help="Skip the point uncertainties (sigma_*)."),
    full_covariance: bool = typer.Option(
        False, "--full-covariance", help="Also write cov_xyz.npy, the (h, w, 3, 3) covariance of every point."),
    workers: Optional[int] = typer.Option(
        None, "--workers", help="Several pairs: in parallel on a local Dask cluster of this many processes "
        "(default: the machine's cores when the pairs, timed on the first, would take over ~30 s serially; else one "
        "after another here; 1: always one after another in this process)."),
    scheduler: Optional[str] = typer.Option(
        None, "--scheduler", help="Several pairs: address of a running Dask scheduler (tcp://host:8786); its workers "
        "need dstereo, the images at the same paths and OUT's parent folder shared."),
    resume: bool = typer.Option(False, "--resume", help="Several pairs: continue from the pairs kept in OUT.partial."),
    retries: int = typer.Option(2, "--retries", help="Reruns of a pair whose worker process died, then it fails."),
    force: bool = typer.Option(False, "--force", help="Replace an existing results folder."),
) -> None:
    """Reconstruct stereo pairs: rectified pair, disparity, depth, point cloud, mesh and summary.json."""
    from dstereo.commands.matching_options import search_range_line
    from dstereo.config import reconstruction as settings
    from dstereo.errors import DstereoError
    from dstereo.stereo.pipeline import run_reconstruction

    if len(left) != len(right):
        raise DstereoError(f"{len(left)} --left but {len(right)} --right images; give them in pairs")
    from dstereo.io.output_location import check_not_inputs
    from dstereo.io.pairing import check_distinct_images, check_order_agrees_with_names

    check_not_inputs(out, [*left, *right, calib, config])

    check_order_agrees_with_names(left, right)
    for a, b in zip(left, right):
        check_distinct_images(a, b)
    layers = []  # defaults < the project's file < --config < flags
    if project is not None:
        if not project.is_dir():
            raise DstereoError(f"project folder {project} does not exist")
        if calib is None:
            calib = next((project / n for n in ("stereo.yml", "stereo.yaml", "calib.txt") if (project / n).is_file()),
                         None)
        found = settings.project_file(project)
        layers += [settings.file_layer(found)] if found is not None else []
    if config is not None:
        layers.append(settings.file_layer(config))
    layers.append(settings.flag_layer({  # parameter -> flag value (dstereo.config.options.RECONSTRUCT)
        "preset": preset, "sgbm": sgbm, "z_min": z_min, "z_max": z_max, "roi": roi, "sgbm.lr_check": lr_check,
        "alpha": alpha, "zero_disparity": zero_disparity, "refine": refine, "outlier_neighbours": outliers,
        "outlier_std": outlier_std, "max_jump": max_jump, "focal_mm": focal_mm, "pixel_size_mm": pixel_size_mm,
        "crop_factor": crop_factor, "focal_px": focal_px, "baseline_mm": baseline_mm, "uncertainty": no_uncertainty,
        "full_covariance": full_covariance, "disparity_sigma": disparity_sigma}))
    cfg = settings.build(*layers)
    settings.check(cfg, _width(left[0]))

    if len(left) == 1:
        results = run_reconstruction(list(zip(left, right)), out, calib, cfg, force)
    else:
        results = _several_pairs(list(zip(left, right)), out, calib, config, cfg, force, workers, scheduler, resume,
                                 retries)
    for r in results:
        s = r.summary
        depth = s.get("depth_mm") or {}
        typer.echo(f"{r.name}: {100 * s['valid_fraction']:.1f}% valid, depth {depth.get('min', float('nan')):.1f}.."
                   f"{depth.get('max', float('nan')):.1f} {s['units']}")
        typer.echo(f"  {search_range_line(s.get('search_range'))}")
        if s.get("refine", {}).get("enabled"):
            typer.echo(f"  sub-pixel refinement: {100 * s['refine']['dropped_fraction']:.2f}% of SGBM's pixels dropped")
        unc = s.get("uncertainty") or {}
        if unc.get("sigma_z_mm"):
            split = unc["median_point"]
            typer.echo(f"  depth std sigma_z: median {unc['sigma_z_mm']['median']:.3g} mm, p95 "
                       f"{unc['sigma_z_mm']['p95']:.3g} mm (sigma_d median {unc['sigma_d_px']:.3g} px); "
                       f"at the median point calibration {split['calibration_mm']:.3g} mm, disparity "
                       f"{split['disparity_mm']:.3g} mm" + ("" if unc["calibration_included"] else
                                                            "; calibration uncertainty not included"))
        check = (s.get("disparity_noise") or {}).get("plane_check") or {}
        if check.get("ratio") is not None:
            typer.echo(f"  noise check: scatter about local surface fits {check['observed_px']:.3g} px = "
                       f"{check['ratio']:.2f}x the predicted sigma_d ({check['tiles']} smooth tiles)"
                       + (f"; sigmas scaled by {s['disparity_noise']['scaled_by']:.2f}"
                          if s["disparity_noise"]["scaled_by"] != 1.0 else ""))
        for w in r.warnings:
            typer.echo(f"dstereo: warning: {w}", err=True)
    typer.echo(f"wrote {out}")


def _several_pairs(pairs, out, calib, config_file, cfg, force, workers, scheduler, resume, retries):
    """Each pair a task (`dstereo.frames.pairs`); Ctrl-C keeps the finished pairs for --resume."""
    from dstereo import __version__
    from dstereo.commands.progress import progress_bars
    from dstereo.errors import DstereoError
    from dstereo.frames import FrameRunner, PartialStore, fingerprint
    from dstereo.frames.pairs import reconstruct_pairs
    from dstereo.io.results import check_output

    check_output(out, force)
    runner = FrameRunner(workers, scheduler, retries)
    key = fingerprint([calib, config_file], [p for pair in pairs for p in pair], (repr(cfg), __version__))
    store = PartialStore(out, key).open(resume, force)
    try:
        with progress_bars(False) as progress:
            return reconstruct_pairs(pairs, out, calib, cfg, force, runner, store, progress)
    except KeyboardInterrupt:
        kept = len(list((store.folder / "pairs").glob("*/pair_done.json")))
        typer.echo(f"dstereo: interrupted: {kept} finished pair(s) kept in {store.folder}; run the same command "
                   "with --resume to continue from them", err=True)
        raise typer.Exit(130)
    except DstereoError:
        if not any((store.folder / "pairs").glob("*/pair_done.json")):
            store.remove()  # nothing worth keeping: leave no work folder behind
        raise


def _width(path: Path) -> int | None:
    """The image's width from its header (None when unreadable: reading it later reports that)."""
    from dstereo.recession.sequence import image_size

    size = image_size(path)
    return None if size is None else size[0]
