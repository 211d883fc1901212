"""Configuration: the thesis's initialisation files (Figures 5.5, 5.14) and dstereo's TOML load to one Config."""

from dataclasses import replace
from pathlib import Path

import pytest

from dstereo.config.calibration import (Config, Step, config_from_thesis_ini, config_from_toml, find_project_config,
                            load_config, parse_step_flag, template, to_toml, validate)
from dstereo.errors import DstereoError

SEED = Path(__file__).resolve().parents[2].parent / "shared" / "seed"
FIGURE_5_5_STEPS = (
    Step(("re",), (0.5,)), Step(("p1", "p2"), (1.5, 1.5)), Step(("k1", "k2", "k3"), (1.5, 1.5, 1.5)),
    Step(("fx", "fy", "cx", "cy"), (1.0, 1.0, 1.0, 1.0)),
)


def _seed(name: str) -> Path:
    from conftest import require_seed

    return require_seed(name)


def test_figure_5_5_file_loads_as_written():
    cfg = load_config(_seed("init-individual.ini"))
    assert cfg.mode == "individual"
    assert cfg.pattern == (9, 6)  # mesh width x mesh height = inner corners
    assert cfg.square == 10.0 and cfg.unit == "mm"
    assert cfg.image_format == "jpg"
    assert cfg.per_set == 10
    assert cfg.model == ("k1", "k2", "p1", "p2", "k3")  # 'k1, k2, k3, p1, p2' in OpenCV order
    assert cfg.steps == FIGURE_5_5_STEPS
    assert cfg.stereo_steps == ()
    assert cfg.warnings == ()
    assert validate(cfg) is cfg


def test_figure_5_14_file_keeps_stereo_steps_apart():
    cfg = load_config(_seed("init-stereo.ini"))
    assert cfg.mode == "stereo"
    assert cfg.steps == ()
    assert cfg.stereo_steps == (Step(("stereo_re",), (3.0,)), Step(("Tnorm",), (0.75,)), Step(("RVnorm",), (0.75,)))
    assert (cfg.image_format_left, cfg.image_format_right) == ("jpg", "jpg")


def test_template_toml_is_figure_5_5():
    ini = load_config(_seed("init-individual.ini"))
    toml = config_from_toml(to_toml(template()), "template")
    stereo = load_config(_seed("init-stereo.ini")).stereo_steps  # the template carries Figure 5.14's stereo steps
    assert toml == replace(ini, image_format_left=None, image_format_right=None, stereo_steps=stereo)


@pytest.mark.parametrize("cfg", [
    template(),
    Config(pattern=(7, 5), square=2.5, unit="cm", glob="left*.png", model=("k1", "k2"), per_set=6, max_subsets=50,
           seed=3, min_subsets=12, steps=(Step(("re", "fx"), (0.4, 2.0), min_subsets=20),),
           stereo_steps=(Step(("Tnorm", "RVx"), (0.75, 1.0)),)),
    Config(pattern=(4, 3)),
])
def test_toml_round_trip(cfg):
    for comments in (True, False):
        assert config_from_toml(to_toml(cfg, comments), "x") == cfg


def test_thesis_syntax_variants():
    text = """
# a comment line
[ Calibration ]
Individual calibration = 1   # trailing comment
image format = "PNG"
Square Size = 2.5 # in mm
mesh   width = 7
mesh height = 5,
images per set = 4,
camera matrix parameters = FX, fy, cx, CY,
distortion coefficients parameters = K1, k2,
[ Optimization ]
[[ Calibration steps ]]
number steps = 2
minimum subsets = 5
[[[ step 2 ]]]
    parameters = FX, fy,   # focal lengths
    max error = 1, 2.5,
[[[ step 1 ]]]
    parameters = RE
    max error = 0.8
    minimum subsets = 3
[ Disparity ]
block size = 5
"""
    cfg = config_from_thesis_ini(text, "t.ini")
    assert cfg.pattern == (7, 5) and cfg.square == 2.5 and cfg.image_format == "png" and cfg.per_set == 4
    assert cfg.model == ("k1", "k2")
    assert cfg.min_subsets == 5
    assert cfg.steps == (Step(("re",), (0.8,), 3), Step(("fx", "fy"), (1.0, 2.5)))
    assert len(cfg.warnings) == 1 and "block size" in cfg.warnings[0]  # other applications' sections: ignored


