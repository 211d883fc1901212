"""Every option of calibrate, reconstruct and optics, declared once: the parameter it sets, its file key, its flag.

A row's `name` is the parameter (a field of the command's configuration type, or a run setting of the command);
its default is that field's default, read from the type itself so it is written in one place only. `file` is the
dotted TOML key (`table.key`; several keys for a parameter read from more than one), `flag` the command-line
flag. Library errors name parameters in backticks (`square`); the CLI turns them into flags with these tables
(`dstereo.config.messages`). Only the standard library is imported: `dstereo --help` reads these tables.
"""

from __future__ import annotations

from dataclasses import MISSING, dataclass, fields
from typing import Any


@dataclass(frozen=True)
class Option:
    """One option: parameter `name`, its TOML key(s) `file` (None: flag only), its `flag` (None: file only)."""

    name: str
    file: tuple[str, ...] = ()
    flag: str | None = None
    help: str = ""
    type: type = str  # the flag's value type (typer parses it); bool flags are switches
    replaces: tuple[str, ...] = ()  # parameters a value given here drops from the lower layers
    in_config: bool = True  # False: a run setting of the command, not a field of its configuration type


@dataclass(frozen=True)
class OptionTable:
    """One command's options; its settings type (a dataclass, e.g. `config.calibration.Config`) holds the
    defaults of the `in_config` ones."""

    command: str
    options: tuple[Option, ...]

    def __getitem__(self, name: str) -> Option:
        for option in self.options:
            if option.name == name:
                return option
        raise KeyError(f"{self.command} has no option {name!r}")

    def names(self) -> tuple[str, ...]:
        return tuple(o.name for o in self.options)

    def flags(self) -> dict[str, str]:
        """parameter -> flag, for every option that has a flag."""
        return {o.name: o.flag for o in self.options if o.flag is not None}

    def file_keys(self) -> dict[str, str]:
        """dotted file key -> parameter."""
        return {key: o.name for o in self.options for key in o.file}

    def defaults(self, kind: type) -> dict[str, Any]:
        """parameter -> default, from the fields of the settings dataclass `kind`."""
        out = {}
        for f in fields(kind):
            if f.default is not MISSING:
                out[f.name] = f.default
            elif f.default_factory is not MISSING:
                out[f.name] = f.default_factory()
        return {o.name: out[o.name] for o in self.options if o.in_config and o.name in out}

    def option(self, name: str, default: Any = None):
        """The typer option of parameter `name`: its flag and help from the table (default None: not given)."""
        import typer

        row = self[name]
        return typer.Option(default, row.flag, help=row.help)


def _opt(name, file=(), flag=None, help="", type=str, replaces=(), in_config=True) -> Option:
    return Option(name, (file,) if isinstance(file, str) else tuple(file), flag, help, type, replaces, in_config)


