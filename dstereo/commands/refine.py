"""`dstereo refine`: correct a stereo calibration from one image pair of an object of known geometry."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def refine(
    calib: Path = typer.Option(..., "--calib", help="stereo.yml or OpenCV YAML with M1 D1 M2 D2 R T."),
    left: Path = typer.Option(..., "--left", help="Left image of the reference object."),
    right: Path = typer.Option(..., "--right", help="Right image, taken at the same moment."),
    out: Path = typer.Option(..., "--out", help="Results folder (refused if it exists, unless --force)."),
    board: Optional[str] = typer.Option(None, "--board", help="Chessboard inner corners COLSxROWS, e.g. 9x6."),
    square: Optional[float] = typer.Option(None, "--square", help="Chessboard square size, mm (with --board)."),
    sphere_diameter: Optional[float] = typer.Option(None, "--sphere-diameter", help="Sphere diameter, mm."),
    distances: Optional[Path] = typer.Option(
        None, "--distances", help="CSV of marks: 'point,NAME,xl,yl,xr,yr' and 'distance,A,B,MM' rows."),
    focal: bool = typer.Option(False, "--focal", help="Also refine both focal lengths."),
    scale_only: Optional[bool] = typer.Option(
        None, "--scale-only/--all", help="Refine the baseline length only (default for a sphere), or the whole rig."),
    z_min: Optional[float] = typer.Option(None, "--z-min", help="Sphere: nearest depth of the scene, mm."),
    z_max: Optional[float] = typer.Option(None, "--z-max", help="Sphere: farthest depth of the scene, mm."),
    force: bool = typer.Option(False, "--force", help="Replace an existing results folder."),
) -> None:
    """Refine rotation, baseline (and focal lengths) so the reconstructed reference matches its known geometry."""
    from dstereo.errors import DstereoError

    given = [n for n, v in (("--board", board), ("--sphere-diameter", sphere_diameter), ("--distances", distances))
             if v is not None]
    if len(given) != 1:
        raise DstereoError(f"give exactly one reference: --board with --square, --sphere-diameter or --distances "
                           f"(got {', '.join(given) or 'none'})")
    if (board is None) != (square is None):
        raise DstereoError("--board and --square go together: the pattern (e.g. 9x6) and the square size in mm")
    if (z_min is None) != (z_max is None) or (z_min is not None and sphere_diameter is None):
        raise DstereoError("--z-min and --z-max go together, and only with --sphere-diameter")

    from dstereo.io.output_location import check_not_inputs
    from dstereo.io.pairing import check_distinct_images

    check_not_inputs(out, [calib, left, right, distances])
    check_distinct_images(left, right)
    from dstereo.reference import Board, Sphere, read_marks
    from dstereo.reference.correction import RIG_CORRECTION_NAMES
    from dstereo.jobs.refine import run_refinement

    marks, config = None, None
    if board is not None:
        from dstereo.config.values import parse_pattern

        reference = Board.from_pattern(parse_pattern(board), float(square))
    elif sphere_diameter is not None:
        reference = Sphere(float(sphere_diameter))
        if z_min is not None:
            from dstereo.stereo.reconstruct import ReconstructionConfig

            config = ReconstructionConfig(depth_range=(z_min, z_max))
    else:
        q_l, q_r, reference = read_marks(distances)
        marks = (q_l, q_r)
    if scale_only is None:
        scale_only = sphere_diameter is not None
    fixed = tuple(n for n in RIG_CORRECTION_NAMES if n != "baseline") if scale_only else ()
    result = run_refinement(calib, left, right, reference, out, focal=focal, fixed=fixed, marks=marks, force=force,
                            config=config)
    r = result.report()
    b, rot = r["baseline"], r["rotation_right_camera_deg"]
    rotation = ", ".join(f"{ax} {rot[ax]['value']:+.5f} +- {rot[ax]['std']:.5f}" for ax in "xyz"
                         if rot[ax]["std"] == rot[ax]["std"])  # NaN: held
    typer.echo(f"baseline {b['percent']:+.4f} % +- {b['std_percent']:.4f} % ({b['mm']:+.4f} mm)"
               + (f"; rotation (deg) {rotation}" if rotation else "; rotation held"))
    typer.echo(f"residual RMS {r['residual_rms']['before']:.4g} -> {r['residual_rms']['after']:.4g} "
               f"{r['residual_rms']['unit']}; {r['conditioning']['message']}")
    if r["poorly_determined"]:
        typer.echo(f"dstereo: warning: not determined by this reference: {', '.join(r['poorly_determined'])}", err=True)
    typer.echo(f"wrote {out}")
