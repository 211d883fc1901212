"""`dstereo` command line: thin wrappers that parse, call one library function and print.

Each subcommand lives in `dstereo/commands/<name>.py` (heavy imports inside the function body so
`dstereo --help` stays instant). Errors a user can fix (`DstereoError`) become one line on stderr, exit 1.
"""

from __future__ import annotations

import os
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
    except DstereoError as exc:  # the library names parameters; the line names the flags of the command that ran
        from dstereo.config.messages import command_of, with_flags

        typer.echo(f"dstereo: error: {with_flags(str(exc), command_of(sys.argv))}", err=True)
        sys.exit(1)
    except OSError as exc:  # a file system refusal while reading or writing (disk full, permissions): name the file
        if os.environ.get("DSTEREO_DEBUG"):
            raise
        where = f" {exc.filename}" if getattr(exc, "filename", None) else ""
        typer.echo(f"dstereo: error:{where}: {exc.strerror or exc}; check the path, free space and permissions",
                   err=True)
        sys.exit(1)
    except Exception as exc:
        # OpenCV's own errors on input no check above caught: one line instead of a traceback (DSTEREO_DEBUG=1
        # shows the traceback)
        cv = exc if _from_opencv(exc) else exc.__cause__ if _from_opencv(exc.__cause__) else None
        if cv is None or os.environ.get("DSTEREO_DEBUG"):
            raise
        detail = " ".join(str(cv).split()).rsplit("error: ", 1)[-1]
        typer.echo(f"dstereo: error: OpenCV refused the input ({detail}); check the images and parameters, and "
                   "report this if they are right (DSTEREO_DEBUG=1 shows where)", err=True)
        sys.exit(1)


def _from_opencv(exc: BaseException | None) -> bool:
    return exc is not None and type(exc).__module__.split(".")[0] == "cv2"


if __name__ == "__main__":
    main()