def _ini(steps: str, calibration: str = "mesh width = 9\nmesh height = 6\nimages per set = 10\n") -> str:
    return (f"[ Calibration ]\nIndividual calibration = 1\n{calibration}"
            f"[ Optimization ]\n[[ Calibration steps ]]\n{steps}")


@pytest.mark.parametrize("steps, message", [
    ("number steps = 1\n[[[ step 1 ]]]\nparameters = fz,\nmax error = 1,\n", "unknown parameter 'fz'"),
    ("number steps = 1\n[[[ step 1 ]]]\nparameters = fx,\nmax error = -1,\n", "must be a positive number"),
    ("number steps = 1\n[[[ step 1 ]]]\nparameters = fx,\nmax error = 0,\n", "must be a positive number"),
    ("number steps = 1\n[[[ step 1 ]]]\nparameters = fx,\nmax error = big,\n", "is not a number"),
    ("number steps = 1\n[[[ step 1 ]]]\nparameters = fx, fy\n", "max error is missing"),
    ("number steps = 1\n[[[ step 1 ]]]\nparameters = fx, fy\nmax error = 1,\n",
     "2 parameter(s) (fx, fy) but 1 max error"),
    ("number steps = 1\n[[[ step 1 ]]]\nmax error = 1,\n", "no parameters"),
    ("number steps = 1\n[[[ step 1 ]]]\nparameters = fx, fx\nmax error = 1, 1\n", "listed twice"),
    ("number steps = 2\n[[[ step 1 ]]]\nparameters = fx\nmax error = 1\n", "number steps = 2 but"),
    ("[[[ step 2 ]]]\nparameters = fx\nmax error = 1\n", "numbered [2]"),
    ("number steps = 1\n[[[ step 1 ]]]\nparameters = fx\nmax error = 1\nalpha = 3\n", "unknown key 'alpha'"),
])
def test_bad_steps_name_the_problem(steps, message):
    with pytest.raises(DstereoError) as exc:
        config_from_thesis_ini(_ini(steps), "bad.ini")
    assert message in str(exc.value) and "bad.ini" in str(exc.value)
    assert "\n" not in str(exc.value)


@pytest.mark.parametrize("calibration, message", [
    ("mesh wdth = 9\n", "unknown key 'mesh wdth'"),
    ("mesh width = 9\n", "both mesh width and mesh height"),
    ("Stereo calibration = 1\n", "both Individual calibration and Stereo calibration are 1"),
    ("camera matrix parameters = fx, fy\n", "always solves fx, fy, cx, cy"),
    ("distortion coefficients parameters = k1, q2\n", "unknown distortion coefficient"),
    ("images per set = 2\n", "m >= 3"),
    ("square size = ten\n", "is not a valid value"),
])
def test_bad_calibration_section(calibration, message):
    with pytest.raises(DstereoError, match=message.replace("(", r"\(")):
        config_from_thesis_ini(_ini("", calibration), "b.ini")


def test_toml_errors():
    base = "[pattern]\ncolumns = 9\nrows = 6\n[calibration]\nper_set = 10\n"
    cases = {
        base + "[[steps]]\nparameters = ['fx', 'k9']\nmax_error = [1, 1]\n": "unknown parameter 'k9'",
        base + "[[steps]]\nparameters = ['fx']\nmax_error = [-0.5]\n": "must be a positive number",
        base + "[[steps]]\nparameters = ['fx', 'fy']\nmax_error = [1]\n": "but 1 max error",
        base + "[[steps]]\nparameters = ['fx']\n": "max error is missing",
        base + "[[steps]]\nparameters = ['fx']\nmax_error = [1]\nmax = 2\n": "unknown key(s) ['max']",
        base + "[images]\nfolde = 'x'\n": "unknown key(s) ['folde'] in [images]",
        base + "[patern]\n": "unknown key or table 'patern'",
        "[pattern]\ncolumns = 9\n": "needs both columns and rows",
        "[calibration]\nper_set = 2\n": "per_set",
        "[calibration]\nmodel = 'k1,k7'\n": "unknown distortion coefficient",
        "x = [": "not valid TOML",
    }
    for text, message in cases.items():
        with pytest.raises(DstereoError) as exc:
            config_from_toml(text, "c.toml")
        assert message in str(exc.value), (text, str(exc.value))


