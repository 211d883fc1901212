"""Can a results folder be made here? Checked before any work, so a long run never ends in a write error."""

from __future__ import annotations

import os
from pathlib import Path

from dstereo.errors import DstereoError


def check_creatable(out: str | Path, flag: str = "--out") -> Path:
    """Refuse `out` unless it is an existing writable folder, or its nearest existing ancestor is a writable folder
    (so `out` and any missing parents can be created). Creates nothing."""
    out = Path(out)
    target = out.absolute()
    probe = target
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        raise DstereoError(f"{flag} {out}: {probe} is a file, not a folder, so {out} cannot be created there; "
                           "choose another location")
    if probe == target and not os.access(probe, os.W_OK | os.X_OK):
        raise DstereoError(f"{flag} {out}: the folder is not writable; choose another location or fix its permissions")
    # atomic writes make a temporary folder next to `out`: its parent (or the nearest existing ancestor) must take it
    parent = probe if probe != target else target.parent
    if not os.access(parent, os.W_OK | os.X_OK):
        raise DstereoError(f"{flag} {out}: {parent} is not writable, so the results folder cannot be made there; "
                           "choose another location")
    return out


def check_not_inputs(out: str | Path, inputs, flag: str = "--out") -> None:
    """Refuse a results folder that is, or holds, one of the inputs: replacing it (--force) would delete them."""
    target = Path(out).absolute().resolve()
    for item in inputs:
        if item is None:
            continue
        path = Path(item).absolute().resolve()
        if path == target or target in path.parents:
            raise DstereoError(f"{flag} {out} holds the input {item}; replacing it would delete the input; "
                               "choose a results folder outside the inputs")
