"""The reconstruction configuration (`dstereo reconstruct`, and the matching options of `dstereo recession`):
layers of parameters from files ([reconstruct] and [sgbm] tables) and flags, merged by the one rule, built into
`dstereo.config.reconstruction_config.ReconstructionConfig`.

SGBM fields travel as `sgbm.<field>` parameters, so a file's [sgbm] block_size and a flag's --sgbm P1=200 both
apply; a `preset` sets every SGBM field, so one given drops the SGBM fields of the layers below it (its
`replaces` in `options.RECONSTRUCT`). The fields the user names are recorded in `sgbm_user`.
"""

from __future__ import annotations

import math
from pathlib import Path

from dstereo.config.files import check_known, read_mapping, table
from dstereo.config.merge import given, merge_layers
from dstereo.config.options import RECONSTRUCT
from dstereo.errors import DstereoError

# Project-folder files reconstruct reads its defaults from, tried in this order.
CONFIG_NAMES = ("dstereo.toml", "reconstruct.toml", "dstereo.json", "reconstruct.json")
_SGBM = "sgbm."


def _sgbm_name(key: str) -> str:
    from dstereo.config.sgbm import CV_NAMES

    return CV_NAMES.get(key, key).strip().lower().replace("-", "_")


def _depth_range(z_min, z_max, where: str) -> dict:
    if z_min is None and z_max is None:
        return {}
    if z_min is None or z_max is None:
        raise DstereoError(f"{where}: give both z_min and z_max (mm), or neither")
    return {"depth_range": (float(z_min), float(z_max))}


def mapping_layer(data: dict, where: str) -> dict:
    """Parameters from {'reconstruct': {...}, 'sgbm': {...}} (the TOML/JSON layout); 'preset' (in either table)
    picks the SGBM starting point, 'z_min'/'z_max' give the depth range in mm."""
    section, sgbm = dict(table(data, "reconstruct", where)), dict(table(data, "sgbm", where))
    declared = {key.split(".", 1)[1] for key in RECONSTRUCT.file_keys() if key.startswith("reconstruct.")}
    check_known(section, declared, where, "reconstruct")
    layer = {}
    preset = section.pop("preset", sgbm.pop("preset", None))
    if preset is not None:
        layer["preset"] = preset
    layer |= {_SGBM + _sgbm_name(k): v for k, v in sgbm.items()}
    layer |= _depth_range(section.pop("z_min", None), section.pop("z_max", None), where)
    if section.get("roi") is not None:
        section["roi"] = tuple(int(v) for v in section["roi"])
    if section.get("depth_range") is not None:
        section["depth_range"] = tuple(float(v) for v in section["depth_range"])
    return layer | section


def file_layer(path: str | Path) -> dict:
    """The parameters a TOML or JSON file gives (see `mapping_layer`), and the file as the layer's `source` (the
    messages of `check` name it and the key instead of the flag)."""
    return {**mapping_layer(read_mapping(path), str(path)), "source": str(path)}


def _origin(name: str, source: str | None) -> str | None:
    """Where parameter `name` of a layer came from: the file and its key; None for a flag (the messages name
    parameters in backticks, which the command line turns into its flags, reconstruct's or recession's)."""
    if not source:
        return None
    if name == "preset":
        return f"{source} [reconstruct] preset (or [sgbm] preset)"
    if name.startswith(_SGBM):
        return f"{source} [sgbm] {name[len(_SGBM):]}"
    return f"{source} [reconstruct] {'z_min/z_max' if name == 'depth_range' else name}"


def given_as(cfg, name: str, value) -> str:
    """`name` with `value` as the user gave it: "FILE [reconstruct] outlier_std = 0" for a file's value, else
    "`outlier_std` 0" (the flag, on the command line)."""
    origin = getattr(cfg, "_origins", {}).get(name)
    return f"{origin} = {value}" if origin else f"`{name}` {value}"


def _roi(text: str) -> tuple[int, int, int, int]:
    try:
        x, y, w, h = (int(v) for v in text.split(","))
    except ValueError:
        raise DstereoError(f"`roi` {text!r}: write x,y,w,h in pixels, e.g. `roi` 100,50,400,300") from None
    return (x, y, w, h)


def _disparity_sigma(text: str) -> dict:
    if text.strip().lower() == "auto":
        return {"disparity_sigma": "auto"}  # a value, not None (None is "not given" and would not override)
    try:
        sigma = float(text)
    except ValueError:
        raise DstereoError(f"`disparity_sigma` {text!r}: give a number of px (e.g. 0.2) or 'auto'") from None
    if not sigma >= 0:
        raise DstereoError(f"`disparity_sigma` {text}: must be >= 0 px")
    return {"disparity_sigma": sigma}


def flag_layer(values: dict) -> dict:
    """`values`: parameter -> the flag's raw value (None: not given). `sgbm` is the list of NAME=VALUE texts,
    `z_min`/`z_max` the depth range's ends, `roi` 'x,y,w,h', `disparity_sigma` a number or 'auto';
    `uncertainty` and `full_covariance` are the switches --no-uncertainty / --full-covariance (True: given)."""
    from dstereo.config.sgbm import parse_overrides

    raw = given(values)
    layer = {k: v for k, v in raw.items()
             if k not in ("sgbm", "z_min", "z_max", "roi", "disparity_sigma", "uncertainty", "full_covariance")}
    layer |= {_SGBM + _sgbm_name(k): v for k, v in parse_overrides(raw.get("sgbm") or []).items()}
    if raw.get("z_min") is not None or raw.get("z_max") is not None:
        if raw.get("z_min") is None or raw.get("z_max") is None:
            raise DstereoError("give both `z_min` and `z_max` (mm), or neither")
        layer["depth_range"] = (raw["z_min"], raw["z_max"])
    if "roi" in raw:
        layer["roi"] = _roi(raw["roi"])
    if "disparity_sigma" in raw:
        layer |= _disparity_sigma(raw["disparity_sigma"])
    layer |= {"uncertainty": False} if raw.get("uncertainty") else {}
    layer |= {"full_covariance": True} if raw.get("full_covariance") else {}
    return layer