CALIBRATE = OptionTable("calibrate", (
    _opt("mode", "mode"),
    _opt("pattern", ("pattern.columns", "pattern.rows"), "--pattern", "Inner corners COLSxROWS, e.g. 9x6."),
    _opt("square", "pattern.square", "--square", "Square size of the board.", float),
    _opt("unit", "pattern.unit", "--unit", "Unit of the square size, a length: um, mm, cm, dm, m, in, ft (mm when "
         "--square is given; without it the board's squares). Written into every calibration file; reconstruct "
         "converts it to mm."),
    _opt("images", "images.folder", "--images", "Image folder (default PROJECT/images)."),
    _opt("image_format", "images.format", "--format", "Image file extension, e.g. jpg."),
    _opt("image_format_left", "images.format_left"),
    _opt("image_format_right", "images.format_right"),
    _opt("glob", "images.glob", "--glob", "Only images whose name matches, e.g. 'left*.jpg'."),
    _opt("model", "calibration.model", "--model"),
    _opt("model_right", "calibration.model_right", "--model-right",
         "Stereo: the right camera's lens model when it differs from the left's --model (e.g. fisheye); "
         "default: --model for both."),
    _opt("per_set", "calibration.per_set", "--per-set", type=int),
    _opt("max_subsets", "calibration.max_subsets", "--max-subsets", type=int),
    _opt("seed", "calibration.seed", "--seed", type=int),
    _opt("min_subsets", "calibration.min_subsets", "--min-subsets", type=int),
    _opt("final", "calibration.final", "--final"),
    _opt("outlier_rejection", "calibration.outlier_rejection", "--no-outlier-rejection", type=bool),
    _opt("board_sag", "calibration.board_sag", "--board-sag/--no-board-sag", type=bool),
    _opt("mrcal_convert", "calibration.mrcal_convert", "--mrcal-convert",
         "A lens mrcal has no twin for (fisheye, splined): also write the nearest mrcal model "
         "(camera.mrcal-opencv8.cameramodel), with its fit error.", bool),
    _opt("steps", "steps", "--step", type=list),
    _opt("stereo_steps", "stereo.steps", "--step", type=list),
    # run settings: flags of the command, not fields of Config
    _opt("config", (), "--config", in_config=False),
    _opt("out", (), "--out", in_config=False),
    _opt("force", (), "--force", type=bool, in_config=False),
    _opt("left", (), "--left", in_config=False),
    _opt("right", (), "--right", in_config=False),
    _opt("projection_range", (), "--projection-range", type=float, in_config=False),
    _opt("projection_method", (), "--projection-method", in_config=False),
    _opt("cross_validate", (), "--cross-validate", type=int, in_config=False),
    _opt("cameras", (), "--cameras", in_config=False),
    _opt("pair", (), "--pair", in_config=False),
    _opt("workers", (), "--workers", "Subsets: solve their blocks on a local Dask cluster of this many processes (one "
         "core each; default and 1: here, in this process; at most 4 x the cores). The results are the same.", int,
         in_config=False),
    _opt("scheduler", (), "--scheduler", "Subsets: solve their blocks on the workers of a running Dask scheduler "
         "(tcp://host:8786); they need dstereo installed.", in_config=False),
    _opt("resume", (), "--resume", "Subsets: continue an interrupted run of more than 20000 subsets from the blocks "
         "kept in OUT.partial (same inputs and options required).", bool, in_config=False),
))

