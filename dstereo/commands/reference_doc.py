"""docs/reference.md's generated part: every command and option, read from the command line itself.

The commands' flags, help texts and defaults are read from the typer application (`register_all`, as `dstereo`
builds it), so the page says what `dstereo COMMAND --help` says; an option declared in the options tables
(`dstereo.config.options`) adds its file key and takes its default from the configuration type (a flag whose
command-line default is "not given" falls back to it). A test (tests/commands/test_reference_doc.py) keeps
docs/reference.md's generated block equal to `markdown()`.

    python -m dstereo.commands.reference_doc            # print the generated block
    python -m dstereo.commands.reference_doc --write    # rewrite it in docs/reference.md, between the markers

It lives with the commands (rank 12) because it reads them. The defaults of the options in a table are the fields
of that command's settings type (`SETTINGS`), as `dstereo.config.merge.merge` reads them.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

BEGIN = "<!-- BEGIN GENERATED: python -m dstereo.commands.reference_doc --write -->"
END = "<!-- END GENERATED -->"
PAGE = Path(__file__).resolve().parents[2] / "docs" / "reference.md"


def _settings_types() -> dict[str, type]:
    """command -> the settings dataclass whose fields hold its options table's defaults."""
    from dstereo.config.calibration import Config
    from dstereo.config.reconstruction_config import ReconstructionConfig
    from dstereo.optics.calculator import OpticsConfig

    return {"calibrate": Config, "reconstruct": ReconstructionConfig, "optics": OpticsConfig}


def _click_group():
    """The click group of every command, built as `dstereo` builds it (without the runtime around it)."""
    import typer
    import typer.main

    from dstereo.commands import register_all

    app = typer.Typer(name="dstereo", add_completion=False, rich_markup_mode=None)
    register_all(app)

    @app.callback()
    def _root() -> None:
        """Multi-command mode."""

    return typer.main.get_command(app)


def _cell(text) -> str:
    """Text for one markdown table cell: one line, pipes escaped."""
    return " ".join(str(text).split()).replace("|", "\\|")


def _value(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, (tuple, list)):
        return ",".join(str(v) for v in value) if value else "-"
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, Path):
        return str(value)
    return str(value)


def _flag(param) -> str:
    names = "/".join(["|".join(param.opts)] + list(param.secondary_opts))
    return names.replace("|", ", ")


def _table_rows(table, param):
    """The options-table rows of a command-line option (the same flag or flags), or ()."""
    if table is None:
        return ()
    given = set(param.opts) | set(param.secondary_opts)
    return tuple(o for o in table.options if o.flag is not None and set(o.flag.split("/")) == given)


def _default(param, rows, defaults) -> str:
    value = _default_value(param, rows, defaults)
    if param.secondary_opts and value in ("on", "off"):  # an on/off pair: name the flag that is the default
        return f"`{param.opts[0] if value == 'on' else param.secondary_opts[0]}`"
    return value


def _default_value(param, rows, defaults) -> str:
    if param.required:
        return "required"
    if getattr(param, "multiple", False) and not param.default and not rows:
        return "-"
    if getattr(param, "is_flag", False) and not param.secondary_opts:
        return "off"  # a lone switch (`--force`, `--no-uncertainty`): not given, it is off
    for row in rows:  # "not given" on the command line: the configuration type's default applies
        if param.default in (None, False, (), []) and row.name in defaults:
            value = defaults[row.name]
            if dataclasses.is_dataclass(value):
                return "see its table"
            return _value(value)
    return _value(param.default)


