"""Reading configuration files: one reader for TOML (and JSON, which reconstruct has always accepted), the
project folder's file, and the check that refuses keys no option declares, naming the file."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from dstereo.errors import DstereoError


def read_text(path: str | Path) -> str:
    path = Path(path)
    if not path.is_file():
        raise DstereoError(f"configuration file {path} does not exist")
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise DstereoError(f"configuration file {path} cannot be read ({exc})") from None


def parse_toml(text: str, where: str) -> dict[str, Any]:
    import tomllib

    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise DstereoError(f"{where}: not valid TOML ({exc})") from None


def read_mapping(path: str | Path) -> dict[str, Any]:
    """A TOML file (JSON for a .json suffix) as a dict; errors name the file."""
    text = read_text(path)
    if Path(path).suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except ValueError as exc:
            raise DstereoError(f"{path}: not valid JSON ({exc})") from None
        if not isinstance(data, dict):
            raise DstereoError(f"{path}: the JSON must be an object of tables, e.g. {{\"reconstruct\": {{...}}}}")
        return data
    return parse_toml(text, str(path))


def find_in_folder(folder: str | Path, names: tuple[str, ...]) -> Path | None:
    """The first of `names` that is a file in `folder`, else None."""
    folder = Path(folder)
    return next((folder / n for n in names if (folder / n).is_file()), None)


def table(data: dict[str, Any], name: str, where: str) -> dict[str, Any]:
    """Table `name` of a parsed file ({} when absent); anything but a table is refused."""
    section = data.get(name, {})
    if not isinstance(section, dict):
        raise DstereoError(f"{where}: {name!r} must be a table ([{name}])")
    return section


def check_known(section: dict[str, Any], known, where: str, name: str) -> None:
    """Refuse keys of table `name` that no option declares, naming the file and the keys it knows."""
    unknown = sorted(set(section) - set(known))
    if unknown:
        raise DstereoError(f"{where}: unknown key(s) {unknown} in [{name}]; known: {sorted(known)}")