RECONSTRUCT = OptionTable("reconstruct", (
    _opt("preset", ("reconstruct.preset", "sgbm.preset"), "--preset",
         "SGBM preset: default, thesis-5.9, thesis-5.15.", replaces=("sgbm.",), in_config=False),
    _opt("sgbm", "sgbm.*", "--sgbm", "SGBM parameter NAME=VALUE (repeat), e.g. block_size=7.", list),
    _opt("depth_range", "reconstruct.depth_range", "--z-min/--z-max"),
    _opt("z_min", "reconstruct.z_min", "--z-min", "Nearest depth of the scene, mm (sets the range).", float,
         in_config=False),  # z_min and z_max set depth_range
    _opt("z_max", "reconstruct.z_max", "--z-max", "Farthest depth of the scene, mm.", float, in_config=False),
    _opt("alpha", "reconstruct.alpha", "--alpha", "Rectification free scaling: -1 default, 0..1 (a rig with a "
         "fisheye: cv2.fisheye's balance, 0 by default; a spherical rectification: 0 the field both cameras see, "
         "1 the field either sees).", float),
    _opt("rectification", "reconstruct.rectification", "--rectification",
         "Rectified images: auto (pinhole where the field fits one, within 75 deg of the axis; else spherical), "
         "pinhole, or spherical (rows: planes through the baseline, columns: the angle within them; for fields "
         "wider than a pinhole image holds).", str),
    _opt("zero_disparity", "reconstruct.zero_disparity", "--zero-disparity/--own-centres",
         "Share one principal point (OpenCV's default) or centre each view.", bool),
    _opt("sgbm.lr_check", "sgbm.lr_check", "--lr-check", "Left-right consistency tolerance, px.", float,
         in_config=False),
    _opt("roi", "reconstruct.roi", "--roi", "x,y,w,h on the rectified left image: keep points inside."),
    _opt("outlier_neighbours", "reconstruct.outlier_neighbours", "--outliers",
         "Statistical outlier removal: neighbours (0 off).", int),
    _opt("outlier_std", "reconstruct.outlier_std", "--outlier-std", "Outlier threshold in std devs.", float),
    _opt("max_jump", "reconstruct.max_jump", "--max-jump", "Relative depth step that breaks the mesh.", float),
    _opt("refine", "reconstruct.refine", "--refine/--no-refine",
         "Refine SGBM's pixel-locked sub-pixel disparity (cubic re-rectification + Lucas-Kanade); pixels it cannot "
         "refine are dropped. Default off: it helps on well-textured, smooth surfaces (speckle), not on scenes "
         "with many slanted or occluding edges.", bool),
    _opt("undistort", "reconstruct.undistort"),
    _opt("color_matching", "reconstruct.color_matching", type=bool),
    _opt("matching_cost", "reconstruct.matching_cost", "--cost",
         "SGBM's cost: auto (default: rank where the two views' grey levels differ, as lit or exposed "
         "differently, else intensity checked by the rank cost, regions where the two mostly disagree dropped, "
         "and where that map is under 80 % dense (over the pixels whose block is not blank) the rank cost with the "
         "fill tried and kept if denser with fills that hold (summary.json density_check); said with its figures "
         "in summary.json search_range.matching_cost), rank (SGBM on each view's 7x7 rank "
         "transform, which survives a brightness or contrast change) or intensity (the grey levels unchecked, "
         "the matching before issue 30)."),
    _opt("fill", "reconstruct.fill", "--fill/--no-fill",
         "Fill unmatched pixels by an edge-aware plane fit where confident (default: auto, the rank cost's maps "
         "only, including the one the density check keeps for a sparse grey-level map; said in summary.json "
         "fill.why): filled points carry their own, larger sigma and the flag "
         "`filled` (filled.npy, points.ply); --fill always, --no-fill never.",
         bool),
    _opt("fill_max_sigma", "reconstruct.fill_max_sigma", "--fill-max-sigma",
         "Largest fill sigma, px, for a pixel to be filled [0.7].", float),
    _opt("focal_mm", "reconstruct.focal_mm", "--focal-mm", "Uncalibrated: lens focal length, mm.", float),
    _opt("pixel_size_mm", "reconstruct.pixel_size_mm", "--pixel-size-mm", "Uncalibrated: pixel pitch, mm.", float),
    _opt("crop_factor", "reconstruct.crop_factor", "--crop-factor", "Uncalibrated: crop factor (36 mm).", float),
    _opt("focal_px", "reconstruct.focal_px", "--focal-px", "Uncalibrated: focal length in px.", float),
    _opt("baseline_mm", "reconstruct.baseline_mm", "--baseline-mm",
         "Uncalibrated: baseline, mm (without it the output is unscaled).", float),
    _opt("ratio", "reconstruct.ratio", type=float),
    _opt("f_threshold", "reconstruct.f_threshold", type=float),
    _opt("uncertainty", "reconstruct.uncertainty", "--no-uncertainty", "Skip the point uncertainties (sigma_*).",
         bool),
    _opt("disparity_sigma", "reconstruct.disparity_sigma", "--disparity-sigma",
         "Disparity noise in rectified px for the point uncertainties, or 'auto' (default: per pixel from the "
         "image gradients and the image noise, checked on smooth parts of the map)."),
    _opt("full_covariance", "reconstruct.full_covariance", "--full-covariance",
         "Also write cov_xyz.npy, the (h, w, 3, 3) covariance of every point.", bool),
    # run settings
    _opt("left", (), "--left", "Left image (repeat for several pairs).", list, in_config=False),
    _opt("right", (), "--right", "Right image, in the same order as --left.", list, in_config=False),
    _opt("out", (), "--out", "Results folder (refused if it exists, unless --force).", in_config=False),
    _opt("calib", (), "--calib", "stereo.yml, OpenCV YAML with M1 D1 M2 D2 R T, or Middlebury calib.txt. Without "
         "it the uncalibrated path runs (needs --focal-mm or --focal-px).", in_config=False),
    _opt("project", (), "--project", "Project folder: its stereo.yml/calib.txt and dstereo.toml are used as "
         "defaults.", in_config=False),
    _opt("config", (), "--config", "TOML/JSON file with [reconstruct] and [sgbm].", in_config=False),
    _opt("workers", (), "--workers", "Several pairs: in parallel on a local Dask cluster of this many processes "
         "(default: the machine's cores when the pairs, timed on the first, would take over ~30 s serially; else "
         "one after another here; 1: always one after another in this process; at most 4 x the cores).", int,
         in_config=False),
    _opt("scheduler", (), "--scheduler", "Several pairs: address of a running Dask scheduler (tcp://host:8786); its "
         "workers need dstereo, the images at the same paths and OUT's parent folder shared.", in_config=False),
    _opt("resume", (), "--resume", "Several pairs: continue from the pairs kept in OUT.partial.", bool,
         in_config=False),
    _opt("retries", (), "--retries", "Reruns of a pair whose worker process died, then it fails.", int,
         in_config=False),
    _opt("force", (), "--force", "Replace an existing results folder.", bool, in_config=False),
))

