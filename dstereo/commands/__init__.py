"""One module per subcommand; `register_all` adds those that exist to the typer app."""

from __future__ import annotations

import importlib

import typer

# (command name, "module:function"). Modules import only typer at top level. Each entry names its module in full
# (the entry-point form), so the import graph has an edge to each command module and to no other module here
# (`reference_doc` reads this list and would otherwise sit in a cycle with it).
COMMANDS = [
    ("init", "dstereo.commands.init_cmd:init"),
    ("calibrate", "dstereo.commands.calibrate:calibrate"),
    ("reconstruct", "dstereo.commands.reconstruct:reconstruct"),
    ("recession", "dstereo.commands.recession:recession"),
    ("optics", "dstereo.commands.optics:optics"),
    ("demo", "dstereo.commands.demo:demo"),
    ("refine", "dstereo.commands.refine:refine"),
    ("diff", "dstereo.commands.diff:diff"),
    ("serve", "dstereo.commands.serve:serve"),
]


def register_all(app: typer.Typer) -> None:
    for name, entry in COMMANDS:
        module, func = entry.split(":")
        try:
            mod = importlib.import_module(module)
        except ModuleNotFoundError as exc:
            if exc.name == module:
                continue  # command not built yet
            raise
        app.command(name)(getattr(mod, func))
