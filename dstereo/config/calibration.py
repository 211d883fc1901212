"""Calibration project configuration: dstereo's TOML and the thesis's own initialisation-file format.

Both formats load into one frozen `Config`. The thesis format (Figures 5.5 and 5.14, files such as
`init-individual.ini`) is configobj-like text: `[ Calibration ]`, `[[ Calibration steps ]]`, `[[[ step 1 ]]]`,
`key = value` lines, `#` comments anywhere, comma lists with optional trailing commas and quoted strings.
Mono optimisation steps (`[ Optimization ]`) and stereo steps (`[ Stereo Optimization ]`) are kept apart.

`mesh width` x `mesh height` are the board's *inner* corners (columns x rows), the `patternSize` the thesis
hands to cv2.findChessboardCorners: its Figure 5.5 says 9 x 6 for OpenCV's sample set, whose board has
10 x 7 squares and 9 x 6 inner corners. (Section 4.2.2.1's "20 x 10 board, 20 mm squares" example lists object
points up to (400, 200), i.e. 21 x 11 points, and so does not fit either reading; the figures and the code
path through OpenCV do.)

`max error` follows section 4.2.2.1: pixels for `re`, the IQR multiple alpha for every other parameter. The
template's comment "Y for the rest of parameters in max_deviation/average" is not what that section describes.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

from dstereo.errors import DstereoError

# Parameter names a mono step may filter; `re` is the subset's RMS reprojection error (px, absolute limit).
MONO_PARAMETERS = ("re", "fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6",
                   "fk1", "fk2", "fk3", "fk4")  # fk: the fisheye lens (cv2.fisheye k1..k4)
# Stereo step parameters (filtered by the stereo pipeline): stereo_re is absolute, the rest IQR.
STEREO_PARAMETERS = ("stereo_re", "Tnorm", "Tx", "Ty", "Tz", "RVnorm", "RVx", "RVy", "RVz")
# Parameters whose max error is an absolute limit in pixels; every other one is an IQR multiple alpha.
ABSOLUTE_PARAMETERS = ("re", "stereo_re")
# Project-folder configuration files, tried in this order.
CONFIG_NAMES = ("dstereo.toml", "calibrate.toml", "init-individual.ini", "init.ini")
# Top-level TOML tables that belong to other commands and are ignored here.
FOREIGN_TABLES = ("reconstruct", "sgbm", "recession", "optics", "demo")
_MODES = ("individual", "stereo")
_FINAL_CHOICES = ("survivors", "mean")  # dstereo.calib.final_solution.FINAL_CHOICES
_DEFAULT_MODEL = ("k1", "k2", "p1", "p2", "k3")


@dataclass(frozen=True)
class Step:
    """One optimisation step: parameters filtered jointly, each with its max error (px for re, else alpha)."""

    parameters: tuple[str, ...]
    max_error: tuple[float, ...]
    min_subsets: int | None = None  # stop the step before it leaves fewer subsets (None: the config's value)

    def describe(self) -> str:
        parts = [f"{p} <= {e:g} px" if p in ABSOLUTE_PARAMETERS else f"{p} within {e:g} IQR"
                 for p, e in zip(self.parameters, self.max_error)]
        return ", ".join(parts)


@dataclass(frozen=True)
class Config:
    """Everything one calibration run needs besides the images themselves."""

    mode: str = "individual"
    pattern: tuple[int, int] | None = None  # inner corners (columns, rows)
    square: float = 1.0
    unit: str = "squares"
    images: str = "images"  # folder, relative to the project (or the configuration file's folder)
    image_format: str | None = None  # file extension, e.g. "jpg"; None: every image type
    image_format_left: str | None = None
    image_format_right: str | None = None
    glob: str | None = None  # file-name pattern inside the folder, e.g. "left*.jpg" (overrides the format)
    model: tuple[str, ...] = _DEFAULT_MODEL  # free distortion coefficients, OpenCV order
    # `model = "auto"` / --model auto: the pipeline chooses the model by held-out views (calib/model_choice.py)
    # and runs on with it; `model` is then replaced by the chosen one
    model_auto: bool = False
    per_set: int | None = None  # images per subset m; None: full-set solve only
    max_subsets: int = 2000
    seed: int = 0
    min_subsets: int | None = None
    steps: tuple[Step, ...] = ()
    stereo_steps: tuple[Step, ...] = ()
    # What camera.yml / stereo.yml hold with subsets: "survivors" (the solve on the surviving subsets' views, a
    # consistent calibration) or "mean" (the thesis's per-parameter subset mean); see calib/final_solution.py
    final: str = "survivors"
    # Iterative k-sigma rejection of outlier corners and views before the subsets (calib/outliers.py)
    outlier_rejection: bool = True
    source: str = field(default="", compare=False)  # the file it was read from, "" for defaults and flags
    warnings: tuple[str, ...] = field(default=(), compare=False)

    def with_overrides(self, **changes) -> "Config":
        """A copy with the given fields replaced; `None` values leave a field as it is."""
        return replace(self, **{k: v for k, v in changes.items() if v is not None})


# --- validation ---------------------------------------------------------------------------------------------


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
    return Step(tuple(params), tuple(errors), _optional_count(min_subsets, f"{where}: minimum subsets"))


def _optional_count(value, where: str) -> int | None:
    if value is None:
        return None
    try:
        number = int(value)
    except (TypeError, ValueError):
        raise DstereoError(f"{where}: {value!r} is not a whole number") from None
    if number != float(value) or number < 1:
        raise DstereoError(f"{where}: {value!r} must be a whole number >= 1")
    return number


def validate(cfg: Config) -> Config:
    """Cross-field checks once files and flags are merged; returns `cfg` unchanged when it is consistent."""
    where = cfg.source or "configuration"
    if cfg.mode not in _MODES:
        raise DstereoError(f"{where}: mode {cfg.mode!r}; use one of {', '.join(_MODES)}")
    if cfg.pattern is None:
        raise DstereoError(f"{where}: no board pattern; pass --pattern COLSxROWS inner corners (e.g. 9x6)")
    if not (cfg.square > 0 and math.isfinite(cfg.square)):
        raise DstereoError(f"{where}: square size {cfg.square} must be a positive number")
    if cfg.per_set is not None and cfg.per_set < 3:
        raise DstereoError(f"{where}: images per set m = {cfg.per_set}; a calibration needs m >= 3")
    if cfg.max_subsets < 1:
        raise DstereoError(f"{where}: max subsets {cfg.max_subsets} must be at least 1")
    if cfg.final not in _FINAL_CHOICES:
        raise DstereoError(f"{where}: final {cfg.final!r}; use one of {', '.join(_FINAL_CHOICES)}")
    if cfg.min_subsets is not None and cfg.min_subsets < 1:
        raise DstereoError(f"{where}: minimum subsets {cfg.min_subsets} must be at least 1")
    if cfg.steps and cfg.per_set is None:
        raise DstereoError(
            f"{where}: optimisation steps need subsets; set images per set (--per-set m, e.g. 10)")
    if cfg.model_auto:
        _check_auto_steps(cfg, where)
    solved = ("re", "fx", "fy", "cx", "cy") + tuple(cfg.model)
    for k, step in enumerate(cfg.steps, 1):
        outside = [p for p in step.parameters if p not in solved]
        if outside:
            raise DstereoError(
                f"{where}: step {k} filters {', '.join(outside)} but the distortion model "
                f"({','.join(cfg.model) or 'none'}) does not solve it; add it to the model or drop it from the step"
            )
    return cfg


def _check_auto_steps(cfg: Config, where: str) -> None:
    """With the model chosen by the data, a step can only filter what every candidate solves."""
    for k, step in enumerate(cfg.steps, 1):
        coeffs = [p for p in step.parameters if p not in ("re", "fx", "fy", "cx", "cy")]
        if coeffs:
            raise DstereoError(
                f"{where}: step {k} filters {', '.join(coeffs)}, but model auto chooses the distortion model from "
                "the data, which may not solve it; filter only re, fx, fy, cx, cy, or name the model")


def is_auto_model(spec) -> bool:
    """True for the model spec "auto" (a flag or a configuration value)."""
    return isinstance(spec, str) and spec.strip().lower() == "auto"


# --- TOML ---------------------------------------------------------------------------------------------------

_TOML_KEYS = {
    "": {"mode"},
    "pattern": {"columns", "rows", "square", "unit"},
    "images": {"folder", "format", "format_left", "format_right", "glob"},
    "calibration": {"model", "per_set", "max_subsets", "seed", "min_subsets", "final", "outlier_rejection"},
}


def config_from_toml(text: str, where: str) -> Config:
    import tomllib

    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise DstereoError(f"{where}: not valid TOML ({exc})") from None
    known_tables = set(_TOML_KEYS) | {"steps", "stereo"}
    for key, value in data.items():
        if key in FOREIGN_TABLES:
            continue
        if key not in known_tables and key not in _TOML_KEYS[""]:
            known = sorted(known_tables - {""} | {"mode"})
            raise DstereoError(f"{where}: unknown key or table {key!r}; known: {known}")
    for table, keys in _TOML_KEYS.items():
        section = data.get(table, {}) if table else {}
        if table and not isinstance(section, dict):
            raise DstereoError(f"{where}: {table!r} must be a table ([{table}])")
        unknown = sorted(set(section) - keys)
        if unknown:
            raise DstereoError(f"{where}: unknown key(s) {unknown} in [{table}]; known: {sorted(keys)}")
    pat, img, cal = data.get("pattern", {}), data.get("images", {}), data.get("calibration", {})
    pattern = None
    if "columns" in pat or "rows" in pat:
        if not ("columns" in pat and "rows" in pat):
            raise DstereoError(f"{where}: [pattern] needs both columns and rows (inner corners)")
        pattern = (_whole(pat["columns"], f"{where}: [pattern] columns", 2),
                   _whole(pat["rows"], f"{where}: [pattern] rows", 2))
    model = cal.get("model", _DEFAULT_MODEL)
    cfg = Config(
        mode=str(data.get("mode", "individual")),
        pattern=pattern,
        square=_number(pat.get("square", 1.0), f"{where}: [pattern] square"),
        unit=str(pat.get("unit", "squares" if "square" not in pat else "mm")),
        images=str(img.get("folder", "images")),
        image_format=_suffix(img.get("format")),
        image_format_left=_suffix(img.get("format_left")),
        image_format_right=_suffix(img.get("format_right")),
        glob=img.get("glob"),
        model=_DEFAULT_MODEL if is_auto_model(model) else _model(model, f"{where}: [calibration] model"),
        model_auto=is_auto_model(model),
        per_set=_optional_whole(cal.get("per_set"), f"{where}: [calibration] per_set", 3),
        max_subsets=_whole(cal.get("max_subsets", 2000), f"{where}: [calibration] max_subsets", 1),
        seed=_whole(cal.get("seed", 0), f"{where}: [calibration] seed", 0),
        min_subsets=_optional_whole(cal.get("min_subsets"), f"{where}: [calibration] min_subsets", 1),
        final=str(cal.get("final", "survivors")),
        outlier_rejection=_flag(cal.get("outlier_rejection", True), f"{where}: [calibration] outlier_rejection"),
        steps=_toml_steps(data.get("steps", []), f"{where}: steps", stereo=False),
        stereo_steps=_toml_steps(data.get("stereo", {}).get("steps", []), f"{where}: stereo.steps", stereo=True),
        source=where,
    )
    extra = sorted(set(data.get("stereo", {})) - {"steps"})
    if extra:
        raise DstereoError(f"{where}: unknown key(s) {extra} in [stereo]; known: ['steps']")
    return cfg


def _flag(value, where: str) -> bool:
    if not isinstance(value, bool):
        raise DstereoError(f"{where}: {value!r} is not true or false")
    return value


def _toml_steps(items, where: str, stereo: bool) -> tuple[Step, ...]:
    if not isinstance(items, list):
        raise DstereoError(f"{where}: write each step as a [[steps]] table")
    steps = []
    for k, item in enumerate(items, 1):
        here = f"{where} {k}"
        unknown = sorted(set(item) - {"parameters", "max_error", "min_subsets"})
        if unknown:
            raise DstereoError(f"{here}: unknown key(s) {unknown}; known: parameters, max_error, min_subsets")
        params, errors = item.get("parameters", []), item.get("max_error")
        params = [params] if isinstance(params, str) else params
        errors = [errors] if isinstance(errors, (int, float)) else errors
        steps.append(make_step(params, errors, here, stereo, item.get("min_subsets")))
    return tuple(steps)


def _number(value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise DstereoError(f"{where}: {value!r} is not a number")
    return float(value)


def _whole(value, where: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise DstereoError(f"{where}: {value!r} must be a whole number >= {minimum}")
    return value


def _optional_whole(value, where: str, minimum: int) -> int | None:
    return None if value is None else _whole(value, where, minimum)


def _suffix(value) -> str | None:
    return None if value in (None, "") else str(value).strip().strip("'\"").lstrip(".").lower()


def _model(spec, where: str) -> tuple[str, ...]:
    from dstereo.models.distortion import parse_model

    try:
        return parse_model(spec)
    except DstereoError as exc:
        raise DstereoError(f"{where}: {exc}") from None


# --- the thesis's initialisation file -----------------------------------------------------------------------

_HEADER = re.compile(r"^(\[+)\s*([^\[\]]*?)\s*(\]+)$")


def _strip_comment(line: str) -> str:
    quote = None
    for i, ch in enumerate(line):
        if ch in "'\"":
            quote = None if quote == ch else (ch if quote is None else quote)
        elif ch == "#" and quote is None:
            return line[:i]
    return line


def _ini_list(value: str) -> list[str]:
    return [v.strip().strip("'\"").strip() for v in value.split(",") if v.strip().strip("'\"").strip()]


def _ini_scalar(value: str) -> str:
    items = _ini_list(value)
    return items[0] if len(items) == 1 else value.strip().strip("'\"")


def _parse_ini_tree(text: str, where: str) -> list[tuple[tuple[str, ...], str, str, int]]:
    """(section path, key, raw value, line number) for every `key = value` line, sections lower-cased."""
    path: list[str] = []
    entries = []
    for number, raw in enumerate(text.splitlines(), 1):
        line = _strip_comment(raw).strip()
        if not line:
            continue
        head = _HEADER.match(line)
        if head:
            depth, close = len(head.group(1)), len(head.group(3))
            if depth != close or depth > len(path) + 1:
                raise DstereoError(f"{where}:{number}: malformed section header {raw.strip()!r}")
            path = path[: depth - 1] + [" ".join(head.group(2).lower().split())]
            continue
        if "=" not in line:
            raise DstereoError(f"{where}:{number}: expected 'key = value', got {raw.strip()!r}")
        key, value = line.split("=", 1)
        entries.append((tuple(path), " ".join(key.lower().split()), value, number))
    return entries


_CALIBRATION_KEYS = {
    "individual calibration", "stereo calibration", "image format", "image format left", "image format right",
    "square size", "mesh width", "mesh height", "images per set", "camera matrix parameters",
    "distortion coefficients parameters",
    # dstereo's additions (optional): unit, subset cap and seed
    "unit", "max subsets", "seed",
}
_STEP_SECTIONS = {"optimization": False, "stereo optimization": True}


def _top_sections(text: str) -> list[str]:
    """Names of the `[ Section ]` headers (one bracket), lower-cased, in file order."""
    found = []
    for raw in text.splitlines():
        head = _HEADER.match(_strip_comment(raw).strip())
        if head and len(head.group(1)) == 1:
            found.append(" ".join(head.group(2).lower().split()))
    return found


def _missing_sections(sections: list[str], mode: str, where: str) -> list[str]:
    """Warnings for a thesis file without the optimisation section its mode uses (it then runs no steps)."""
    wanted = "optimization" if mode == "individual" else "stereo optimization"
    if wanted in sections:
        return []
    title = "[ Optimization ]" if mode == "individual" else "[ Stereo Optimization ]"
    others = [f"[ {s} ]" for s in sections if s not in ("calibration", wanted)]
    return [f"{where}: no {title} section, so no optimisation step filters the subsets (thesis Figure "
            f"{'5.5' if mode == 'individual' else '5.14'} has one)"
            + (f"; found {', '.join(others)}: check its spelling" if others else "")]


def config_from_thesis_ini(text: str, where: str) -> Config:
    """Config from the thesis's initialisation file (Figures 5.5 / 5.14), comments and trailing commas allowed."""
    entries = _parse_ini_tree(text, where)
    sections = _top_sections(text)
    if "calibration" not in sections:
        found = ", ".join(f"[ {s} ]" for s in sections) or "no sections"
        raise DstereoError(f"{where}: no [ Calibration ] section (found {found}); a thesis initialisation file "
                           "starts with [ Calibration ] (Individual/Stereo calibration, mesh width, mesh height, "
                           "square size, images per set); add it, or use a dstereo.toml (dstereo init writes one)")
    calib: dict[str, tuple[str, int]] = {}
    steps_meta: dict[bool, dict[str, tuple[str, int]]] = {False: {}, True: {}}
    step_blocks: dict[bool, dict[int, dict[str, tuple[str, int]]]] = {False: {}, True: {}}
    warnings: list[str] = []
    for path, key, value, line in entries:
        here = f"{where}:{line}"
        top = path[0] if path else ""
        if top == "calibration" and len(path) == 1:
            if key not in _CALIBRATION_KEYS:
                raise DstereoError(
                    f"{here}: unknown key {key!r} in [ Calibration ]; known: {sorted(_CALIBRATION_KEYS)}")
            calib[key] = (value, line)
        elif top in _STEP_SECTIONS:
            stereo = _STEP_SECTIONS[top]
            if len(path) == 1:
                raise DstereoError(f"{here}: {key!r} belongs in a [[ Calibration steps ]] block")
            if path[1] != "calibration steps":
                raise DstereoError(f"{here}: unknown block [[ {path[1]} ]]; use [[ Calibration steps ]]")
            if len(path) == 2:
                if key not in ("number steps", "minimum subsets"):
                    raise DstereoError(f"{here}: unknown key {key!r}; use 'number steps' (and 'minimum subsets')")
                steps_meta[stereo][key] = (value, line)
                continue
            match = re.fullmatch(r"step\s*(\d+)", path[2])
            if not match or len(path) > 3:
                raise DstereoError(
                    f"{here}: unknown block [[[ {path[-1]} ]]]; name steps [[[ step 1 ]]], [[[ step 2 ]]], ...")
            if key not in ("parameters", "max error", "minimum subsets"):
                raise DstereoError(f"{here}: unknown key {key!r} in a step; use parameters, max error, minimum subsets")
            step_blocks[stereo].setdefault(int(match.group(1)), {})[key] = (value, line)
        else:
            name = f"[ {top} ]" if top else "the top of the file"
            warnings.append(f"{where}:{line}: key {key!r} in {name} is not used by dstereo calibrate (ignored)")

    def get(key, convert, default=None):
        if key not in calib:
            return default
        value, line = calib[key]
        try:
            return convert(_ini_scalar(value))
        except ValueError:
            raise DstereoError(f"{where}:{line}: {key} = {value.strip()!r} is not a valid value") from None

    individual, stereo = get("individual calibration", int), get("stereo calibration", int)
    if individual not in (None, 0, 1) or stereo not in (None, 0, 1):
        raise DstereoError(f"{where}: 'Individual calibration' and 'Stereo calibration' take 1 or 0")
    if individual == 1 and stereo == 1:
        raise DstereoError(f"{where}: both Individual calibration and Stereo calibration are 1; set one of them to 1")
    if individual == 0 and stereo == 0:
        raise DstereoError(f"{where}: Individual calibration and Stereo calibration are both 0; set one of them to 1")
    mode = "stereo" if stereo == 1 else "individual"
    width, height = get("mesh width", int), get("mesh height", int)
    if (width is None) != (height is None):
        raise DstereoError(f"{where}: give both mesh width and mesh height (inner corners)")
    if width is not None and (width < 2 or height < 2):
        raise DstereoError(f"{where}: mesh {width} x {height} needs at least 2 inner corners per side")
    if "camera matrix parameters" in calib:
        value, line = calib["camera matrix parameters"]
        given = sorted(p.lower() for p in _ini_list(value))
        if given != sorted(["fx", "fy", "cx", "cy"]):
            raise DstereoError(
                f"{where}:{line}: camera matrix parameters = {value.strip()}; dstereo always solves fx, fy, cx, cy")
    model, model_auto = _DEFAULT_MODEL, False
    if "distortion coefficients parameters" in calib:
        value, line = calib["distortion coefficients parameters"]
        model_auto = [v.lower() for v in _ini_list(value)] == ["auto"]
        if not model_auto:
            model = _model(_ini_list(value), f"{where}:{line}: distortion coefficients parameters")
    per_set = get("images per set", int)
    if per_set is not None and per_set < 3:
        raise DstereoError(f"{where}: images per set = {per_set}; a calibration needs m >= 3")
    square = get("square size", float)
    return Config(
        mode=mode,
        pattern=(width, height) if width is not None else None,
        square=square if square is not None else 1.0,
        unit=get("unit", str, "mm" if square is not None else "squares"),
        image_format=_suffix(get("image format", str)),
        image_format_left=_suffix(get("image format left", str)),
        image_format_right=_suffix(get("image format right", str)),
        model=model,
        model_auto=model_auto,
        per_set=per_set,
        max_subsets=get("max subsets", int, 2000),
        seed=get("seed", int, 0),
        min_subsets=_ini_min(steps_meta[False], where),
        steps=_ini_steps(steps_meta[False], step_blocks[False], where, "[ Optimization ]", stereo=False),
        stereo_steps=_ini_steps(steps_meta[True], step_blocks[True], where, "[ Stereo Optimization ]", stereo=True),
        source=where,
        warnings=tuple(warnings + _missing_sections(sections, mode, where)),
    )


