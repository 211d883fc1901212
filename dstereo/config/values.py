"""Checked values read from a file or a flag: numbers, whole numbers, switches, file suffixes, lens models.
`where` names the file and key (or the parameter) so each error says what to fix."""

from __future__ import annotations

from dstereo.errors import DstereoError


def number(value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise DstereoError(f"{where}: {value!r} is not a number")
    return float(value)


def whole(value, where: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise DstereoError(f"{where}: {value!r} must be a whole number >= {minimum}")
    return value


def optional_whole(value, where: str, minimum: int) -> int | None:
    return None if value is None else whole(value, where, minimum)


def flag(value, where: str) -> bool:
    if not isinstance(value, bool):
        raise DstereoError(f"{where}: {value!r} is not true or false")
    return value


def suffix(value) -> str | None:
    """'.JPG' -> 'jpg' (None or '' -> None: every image type)."""
    return None if value in (None, "") else str(value).strip().strip("'\"").lstrip(".").lower()


def is_auto_model(spec) -> bool:
    """True for the model spec "auto" (a flag or a configuration value)."""
    return isinstance(spec, str) and spec.strip().lower() == "auto"


def model(spec, where: str) -> tuple[str, ...]:
    from dstereo.models.distortion import PRESETS, parse_model

    names = spec.replace(" ", ",").split(",") if isinstance(spec, str) else list(spec)
    if not any(str(n).strip() for n in names):
        # an empty name used to mean "no coefficient free": a calibration with no distortion, silently; that lens
        # is asked for by name (none), so an empty value is a slip (an unset shell variable, a stray quote)
        raise DstereoError(f"{where}: {spec!r} names no lens model; use one of {', '.join(PRESETS)}, "
                           "splined:NXxNY, or coefficients such as k1,k2,p1,p2 (none: no distortion)")
    try:
        return parse_model(spec)
    except DstereoError as exc:
        raise DstereoError(f"{where}: {str(exc).removeprefix('model: ')}") from None


def right_model(spec, where: str) -> tuple[str, ...]:
    """A stereo rig's right-camera lens model (`model_right`): a model spec, not "auto" (the rig's model is
    chosen per camera alone)."""
    if is_auto_model(spec):
        raise DstereoError(f"{where}: auto is not available for one camera of a rig; name its model (e.g. fisheye)")
    return model(spec, where)


def model_layer(spec, where: str) -> dict:
    """The parameters a lens-model spec sets: `model_auto`, and `model` unless the data chooses it ("auto")."""
    if is_auto_model(spec):
        return {"model_auto": True}
    try:
        return {"model": model(spec, where), "model_auto": False}
    except DstereoError as exc:  # one camera's model may also be chosen from the data
        raise DstereoError(f"{exc}; or auto (the model that best predicts held-out views)") from None


def parse_pattern(text: str | tuple[int, int]) -> tuple[int, int]:
    """'9x6' -> (9, 6) inner corners (columns x rows)."""
    if isinstance(text, tuple):
        cols, rows = text
    else:
        try:
            cols, rows = (int(v) for v in str(text).lower().replace(",", "x").split("x"))
        except ValueError:
            raise DstereoError(f"pattern: '{text}' is not COLSxROWS inner corners, e.g. 9x6") from None
    if cols < 2 or rows < 2:
        raise DstereoError(f"pattern: {cols}x{rows} has fewer than 2 inner corners per side; use e.g. 9x6")
    return int(cols), int(rows)