def test_toml_ignores_other_commands_tables():
    cfg = config_from_toml("[pattern]\ncolumns = 9\nrows = 6\n[reconstruct]\nalpha = 0\n[sgbm]\nblock_size = 5\n", "d")
    assert cfg.pattern == (9, 6)


def test_validate_cross_checks():
    with pytest.raises(DstereoError, match="no board pattern"):
        validate(Config())
    with pytest.raises(DstereoError, match="need subsets"):
        validate(Config(pattern=(9, 6), steps=(Step(("fx",), (1.0,)),)))
    with pytest.raises(DstereoError, match="step 1 filters k3 but the distortion model"):
        validate(Config(pattern=(9, 6), per_set=5, model=("k1", "k2"), steps=(Step(("k3",), (1.0,)),)))
    with pytest.raises(DstereoError, match="square size"):
        validate(Config(pattern=(9, 6), square=-1.0))


def test_step_flags():
    assert parse_step_flag("re=0.5", 1) == Step(("re",), (0.5,))
    assert parse_step_flag("P1=1.5, p2=1.5", 2) == Step(("p1", "p2"), (1.5, 1.5))
    with pytest.raises(DstereoError, match="NAME=MAX_ERROR"):
        parse_step_flag("fx,fy=1", 1)
    with pytest.raises(DstereoError, match="unknown parameter 'tx'"):
        parse_step_flag("tx=1", 1)  # stereo names are not mono step parameters


def test_project_config_discovery(tmp_path):
    assert find_project_config(tmp_path) is None
    (tmp_path / "my.ini").write_text("[ Calibration ]\n")
    assert find_project_config(tmp_path) == tmp_path / "my.ini"
    (tmp_path / "other.toml").write_text("")
    with pytest.raises(DstereoError, match="several configuration files"):
        find_project_config(tmp_path)
    (tmp_path / "dstereo.toml").write_text("")
    assert find_project_config(tmp_path) == tmp_path / "dstereo.toml"
    with pytest.raises(DstereoError, match="does not exist"):
        find_project_config(tmp_path / "nope")
    with pytest.raises(DstereoError, match="does not exist"):
        load_config(tmp_path / "nope.toml")


# --- one configuration system: the option tables, the merge rule, the flags -----------------------------------------
# Each command's configuration is captured where the command hands it on (validate / check / compute_optics), so
# these tests run the real plumbing from argv to the parameter without calibrating or matching anything.

import numpy as np  # noqa: E402

from conftest import run_cli  # noqa: E402
from dstereo.config import CALIBRATE, OPTICS, RECONSTRUCT, merge, merge_layers, with_flags  # noqa: E402
from dstereo.config.options import Option, OptionTable  # noqa: E402


class _Captured(Exception):
    def __init__(self, value):
        super().__init__("captured")
        self.value = value


def _capture(monkeypatch, target: str):
    def grab(value, *_, **__):
        raise _Captured(value)

    monkeypatch.setattr(target, grab)


def _run_captured(*args):
    from dstereo.cli import app

    try:
        app([str(a) for a in args], standalone_mode=False)
    except _Captured as captured:
        return captured.value
    raise AssertionError(f"the command finished without reaching the capture point: {args}")


def _calibrate_cfg(monkeypatch, tmp_path, toml: str | None, *flags):
    _capture(monkeypatch, "dstereo.config.calibration.validate")
    args = ["calibrate", *flags]
    if toml is not None:
        (tmp_path / "c.toml").write_text(toml)
        args += ["--config", tmp_path / "c.toml"]
    return _run_captured(*args)


