"""`dstereo diff A B`: compare two calibrations of one camera with what their uncertainties predict."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def diff(
    a: str = typer.Argument(..., help="The first camera: a camera's results folder or camera.yml (its "
                            "calibration_covariance.npz and projection_uncertainty.npz beside it are read), or a "
                            "rig's camera STEREO_YML:left / :right."),
    b: str = typer.Argument(..., help="The second camera, given as A."),
    out: Optional[Path] = typer.Option(
        None, "--out", help="Results folder: diff.json, diff.npz, diff.png, report.md, report.html (refused if it "
        "exists, unless --force); without it the summary is printed only."),
    distance: Optional[float] = typer.Option(
        None, "--distance", help="Distance of the compared points, in the calibrations' unit (inf: directions only, "
        "the transform a rotation) [A's projection-uncertainty range: its mean board distance]."),
    grid: Optional[str] = typer.Option(None, "--grid", help="Grid of compared pixels, COLSxROWS [A's map grid, "
                                       "32x24]."),
    force: bool = typer.Option(False, "--force", help="Replace an existing results folder."),
) -> None:
    """Compare two calibrations of one camera: the projection difference over the image with the implied transform
    fitted, against the difference both uncertainties predict (ratio, Mahalanobis distance, the band a right
    prediction falls in)."""
    from dstereo.errors import DstereoError

    size = None
    if grid is not None:
        try:
            size = tuple(int(x) for x in grid.lower().split("x"))
        except ValueError:
            size = ()
        if len(size) != 2:
            raise DstereoError(f"--grid {grid!r}: give COLSxROWS, e.g. 32x24")
    from dstereo.jobs.diff import run_diff

    result = run_diff(a, b, out, distance, size, force)
    s = result.summary()
    t = s["implied_transform"]
    typer.echo(f"A {s['a']}\nB {s['b']}")
    typer.echo(f"implied transform: rotation {t['rotation_deg']:.4g} deg, translation "
               f"{', '.join(f'{x:.4g}' for x in t['translation'])} {s['unit'] or ''}; weights: {s['weighting']}")
    typer.echo(result.verdict())
    for note in s["notes"]:
        typer.echo(f"dstereo: note: {note}", err=True)
    if out is not None:
        typer.echo(f"wrote {out}")