def _ini_min(meta, where) -> int | None:
    if "minimum subsets" not in meta:
        return None
    value, line = meta["minimum subsets"]
    return _optional_count(_ini_scalar(value), f"{where}:{line}: minimum subsets")


def _ini_steps(meta, blocks, where, section, stereo) -> tuple[Step, ...]:
    numbers = sorted(blocks)
    if "number steps" in meta:
        value, line = meta["number steps"]
        try:
            declared = int(_ini_scalar(value))
        except ValueError:
            raise DstereoError(f"{where}:{line}: number steps = {value.strip()!r} is not a whole number") from None
        if declared != len(numbers):
            raise DstereoError(
                f"{where}:{line}: number steps = {declared} but {section} has {len(numbers)} [[[ step k ]]] block(s)")
    if numbers != list(range(1, len(numbers) + 1)):
        raise DstereoError(f"{where}: {section} steps are numbered {numbers}; number them 1, 2, 3, ... without gaps")
    steps = []
    for k in numbers:
        block = blocks[k]
        line = min(v[1] for v in block.values())
        here = f"{where}:{line}: step {k}"
        params = _ini_list(block["parameters"][0]) if "parameters" in block else []
        errors = _ini_list(block["max error"][0]) if "max error" in block else None
        minimum = _ini_scalar(block["minimum subsets"][0]) if "minimum subsets" in block else None
        steps.append(make_step(params, errors, here, stereo, minimum))
    return tuple(steps)