def _pair(tmp_path):
    import cv2

    paths = []
    for name, seed in (("left0.png", 1), ("right0.png", 2)):
        cv2.imwrite(str(tmp_path / name), np.random.default_rng(seed).integers(0, 255, (48, 64), dtype=np.uint8))
        paths.append(tmp_path / name)
    return paths


def _reconstruct_cfg(monkeypatch, tmp_path, toml: str | None, *flags):
    _capture(monkeypatch, "dstereo.config.reconstruction.check")
    left, right = _pair(tmp_path)
    args = ["reconstruct", "--left", left, "--right", right, "--out", tmp_path / "out", *flags]
    if toml is not None:
        (tmp_path / "r.toml").write_text(toml)
        args += ["--config", tmp_path / "r.toml"]
    return _run_captured(*args)


OPTICS_BASE = {"focus_distance": "1000", "focal_length": "50", "sensor": "22.5x16.9", "f_number": "16"}


def _optics_cfg(monkeypatch, tmp_path, toml: str | None, *flags, base=OPTICS_BASE):
    _capture(monkeypatch, "dstereo.optics.calculator.compute_optics")
    args = ["optics", *flags]
    for name, value in base.items():
        args += [OPTICS[name].flag, value]
    if toml is not None:
        (tmp_path / "o.toml").write_text(toml)
        args += ["--config", tmp_path / "o.toml"]
    return _run_captured(*args)


def test_calibrate_precedence_default_file_flag(monkeypatch, tmp_path):
    assert _calibrate_cfg(monkeypatch, tmp_path, None).seed == Config().seed == 0
    assert _calibrate_cfg(monkeypatch, tmp_path, "[calibration]\nseed = 5\n").seed == 5
    assert _calibrate_cfg(monkeypatch, tmp_path, "[calibration]\nseed = 5\n", "--seed", "9").seed == 9
    # a key the flags leave alone keeps the file's value while another is overridden
    both = _calibrate_cfg(monkeypatch, tmp_path, "[calibration]\nseed = 5\nmax_subsets = 40\n", "--seed", "9")
    assert (both.seed, both.max_subsets) == (9, 40)


def test_calibrate_unit_follows_a_square_given_anywhere(monkeypatch, tmp_path):
    assert _calibrate_cfg(monkeypatch, tmp_path, None).unit == "squares"
    assert _calibrate_cfg(monkeypatch, tmp_path, None, "--square", "2").unit == "mm"
    assert _calibrate_cfg(monkeypatch, tmp_path, "[pattern]\nsquare = 2\n").unit == "mm"
    assert _calibrate_cfg(monkeypatch, tmp_path, '[pattern]\nunit = "in"\n', "--square", "2").unit == "in"


def test_reconstruct_precedence_default_project_file_config_flag(monkeypatch, tmp_path):
    from dstereo.stereo.reconstruct import ReconstructionConfig

    assert _reconstruct_cfg(monkeypatch, tmp_path, None).max_jump == ReconstructionConfig().max_jump
    assert _reconstruct_cfg(monkeypatch, tmp_path, "[reconstruct]\nmax_jump = 0.2\n").max_jump == 0.2
    assert _reconstruct_cfg(monkeypatch, tmp_path, "[reconstruct]\nmax_jump = 0.2\n", "--max-jump",
                            "0.3").max_jump == 0.3
    project = tmp_path / "project"
    project.mkdir()
    (project / "dstereo.toml").write_text("[reconstruct]\nmax_jump = 0.1\nalpha = 0.5\n")
    layered = _reconstruct_cfg(monkeypatch, tmp_path, "[reconstruct]\nmax_jump = 0.2\n", "--project", project)
    assert (layered.max_jump, layered.alpha) == (0.2, 0.5)  # --config over the project's file, key by key


