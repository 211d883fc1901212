"""dstereo's calibration TOML read into a layer of calibration parameters: only the keys the file gives, each
checked where it is read so the error names the file and the key. The keys are the CALIBRATE table's."""

from __future__ import annotations

from dstereo.config.files import check_known, table
from dstereo.config.options import CALIBRATE
from dstereo.config.steps import Step, make_step
from dstereo.config.values import flag, model_layer, right_model, number, optional_whole, suffix, whole
from dstereo.errors import DstereoError

# Top-level TOML tables that belong to other commands and are ignored here.
FOREIGN_TABLES = ("reconstruct", "sgbm", "recession", "optics", "demo")


def _declared() -> dict[str, set[str]]:
    """table -> its keys, from the option table ('' holds the top-level keys)."""
    out: dict[str, set[str]] = {"": set()}
    for key in CALIBRATE.file_keys():
        head, _, tail = key.rpartition(".")
        out.setdefault(head, set()).add(tail)
    return out


def _check_tables(data: dict, where: str) -> dict[str, set[str]]:
    declared = _declared()
    known = declared[""] | set(declared) - {""}
    for key in data:
        if key not in FOREIGN_TABLES and key not in known:
            raise DstereoError(f"{where}: unknown key or table {key!r}; known: {sorted(known)}")
    for name, keys in declared.items():
        if name:
            check_known(table(data, name, where), keys, where, name)
    return declared


def toml_layer(data: dict, where: str) -> dict:
    """Calibration parameters from a parsed dstereo TOML (see `dstereo init` for the layout)."""
    _check_tables(data, where)
    pat, img, cal = (table(data, n, where) for n in ("pattern", "images", "calibration"))
    layer: dict = {}
    if "mode" in data:
        layer["mode"] = str(data["mode"])
    if "columns" in pat or "rows" in pat:
        if not ("columns" in pat and "rows" in pat):
            raise DstereoError(f"{where}: [pattern] needs both columns and rows (inner corners)")
        layer["pattern"] = (whole(pat["columns"], f"{where}: [pattern] columns", 2),
                            whole(pat["rows"], f"{where}: [pattern] rows", 2))
    if "square" in pat:
        layer["square"] = number(pat["square"], f"{where}: [pattern] square")
    if "unit" in pat:
        layer["unit"] = str(pat["unit"])
    for key, name in (("folder", "images"), ("format", "image_format"), ("format_left", "image_format_left"),
                      ("format_right", "image_format_right")):
        if key in img:
            layer[name] = str(img[key]) if key == "folder" else suffix(img[key])
    if "glob" in img:
        layer["glob"] = str(img["glob"])
    if "model" in cal:
        layer |= model_layer(cal["model"], f"{where}: [calibration] model")
    if "model_right" in cal:
        layer["model_right"] = right_model(cal["model_right"], f"{where}: [calibration] model_right")
    for key, minimum in (("per_set", 3), ("max_subsets", 1), ("seed", 0), ("min_subsets", 1)):
        if key in cal:
            layer[key] = (optional_whole if key in ("per_set", "min_subsets") else whole)(
                cal[key], f"{where}: [calibration] {key}", minimum)
    if "final" in cal:
        layer["final"] = str(cal["final"])
    if "outlier_rejection" in cal:
        layer["outlier_rejection"] = flag(cal["outlier_rejection"], f"{where}: [calibration] outlier_rejection")
    if "board_sag" in cal:
        layer["board_sag"] = flag(cal["board_sag"], f"{where}: [calibration] board_sag")
    if "mrcal_convert" in cal:
        layer["mrcal_convert"] = flag(cal["mrcal_convert"], f"{where}: [calibration] mrcal_convert")
    if "steps" in data:
        layer["steps"] = _toml_steps(data["steps"], f"{where}: steps", stereo=False)
    if "steps" in table(data, "stereo", where):
        layer["stereo_steps"] = _toml_steps(data["stereo"]["steps"], f"{where}: stereo.steps", stereo=True)
    return layer


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