def _command_section(name: str, command) -> list[str]:
    from dstereo.config.options import TABLES

    table = TABLES.get(name)
    defaults = table.defaults(_settings_types()[name]) if table is not None else {}
    params = [p for p in command.params if not getattr(p, "hidden", False)]
    arguments = [p for p in params if p.param_type_name == "argument"]
    options = [p for p in params if p.param_type_name == "option"]
    usage = " ".join(["dstereo", name, "[OPTIONS]"]
                     + [(p.name.upper() if p.required else f"[{p.name.upper()}]") for p in arguments])
    lines = [f"### `dstereo {name}`", "", _cell(command.help or ""), "", f"`{usage}`", ""]
    for p in arguments:
        lines += [f"- `{p.name.upper()}`{'' if p.required else ' (optional)'}: {_cell(getattr(p, 'help', '') or '')}"]
    if arguments:
        lines.append("")
    with_file = table is not None
    head = ["option", "default"] + (["file key"] if with_file else []) + ["what it sets"]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for p in options:
        rows = _table_rows(table, p)
        cells = [f"`{_flag(p)}`", _cell(_default(p, rows, defaults))]
        if with_file:
            keys = [k for r in rows for k in r.file]
            cells.append(", ".join(f"`{k}`" for k in keys) if keys else "-")
        cells.append(_cell(getattr(p, "help", "") or ""))
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    if table is not None:
        file_only = [o for o in table.options if o.flag is None and o.file]
        if file_only:
            lines += [f"File-only settings of `{name}` (no flag; set them in the configuration file):", "",
                      "| file key | parameter | default |", "|---|---|---|"]
            for o in file_only:
                keys = ", ".join(f"`{k}`" for k in o.file)
                lines.append(f"| {keys} | `{o.name}` | {_cell(_value(defaults.get(o.name)))} |")
            lines.append("")
        nested = [(k, v) for k, v in defaults.items() if dataclasses.is_dataclass(v)]
        for key, value in nested:
            lines += [f"`{name}`: `{key}` settings (`[{key}]` in the file; on the command line "
                      f"`--{key} NAME=VALUE`):", "", "| name | default |", "|---|---|"]
            for f in dataclasses.fields(value):
                lines.append(f"| `{f.name}` | {_cell(_value(getattr(value, f.name)))} |")
            lines.append("")
    return lines


def markdown() -> str:
    """The generated block of docs/reference.md (without the markers)."""
    group = _click_group()
    names = list(group.commands)
    lines = ["## Commands", "", "| command | what it does |", "|---|---|"]
    for name in names:
        first = _cell(group.commands[name].help or "").split(". ")[0].rstrip(".")
        lines.append(f"| [`{name}`](#dstereo-{name}) | {first}. |")
    lines += ["", "Every command also takes `--help`. The default column gives the value used when the option is "
              "not given (for options that also have a file key: when neither the file nor the flag sets it); "
              "`-` means none (the command decides, as the help text says).", ""]
    for name in names:
        lines += _command_section(name, group.commands[name])
    uses: dict[str, list[str]] = {}
    for name in names:
        for p in group.commands[name].params:
            if p.param_type_name == "option" and not getattr(p, "hidden", False):
                uses.setdefault(_flag(p), []).append(name)
    lines += ["### Which command takes which option", "", "| option | commands |", "|---|---|"]
    for flag in sorted(uses, key=lambda f: f.lstrip("-").lower()):
        lines.append(f"| `{flag}` | {', '.join(uses[flag])} |")
    return "\n".join(lines) + "\n"


def replace_block(page: str, block: str) -> str:
    """`page` with the text between BEGIN and END replaced by `block`."""
    start, end = page.index(BEGIN) + len(BEGIN), page.index(END)
    return page[:start] + "\n" + block + page[end:]


def generated_block(page: str) -> str:
    """The text between the markers of `page`, as `replace_block` writes it."""
    start, end = page.index(BEGIN) + len(BEGIN), page.index(END)
    return page[start:end].removeprefix("\n")


if __name__ == "__main__":
    if sys.argv[1:] == ["--write"]:
        PAGE.write_text(replace_block(PAGE.read_text(), markdown()))
        print(f"wrote {PAGE}")
    else:
        sys.stdout.write(markdown())