def build(*layers: dict, sgbm_base=None):
    """ReconstructionConfig from layers, lowest first: defaults < project file < --config file < flags.
    `sgbm_base`: the SGBM parameters without a preset (default: the 'default' preset)."""
    from dataclasses import replace

    from dstereo.config.sgbm import PRESETS
    from dstereo.config.reconstruction_config import ReconstructionConfig

    origins: dict[str, str | None] = {}
    plain = []
    for layer in layers:
        source = layer.get("source")
        plain.append({k: v for k, v in layer.items() if k != "source"})
        origins |= {k: _origin(k, source) for k, v in plain[-1].items() if v is not None}
    merged = merge_layers(RECONSTRUCT, *plain)
    if isinstance(merged.get("disparity_sigma"), str) and merged["disparity_sigma"].strip().lower() == "auto":
        merged["disparity_sigma"] = None  # estimated from the images
    preset = merged.pop("preset", None)
    if preset is not None and preset not in PRESETS:
        where = f"{origins['preset']} = {preset!r}" if origins.get("preset") else f"`preset` {preset!r}"
        raise DstereoError(f"{where}: unknown SGBM preset; use one of {sorted(PRESETS)}")
    base = PRESETS[preset] if preset is not None else (sgbm_base or ReconstructionConfig().sgbm)
    overrides = {k[len(_SGBM):]: merged.pop(k) for k in list(merged) if k.startswith(_SGBM)}
    user = (("preset",) if preset is not None else ()) + tuple(overrides)
    cfg = replace(ReconstructionConfig(), sgbm=base.with_overrides(overrides), sgbm_user=user, **merged)
    try:  # where each value came from, for `check`'s messages: beside the fields (not one: results never show it)
        object.__setattr__(cfg, "_origins", origins)
    except (AttributeError, TypeError):  # a type with __slots__: the messages name the parameters, as before
        pass
    return cfg


def load_config(path: str | Path):
    """ReconstructionConfig from a TOML or JSON file over the defaults."""
    return build(file_layer(path))


def config_from_mapping(data: dict, where: str = "config"):
    """ReconstructionConfig from a parsed {'reconstruct': ..., 'sgbm': ...} mapping over the defaults."""
    return build(mapping_layer(data, where))


def project_file(project: str | Path) -> Path | None:
    """The project folder's reconstruction file (one of CONFIG_NAMES), else None."""
    from dstereo.config.files import find_in_folder

    return find_in_folder(project, CONFIG_NAMES)


# Parameters that must be positive when given (checked after files and flags are merged, so a file's value is held
# to the same rule as a flag's).
_POSITIVE = ("outlier_std", "max_jump", "fill_max_sigma", "focal_mm", "pixel_size_mm", "crop_factor", "focal_px", "baseline_mm")


def check(cfg, image_size: tuple[int, int] | None = None) -> None:
    """Refuse values no reconstruction can use (one line naming the parameter), before any work. With the
    images' (width, height), the SGBM settings the user named are checked against them too
    (`SGBMParams.check_image`)."""
    for name in _POSITIVE:
        value = getattr(cfg, name)
        if value is not None and not (math.isfinite(value) and value > 0):
            raise DstereoError(f"{given_as(cfg, name, value)}: must be a positive number")
    if cfg.outlier_neighbours < 0:
        raise DstereoError(f"{given_as(cfg, 'outlier_neighbours', cfg.outlier_neighbours)}: give a number of "
                           "neighbours >= 0 (0 turns it off)")
    if not (cfg.alpha == -1 or 0 <= cfg.alpha <= 1):
        raise DstereoError(f"{given_as(cfg, 'alpha', cfg.alpha)}: rectification's free scaling is -1 (OpenCV's "
                           "default) or 0..1")
    if cfg.matching_cost not in ("auto", "rank", "intensity"):
        raise DstereoError(f"{given_as(cfg, 'matching_cost', cfg.matching_cost)}: use auto, rank or intensity")
    if cfg.rectification not in ("auto", "pinhole", "spherical"):
        raise DstereoError(f"{given_as(cfg, 'rectification', cfg.rectification)}: use auto, pinhole or spherical")
    lr = cfg.sgbm.lr_check
    if lr is not None and not (math.isfinite(lr) and lr >= 0):
        raise DstereoError(f"{given_as(cfg, 'sgbm.lr_check', lr)}: the left-right tolerance is a distance in px, >= 0")
    if image_size is None:
        return
    from dstereo.config.reconstruction_config import user_sgbm_names

    image_width = image_size[0]
    # colour matching gives SGBM three channels (judged by the setting: a grey image is then checked as colour)
    cfg.sgbm.check_image(image_size, 3 if cfg.color_matching and cfg.matching_cost != "rank" else 1,
                         user_sgbm_names(cfg))
    lo, n = cfg.sgbm.min_disparity, cfg.sgbm.num_disparities
    if lo <= -image_width or lo + n > 2 * image_width:
        raise DstereoError(f"`sgbm` min_disparity={lo} with num_disparities={n} searches disparities "
                           f"{lo}..{lo + n - 1} px, far outside the {image_width} px wide image; set the range "
                           "from the scene's depth with `depth_range`")