def test_reconstruct_sgbm_fields_merge_per_key_and_a_preset_replaces_them(monkeypatch, tmp_path):
    from dstereo.stereo.disparity import PRESETS

    toml = "[sgbm]\nblock_size = 7\n"
    cfg = _reconstruct_cfg(monkeypatch, tmp_path, toml, "--sgbm", "uniqueness_ratio=5")
    assert (cfg.sgbm.block_size, cfg.sgbm.uniqueness_ratio) == (7, 5)  # the file's field and the flag's
    assert set(cfg.sgbm_user) == {"block_size", "uniqueness_ratio"}
    cfg = _reconstruct_cfg(monkeypatch, tmp_path, toml, "--preset", "thesis-5.15")
    assert cfg.sgbm == PRESETS["thesis-5.15"] and cfg.sgbm_user == ("preset",)  # the flag's preset sets them all


def test_optics_precedence_default_file_flag(monkeypatch, tmp_path):
    from dstereo.optics.calculator import DEFAULT_WAVELENGTH_MM

    assert _optics_cfg(monkeypatch, tmp_path, None).wavelength == DEFAULT_WAVELENGTH_MM
    assert _optics_cfg(monkeypatch, tmp_path, "[optics]\nwavelength = 0.0006\n").wavelength == 0.0006
    assert _optics_cfg(monkeypatch, tmp_path, "[optics]\nwavelength = 0.0006\n", "--wavelength",
                       "0.0007").wavelength == 0.0007


def test_optics_sensor_and_crop_factor_replace_each_other_across_layers(monkeypatch, tmp_path):
    base = {k: v for k, v in OPTICS_BASE.items() if k != "sensor"}
    cfg = _optics_cfg(monkeypatch, tmp_path, '[optics]\nsensor = "22.5x16.9"\n', "--crop-factor", "1.5", base=base)
    assert (cfg.sensor, cfg.crop_factor) == (None, 1.5)
    cfg = _optics_cfg(monkeypatch, tmp_path, "[optics]\ncrop_factor = 1.5\n", "--sensor", "20x10", base=base)
    assert (cfg.sensor, cfg.crop_factor) == ((20.0, 10.0), None)


# One case per declared option: (file text, flags, how to read the parameter, the value both must give). Every
# option of a table must have a case (test_every_option_has_a_case), so a new option comes with its check.
def _attr(path):
    def read(cfg):
        for part in path.split("."):
            cfg = getattr(cfg, part)
        return cfg
    return read


