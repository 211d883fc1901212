"""`dstereo calibrate`'s checks of a request before any work: the results folder, the corner cache, the pair,
and the refusals of the capabilities table (dstereo/config/capabilities.py) as the user asked."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def check_run_options(projection_method: str, cross_validate: int, projection_range, pair, cameras) -> None:
    """The run settings that are not configuration (`dstereo.config`): refused in one line each."""
    from dstereo.errors import DstereoError
    from dstereo.uncertainty.projection import METHODS

    if projection_method not in METHODS:
        raise DstereoError(f"--projection-method {projection_method}: use one of {', '.join(METHODS)}")
    if cross_validate < 0:
        raise DstereoError(f"--cross-validate {cross_validate}: give a number of splits (4 or more), or leave it out")
    if projection_range is not None and not projection_range > 0:
        raise DstereoError(f"--projection-range {projection_range}: give a positive distance in the board's unit")
    if pair is not None and cameras is None:
        raise DstereoError("--pair: only with --cameras DIR (a rig of several cameras)")


def corner_cache_usable() -> bool:
    """Whether the corner cache can be written; if not, one warning line now and the run goes on without it. Called
    after every refusal of the input (a refused run prints its one error line only), before the detection."""
    from dstereo.io.corners import corner_cache_problem

    problem = corner_cache_problem()
    if problem is not None:
        typer.echo(f"dstereo: warning: {problem}", err=True)
    return problem is None


def results_folder(out, project, force: bool, cfg, inputs=()):
    """--out, else PROJECT/results; refused before any work if it exists without --force, or if it holds an input
    (images, configuration). Prints config warnings."""
    from dstereo.errors import DstereoError
    from dstereo.io.output_location import check_not_inputs
    from dstereo.io.results import check_output

    if out is None:
        if project is None:
            raise DstereoError("no results folder: give --out DIR (or a PROJECT folder, which gets PROJECT/results)")
        out = project / "results"
    check_not_inputs(out, inputs)
    check_output(out, force)
    for warning in cfg.warnings:
        typer.echo(f"dstereo: warning: {warning}", err=True)
    return out


def stereo_layout(images: Path) -> bool:
    from dstereo.io.pairing import has_stereo_layout

    return has_stereo_layout(images)


def pair_of(spec: Optional[str]):
    from dstereo.errors import DstereoError

    if spec is None:
        return None
    names = [p.strip() for p in spec.split(",")]
    if len(names) != 2 or not all(names):
        raise DstereoError(f"--pair {spec}: give two camera subfolder names, A,B")
    return tuple(names)


def as_given(cfg, name: str, flag: str, value: str | None = None) -> str:
    """A configuration value as the user gave it: "--model auto" from the flag, "FILE [calibration] model = auto"
    from a file (`Config.origins`), so a message does not put a file's value on a flag."""
    origin = cfg.origins.get(name, flag)
    if value is None:
        return origin
    return f"{origin} {value}" if origin.startswith("-") else f"{origin} = {value}"


def refuse_splined_where_unsupported(cfg, rig: bool, cross_validate: int) -> None:
    """The splined lens (models/splined.py) is for one camera's full-set calibration (issue 16 item 2)."""
    from dstereo.errors import DstereoError
    from dstereo.models.distortion import lens_model

    right = getattr(cfg, "model_right", None)
    from dstereo.config.capabilities import SPLINED, refuse

    if rig and right is not None and lens_model(tuple(right)) == "splined":
        refuse(SPLINED, "--left/--right", as_given(cfg, "model_right", "--model-right", "splined"))
    if lens_model(tuple(cfg.model)) != "splined":
        return
    if rig:
        refuse(SPLINED, "--cameras", as_given(cfg, "model", "--model", "splined"))
    if cross_validate or cfg.per_set is not None:
        raise DstereoError(f"{as_given(cfg, 'model', '--model', 'splined')}: subsets (`per_set`) and --cross-validate "
                           "are not available for the "
                           "splined lens (its knots are ~160 parameters); run it on the full set alone")
