"""The one merge rule of every command: defaults < project file < command-line flags.

A layer is a dict parameter -> value holding only what that source gave (a flag left out is None and absent).
Later layers win key by key. An option's `replaces` names parameters (or prefixes ending in '.') that a value it
gives drops from the layers below: optics' sensor and crop factor exclude each other, a reconstruction preset
sets every SGBM field.
"""

from __future__ import annotations

from typing import Any, Mapping

from dstereo.config.options import OptionTable


def given(values: Mapping[str, Any]) -> dict[str, Any]:
    """The layer of a command's flags: those given (not None)."""
    return {k: v for k, v in values.items() if v is not None}


def _dropped(table: OptionTable, layer: Mapping[str, Any]) -> tuple[str, ...]:
    names = set(table.names())
    return tuple(r for key in given(layer) if key in names for r in table[key].replaces)


def _is_dropped(key: str, dropped: tuple[str, ...]) -> bool:
    return any(key == d or (d.endswith(".") and key.startswith(d)) for d in dropped)


def merge_layers(table: OptionTable, *layers: Mapping[str, Any]) -> dict[str, Any]:
    """Layers merged lowest first (file layers, then the flags); the defaults are not included (see `merge`)."""
    merged: dict[str, Any] = {}
    for layer in layers:
        dropped = _dropped(table, layer)
        merged = {k: v for k, v in merged.items() if not _is_dropped(k, dropped)}
        merged.update(given(layer))
    return merged


def merge(table: OptionTable, kind: type, *layers: Mapping[str, Any]) -> dict[str, Any]:
    """The defaults (the fields of `kind`, the table's settings dataclass), then each layer in turn
    (see `merge_layers`)."""
    return {**table.defaults(kind), **merge_layers(table, *layers)}