CALIBRATE_CASES = {
    "mode": ('mode = "stereo"\n', None, "mode", "stereo"),
    "pattern": ("[pattern]\ncolumns = 7\nrows = 5\n", ["--pattern", "7x5"], "pattern", (7, 5)),
    "square": ("[pattern]\nsquare = 2.5\n", ["--square", "2.5"], "square", 2.5),
    "unit": ('[pattern]\nunit = "cm"\n', ["--unit", "cm"], "unit", "cm"),
    "images": ('[images]\nfolder = "pics"\n', ["--images", "pics"], "images", "pics"),
    "image_format": ('[images]\nformat = "png"\n', ["--format", "png"], "image_format", "png"),
    "image_format_left": ('[images]\nformat_left = "png"\n', None, "image_format_left", "png"),
    "image_format_right": ('[images]\nformat_right = "tif"\n', None, "image_format_right", "tif"),
    "glob": ('[images]\nglob = "a*.png"\n', ["--glob", "a*.png"], "glob", "a*.png"),
    "model": ('[calibration]\nmodel = "k1k2"\n', ["--model", "k1k2"], "model", ("k1", "k2")),
    "model_right": ('[calibration]\nmodel_right = "fisheye"\n', ["--model-right", "fisheye"], "model_right",
                    ("fk1", "fk2", "fk3", "fk4")),
    "per_set": ("[calibration]\nper_set = 7\n", ["--per-set", "7"], "per_set", 7),
    "max_subsets": ("[calibration]\nmax_subsets = 50\n", ["--max-subsets", "50"], "max_subsets", 50),
    "seed": ("[calibration]\nseed = 3\n", ["--seed", "3"], "seed", 3),
    "min_subsets": ("[calibration]\nmin_subsets = 4\n", ["--min-subsets", "4"], "min_subsets", 4),
    "final": ('[calibration]\nfinal = "mean"\n', ["--final", "mean"], "final", "mean"),
    "outlier_rejection": ("[calibration]\noutlier_rejection = false\n", ["--no-outlier-rejection"],
                          "outlier_rejection", False),
    "board_sag": ("[calibration]\nboard_sag = false\n", ["--no-board-sag"], "board_sag", False),
    "mrcal_convert": ("[calibration]\nmrcal_convert = true\n", ["--mrcal-convert"], "mrcal_convert", True),
    "steps": ('[[steps]]\nparameters = ["re"]\nmax_error = [0.5]\n', ["--step", "re=0.5"], "steps",
              (Step(("re",), (0.5,)),)),
    "stereo_steps": ('[[stereo.steps]]\nparameters = ["Tnorm"]\nmax_error = [0.75]\n', ["--step", "Tnorm=0.75"],
                     "stereo_steps", (Step(("Tnorm",), (0.75,)),)),
}
RECONSTRUCT_CASES = {
    "preset": ('[reconstruct]\npreset = "thesis-5.9"\n', ["--preset", "thesis-5.9"], "sgbm.min_disparity", 16),
    "sgbm": ("[sgbm]\nblock_size = 7\n", ["--sgbm", "block_size=7"], "sgbm.block_size", 7),
    "depth_range": ("[reconstruct]\ndepth_range = [500, 700]\n", ["--z-min", "500", "--z-max", "700"],
                    "depth_range", (500.0, 700.0)),
    "z_min": ("[reconstruct]\nz_min = 450\nz_max = 700\n", ["--z-min", "450", "--z-max", "700"], "depth_range",
              (450.0, 700.0)),
    "z_max": ("[reconstruct]\nz_min = 500\nz_max = 750\n", ["--z-min", "500", "--z-max", "750"], "depth_range",
              (500.0, 750.0)),
    "alpha": ("[reconstruct]\nalpha = 0.5\n", ["--alpha", "0.5"], "alpha", 0.5),
    "rectification": ("[reconstruct]\nrectification = \"spherical\"\n", ["--rectification", "spherical"],
                      "rectification", "spherical"),
    "zero_disparity": ("[reconstruct]\nzero_disparity = true\n", ["--zero-disparity"], "zero_disparity", True),
    "sgbm.lr_check": ("[sgbm]\nlr_check = 1.5\n", ["--lr-check", "1.5"], "sgbm.lr_check", 1.5),
    "roi": ("[reconstruct]\nroi = [1, 2, 30, 40]\n", ["--roi", "1,2,30,40"], "roi", (1, 2, 30, 40)),
    "outlier_neighbours": ("[reconstruct]\noutlier_neighbours = 8\n", ["--outliers", "8"], "outlier_neighbours", 8),
    "outlier_std": ("[reconstruct]\noutlier_std = 3.0\n", ["--outlier-std", "3"], "outlier_std", 3.0),
    "max_jump": ("[reconstruct]\nmax_jump = 0.1\n", ["--max-jump", "0.1"], "max_jump", 0.1),
    "refine": ("[reconstruct]\nrefine = true\n", ["--refine"], "refine", True),
    "undistort": ('[reconstruct]\nundistort = "exact"\n', None, "undistort", "exact"),
    "color_matching": ("[reconstruct]\ncolor_matching = true\n", None, "color_matching", True),
    "matching_cost": ('[reconstruct]\nmatching_cost = "intensity"\n', ["--cost", "intensity"], "matching_cost",
                      "intensity"),
    "fill": ("[reconstruct]\nfill = true\n", ["--fill"], "fill", True),
    "fill_max_sigma": ("[reconstruct]\nfill_max_sigma = 2.5\n", ["--fill-max-sigma", "2.5"], "fill_max_sigma", 2.5),
    "focal_mm": ("[reconstruct]\nfocal_mm = 35.0\n", ["--focal-mm", "35"], "focal_mm", 35.0),
    "pixel_size_mm": ("[reconstruct]\npixel_size_mm = 0.005\n", ["--pixel-size-mm", "0.005"], "pixel_size_mm",
                      0.005),
    "crop_factor": ("[reconstruct]\ncrop_factor = 1.5\n", ["--crop-factor", "1.5"], "crop_factor", 1.5),
    "focal_px": ("[reconstruct]\nfocal_px = 800.0\n", ["--focal-px", "800"], "focal_px", 800.0),
    "baseline_mm": ("[reconstruct]\nbaseline_mm = 120.0\n", ["--baseline-mm", "120"], "baseline_mm", 120.0),
    "ratio": ("[reconstruct]\nratio = 0.6\n", None, "ratio", 0.6),
    "f_threshold": ("[reconstruct]\nf_threshold = 2.0\n", None, "f_threshold", 2.0),
    "uncertainty": ("[reconstruct]\nuncertainty = false\n", ["--no-uncertainty"], "uncertainty", False),
    "disparity_sigma": ("[reconstruct]\ndisparity_sigma = 0.3\n", ["--disparity-sigma", "0.3"], "disparity_sigma",
                        0.3),
    "full_covariance": ("[reconstruct]\nfull_covariance = true\n", ["--full-covariance"], "full_covariance", True),
}
OPTICS_CASES = {
    "focus_distance": ("[optics]\nfocus_distance = 1200\n", ["--focus-distance", "1200"], "focus_distance", 1200.0),
    "focal_length": ("[optics]\nfocal_length = 35\n", ["--focal-length", "35"], "focal_length", 35.0),
    "sensor": ('[optics]\nsensor = "23.5x15.6"\n', ["--sensor", "23.5x15.6"], "sensor", (23.5, 15.6)),
    "crop_factor": ("[optics]\ncrop_factor = 1.5\n", ["--crop-factor", "1.5"], "crop_factor", 1.5),
    "f_number": ("[optics]\nf_number = 8\n", ["--f-number", "8"], "f_number", 8.0),
    "coc": ("[optics]\ncoc = 0.02\n", ["--coc", "0.02"], "coc", 0.02),
    "pixel_size": ("[optics]\npixel_size = 0.005\n", ["--pixel-size", "0.005"], "pixel_size", 0.005),
    "wavelength": ("[optics]\nwavelength = 0.0006\n", ["--wavelength", "0.0006"], "wavelength", 0.0006),
    "baseline": ("[optics]\nbaseline = 200\n", ["--baseline", "200"], "baseline", 200.0),
    "disparity_precision": ("[optics]\ndisparity_precision = 0.5\n", ["--disparity-precision", "0.5"],
                            "disparity_precision", 0.5),
    "dof_focal_length": ('[optics]\ndof_focal_length = "lens"\n', ["--dof-focal-length", "lens"],
                         "dof_focal_length", "lens"),
}
CASES = {"calibrate": CALIBRATE_CASES, "reconstruct": RECONSTRUCT_CASES, "optics": OPTICS_CASES}
TABLES = {"calibrate": CALIBRATE, "reconstruct": RECONSTRUCT, "optics": OPTICS}