# --- files, project folders and flags -----------------------------------------------------------------------


def load_config(path: str | Path) -> Config:
    """Config from a `.toml` file or from a thesis initialisation file (any other suffix)."""
    path = Path(path)
    if not path.is_file():
        raise DstereoError(f"configuration file {path} does not exist")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise DstereoError(f"configuration file {path} cannot be read ({exc})") from None
    if path.suffix.lower() == ".toml":
        return config_from_toml(text, str(path))
    return config_from_thesis_ini(text, str(path))


def find_project_config(project: str | Path) -> Path | None:
    """The project's configuration file: one of CONFIG_NAMES, else the single *.toml / *.ini in the folder."""
    project = Path(project)
    if not project.is_dir():
        raise DstereoError(f"project folder {project} does not exist")
    for name in CONFIG_NAMES:
        if (project / name).is_file():
            return project / name
    found = sorted(p for p in project.iterdir() if p.is_file() and p.suffix.lower() in (".toml", ".ini"))
    if len(found) > 1:
        raise DstereoError(
            f"project folder {project} holds several configuration files ({', '.join(p.name for p in found)}); "
            "pick one with --config")
    return found[0] if found else None


def _step_items(text: str, where: str) -> tuple[list[str], list[str]]:
    params, errors = [], []
    for item in (s for s in text.split(",") if s.strip()):
        if "=" not in item:
            raise DstereoError(f"{where}: write NAME=MAX_ERROR pairs, e.g. --step fx=1.0,fy=1.0")
        name, value = item.split("=", 1)
        params.append(name)
        errors.append(value.strip())
    return params, errors


