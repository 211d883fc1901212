"""`dstereo calibrate`'s flags as a layer of calibration parameters (only the flags given)."""

from __future__ import annotations

from dstereo.config.merge import given
from dstereo.config.steps import parse_step_flags
from dstereo.config.values import model_layer, right_model


def flag_layer(values: dict) -> dict:
    """`values`: parameter -> the flag's raw value (None: not given; `steps`: the list of --step texts;
    `outlier_rejection`: True when --no-outlier-rejection was given). Returns the parameters they set."""
    raw = given(values)
    layer = {k: v for k, v in raw.items()
             if k not in ("pattern", "model", "model_right", "steps", "outlier_rejection", "images", "board_sag",
                          "mrcal_convert")}
    if raw.get("mrcal_convert"):  # --mrcal-convert (False: not given)
        layer["mrcal_convert"] = True
    if "board_sag" in raw:  # --board-sag / --no-board-sag (None: not given)
        layer["board_sag"] = bool(raw["board_sag"])
    if "pattern" in raw:
        from dstereo.config.values import parse_pattern

        layer["pattern"] = parse_pattern(raw["pattern"])
    if "images" in raw:
        layer["images"] = str(raw["images"])
    if "model" in raw:
        layer |= model_layer(raw["model"], "`model`")
    if "model_right" in raw:
        layer["model_right"] = right_model(raw["model_right"], "`model_right`")
    if raw.get("outlier_rejection"):
        layer["outlier_rejection"] = False
    mono, stereo = parse_step_flags(list(raw.get("steps") or []))
    layer |= given({"steps": mono, "stereo_steps": stereo})
    return layer
