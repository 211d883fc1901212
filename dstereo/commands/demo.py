"""`dstereo demo`: a synthetic stereo experiment with known truth, end to end (`make demo`)."""

from __future__ import annotations

import time
from pathlib import Path

import typer


def demo(
    out: Path = typer.Option(Path("demo_out"), "--out", help="Folder for everything the demo writes (refused if "
                             "it exists, unless --force)."),
    force: bool = typer.Option(False, "--force", help="Replace an existing --out folder."),
    quick: bool = typer.Option(False, "--quick", help="Fewer calibration views and subsets (a shorter run)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the board poses, speckle, sensor noise and subset sample."),
) -> None:
    """Render a stereo calibration set and the cork sample in the reduced thesis geometry, calibrate the rig
    (the thesis's path with subsets and stereo steps, then a joint refinement), reconstruct the sample and
    compare everything with the truth."""
    from dstereo.io.results import check_output

    check_output(out, force)  # before any rendering
    from dstereo.demo.run import run_demo

    started = time.perf_counter()
    comparison = run_demo(out, force, quick, seed, progress=_StageLines(started))
    _print(comparison, out, time.perf_counter() - started)


class _StageLines:
    """progress(stage, done, total) -> one line on stderr each time the stage changes."""

    def __init__(self, started: float):
        self.started, self.stage = started, None

    def __call__(self, stage: str, done: int, total: int) -> None:
        if stage != self.stage:
            self.stage = stage
            typer.echo(f"[{time.perf_counter() - self.started:6.1f} s] {stage}", err=True)


def _print(comparison: dict, out: Path, elapsed: float) -> None:
    from dstereo.demo.report import TABLE_HEADER, notes, surface_lines, table_rows

    rows = [TABLE_HEADER] + table_rows(comparison)
    widths = [max(len(r[j]) for r in rows) for j in range(len(TABLE_HEADER))]

    def line(r):
        return "  ".join(c.ljust(w) if j == 0 else c.rjust(w) for j, (c, w) in enumerate(zip(r, widths)))

    st, sub, surf = comparison["stereo"], comparison["subsets"], comparison["surface"]["joint"]
    ind = sub["individual"]
    typer.echo("")
    typer.echo(f"Calibration, thesis path: each camera alone ({ind['left']['plan']} of m = {sub['per_set']}; RMS "
               f"{ind['left']['rms_px']:.4f} / {ind['right']['rms_px']:.4f} px), then {st['pairs']} stereo pairs "
               f"(RMS {st['thesis_rms_px']:.4f} px) and {sub['plan']}: {sub['survivors']} of {sub['converged']} "
               "survive the stereo steps (stereo_re, Tnorm, RVnorm).")
    typer.echo(f"Joint refinement: RMS {st['joint_rms_px']:.4f} px, {st['joint_status']}.")
    typer.echo("")
    typer.echo(line(rows[0]))
    typer.echo("  ".join("-" * w for w in widths))
    for r in rows[1:]:
        typer.echo(line(r))
    typer.echo("")
    for note in notes(comparison):
        typer.echo(note)
    typer.echo(f"Surface (joint): {surf['on_sample']} points on the sample ({100 * surf['coverage']:.1f} % of its "
               f"pixels), {surf['off_sample']} off it; median |error| {surf['median_abs_mm']:.3f} mm, mean "
               f"{surf['mean_mm']:+.3f} mm.")
    for text in surface_lines(comparison):
        typer.echo(text)
    for warning in comparison["calibration_warnings"]:
        typer.echo(f"dstereo: warning: calibration: {warning}", err=True)
    for warning in comparison["warnings"]:
        typer.echo(f"WARNING: {warning}")
    typer.echo("")
    typer.echo(f"Results in {out}/ ({elapsed:.0f} s):")
    for name, path in comparison["paths"].items():
        typer.echo(f"  {name:<15} {out / path}")