def _settings_of(table: OptionTable) -> list[str]:
    """Options that reach the configuration (a file key, or a field of the configuration type)."""
    return [o.name for o in table.options if o.file or o.in_config]


@pytest.mark.parametrize("command", sorted(TABLES))
def test_every_option_has_a_case(command):
    assert sorted(CASES[command]) == sorted(_settings_of(TABLES[command]))


def _case_cfg(command, monkeypatch, tmp_path, toml, flags):
    if command == "calibrate":
        return _calibrate_cfg(monkeypatch, tmp_path, toml, *flags)
    if command == "reconstruct":
        return _reconstruct_cfg(monkeypatch, tmp_path, toml, *flags)
    name = next(n for n, c in OPTICS_CASES.items() if c[1] == flags or c[0] == toml)
    base = {k: v for k, v in OPTICS_BASE.items() if k != name and not (name == "crop_factor" and k == "sensor")}
    extra = ["--pixel-size", "0.005"] if name == "baseline" else []  # the stereo figures need the pixel size
    return _optics_cfg(monkeypatch, tmp_path, toml, *extra, *flags, base=base)


@pytest.mark.parametrize("command, name", [(c, n) for c in sorted(CASES) for n in sorted(CASES[c])])
def test_file_key_and_flag_reach_the_parameter(monkeypatch, tmp_path, command, name):
    toml, flags, path, expected = CASES[command][name]
    option = TABLES[command][name]
    read = _attr(path)
    default = read(_case_cfg(command, monkeypatch, tmp_path, None, [])) if command != "optics" else None
    assert default != expected  # the case would pass with the option ignored otherwise
    assert read(_case_cfg(command, monkeypatch, tmp_path, toml, [])) == expected, option.file
    assert (flags is None) == (option.flag is None), option
    if flags is not None:
        assert read(_case_cfg(command, monkeypatch, tmp_path, None, flags)) == expected, option.flag


