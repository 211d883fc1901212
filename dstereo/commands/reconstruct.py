"""`dstereo reconstruct`: rectify, match and triangulate stereo pairs into a results folder."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dstereo.config.options import RECONSTRUCT


def reconstruct(  # flags and help: dstereo.config.options.RECONSTRUCT
    left: list[Path] = RECONSTRUCT.option("left", ...),
    right: list[Path] = RECONSTRUCT.option("right", ...),
    out: Path = RECONSTRUCT.option("out", ...),
    calib: Optional[Path] = RECONSTRUCT.option("calib"),
    project: Optional[Path] = RECONSTRUCT.option("project"),
    config: Optional[Path] = RECONSTRUCT.option("config"),
    preset: Optional[str] = RECONSTRUCT.option("preset"),
    sgbm: list[str] = RECONSTRUCT.option("sgbm", []),
    z_min: Optional[float] = RECONSTRUCT.option("z_min"),
    z_max: Optional[float] = RECONSTRUCT.option("z_max"),
    alpha: Optional[float] = RECONSTRUCT.option("alpha"),
    rectification: Optional[str] = RECONSTRUCT.option("rectification"),
    zero_disparity: Optional[bool] = RECONSTRUCT.option("zero_disparity"),
    lr_check: Optional[float] = RECONSTRUCT.option("sgbm.lr_check"),
    roi: Optional[str] = RECONSTRUCT.option("roi"),
    outliers: Optional[int] = RECONSTRUCT.option("outlier_neighbours"),
    outlier_std: Optional[float] = RECONSTRUCT.option("outlier_std"),
    max_jump: Optional[float] = RECONSTRUCT.option("max_jump"),
    refine: Optional[bool] = RECONSTRUCT.option("refine"),
    cost: Optional[str] = RECONSTRUCT.option("matching_cost"),
    fill: Optional[bool] = RECONSTRUCT.option("fill"),
    fill_max_sigma: Optional[float] = RECONSTRUCT.option("fill_max_sigma"),
    focal_mm: Optional[float] = RECONSTRUCT.option("focal_mm"),
    pixel_size_mm: Optional[float] = RECONSTRUCT.option("pixel_size_mm"),
    crop_factor: Optional[float] = RECONSTRUCT.option("crop_factor"),
    focal_px: Optional[float] = RECONSTRUCT.option("focal_px"),
    baseline_mm: Optional[float] = RECONSTRUCT.option("baseline_mm"),
    disparity_sigma: Optional[str] = RECONSTRUCT.option("disparity_sigma"),
    no_uncertainty: bool = RECONSTRUCT.option("uncertainty", False),
    full_covariance: bool = RECONSTRUCT.option("full_covariance", False),
    workers: Optional[int] = RECONSTRUCT.option("workers"),
    scheduler: Optional[str] = RECONSTRUCT.option("scheduler"),
    resume: bool = RECONSTRUCT.option("resume", False),
    retries: int = RECONSTRUCT.option("retries", 2),
    force: bool = RECONSTRUCT.option("force", False),
) -> None:
    """Reconstruct stereo pairs: rectified pair, disparity, depth, point cloud, mesh and summary.json."""
    from dstereo.commands.matching_options import (density_check_line, fill_line, matching_cost_lines,
                                                   search_range_line, search_range_tries)
    from dstereo.config import reconstruction as settings
    from dstereo.errors import DstereoError
    from dstereo.jobs.reconstruct import run_reconstruction

    if len(left) != len(right):
        raise DstereoError(f"{len(left)} --left but {len(right)} --right images; give them in pairs")
    from dstereo.io.output_location import check_not_inputs
    from dstereo.io.pairing import check_distinct_images, check_order_agrees_with_names

    check_not_inputs(out, [*left, *right, calib, config])
    from dstereo.runtime.tasks import FrameRunner

    FrameRunner(workers, scheduler, retries)  # refuses a worker count or address it cannot use, before any work

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
        "alpha": alpha, "rectification": rectification, "zero_disparity": zero_disparity, "refine": refine,
        "matching_cost": cost, "fill": fill, "fill_max_sigma": fill_max_sigma, "outlier_neighbours": outliers,
        "outlier_std": outlier_std, "max_jump": max_jump, "focal_mm": focal_mm, "pixel_size_mm": pixel_size_mm,
        "crop_factor": crop_factor, "focal_px": focal_px, "baseline_mm": baseline_mm, "uncertainty": no_uncertainty,
        "full_covariance": full_covariance, "disparity_sigma": disparity_sigma}))
    cfg = settings.build(*layers)
    settings.check(cfg, _size(left[0]))

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
        if s.get("rectification"):
            typer.echo(f"  rectification: {s['rectification']['projection']} ({s['rectification']['why']})")
        typer.echo(f"  {search_range_line(s.get('search_range'))}")
        for line in search_range_tries(s.get("search_range")):
            typer.echo(f"    {line}")
        if s.get("refine", {}).get("enabled"):
            typer.echo(f"  sub-pixel refinement: {100 * s['refine']['dropped_fraction']:.2f}% of SGBM's pixels dropped")
        for line in matching_cost_lines(s.get("search_range")):
            typer.echo(f"  {line}")
        if (line := fill_line(s.get("fill"))) is not None:
            typer.echo(f"  {line}")
        if (line := density_check_line(s.get("density_check"))) is not None:
            typer.echo(f"  {line}")
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
    """Each pair a task (`dstereo.jobs.reconstruct_pairs`); Ctrl-C keeps the finished pairs for --resume."""
    from dstereo import __version__
    from dstereo.commands.progress import progress_bars
    from dstereo.errors import DstereoError
    from dstereo.io.partial_store import PartialStore, fingerprint
    from dstereo.runtime.tasks import FrameRunner
    from dstereo.jobs.reconstruct_pairs import reconstruct_pairs
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


def _size(path: Path) -> tuple[int, int] | None:
    """The image's (width, height) from its header (None when unreadable: reading it later reports that)."""
    from dstereo.io.sequence_files import image_size

    return image_size(path)
