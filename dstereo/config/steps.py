"""Optimisation steps (thesis section 4.2.2.1): which parameters a step filters and by how much, from a file or
from the `--step NAME=MAX[,NAME=MAX...]` flag syntax (parameter `steps`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from dstereo.errors import DstereoError

# Parameter names a mono step may filter; `re` is the subset's RMS reprojection error (px, absolute limit).
MONO_PARAMETERS = ("re", "fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6",
                   "fk1", "fk2", "fk3", "fk4")  # fk: the fisheye lens (cv2.fisheye k1..k4)
# Stereo step parameters (filtered by the stereo pipeline): stereo_re is absolute, the rest IQR.
STEREO_PARAMETERS = ("stereo_re", "Tnorm", "Tx", "Ty", "Tz", "RVnorm", "RVx", "RVy", "RVz")
# Parameters whose max error is an absolute limit in pixels; every other one is an IQR multiple alpha.
ABSOLUTE_PARAMETERS = ("re", "stereo_re")


@dataclass(frozen=True)
class Step:
    """One optimisation step: parameters filtered jointly, each with its max error (px for re, else alpha)."""

    parameters: tuple[str, ...]
    max_error: tuple[float, ...]
    min_subsets: int | None = None  # stop the step before it leaves fewer subsets (None: the config's value)

    def describe(self) -> str:
        parts = [f"{p} <= {e:g} px" if is_absolute(p) else f"{p} within {e:g} IQR"
                 for p, e in zip(self.parameters, self.max_error)]
        return ", ".join(parts)


def is_absolute(column: str) -> bool:
    """A column filtered by an absolute limit (px): `re`, `stereo_re`, and a rig pair's `stereo_re@a-b`."""
    return column.split("@")[0] in ABSOLUTE_PARAMETERS


def canonical_parameter(name: str, where: str, stereo: bool = False) -> str:
    """'FX' -> 'fx', 'RV_norm' -> 'RVnorm'; unknown names raise naming the allowed ones."""
    allowed = STEREO_PARAMETERS if stereo else MONO_PARAMETERS
    key = str(name).strip().lower().replace("_", "").replace(" ", "")
    for known in allowed:
        if known.lower().replace("_", "") == key:
            return known
    raise DstereoError(f"{where}: unknown parameter {name!r}; use one of {', '.join(allowed)}")


def make_step(parameters, max_error, where: str, stereo: bool = False, min_subsets=None) -> Step:
    """Validated Step from raw lists (strings or numbers) as read from a file or a flag."""
    params = [canonical_parameter(p, where, stereo) for p in parameters]
    if not params:
        raise DstereoError(f"{where}: no parameters; name at least one, e.g. parameters = fx, fy")
    dup = sorted({p for p in params if params.count(p) > 1})
    if dup:
        raise DstereoError(f"{where}: parameter(s) {dup} listed twice in one step")
    if max_error is None:
        raise DstereoError(f"{where}: max error is missing; give one value per parameter ({', '.join(params)})")
    errors = []
    for value in max_error:
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise DstereoError(f"{where}: max error {value!r} is not a number") from None
        if not math.isfinite(number) or number <= 0:
            raise DstereoError(f"{where}: max error {value!r} must be a positive number (px for re, else IQR multiple)")
        errors.append(number)
    if len(errors) != len(params):
        raise DstereoError(
            f"{where}: {len(params)} parameter(s) ({', '.join(params)}) but {len(errors)} max error value(s); "
            "give one max error per parameter"
        )
    return Step(tuple(params), tuple(errors), optional_count(min_subsets, f"{where}: minimum subsets"))


def optional_count(value, where: str) -> int | None:
    if value is None:
        return None
    try:
        number = int(value)
    except (TypeError, ValueError):
        raise DstereoError(f"{where}: {value!r} is not a whole number") from None
    if number != float(value) or number < 1:
        raise DstereoError(f"{where}: {value!r} must be a whole number >= 1")
    return number



def _step_items(text: str, where: str) -> tuple[list[str], list[str]]:
    params, errors = [], []
    for item in (s for s in text.split(",") if s.strip()):
        if "=" not in item:
            raise DstereoError(f"{where}: write NAME=MAX_ERROR pairs, e.g. `steps` fx=1.0,fy=1.0")
        name, value = item.split("=", 1)
        params.append(name)
        errors.append(value.strip())
    return params, errors


def parse_step_flag(text: str, index: int, stereo: bool = False) -> Step:
    """'re=0.5' or 'p1=1.5,p2=1.5' (one `--step` flag) -> Step (one flag per step, in order); `stereo`: the names are
    the stereo step parameters (stereo_re, Tnorm, ...)."""
    where = f"`steps` {text!r} (step {index})"
    params, errors = _step_items(text, where)
    return make_step(params, errors, where, stereo)


def _is_stereo_name(name: str) -> bool | None:
    """True for a stereo step parameter, False for a one-camera one, None for neither."""
    key = str(name).strip().lower().replace("_", "").replace(" ", "")
    for stereo, allowed in ((False, MONO_PARAMETERS), (True, STEREO_PARAMETERS)):
        if any(known.lower().replace("_", "") == key for known in allowed):
            return stereo
    return None


def parse_step_flags(texts: list[str]) -> tuple[tuple[Step, ...] | None, tuple[Step, ...] | None]:
    """Every --step flag -> (one-camera steps, stereo steps), each None when no flag gave that kind (the file's
    steps of that kind then stay). A flag's kind follows its names: re, fx, ..., k6 are one-camera parameters,
    stereo_re, Tnorm, Tx, Ty, Tz, RVnorm, RVx, RVy, RVz stereo ones; one flag holds one kind."""
    mono, stereo = [], []
    for index, text in enumerate(texts, 1):
        where = f"`steps` {text!r} (step {index})"
        params, _ = _step_items(text, where)
        kinds = {_is_stereo_name(p) for p in params}
        if None in kinds:
            bad = next(p for p in params if _is_stereo_name(p) is None)
            raise DstereoError(f"{where}: unknown parameter {bad!r}; one-camera steps use {', '.join(MONO_PARAMETERS)}"
                               f"; stereo steps use {', '.join(STEREO_PARAMETERS)}")
        if len(kinds) > 1:
            raise DstereoError(f"{where}: mixes one-camera and stereo parameters; give them as separate `steps` "
                               "items (e.g. `steps` re=0.5 and `steps` stereo_re=3)")
        is_stereo = kinds == {True}
        (stereo if is_stereo else mono).append(parse_step_flag(text, index, is_stereo))
    return (tuple(mono) if mono else None), (tuple(stereo) if stereo else None)


