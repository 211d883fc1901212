"""A calibration configuration written as dstereo TOML (what `dstereo init` writes and a results folder keeps)."""

from __future__ import annotations


def _toml_str(value: str) -> str:
    return '"' + str(value).replace("\\", "\\\\").replace('"', '\\"') + '"'


def _toml_list(values) -> str:
    return "[" + ", ".join(_toml_str(v) if isinstance(v, str) else f"{v!r}" for v in values) + "]"


def to_toml(cfg, comments: bool = True) -> str:
    """`cfg` (a calibration Config) as dstereo TOML (what `dstereo init` writes and the results folder keeps)."""
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
    if not cfg.board_sag:
        out.append("board_sag = false" + c("a flat board (default true: the board's sag x, y is solved)"))
    if cfg.mrcal_convert:
        out.append("mrcal_convert = true" + c("a lens mrcal has no twin for: also the nearest mrcal model"))
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

