"""`dstereo init`: a calibration project folder with a commented configuration and an images/ folder."""

from __future__ import annotations

from pathlib import Path

import typer


def init(
    project: Path = typer.Argument(..., help="Project folder to create (or fill, if it exists)."),
    force: bool = typer.Option(False, "--force", help="Overwrite an existing dstereo.toml."),
) -> None:
    """Write PROJECT/dstereo.toml (the thesis's Figure 5.5 set-up, commented) and create PROJECT/images/."""
    from dstereo.config.calibration import template, to_toml
    from dstereo.errors import DstereoError

    if project.exists() and not project.is_dir():
        raise DstereoError(f"init: {project} exists and is not a folder")
    target = project / "dstereo.toml"
    if target.exists() and not force:
        raise DstereoError(f"init: {target} already exists; edit it, or pass --force to overwrite it")
    (project / "images").mkdir(parents=True, exist_ok=True)
    target.write_text(to_toml(template()))
    typer.echo(f"wrote {target}; put the chessboard images in {project / 'images'} and run: "
               f"dstereo calibrate {project}")