def parse_step_flag(text: str, index: int, stereo: bool = False) -> Step:
    """'--step re=0.5' or '--step p1=1.5,p2=1.5' -> Step (one flag per step, in order); `stereo`: the names are
    the stereo step parameters (stereo_re, Tnorm, ...)."""
    where = f"--step {text!r} (step {index})"
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
        where = f"--step {text!r} (step {index})"
        params, _ = _step_items(text, where)
        kinds = {_is_stereo_name(p) for p in params}
        if None in kinds:
            bad = next(p for p in params if _is_stereo_name(p) is None)
            raise DstereoError(f"{where}: unknown parameter {bad!r}; one-camera steps use {', '.join(MONO_PARAMETERS)}"
                               f"; stereo steps use {', '.join(STEREO_PARAMETERS)}")
        if len(kinds) > 1:
            raise DstereoError(f"{where}: mixes one-camera and stereo parameters; give them as separate --step flags "
                               "(e.g. --step re=0.5 --step stereo_re=3)")
        is_stereo = kinds == {True}
        (stereo if is_stereo else mono).append(parse_step_flag(text, index, is_stereo))
    return (tuple(mono) if mono else None), (tuple(stereo) if stereo else None)


# --- writing ------------------------------------------------------------------------------------------------


def _toml_str(value: str) -> str:
    return '"' + str(value).replace("\\", "\\\\").replace('"', '\\"') + '"'


