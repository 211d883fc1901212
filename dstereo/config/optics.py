"""The optics configuration (`dstereo optics`): the [optics] table of a TOML file as a layer of parameters,
merged with the flags by the one rule (flags over the file; a sensor size and a crop factor exclude each other
across layers, `options.OPTICS`), then checked into an `OpticsConfig` by `dstereo.optics.calculator.make_config`."""

from __future__ import annotations

from pathlib import Path

from dstereo.config.files import check_known, read_mapping
from dstereo.config.merge import merge_layers
from dstereo.config.options import OPTICS
from dstereo.errors import DstereoError


def file_layer(path: str | Path) -> dict:
    """The `[optics]` table of a TOML file; a file without one, or with keys no option declares, is refused."""
    data = read_mapping(path)
    declared = sorted(key.split(".", 1)[1] for key in OPTICS.file_keys())
    section = data.get("optics")
    if not isinstance(section, dict):
        raise DstereoError(f"{path}: no [optics] section; add one with keys {', '.join(declared)}")
    check_known(section, declared, str(path), "optics")
    return dict(section)


def settings(*layers: dict) -> dict:
    """The merged parameters (lowest layer first); defaults stay to `make_config`, which knows which are needed."""
    return merge_layers(OPTICS, *layers)
