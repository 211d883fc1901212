"""`dstereo` command line: thin wrappers that parse, call one library function and print.

Each subcommand lives in `dstereo/commands/<name>.py` (heavy imports inside the function body so
`dstereo --help` stays instant). Errors a user can fix (`DstereoError`) become one line on stderr, exit 1.
"""

from __future__ import annotations

import sys

import typer

from dstereo.commands import register_all
from dstereo.errors import DstereoError

app = typer.Typer(
    name="dstereo",
    help="Differentiable stereo photogrammetry: calibrate, rectify, reconstruct, measure with error bars.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,  # help reads as written: option texts use [brackets] for sections and defaults
)
register_all(app)


@app.callback()
def _root() -> None:
    """Keeps typer in multi-command mode even while only one subcommand is registered."""


def main() -> None:
    try:
        app()  # standalone: usage errors print and exit 2 by themselves
    except DstereoError as exc:
        typer.echo(f"dstereo: error: {exc}", err=True)
        sys.exit(1)


if __name__ == "__main__":
    main()
