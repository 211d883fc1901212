"""Library errors name parameters in backticks (`square`); the command line names its flags instead. This turns
one into the other for the command that ran, using the option tables, so a message is written once."""

from __future__ import annotations

import re

from dstereo.config.options import flags_of

_PARAMETER = re.compile(r"`([A-Za-z_][A-Za-z0-9_.]*)`")


def with_flags(message: str, command: str | None) -> str:
    """`message` with each `parameter` of `command` replaced by its flag; other backticked names lose the
    backticks only."""
    flags = flags_of(command)
    return _PARAMETER.sub(lambda m: flags.get(m.group(1), m.group(1)), message)


def command_of(argv: list[str]) -> str | None:
    """The subcommand in `dstereo SUBCOMMAND ...` (the first word that is not an option)."""
    return next((a for a in argv[1:] if not a.startswith("-")), None)
