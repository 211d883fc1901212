"""The length unit of a calibration: the board's square size sets the scale of every length it solves (T, board
poses, board sag), so the unit is part of the result. Calibration files carry it (`unit`); readers that work in mm
convert with `MM_PER_UNIT`. Standard library only (`dstereo --help` reads the configuration modules)."""

from __future__ import annotations

from dstereo.errors import DstereoError

# mm per unit of each accepted length unit.
MM_PER_UNIT = {"um": 1e-3, "mm": 1.0, "cm": 10.0, "dm": 100.0, "m": 1000.0, "in": 25.4, "ft": 304.8}
# Without a square size the board's own square is the unit: lengths are in squares, with no physical scale.
SQUARES = "squares"
UNITS = (*MM_PER_UNIT, SQUARES)


def check_unit(unit, where: str) -> str:
    """`unit` lower-cased when it is a length unit (or `squares`); else one line: `where` (the parameter or file
    with the value, e.g. "--unit parsec") and the units accepted."""
    text = str(unit).strip().lower()
    if text not in UNITS:
        raise DstereoError(f"{where}: not a length unit; use one of {', '.join(UNITS)} (squares: the board's square "
                           "is the unit, as when no square size is given)")
    return text


def mm_per(unit: str, where: str) -> float:
    """mm per `unit`; a file in board squares has no physical scale and is refused by a reader that needs one."""
    if unit == SQUARES:
        raise DstereoError(f"{where}: its lengths are in board squares (it was calibrated without a square size), so "
                           "depths in mm cannot be computed from it; calibrate again with --square SIZE --unit mm "
                           "(the board's measured square)")
    return MM_PER_UNIT[check_unit(unit, f"{where}: unit {unit!r}")]
