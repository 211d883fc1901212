"""One module per subcommand; `register_all` adds those that exist to the typer app."""

from __future__ import annotations

import importlib

import typer

# (command name, module under dstereo.commands, function name). Modules import only typer at top level.
COMMANDS = [
    ("init", "init_cmd", "init"),
    ("calibrate", "calibrate", "calibrate"),
    ("reconstruct", "reconstruct", "reconstruct"),
    ("recession", "recession", "recession"),
    ("optics", "optics", "optics"),
    ("demo", "demo", "demo"),
    ("refine", "refine", "refine"),
    ("serve", "serve", "serve"),
]


def register_all(app: typer.Typer) -> None:
    for name, module, func in COMMANDS:
        try:
            mod = importlib.import_module(f"dstereo.commands.{module}")
        except ModuleNotFoundError as exc:
            if exc.name == f"dstereo.commands.{module}":
                continue  # command not built yet
            raise
        app.command(name)(getattr(mod, func))