def _toml_list(values) -> str:
    return "[" + ", ".join(_toml_str(v) if isinstance(v, str) else f"{v!r}" for v in values) + "]"


def to_toml(cfg: Config, comments: bool = True) -> str:
    """The configuration as dstereo TOML (what `dstereo init` writes and the results folder keeps)."""
    c = (lambda text: f"  # {text}") if comments else (lambda text: "")
    cols, rows = cfg.pattern if cfg.pattern is not None else (9, 6)
    out = []
    if comments:
        out += [
            "# dstereo calibration project (the thesis's initialisation file, Figure 5.5, in TOML).",
            "# Layout: this file next to a folder `images/` holding the chessboard pictures; run",
            "#     dstereo calibrate PROJECT_FOLDER",
            "# Command-line flags override what is written here.",
            "",
        ]
    out += [f"mode = {_toml_str(cfg.mode)}" + c("individual: one camera from images/"), ""]
    out += ["[pattern]", f"columns = {cols}" + c("inner corners along the board's width (thesis: mesh width)"),
            f"rows = {rows}" + c("inner corners along its height (thesis: mesh height)"),
            f"square = {cfg.square!r}" + c("size of one square, in `unit`"),
            f"unit = {_toml_str(cfg.unit)}", ""]
    out += ["[images]", f"folder = {_toml_str(cfg.images)}" + c("relative to the project folder")]
    for key, value in (("format", cfg.image_format), ("format_left", cfg.image_format_left),
                       ("format_right", cfg.image_format_right), ("glob", cfg.glob)):
        if value is not None:
            out.append(f"{key} = {_toml_str(value)}" + (c("file extension of the images") if key == "format" else ""))
    if comments and cfg.glob is None:
        out.append('# glob = "left*.jpg"  # only files matching this name pattern')
    out += ["", "[calibration]",
            (f"model = {_toml_str('auto')}" if cfg.model_auto else f"model = {_toml_list(cfg.model)}")
            + c("free distortion coefficients; or a preset: k1, k1k2, k1k2p1p2, k1k2k3p1p2, rational, fisheye; "
                "or auto (chosen by held-out views)")]
    if cfg.per_set is not None:
        out.append(f"per_set = {cfg.per_set}" + c("images per subset m: C(N, m) subsets are solved"))
    elif comments:
        out.append("# per_set = 10  # images per subset m; without it only the full set is solved")
    out += [f"max_subsets = {cfg.max_subsets}" + c("more than this many subsets: a seeded random sample"),
            f"seed = {cfg.seed}"]
    if cfg.min_subsets is not None:
        out.append(f"min_subsets = {cfg.min_subsets}" + c("a step stops before it leaves fewer subsets"))
    elif comments:
        out.append("# min_subsets = 50  # a step stops before it leaves fewer subsets")
    if not cfg.outlier_rejection:
        out.append("outlier_rejection = false" + c("keep every corner (default true: k-sigma rejection)"))
    if cfg.final != "survivors":
        out.append(f"final = {_toml_str(cfg.final)}" + c("camera file: the thesis's subset mean, not the "
                                                         "survivors' solve"))
    elif comments:
        out.append('# final = "mean"  # camera file: the thesis\'s subset mean instead of the survivors\' solve')
    if comments:
        out += ["", "# Optimisation steps, run in order (thesis section 4.2.2.1). Parameters of one step are filtered",
                "# jointly. re: subsets whose RMS reprojection error exceeds max_error (px) are removed. Others",
                "# (fx fy cx cy k1..k6 p1 p2): subsets outside [Q1 - a IQR, Q3 + a IQR], a = max_error, are removed",
                "# and the quartiles recomputed until none is outside."]
    for step_list, table in ((cfg.steps, "steps"), (cfg.stereo_steps, "stereo.steps")):
        if comments and table == "stereo.steps":
            out += ["", "# Stereo steps (thesis Figure 5.14), used when the project is a stereo rig",
                    "# (images/images_left + images/images_right, or --left/--right); they filter the",
                    "# subsets of pairs after each camera's own steps above. stereo_re: subsets whose stereo",
                    "# RMS reprojection error exceeds max_error (px) are removed. Tnorm Tx Ty Tz (translation,",
                    "# its norm = the baseline) and RVnorm RVx RVy RVz (rotation vector, rad): the IQR rule",
                    "# above with a = max_error. From the command line:",
                    "#     --step stereo_re=3 --step Tnorm=0.75 --step RVnorm=0.75"]
            if not step_list:
                out += ["# [[stereo.steps]]", '# parameters = ["stereo_re"]', "# max_error = [3.0]"]
        for step in step_list:
            out += ["", f"[[{table}]]", f"parameters = {_toml_list(step.parameters)}",
                    f"max_error = {_toml_list(step.max_error)}"]
            if step.min_subsets is not None:
                out.append(f"min_subsets = {step.min_subsets}")
    return "\n".join(out) + "\n"


def template() -> Config:
    """The thesis's Figure 5.5 configuration with Figure 5.14's stereo steps (what `dstereo init` writes)."""
    steps = (Step(("re",), (0.5,)), Step(("p1", "p2"), (1.5, 1.5)), Step(("k1", "k2", "k3"), (1.5, 1.5, 1.5)),
             Step(("fx", "fy", "cx", "cy"), (1.0, 1.0, 1.0, 1.0)))
    stereo_steps = (Step(("stereo_re",), (3.0,)), Step(("Tnorm",), (0.75,)), Step(("RVnorm",), (0.75,)))
    return Config(pattern=(9, 6), square=10.0, unit="mm", image_format="jpg", per_set=10, steps=steps,
                  stereo_steps=stereo_steps)


def as_dict(cfg: Config) -> dict:
    """JSON-ready view (for summary.json)."""
    out = {}
    for f in fields(cfg):
        value = getattr(cfg, f.name)
        if f.name in ("steps", "stereo_steps"):
            value = [{"parameters": list(s.parameters), "max_error": list(s.max_error), "min_subsets": s.min_subsets}
                     for s in value]
        elif isinstance(value, tuple):
            value = list(value)
        out[f.name] = value
    return out
