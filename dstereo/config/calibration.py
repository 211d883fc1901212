"""The calibration configuration: one frozen `Config`, built from defaults < project file < flags.

The project file is dstereo's TOML (`calibration_toml`) or the thesis's initialisation file (`thesis_ini`); both
read into a layer of parameters, merged by the one rule (`merge`) with the command's flags. Step types and the
flag syntax of `--step` live in `steps`; the TOML writer in `calibration_writer`. The names other modules have
imported from here stay importable from here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

from dstereo.config.calibration_toml import FOREIGN_TABLES, toml_layer
from dstereo.config.calibration_writer import to_toml
from dstereo.config.files import parse_toml, read_text
from dstereo.config.merge import merge
from dstereo.config.options import CALIBRATE
from dstereo.config.steps import (ABSOLUTE_PARAMETERS, MONO_PARAMETERS, STEREO_PARAMETERS, Step, canonical_parameter,
                                  make_step, parse_step_flag, parse_step_flags)
from dstereo.config.thesis_ini import ini_layer
from dstereo.config.units import check_unit
from dstereo.config.values import is_auto_model
from dstereo.errors import DstereoError

__all__ = ["ABSOLUTE_PARAMETERS", "CONFIG_NAMES", "FOREIGN_TABLES", "MONO_PARAMETERS", "STEREO_PARAMETERS", "Config",
           "Step", "as_dict", "build_config", "canonical_parameter", "config_from_thesis_ini", "config_from_toml",
           "file_layer", "find_project_config", "given_as", "is_auto_model", "load_config", "make_step",
           "parse_step_flag", "parse_step_flags", "template", "to_toml", "validate"]

# Project-folder configuration files, tried in this order.
CONFIG_NAMES = ("dstereo.toml", "calibrate.toml", "init-individual.ini", "init.ini")
_MODES = ("individual", "stereo")
_FINAL_CHOICES = ("survivors", "mean")  # dstereo.calib.final_solution.FINAL_CHOICES
_DEFAULT_MODEL = ("k1", "k2", "p1", "p2", "k3")


@dataclass(frozen=True)
class Config:
    """Everything one calibration run needs besides the images themselves (options: `options.CALIBRATE`)."""

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
    # A stereo rig's right camera when its lens differs from the left's (`model`): e.g. a pinhole left and a
    # fisheye right (--model-right fisheye); None: the right camera takes `model` too
    model_right: tuple[str, ...] | None = None
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
    # solve the board's two sag parameters with the rest (calib/problem.py). On by default: every real board
    # measured sags 3-22 sigma and fits 4-22 % better (experiments/results/board_sag_real.md); every camera and rig
    # solves it (--model auto too: the chosen lens is solved again with it)
    board_sag: bool = True
    # a lens mrcal has no twin for (fisheye, splined): also write the nearest mrcal model, with its fit error
    # (calib/mrcal_convert.py)
    mrcal_convert: bool = False
    source: str = field(default="", compare=False)  # the file it was read from, "" for defaults and flags
    warnings: tuple[str, ...] = field(default=(), compare=False)
    # parameter -> where its value came from ("--square", "dstereo.toml [pattern] square"); absent: the default.
    # Messages name the origin, so a value from a file is not blamed on a flag nor a flag's on the file.
    origins: dict = field(default_factory=dict, compare=False)

    def with_overrides(self, **changes) -> "Config":
        """A copy with the given fields replaced; `None` values leave a field as it is. A value set here came from
        the code, not from the file or flag that gave the one it replaces: its origin goes."""
        changes = {k: v for k, v in changes.items() if v is not None}
        origins = {k: v for k, v in self.origins.items() if k not in changes}
        return replace(self, **changes, origins=origins)


# --- files, layers and the merge ----------------------------------------------------------------------------


def file_layer(path: str | Path) -> dict:
    """The parameters a configuration file gives: `.toml` is dstereo's TOML, any other suffix the thesis's file.
    The layer also names its `source` (and `warnings` for a thesis file)."""
    text, where = read_text(path), str(path)
    layer = toml_layer(parse_toml(text, where), where) if Path(path).suffix.lower() == ".toml" else \
        ini_layer(text, where)
    return {**layer, "source": where}


def build_config(*layers: dict) -> Config:
    """Config from layers, lowest first (a file's, then the flags'): defaults < file < flags, key by key. The
    unit follows the square when none is given: a square size given anywhere is in mm."""
    merged = merge(CALIBRATE, Config, *layers)  # `model_auto` (set with `model`), `source` and `warnings` pass through
    if not any("unit" in layer for layer in layers) and any("square" in layer for layer in layers):
        merged["unit"] = "mm"
    origins: dict[str, str] = {}
    for layer in layers:
        where = layer.get("source")
        for name in layer:
            if name not in ("source", "warnings") and layer[name] is not None:
                # `model_auto` is set by `model` (auto, or a named model that turns it off): the same origin
                origins[name] = _origin("model" if name == "model_auto" else name, where)
    return Config(**merged, origins=origins)


def _origin(name: str, source: str | None) -> str:
    """Where parameter `name` of a layer came from: the file and its key, or the flag (a layer without a source)."""
    row = CALIBRATE[name] if name in CALIBRATE.names() else None
    if not source:
        return (row.flag if row is not None and row.flag else f"`{name}`")
    if Path(source).suffix.lower() == ".toml":
        key = row.file[0] if row is not None and row.file else name
        table, _, tail = key.rpartition(".")
        key = {"pattern.columns": "[pattern] columns/rows", "steps": "[[steps]]",
               "stereo.steps": "[[stereo.steps]]"}.get(key, f"[{table}] {tail}" if table else tail)
        return f"{source} {key}"
    from dstereo.config.thesis_ini import ini_key

    return f"{source} ({ini_key(name)})"


def given_as(cfg: Config, name: str) -> str:
    """Parameter `name` with its value as the user gave it: "--square -1", "dstereo.toml [pattern] square = -1";
    a default (or a Config built in code) names the parameter in backticks (the CLI turns it into the flag)."""
    value = getattr(cfg, name)
    text = ",".join(map(str, value)) if isinstance(value, tuple) else value
    origin = cfg.origins.get(name)
    if origin is None:
        return f"`{name}` {text!r}" if isinstance(text, str) else f"`{name}` {text}"
    if origin.startswith("-"):
        return f"{origin} {text}"
    return f"{origin} = {text!r}" if isinstance(text, str) else f"{origin} = {text}"


def load_config(path: str | Path) -> Config:
    """Config from a `.toml` file or from a thesis initialisation file (any other suffix), over the defaults."""
    return build_config(file_layer(path))


def config_from_toml(text: str, where: str) -> Config:
    return build_config({**toml_layer(parse_toml(text, where), where), "source": where})


def config_from_thesis_ini(text: str, where: str) -> Config:
    return build_config({**ini_layer(text, where), "source": where})


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
            "pick one with `config`")
    return found[0] if found else None


# --- validation ---------------------------------------------------------------------------------------------


def validate(cfg: Config) -> Config:
    """Cross-field checks once files and flags are merged; returns `cfg` with its unit in canonical form when it is
    consistent. Each message names where the value came from (`given_as`): the flag, or the file and its key."""
    where = cfg.source or "configuration"
    if cfg.mode not in _MODES:
        raise DstereoError(f"{given_as(cfg, 'mode')}; use one of {', '.join(_MODES)}")
    if cfg.pattern is None:
        raise DstereoError(f"{where}: no board pattern; give --pattern COLSxROWS inner corners (e.g. 9x6) or set "
                           "[pattern] columns and rows in the configuration file")
    if not (cfg.square > 0 and math.isfinite(cfg.square)):
        raise DstereoError(f"{given_as(cfg, 'square')}: the board square size must be a positive number")
    unit = check_unit(cfg.unit, given_as(cfg, "unit"))
    if cfg.per_set is not None and cfg.per_set < 3:
        raise DstereoError(f"{given_as(cfg, 'per_set')}: images per set m; a calibration needs m >= 3")
    if cfg.max_subsets < 1:
        raise DstereoError(f"{given_as(cfg, 'max_subsets')}: must be at least 1")
    if cfg.final not in _FINAL_CHOICES:
        raise DstereoError(f"{given_as(cfg, 'final')}; use one of {', '.join(_FINAL_CHOICES)}")
    if cfg.min_subsets is not None and cfg.min_subsets < 1:
        raise DstereoError(f"{given_as(cfg, 'min_subsets')}: must be at least 1")
    if cfg.steps and cfg.per_set is None:
        raise DstereoError(
            f"{cfg.origins.get('steps', where)}: optimisation steps need subsets; set images per set (--per-set M, "
            "or per_set in the configuration file, e.g. 10)")
    if cfg.model_auto:
        _check_auto_steps(cfg, cfg.origins.get("steps", where))
    solved = ("re", "fx", "fy", "cx", "cy") + tuple(cfg.model)
    for k, step in enumerate(cfg.steps, 1):
        outside = [p for p in step.parameters if p not in solved]
        if outside:
            raise DstereoError(
                f"{cfg.origins.get('steps', where)}: step {k} filters {', '.join(outside)} but the distortion model "
                f"({','.join(cfg.model) or 'none'}, {cfg.origins.get('model', 'the default')}) does not solve it; "
                "add it to the model or drop it from the step"
            )
    return cfg if unit == cfg.unit else replace(cfg, unit=unit)


def _check_auto_steps(cfg: Config, where: str) -> None:
    """With the model chosen by the data, a step can only filter what every candidate solves."""
    for k, step in enumerate(cfg.steps, 1):
        coeffs = [p for p in step.parameters if p not in ("re", "fx", "fy", "cx", "cy")]
        if coeffs:
            raise DstereoError(
                f"{where}: step {k} filters {', '.join(coeffs)}, but model auto chooses the distortion model from "
                "the data, which may not solve it; filter only re, fx, fy, cx, cy, or name the model")


# --- the template and the JSON view -------------------------------------------------------------------------

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
        if f.name == "origins":  # where each value came from: for messages, not part of the results
            continue
        if f.name in ("steps", "stereo_steps"):
            value = [{"parameters": list(s.parameters), "max_error": list(s.max_error), "min_subsets": s.min_subsets}
                     for s in value]
        elif isinstance(value, tuple):
            value = list(value)
        out[f.name] = value
    return out