def _typer_flags(command: str) -> dict[str, set[str]]:
    """typer parameter name -> its flags, as the command declares them."""
    import typer

    from dstereo.cli import app

    click_command = typer.main.get_command(app).commands[command]
    return {p.name: set(p.opts) | set(p.secondary_opts) for p in click_command.params}


# Flags that set nothing a configuration holds (console output, cache use): the tables leave them out.
PRESENTATION_FLAGS = {"calibrate": {"--quiet", "-q", "--no-cache"}, "reconstruct": set(), "optics": {"--json"}}


@pytest.mark.parametrize("command", sorted(TABLES))
def test_the_tables_and_the_commands_declare_the_same_flags(command):
    declared = {f for o in TABLES[command].options if o.flag for f in o.flag.split("/")}
    actual = {f for flags in _typer_flags(command).values() for f in flags if f.startswith("-")}
    assert declared == actual - PRESENTATION_FLAGS[command]


@pytest.mark.parametrize("command, name", [(c, o.name) for c in sorted(TABLES) for o in TABLES[c].options
                                           if o.help])
def test_help_text_comes_from_the_table(command, name):
    code, out, _ = run_cli(command, "--help")
    option = TABLES[command][name]
    assert code == 0 and "".join(option.help.split()) in "".join(out.split())  # help wraps at spaces and hyphens


@pytest.mark.parametrize("command, write, needle", [
    ("calibrate", ("c.toml", "[pattern]\ncolour = 3\n"), "colour"),
    ("calibrate", ("c.ini", "[ Calibration ]\nmesh colour = 3\n"), "mesh colour"),
    ("reconstruct", ("r.toml", "[reconstruct]\nzmin = 3\n"), "zmin"),
    ("optics", ("o.toml", "[optics]\napperture = 2\n"), "apperture"),
])
def test_unknown_keys_are_refused_naming_the_file(tmp_path, command, write, needle):
    from dstereo.config import calibration, optics, reconstruction

    name, text = write
    (tmp_path / name).write_text(text)
    reader = {"calibrate": calibration.load_config, "reconstruct": reconstruction.load_config,
              "optics": optics.file_layer}[command]
    with pytest.raises(DstereoError) as exc:
        reader(tmp_path / name)
    assert needle in str(exc.value) and name in str(exc.value)


def test_one_merge_rule_over_layers():
    table = OptionTable("t", (Option("a", replaces=("b",)), Option("b"), Option("seed")))
    assert merge_layers(table, {"a": 1, "b": 2}, {"b": 3, "a": None}) == {"a": 1, "b": 3}  # None: not given
    assert merge_layers(table, {"b": 2}, {"a": 1}) == {"a": 1}  # a given above drops b below
    assert merge(table, Config, {}) == {"seed": Config().seed}  # the defaults come from the configuration type


def test_library_errors_name_parameters_and_the_cli_line_names_flags():
    message = "c.toml: `square` (board square size) 0 must be positive; see `unknown_thing`"
    assert with_flags(message, "calibrate") == "c.toml: --square (board square size) 0 must be positive; see " \
                                               "unknown_thing"
    assert with_flags("`crop_factor` 0", "reconstruct") == with_flags("`crop_factor` 0", "optics") == \
        "--crop-factor 0"
    assert with_flags("`baseline` 0", "optics") == "--baseline 0"