OPTICS = OptionTable("optics", (
    _opt("focus_distance", "optics.focus_distance", "--focus-distance", "Distance to the subject, mm.", float),
    _opt("focal_length", "optics.focal_length", "--focal-length", "Lens focal length, mm.", float),
    _opt("sensor", "optics.sensor", "--sensor", "Sensor WIDTHxHEIGHT in mm, e.g. 22.5x16.9.",
         replaces=("crop_factor",)),
    _opt("crop_factor", "optics.crop_factor", "--crop-factor", "Crop factor (instead of --sensor).", float,
         replaces=("sensor",)),
    _opt("f_number", "optics.f_number", "--f-number", "Aperture f-number N.", float),
    _opt("coc", "optics.coc", "--coc", "Circle of confusion, mm [from the sensor diagonal].", float),
    _opt("pixel_size", "optics.pixel_size", "--pixel-size", "Pixel pitch, mm.", float),
    _opt("wavelength", "optics.wavelength", "--wavelength", "Light wavelength, mm [0.00055].", float),
    _opt("baseline", "optics.baseline", "--baseline", "Stereo baseline, mm.", float),
    _opt("disparity_precision", "optics.disparity_precision", "--disparity-precision",
         "Matcher sub-pixel precision, px [1].", float),
    _opt("dof_focal_length", "optics.dof_focal_length", "--dof-focal-length",
         "Focal length in the DoF equations: effective (thesis) or lens [effective]."),
    _opt("config", (), "--config", "TOML file with an [optics] section; flags override.", in_config=False),
    _opt("plots", (), "--plots", "Write the three DoF figures (PNG) and report.md, report.html to this folder.", in_config=False),
))

# Flags of the commands without a table of their own (recession shares reconstruct's matching options).
RUN_FLAGS = {
    "recession": {"fps": "--fps", "timestamps": "--timestamps", "grid": "--grid", "axis": "--axis",
                  "point": "--point", "stagnation_radius": "--stagnation-radius", "min_points": "--min-points",
                  "workers": "--workers", "scheduler": "--scheduler", "resume": "--resume", "force": "--force",
                  "out": "--out", "calib": "--calib", "left": "--left", "right": "--right"},
    "refine": {"board": "--board", "square": "--square", "out": "--out", "force": "--force", "calib": "--calib",
               "left": "--left", "right": "--right", "depth_range": "--z-min/--z-max", "z_min": "--z-min",
               "z_max": "--z-max"},
    "demo": {"out": "--out", "force": "--force"},
    "diff": {"out": "--out", "force": "--force", "distance": "--distance", "grid": "--grid"},
}

TABLES = {t.command: t for t in (CALIBRATE, RECONSTRUCT, OPTICS)}


def flags_of(command: str | None) -> dict[str, str]:
    """parameter -> flag for `command` (empty for a command that has none)."""
    if command in TABLES:
        return TABLES[command].flags()
    out = dict(RUN_FLAGS.get(command, {}))
    if command == "recession":  # its matching options are reconstruct's
        out = {**{k: v for k, v in RECONSTRUCT.flags().items()}, **out}
    return out
