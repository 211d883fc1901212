"""The thesis's initialisation file (Figures 5.5 and 5.14, e.g. `init-individual.ini`) read into a layer of
calibration parameters: configobj-like text, `[ Calibration ]`, `[[ Calibration steps ]]`, `[[[ step 1 ]]]`,
`key = value` lines, `#` comments anywhere, comma lists with optional trailing commas and quoted strings. Mono
optimisation steps (`[ Optimization ]`) and stereo steps (`[ Stereo Optimization ]`) are kept apart.

`mesh width` x `mesh height` are the board's *inner* corners (columns x rows), the `patternSize` the thesis
hands to cv2.findChessboardCorners: its Figure 5.5 says 9 x 6 for OpenCV's sample set, whose board has
10 x 7 squares and 9 x 6 inner corners. (Section 4.2.2.1's "20 x 10 board, 20 mm squares" example lists object
points up to (400, 200), i.e. 21 x 11 points, and so does not fit either reading; the figures and the code
path through OpenCV do.)

`max error` follows section 4.2.2.1: pixels for `re`, the IQR multiple alpha for every other parameter. The
template's comment "Y for the rest of parameters in max_deviation/average" is not what that section describes.
"""

from __future__ import annotations

import re

from dstereo.config.steps import Step, make_step, optional_count
from dstereo.config.values import model_layer, suffix
from dstereo.errors import DstereoError

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


def _read_entries(text: str, where: str):
    """The [ Calibration ] keys, the step sections' meta keys and step blocks, each value with its line number;
    plus warnings for keys dstereo does not use."""
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
    return calib, steps_meta, step_blocks, warnings


def ini_layer(text: str, where: str) -> dict:
    """Calibration parameters from the thesis's initialisation file (Figures 5.5 / 5.14): the keys it gives, and
    `warnings` (keys dstereo ignores, a missing optimisation section). Comments and trailing commas allowed."""
    calib, steps_meta, step_blocks, warnings = _read_entries(text, where)

    def get(key, convert):
        value, line = calib[key]
        try:
            return convert(_ini_scalar(value))
        except ValueError:
            raise DstereoError(f"{where}:{line}: {key} = {value.strip()!r} is not a valid value") from None

    layer = {k: get(key, convert) for key, k, convert in _SCALARS if key in calib}
    layer |= _mode(layer.pop("individual", None), layer.pop("stereo", None), where)
    width, height = layer.pop("width", None), layer.pop("height", None)
    if (width is None) != (height is None):
        raise DstereoError(f"{where}: give both mesh width and mesh height (inner corners)")
    if width is not None:
        if width < 2 or height < 2:
            raise DstereoError(f"{where}: mesh {width} x {height} needs at least 2 inner corners per side")
        layer["pattern"] = (width, height)
    _check_camera_matrix(calib, where)
    if "distortion coefficients parameters" in calib:
        value, line = calib["distortion coefficients parameters"]
        items = _ini_list(value)
        layer |= model_layer("auto" if [v.lower() for v in items] == ["auto"] else items,
                             f"{where}:{line}: distortion coefficients parameters")
    if layer.get("per_set") is not None and layer["per_set"] < 3:
        raise DstereoError(f"{where}: images per set = {layer['per_set']}; a calibration needs m >= 3")
    for name in ("image_format", "image_format_left", "image_format_right"):
        if name in layer:
            layer[name] = suffix(layer[name])
    minimum = _ini_min(steps_meta[False], where)
    if minimum is not None:
        layer["min_subsets"] = minimum
    layer["steps"] = _ini_steps(steps_meta[False], step_blocks[False], where, "[ Optimization ]", stereo=False)
    layer["stereo_steps"] = _ini_steps(steps_meta[True], step_blocks[True], where, "[ Stereo Optimization ]",
                                       stereo=True)
    layer["warnings"] = tuple(warnings + _missing_sections(_top_sections(text), layer["mode"], where))
    return layer


# (thesis key, parameter, conversion); 'individual'/'stereo' and 'width'/'height' are combined in ini_layer.
_SCALARS = (
    ("individual calibration", "individual", int), ("stereo calibration", "stereo", int),
    ("mesh width", "width", int), ("mesh height", "height", int), ("square size", "square", float),
    ("unit", "unit", str), ("image format", "image_format", str), ("image format left", "image_format_left", str),
    ("image format right", "image_format_right", str), ("images per set", "per_set", int),
    ("max subsets", "max_subsets", int), ("seed", "seed", int),
)


def ini_key(name: str) -> str:
    """The thesis file's key of parameter `name` (for messages that name where a value came from)."""
    keys = {"pattern": "mesh width/mesh height", "mode": "individual/stereo calibration",
            "model": "distortion coefficients parameters", "model_auto": "distortion coefficients parameters",
            "steps": "[ Optimization ]", "stereo_steps": "[ Stereo Optimization ]", "min_subsets": "[ Optimization ]"}
    return keys.get(name) or next((key for key, param, _ in _SCALARS if param == name), name)


def _mode(individual, stereo, where: str) -> dict:
    if individual not in (None, 0, 1) or stereo not in (None, 0, 1):
        raise DstereoError(f"{where}: 'Individual calibration' and 'Stereo calibration' take 1 or 0")
    if individual == 1 and stereo == 1:
        raise DstereoError(f"{where}: both Individual calibration and Stereo calibration are 1; set one of them to 1")
    if individual == 0 and stereo == 0:
        raise DstereoError(f"{where}: Individual calibration and Stereo calibration are both 0; set one of them to 1")
    return {"mode": "stereo" if stereo == 1 else "individual"}


def _check_camera_matrix(calib: dict, where: str) -> None:
    if "camera matrix parameters" in calib:
        value, line = calib["camera matrix parameters"]
        given = sorted(p.lower() for p in _ini_list(value))
        if given != sorted(["fx", "fy", "cx", "cy"]):
            raise DstereoError(
                f"{where}:{line}: camera matrix parameters = {value.strip()}; dstereo always solves fx, fy, cx, cy")



def _ini_min(meta, where) -> int | None:
    if "minimum subsets" not in meta:
        return None
    value, line = meta["minimum subsets"]
    return optional_count(_ini_scalar(value), f"{where}:{line}: minimum subsets")


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


