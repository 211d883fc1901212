"""`dstereo calibrate`'s runs (one camera, a stereo pair or N cameras, all through the one job
`jobs.calibrate_cameras.calibrate_rig`): call the job, write its folder (`io.cameras_files.write_results`), print
its console text."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from dstereo.commands.calibrate_checks import corner_cache_usable, results_folder
from dstereo.commands.progress import progress_bars


def run_request(request, started: float) -> None:
    """The one job on a checked request (calibrate_request.py), its folder written and its console text printed."""
    r = request
    if r.rig == "cameras":
        run_cameras(r.cameras, r.cfg, r.pair, r.project, r.out, r.force, r.quiet, r.use_cache, started,
                    r.projection_range, r.cross_validate)
    elif r.rig == "stereo":
        run_stereo(r.images, r.cfg, r.left, r.right, r.project, r.out, r.force, r.quiet, r.use_cache, started,
                   r.projection_range, r.cross_validate)
    else:
        run_camera(r.images, r.cfg, r.out, r.force, r.quiet, r.use_cache, started, r.projection_range,
                   r.projection_method, r.cross_validate)


def run_stereo(images, cfg, left, right, project, out, force, quiet, use_cache, started,
                projection_range=None, cross_validate: int = 0) -> None:
    """Stereo mode (thesis 4.2.2.2): the K-camera job on the two cameras; see dstereo.jobs.calibrate_stereo."""
    from dstereo.jobs.calibrate_stereo import calibrate_stereo_project, stereo_sources
    from dstereo.errors import DstereoError
    from dstereo.io.cameras_files import write_results

    if left is not None and right is not None and left.is_dir() and left.resolve() == Path(right).resolve():
        raise DstereoError(f"--left and --right are the same folder {left}; give each camera's images, e.g. "
                           f"--left '{left}/left*.jpg' --right '{left}/right*.jpg'")
    sources = stereo_sources(images, cfg, left, right)
    out = results_folder(out, project, force, cfg, inputs=[*sources.mono_left, *sources.mono_right,
                                                            *sources.stereo_left, *sources.stereo_right])
    use_cache = use_cache and corner_cache_usable()
    with progress_bars(quiet) as progress:
        job = calibrate_stereo_project(sources, cfg, progress=progress, use_cache=use_cache, scratch=Path(out).parent,
                                       cross_validate=cross_validate, projection_range=projection_range)
        write_results(out, job, force)
    _print_rig(job, out, quiet, started)


def run_cameras(root, cfg, pair, project, out, force, quiet, use_cache, started, projection_range=None,
                 cross_validate: int = 0) -> None:
    """N cameras (--cameras DIR): see dstereo.jobs.calibrate_cameras."""
    from dstereo.jobs.calibrate_cameras import calibrate_cameras_project, camera_folders
    from dstereo.io.cameras_files import write_results

    folders = camera_folders(root, cfg)
    out = results_folder(out, project, force, cfg, inputs=[root, *folders])
    use_cache = use_cache and corner_cache_usable()
    with progress_bars(quiet) as progress:
        job = calibrate_cameras_project(root, cfg, progress=progress, use_cache=use_cache, scratch=Path(out).parent,
                                        cross_validate=cross_validate, projection_range=projection_range,
                                        pairs=pair)
        write_results(out, job, force)
    _print_rig(job, out, quiet, started)


def _print_rig(job, out: Path, quiet: bool, started: float) -> None:
    """A rig's warnings (stderr) and console text: each camera in the rig, the rig's fit and checks."""
    import numpy as np

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
        for pair in job.pair_files:
            typer.echo("\n".join(_pair_lines(job, pair)))
        if job.consistency is not None:
            typer.echo(job.consistency.line())
        if job.cross_validation is not None:
            typer.echo(job.cross_validation.verdict())
        if job.subsets is not None:
            typer.echo("\n".join(job.subsets.lines()))
        typer.echo(f"wrote {out}")


def _pair_lines(job, pair) -> list[str]:
    """A pair's rig table: the written (joint) value +- its std (the pair file's covariance) beside, with subsets,
    the thesis's subset mean +- spread over the surviving subsets (`NAME@a-b` columns)."""
    a, b = job.labels[pair.a], job.labels[pair.b]
    stats = job.subsets.stats() if job.subsets is not None else {}
    pm = lambda v, e: f"{v:.6g} +- {e:.3g}"  # noqa: E731
    head = f"{a}-{b} ({job.config.unit}, rad)"
    kept = "" if job.subsets is None else f"subset mean +- spread of {int(job.subsets.filtering.survivors.sum())}"
    lines = [f"{head:>14}  {'rig +- std (pair covariance)':>30}  {kept}"]
    for name, (value, std) in pair.columns().items():
        s = stats.get(f"{name}@{a}-{b}")
        lines.append(f"{name:>14}  {pm(value, std):>30}  {'' if s is None else pm(s['mean'], s['std'])}")
    return lines


def _chosen(job, label: str) -> str:
    """", model auto: <preset>" for a camera whose lens --model auto chose."""
    choice = job.cameras[job.labels.index(label)].model_choice
    return "" if choice is None else f", model auto: {choice.chosen}"


def run_camera(images: Path, cfg, out: Path, force: bool, quiet: bool, use_cache: bool, started: float,
         projection_range: float | None = None, projection_method: str = "pose-compensated",
         cross_validate: int = 0) -> None:
    from dstereo.io.results import EarlyFigures

    use_cache = use_cache and corner_cache_usable()
    early = EarlyFigures(out)  # the parameter figures, drawn while the survivors' solve and the writing run
    try:
        _run_and_write(images, cfg, out, force, quiet, use_cache, started, projection_range, projection_method,
                       cross_validate, early)
    finally:
        early.discard()


def _run_and_write(images, cfg, out, force, quiet, use_cache, started, projection_range, projection_method,
                   cross_validate, early) -> None:
    from dstereo.jobs.calibrate_cameras import calibrate_images
    from dstereo.io.cameras_files import write_results

    with progress_bars(quiet) as progress:
        job = calibrate_images(images, cfg, progress=progress, use_cache=use_cache, scratch=Path(out).parent,
                               after_steps=early.parameters, cross_validate=cross_validate,
                               projection_range=projection_range, projection_method=projection_method)
        cal = job.cameras[0]
        t0 = time.perf_counter()
        if progress is not None:
            progress("writing results", 0, 1)
        write_results(out, job, force, early=early)
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
            for n, v, s in zip(full.names, full.values, reported_std(full)) if full.camera().lens != "splined" or
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
